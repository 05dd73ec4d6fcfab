"""`flightsim score` (SPEC §9, §10): truth and blind modes on run directories and single files,
outputs, and one-line errors with exit status 2."""
import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from flightsim.engine.config import RunConfig, validate
from flightsim.core.errors import InputError
from flightsim.outputs.las_points import read_points
from flightsim.scoring.planes import fit_points
from flightsim.scoring.score import TABLE_COLUMNS, score_points

ROOT = Path(__file__).resolve().parents[1]
ORIGIN = np.array([409_000.0, 3_393_000.0, 450.0])


def flightsim(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "flightsim", *args], capture_output=True, text=True, env=env,
                          timeout=600)


def error_lines(result) -> list[str]:
    return [line for line in result.stderr.splitlines() if "CUDA" not in line]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A 1.5 s flight at 500 m over the calibration field, both georeferencing models."""
    from flightsim.engine.run import simulate_to_directory

    cfg = RunConfig()
    cfg.flight.duration_s = 1.5
    directory = tmp_path_factory.mktemp("run")
    simulate_to_directory(validate(cfg), directory)
    return directory


def write_las(path: Path, xyz: np.ndarray, classification: int = 1, plane_id: np.ndarray | None = None) -> Path:
    """A LAS 1.4 point-format-6 file written with laspy alone (no flightsim code), mm scale."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    if plane_id is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="plane_id", type=np.int32))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = np.full(len(xyz), classification, dtype=np.uint8)
    if plane_id is not None:
        las.plane_id = plane_id.astype(np.int32)
    las.write(path)
    return path


def tilted_plane(n: int, slope: float, azimuth_deg: float, sigma: float, rng, half: float = 40.0, shift=(0, 0, 0)):
    """Points of z = −slope·(x·sin a + y·cos a) + N(0, σ²) vertical noise, about ORIGIN + shift."""
    a = math.radians(azimuth_deg)
    xy = rng.uniform(-half, half, size=(n, 2))
    z = -slope * (xy[:, 0] * math.sin(a) + xy[:, 1] * math.cos(a)) + rng.normal(0.0, sigma, n)
    return np.column_stack([xy, z]) + ORIGIN + np.asarray(shift, dtype=float)


# --- command line ------------------------------------------------------------------------------

def test_truth_mode_on_a_run_directory_reproduces_the_simulators_rms(run_dir, tmp_path):
    result = flightsim("score", str(run_dir), "--out", str(tmp_path / "score"))
    assert result.returncode == 0, result.stderr
    document = json.loads((tmp_path / "score" / "score.json").read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    sources = {Path(s["source"]).name: s for s in document["sources"]}
    assert set(sources) == {"exact", "nominal"} and document["mode"] == "truth"
    # independent paths: moments summed in the simulator vs the mm-quantised LAS tiles
    assert sources["nominal"]["rms_m"] == pytest.approx(summary["rms_m"]["nominal"], rel=0.01)
    assert sources["exact"]["rms_m"] < 1e-3
    for s in sources.values():
        assert s["edge_buffer_m"] == pytest.approx(summary["edge_buffer_m"])
        assert s["points"] == summary["points"]["nominal"]
        assert s["points_used"] + s["points_excluded"] + s["points_unassigned"] == s["points"]
    with open(tmp_path / "score" / "planes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == TABLE_COLUMNS
    assert len(rows) == sum(s["planes"] for s in sources.values())
    for row in rows:
        normal = np.array([float(row["nx"]), float(row["ny"]), float(row["nz"])])
        assert np.linalg.norm(normal) == pytest.approx(1.0) and normal[2] >= 0.0


def test_blind_mode_on_a_run_directory(run_dir, tmp_path):
    result = flightsim("score", str(run_dir), "--mode", "blind", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    sources = {Path(s["source"]).name: s for s in json.loads((tmp_path / "score.json").read_text())["sources"]}
    summary = json.loads((run_dir / "summary.json").read_text())
    assert sources["nominal"]["rms_m"] == pytest.approx(summary["rms_m"]["nominal"], rel=0.10)
    with open(tmp_path / "planes.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["source"].endswith("nominal")]
    assert len(rows) == sources["nominal"]["planes"] > 10
    matched = [r for r in rows if int(r["truth_plane_id"]) >= 0]
    assert len(matched) == len(rows) and all(float(r["truth_fraction"]) > 0.9 for r in matched)


def test_single_files_print_a_table(run_dir):
    tile = max((run_dir / "nominal").glob("*.las"), key=lambda p: p.stat().st_size)
    for mode in ("truth", "blind"):
        result = flightsim("score", str(tile), "--mode", mode)
        assert result.returncode == 0, result.stderr
        first = result.stdout.splitlines()[0]
        assert str(tile) in first and f"[{mode}]" in first and "RMS pooled" in first


def test_any_las_file_is_scored_blind_and_refused_in_truth_mode(tmp_path):
    rng = np.random.default_rng(1)
    sigma = 0.02
    path = write_las(tmp_path / "plain.las", tilted_plane(6000, 0.20, 30.0, sigma, rng))
    result = flightsim("score", str(path), "--mode", "blind", "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    with open(tmp_path / "out" / "planes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1
    assert float(rows[0]["pitch_deg"]) == pytest.approx(math.degrees(math.atan(0.20)), abs=0.1)  # 11.31°
    assert float(rows[0]["azimuth_deg"]) == pytest.approx(30.0, abs=0.5)
    # vertical noise σ on a plane of slope s is σ·cos(atan s) along its normal
    assert float(rows[0]["rms_m"]) == pytest.approx(sigma * math.cos(math.atan(0.20)), rel=0.05)
    assert rows[0]["truth_plane_id"] == "-1"

    refused = flightsim("score", str(path))  # truth mode is the default
    lines = error_lines(refused)
    assert refused.returncode == 2 and len(lines) == 1
    assert "plane_id" in lines[0] and str(path) in lines[0] and "Traceback" not in refused.stderr


@pytest.mark.parametrize("make_args, field", [
    (lambda tmp, run: [str(tmp / "missing.las")], "PATH"),
    (lambda tmp, run: [str(tmp)], "PATH"),  # a directory without LAS files
    (lambda tmp, run: [str(run), "--edge-buffer", "-1"], "--edge-buffer"),
    (lambda tmp, run: [str(run), "--edge-buffer", "nan"], "--edge-buffer"),
    (lambda tmp, run: [str(run), "--edge-buffer", "5"], "--edge-buffer"),  # beyond the recorded edge distances
    (lambda tmp, run: [str(run), "--edge-buffer", "wide"], "--edge-buffer"),
    (lambda tmp, run: [str(run), "--mode", "psychic"], "--mode"),
])
def test_bad_input_exits_2_with_one_line(run_dir, tmp_path, make_args, field):
    result = flightsim("score", *make_args(tmp_path, run_dir))
    lines = error_lines(result)
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in result.stderr


def test_unreadable_or_foreign_files_exit_2(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("not a point cloud")
    broken = tmp_path / "broken.las"
    broken.write_bytes(b"LASF" + bytes(200))
    for path in (text, broken):
        result = flightsim("score", str(path), "--mode", "blind")
        lines = error_lines(result)
        assert result.returncode == 2 and len(lines) == 1 and str(path) in lines[0], result.stderr
    taken = tmp_path / "taken"
    taken.write_text("")
    result = flightsim("score", str(broken), "--out", str(taken))
    assert result.returncode == 2 and "--out" in error_lines(result)[0]


# --- library -------------------------------------------------------------------------------------

def test_truth_mode_excludes_exactly_the_points_within_the_buffer(run_dir):
    batch, _ = read_points(sorted((run_dir / "nominal").glob("*.las")))
    buffer = json.loads((run_dir / "summary.json").read_text())["edge_buffer_m"]
    result = score_points(batch, "truth", buffer)
    near_edge = batch.edge_distance_m < np.float32(buffer)
    assert result.points_excluded == np.count_nonzero(near_edge & (batch.plane_id >= 0))
    xyz = np.column_stack([batch.x, batch.y, batch.z])
    for fit in result.fits[:10]:
        direct = fit_points(xyz[(batch.plane_id == fit.plane_id) & ~near_edge])
        assert fit.n == direct.n and fit.rms_m == pytest.approx(direct.rms_m, rel=1e-9)
        assert np.allclose(fit.centroid, direct.centroid, atol=1e-6, rtol=0)
    smaller = score_points(batch, "truth", 0.5 * buffer)
    assert smaller.points_excluded == np.count_nonzero((batch.edge_distance_m < np.float32(0.5 * buffer))
                                                       & (batch.plane_id >= 0))


def test_truth_mode_without_edge_distances_estimates_the_boundary(tmp_path):
    rng = np.random.default_rng(9)
    sigma = 0.01
    grid = np.stack(np.meshgrid(np.arange(-20, 20, 0.5), np.arange(-20, 20, 0.5)), -1).reshape(-1, 2)
    xy = grid + rng.uniform(-0.1, 0.1, grid.shape)
    low = np.column_stack([xy, rng.normal(0, sigma, len(xy))]) + ORIGIN
    high = low + [100.0, 0.0, 12.0]
    path = write_las(tmp_path / "ids.las", np.concatenate([low, high]), 2,
                     np.repeat([0, 1], len(xy)))
    batch, _ = read_points(path)
    assert batch.edge_distance_m is None
    result = score_points(batch, "truth", edge_buffer_m=0.8, source=str(path))
    assert [f.plane_id for f in result.fits] == [0, 1]
    for fit in result.fits:
        assert fit.rms_m == pytest.approx(sigma, rel=0.1) and fit.pitch_deg < 0.2
    # the estimated boundary runs through the outermost points: here the sides of the square
    edge = np.min(np.column_stack([xy - xy.min(axis=0), xy.max(axis=0) - xy]), axis=1)
    assert result.points_excluded == pytest.approx(2 * np.count_nonzero(edge < 0.8), rel=0.05)
    assert result.points_used + result.points_excluded == len(batch)


def test_truth_mode_needs_plane_ids():
    rng = np.random.default_rng(0)
    xyz = tilted_plane(100, 0.1, 0.0, 0.01, rng)
    from flightsim.outputs.las_points import PointBatch

    n = len(xyz)
    batch = PointBatch(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], gps_time=np.zeros(n), point_source_id=np.zeros(n, int),
                       classification=np.ones(n, int), scan_angle_deg=np.zeros(n), intensity=np.zeros(n, int),
                       beam_row=None, beam_col=None, prism_angle_deg=None, range_m=None, plane_id=np.full(n, -1))
    with pytest.raises(InputError, match="plane_id"):
        score_points(batch, "truth", source="x.las")
    assert len(score_points(batch, "blind").fits) == 1
