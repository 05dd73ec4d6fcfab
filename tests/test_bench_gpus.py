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
    assert serial["points_written"] == shared["points_written"] > 0 and serial["bytes"] == shared["bytes"]
    assert (serial["workers"], shared["workers"]) == (1, 2) and not (tmp_path / "two").exists()
    assert serial["segments_s"] > 0 and serial["merges_s"] > 0 and 0 < serial["busy_share"] <= 1.01


def test_tile_digests_are_each_files_sha256_by_relative_path(tmp_path):
    (tmp_path / "exact").mkdir()
    (tmp_path / "exact" / "a.laz").write_bytes(b"abc")
    (tmp_path / "exact" / ".a.laz.123.part").write_bytes(b"left by a dead attempt")
    (tmp_path / "survey.json").write_text("{}")
    assert bench_gpus.tile_digests(tmp_path) == {
        "exact/a.laz": "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"}  # FIPS 180-2's "abc"


def test_a_survey_to_las_writes_las_tiles(tmp_path):
    run = bench_gpus.survey_run(tmp_path / "las", SMALL_SURVEY, None, 0.8, laz=False)
    assert len(run["outputs"]) == 4 and all(name.endswith(".las") for name in run["outputs"])
    assert "output.laz=false" in run["command"]


def test_differences_name_each_column_that_differs_and_by_how_much():
    rows = [{"model": "exact", "rms_m": "0.0125", "points": "10"}, {"model": "nominal", "rms_m": "0.5", "points": "9"}]
    others = [rows[0], {"model": "nominal", "rms_m": "0.4", "points": "9"}]
    assert bench_gpus.compare(rows, rows) == {"rows": [2, 2], "columns": {}}
    found = bench_gpus.compare(rows, others)
    assert found["columns"].keys() == {"rms_m"} and found["columns"]["rms_m"]["rows"] == 1
    assert found["columns"]["rms_m"]["max_abs"] == pytest.approx(0.1) and found["columns"]["rms_m"]["max_rel"] == \
        pytest.approx(0.2)
    assert bench_gpus.compare({"a.laz": "1", "b.laz": "2"}, {"a.laz": "1", "b.laz": "3", "c.laz": "4"}) == \
        {"tiles": 2, "tiles_differing": ["b.laz", "c.laz"]}


def test_the_table_shows_each_pair_with_its_speed_up_and_what_differed():
    sweep = {"command": "flightsim sweep --gpus 0", "workers": 1, "wall_s": 20.0, "rows": 500, "busy_share": 0.9}
    survey = {"command": "flightsim survey --gpus 0", "workers": 16, "wall_s": 60.0, "points_written": 8.5e8,
              "bytes": 6e9, "points_per_s": 1.4e7, "segments_s": 300.0, "merges_s": 500.0, "busy_share": 0.8}
    same_rows = {"rows": [500, 500], "columns": {}}
    record = {"gpus": 2, "gpu_name": "GPU", "cpu_count": 32, "disk_write_bytes_per_s": 2e9,
              "study_repeat": {"wall_s": 19.0, "differences": {"rows": [500, 500], "columns": {
                  "rms_m": {"rows": 3, "max_abs": 4.2e-12, "max_rel": 1e-5}}}},
              "pairs": {"study": {"runs": [sweep, {**sweep, "wall_s": 11.0}], "speedup": 20 / 11,
                                  "differences": same_rows},
                        "survey to LAZ": {"runs": [survey, {**survey, "wall_s": 30.0}], "speedup": 2.0,
                                          "differences": {"tiles": 800, "tiles_differing": []}}}}
    text = "\n".join(bench_gpus.markdown({"gpus": record}))
    assert "| study | `flightsim sweep --gpus 0` | 1 | 20.0 | 1 | 90% | – | 500 rows |" in text
    assert "| 11.0 | 1.82× | 90% | all 500 rows alike |" in text
    assert "| 30.0 | 2.00× | 80% | all 800 tiles byte for byte |" in text
    assert "6.00 GB (0.050 of the disk's rate)" in text  # 6e9 B / 60 s / 2e9 B/s
    assert "6.00 GB (0.100 of the disk's rate)" in text
    assert "rms_m in 3 rows, by ≤ 4.2e-12" in text and "disk writes 2000 MB/s" in text


def test_a_configurations_wall_counts_once_though_it_has_a_row_per_model(tmp_path):
    path = tmp_path / "sweep.csv"
    path.write_text("altitude_m,array,spacing_mrad,model,rms_m,points,returns,planes,edge_buffer_m,wall_s\n"
                    "500.0,2,2.314,exact,1e-07,3922,4004,30,0.237,0.5\n"
                    "500.0,2,2.314,nominal,0.032,3922,4004,30,0.237,0.5\n"
                    "500.0,3,2.314,exact,2e-07,5000,5100,31,0.398,0.25\n"
                    "500.0,3,2.314,nominal,0.041,5000,5100,31,0.398,0.25\n"
                    "1000.0,3,2.314,nominal,0.08,4000,4100,31,0.79,0.125\n")
    assert bench_gpus.configurations_wall_s(path) == 0.875
