"""`flightsim bench --sections gpus` (flightsim/studies/bench_gpus.py): its runs of one command in two placements
give the outputs it compares, on this machine's CPU workers; on fewer than two GPUs the section says so."""
import hashlib

import pytest

from flightsim.studies import bench_gpus
from flightsim.studies.bench_common import sizes

SMALL_SURVEY = ["--tile-m", "400", "--altitude", "300", "--models", "nominal", "--set", "risley.prf_hz=500"]


def test_fewer_than_two_gpus_is_a_record_saying_so_and_no_table():
    record = bench_gpus.gpu_scaling("cpu", sizes("cpu", quick=True))
    assert record == {"gpus": 0, "skipped": "needs a machine with two or more GPUs"}
    assert bench_gpus.markdown({"gpus": record}) == [] and bench_gpus.markdown({}) == []


def test_a_sweep_on_two_workers_has_the_serial_rows_but_their_wall_times(tmp_path):
    grid = (["500"], ["2", "3"], ["2.314"])
    serial = bench_gpus.sweep_run(tmp_path / "serial", ["--device", "cpu"], grid)
    shared = bench_gpus.sweep_run(tmp_path / "two", ["--device", "cpu", "--workers", "2"], grid)
    assert serial["rows"] == shared["rows"] == 4  # two configurations × both models
    assert serial["outputs"] == shared["outputs"] and "wall_s" not in serial["outputs"][0]
    assert {r["array"] for r in serial["outputs"]} == {"2", "3"}
    assert (serial["workers"], shared["workers"]) == (1, 2)
    assert 0 < serial["busy_share"] <= 1 and 0 < shared["busy_share"] <= 1


def test_a_survey_on_two_workers_writes_the_serial_tiles_byte_for_byte(tmp_path):
    serial = bench_gpus.survey_run(tmp_path / "serial", SMALL_SURVEY, None, 0.8)
    shared = bench_gpus.survey_run(tmp_path / "two", SMALL_SURVEY, 2, 0.8)
    assert serial["outputs"] == shared["outputs"] and len(serial["outputs"]) == 4  # the nominal model's tiles
    assert all(name.startswith("nominal/") and name.endswith(".laz") for name in serial["outputs"])
    assert serial["points_written"] == shared["points_written"] > 0 and serial["laz_bytes"] == shared["laz_bytes"]
    assert (serial["workers"], shared["workers"]) == (1, 2) and not (tmp_path / "two").exists()
    assert serial["segments_s"] > 0 and serial["merges_s"] > 0 and 0 < serial["busy_share"] <= 1.01


def test_tile_digests_are_each_files_sha256_by_relative_path(tmp_path):
    (tmp_path / "exact").mkdir()
    (tmp_path / "exact" / "a.laz").write_bytes(b"abc")
    (tmp_path / "exact" / ".a.laz.123.part").write_bytes(b"left by a dead attempt")
    (tmp_path / "survey.json").write_text("{}")
    assert bench_gpus.tile_digests(tmp_path) == {
        "exact/a.laz": "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"}  # FIPS 180-2's "abc"


def test_the_table_shows_each_pair_with_its_speed_up():
    run = {"command": "flightsim sweep --gpus 0", "workers": 1, "wall_s": 20.0, "rows": 500, "busy_share": 0.9}
    survey = {"command": "flightsim survey --gpus 0", "workers": 16, "wall_s": 60.0, "points_written": 8.5e8,
              "laz_bytes": 6.1e9, "points_per_s": 1.4e7, "segments_s": 300.0, "merges_s": 500.0, "busy_share": 0.8}
    record = {"gpus": 2, "gpu_name": "GPU", "cpu_count": 32, "disk_write_bytes_per_s": 2e9,
              "study": [run, {**run, "wall_s": 11.0}], "survey": [survey, {**survey, "wall_s": 32.0}],
              "study_speedup": 20 / 11, "survey_speedup": 60 / 32, "survey_laz_of_disk": 6.1e9 / 32 / 2e9}
    text = "\n".join(bench_gpus.markdown({"gpus": record}))
    assert "| study | `flightsim sweep --gpus 0` | 1 | 20.0 | 1 | 90% | 500 rows |" in text
    assert "| 11.0 | 1.82× |" in text and "| 32.0 | 1.88× |" in text
    assert "LAZ rate on every GPU ÷ the disk's: 0.10." in text and "disk writes 2000 MB/s" in text
