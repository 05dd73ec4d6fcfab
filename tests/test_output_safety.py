"""Outputs are reproducible and safe: identical bytes for the same config and seed, nothing
half-written after a crash, a killed run completed by running the same command again, and no
output directory clobbered without --overwrite (SPEC §8, §10).

The crash tests start the real command line in a subprocess and SIGKILL it at several moments
(fractions of a clean run's duration, so they land in start-up, in the middle and near the end
on any machine), check what is on disk, then rerun and compare with the clean run.
"""
import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pytest

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.run import simulate_to_directory

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
KILL_AT = (0.3, 0.55, 0.7, 0.85, 0.95)  # fractions of a clean run's wall time (start-up takes ~1 s)


def config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in settings.items():
        set_value(cfg, key.replace("__", "."), value)
    return validate(cfg)


def tile_bytes(directory: Path) -> dict[str, bytes]:
    """{model/tile: bytes} of every finished tile under a run directory."""
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.glob("*/*.la[sz]"))}


# ---------------------------------------------------------------------------------------------
# determinism


@pytest.mark.parametrize("noise_m", [0.0, 0.05])
def test_same_config_and_seed_give_identical_las_bytes(tmp_path, noise_m):
    cfg = config(flight__duration_s=0.4, instrument__errors="ranging", ranging__noise_m=noise_m, run__seed=11,
                 output__position_error=True)
    first = simulate_to_directory(cfg, tmp_path / "a")
    second = simulate_to_directory(cfg, tmp_path / "b")
    a, b = tile_bytes(tmp_path / "a"), tile_bytes(tmp_path / "b")
    assert a and a == b
    assert (tmp_path / "a/run.toml").read_bytes() == (tmp_path / "b/run.toml").read_bytes()
    assert first["rms_m"] == second["rms_m"]


def test_range_noise_depends_on_the_seed_only_not_on_chunking(tmp_path):
    runs = {}
    for name, seed, chunk in (("auto", 5, 0), ("small_chunks", 5, 97), ("other_seed", 6, 0)):
        cfg = config(flight__duration_s=0.3, instrument__errors="ranging", ranging__noise_m=0.05, run__seed=seed,
                     run__chunk_pulses=chunk)
        simulate_to_directory(cfg, tmp_path / name)
        runs[name] = tile_bytes(tmp_path / name)
    assert runs["auto"] == runs["small_chunks"]
    assert runs["auto"].keys() == runs["other_seed"].keys() and runs["auto"] != runs["other_seed"]
    ranges = [np.concatenate([np.asarray(laspy.read(tmp_path / n / t)["range"]) for t in sorted(runs[n])])
              for n in ("auto", "other_seed")]
    difference = (ranges[0] - ranges[1]).astype(np.float64)
    assert 0.05 < difference.std() / np.sqrt(2) < 0.06  # two independent N(0, 5 cm) draws per point


# ---------------------------------------------------------------------------------------------
# crashes


def start(args: list[str], cwd: Path) -> subprocess.Popen:
    """The command line in a subprocess, its output discarded."""
    return subprocess.Popen([sys.executable, "-m", "flightsim", *args], cwd=cwd, env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def finish(args: list[str], cwd: Path) -> tuple[subprocess.CompletedProcess, float]:
    """Run the command line to its end: (the completed process, its wall time [s])."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "flightsim", *args], cwd=cwd, env=ENV, capture_output=True,
                          text=True, timeout=600)
    return done, time.perf_counter() - started


def kill_after(args: list[str], cwd: Path, seconds: float) -> None:
    """Start the command and SIGKILL it after ``seconds``; if it ends sooner it must have succeeded."""
    process = start(args, cwd)
    try:
        assert process.wait(timeout=seconds) == 0, f"{args} failed before it could be killed"
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGKILL)
        process.wait()


def assert_every_tile_is_complete(directory: Path, reference: dict[str, bytes]) -> None:
    """Each *.las/*.laz present opens, holds its header's point count, and is the clean run's tile."""
    for name, data in tile_bytes(directory).items():
        las = laspy.read(directory / name)
        assert len(las.points) == las.header.point_count > 0, name
        assert data == reference[name], f"{name} differs from the clean run's"


SIMULATE = ["simulate", "--duration", "5", "--set", "run.chunk_pulses=500", "--set", "output.tile_size_m=100",
            "--set", "instrument.errors=ranging", "--set", "ranging.noise_m=0.01", "--seed", "4"]


def test_killed_simulation_leaves_only_complete_tiles_and_a_rerun_completes_it(tmp_path):
    done, clean_s = finish([*SIMULATE, "--out", "clean"], tmp_path)
    assert done.returncode == 0, done.stderr
    reference = tile_bytes(tmp_path / "clean")
    assert len(reference) >= 10
    out = tmp_path / "killed"
    for fraction in KILL_AT:
        kill_after([*SIMULATE, "--out", str(out)], tmp_path, fraction * clean_s)
        if out.exists():
            assert_every_tile_is_complete(out, reference)
            summary = out / "summary.json"
            if summary.exists():  # it finished before the kill: then every tile is there
                assert tile_bytes(out) == reference and json.loads(summary.read_text())
                break
    if not (out / "summary.json").exists():
        done, _ = finish([*SIMULATE, "--out", str(out)], tmp_path)
        assert done.returncode == 0, done.stderr
    assert tile_bytes(out) == reference
    assert not list(out.rglob("*.part"))
    ours = json.loads((out / "summary.json").read_text())
    clean = json.loads((tmp_path / "clean/summary.json").read_text())
    assert ours["points"] == clean["points"] and ours["tiles"] == clean["tiles"]


SWEEP = ["sweep", "--scene", "plane", "--altitudes", "500,1000,1500,2000,2500,3000", "--arrays", "2,3,4",
         "--duration", "1"]
KEY_COLUMNS = ("altitude_m", "array", "spacing_mrad", "model")


def read_table(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def without_timing(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "wall_s"} for row in rows]


def test_killed_sweep_keeps_whole_rows_and_resumes_without_duplicates(tmp_path):
    done, clean_s = finish([*SWEEP, "--out", "clean"], tmp_path)
    assert done.returncode == 0, done.stderr
    reference = read_table(tmp_path / "clean/sweep.csv")
    assert len(reference) == 36
    expected = {tuple(r[k] for k in KEY_COLUMNS): r for r in without_timing(reference)}
    out = tmp_path / "killed"
    finished_rows = 0
    for fraction in KILL_AT:
        kill_after([*SWEEP, "--out", str(out)], tmp_path, fraction * clean_s)
        rows = list((out / "rows").glob("*.json")) if (out / "rows").exists() else []
        for row_file in rows:  # every row file is whole
            assert len(json.loads(row_file.read_text())["rows"]) == 2
        assert len(rows) >= finished_rows  # resuming never loses finished rows
        finished_rows = len(rows)
        if (out / "sweep.csv").exists():  # made from finished row files only: whole, never a row twice
            table = {tuple(r[k] for k in KEY_COLUMNS): r for r in without_timing(read_table(out / "sweep.csv"))}
            assert len(table) == len(read_table(out / "sweep.csv")) <= 2 * len(rows)
            assert all(table[key] == expected[key] for key in table)
    done, _ = finish([*SWEEP, "--out", str(out)], tmp_path)
    assert done.returncode == 0, done.stderr
    assert without_timing(read_table(out / "sweep.csv")) == without_timing(reference)
    assert len(list((out / "rows").glob("*.json"))) == 18


# ---------------------------------------------------------------------------------------------
# leftovers and refusals


def simulate_args(out: Path) -> list[str]:
    return ["simulate", "--scene", "plane", "--duration", "0.2", "--out", str(out)]


def test_run_stopped_while_writing_its_config_is_redone(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / ".run.toml.part").write_text("[scene]\nname = \"pla")  # killed mid-write of run.toml
    done, _ = finish(simulate_args(out), tmp_path)
    assert done.returncode == 0, done.stderr
    assert (out / "summary.json").is_file() and not list(out.rglob("*.part"))


def test_unfinished_run_of_another_config_is_not_replaced_without_overwrite(tmp_path):
    out = tmp_path / "run"
    done, _ = finish(simulate_args(out), tmp_path)
    assert done.returncode == 0
    (out / "summary.json").unlink()  # as if it had been killed before finishing
    before = tile_bytes(out)
    other = ["simulate", "--scene", "plane", "--duration", "0.3", "--out", str(out)]
    done, _ = finish(other, tmp_path)
    assert done.returncode == 2 and "--overwrite" in done.stderr
    assert tile_bytes(out) == before
    done, _ = finish([*other, "--overwrite"], tmp_path)
    assert done.returncode == 0 and tile_bytes(out) != before


def test_sweep_refuses_a_directory_of_other_files_without_overwrite(tmp_path):
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    args = ["sweep", "--scene", "plane", "--altitudes", "500", "--duration", "0.2", "--out", str(out)]
    done, _ = finish(args, tmp_path)
    assert done.returncode == 2 and "--out" in done.stderr and "--overwrite" in done.stderr
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_sweep_killed_while_writing_its_table_resumes(tmp_path):
    out = tmp_path / "sweep"
    args = ["sweep", "--scene", "plane", "--altitudes", "500,1000", "--duration", "0.2", "--out", str(out)]
    done, _ = finish(args, tmp_path)
    assert done.returncode == 0
    table = (out / "sweep.csv").read_text()
    (out / ".sweep.csv.part").write_text(table[: len(table) // 2])  # killed in the middle of write_atomic
    done, _ = finish(args, tmp_path)
    assert done.returncode == 0, done.stderr
    assert (out / "sweep.csv").read_text() == table


def test_sweep_does_not_replace_another_sweep_without_overwrite(tmp_path):
    out = tmp_path / "sweep"
    first = ["sweep", "--scene", "plane", "--altitudes", "500,1000", "--duration", "0.2", "--out", str(out)]
    done, _ = finish(first, tmp_path)
    assert done.returncode == 0
    table = (out / "sweep.csv").read_text()
    second = ["sweep", "--scene", "plane", "--altitudes", "2000", "--duration", "0.2", "--out", str(out)]
    done, _ = finish(second, tmp_path)
    assert done.returncode == 2 and "--overwrite" in done.stderr
    assert (out / "sweep.csv").read_text() == table
