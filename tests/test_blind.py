"""Blind plane extraction against known geometry: a synthetic gable roof, and the simulated
calibration field compared with the scene's planes and with truth-mode fits."""
import math
import time

import numpy as np
import pytest

from flightsim.scoring.blind import extract_planes
from flightsim.engine.config import RunConfig, validate
from flightsim.outputs.las_points import read_points
from flightsim.scoring.planes import fit_points
from flightsim.engine.world import build_scene

ORIGIN = np.array([409_000.0, 3_393_000.0, 450.0])


def gable_house(pitch_deg: float, ridge_azimuth_deg: float, sigma: float, rng, spacing: float = 0.5,
                length: float = 24.0, width: float = 14.0, eave: float = 8.0, ground_half: float = 30.0):
    """Points of a gable roof (class 6) over flat ground (class 2), with N(0, σ²) noise along each
    surface's normal.

    Returns xyz (n, 3), class (n,), face (n,) (0, 1 roof faces, 2 ground), the faces' unit
    normals (3, 3), and each roof point's true horizontal distance from the ridge.
    """
    a = math.radians(ridge_azimuth_deg)
    along = np.array([math.sin(a), math.cos(a)])  # ridge direction (E, N)
    across = np.array([math.cos(a), -math.sin(a)])  # 90° clockwise from it
    t = math.tan(math.radians(pitch_deg))
    s = np.arange(-length / 2, length / 2, spacing) + spacing / 2
    c = np.arange(-width / 2, width / 2, spacing) + spacing / 2
    s, c = (g.ravel() + rng.uniform(-0.2, 0.2, g.size) * spacing for g in np.meshgrid(s, c))
    xy = np.outer(s, along) + np.outer(c, across)
    z = eave + (width / 2 - np.abs(c)) * t
    face = (c > 0).astype(int)  # face 1 descends towards `across`, face 0 towards −across
    normals = np.array([[*(-across * math.sin(math.radians(pitch_deg))), math.cos(math.radians(pitch_deg))],
                        [*(across * math.sin(math.radians(pitch_deg))), math.cos(math.radians(pitch_deg))],
                        [0.0, 0.0, 1.0]])
    roof = np.column_stack([xy, z]) + rng.normal(0.0, sigma, len(z))[:, None] * normals[face]
    g = np.arange(-ground_half, ground_half, spacing) + spacing / 2
    gx, gy = (v.ravel() + rng.uniform(-0.2, 0.2, v.size) * spacing for v in np.meshgrid(g, g))
    gxy = np.column_stack([gx, gy])
    inside = (np.abs(gxy @ along) < length / 2 + 1) & (np.abs(gxy @ across) < width / 2 + 1)
    ground = np.column_stack([gx, gy, rng.normal(0.0, sigma, gx.size)])[~inside]
    xyz = np.concatenate([roof, ground]) + ORIGIN
    cls = np.concatenate([np.full(len(roof), 6), np.full(len(ground), 2)])
    faces = np.concatenate([face, np.full(len(ground), 2)])
    ridge_distance = np.concatenate([np.abs(c), np.full(len(ground), np.inf)])
    return xyz, cls, faces, normals, ridge_distance


def segment_for(result, faces, face):
    """The segment most of whose fitted points lie on ``face``, and that share."""
    best, share = None, 0.0
    for seg in result.segments:
        counts = np.bincount(faces[seg.indices], minlength=3)
        if counts.argmax() == face and counts[face] > (0 if best is None else len(best.indices) * share):
            best, share = seg, counts[face] / len(seg.indices)
    return best, share


def angle_deg(a, b) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), abs(float(np.dot(a, b)))))


@pytest.mark.parametrize("pitch_deg, ridge_azimuth_deg, sigma", [
    (15.0, 0.0, 0.005), (30.0, 60.0, 0.05), (45.0, 135.0, 0.05), (20.0, 100.0, 0.15)])
def test_gable_roof_faces_are_recovered(pitch_deg, ridge_azimuth_deg, sigma):
    rng = np.random.default_rng(int(pitch_deg * 10 + ridge_azimuth_deg))
    xyz, cls, faces, normals, ridge_distance = gable_house(pitch_deg, ridge_azimuth_deg, sigma, rng)
    buffer = 0.5
    result = extract_planes(xyz, cls, edge_buffer_m=buffer)
    for face in (0, 1, 2):
        seg, share = segment_for(result, faces, face)
        assert seg is not None, f"face {face} not found"
        assert share > 0.99  # at σ = 0.15 m a few points beyond the buffer are nearer the other face
        assert seg.classification == (2 if face == 2 else 6)
        total = np.count_nonzero(faces == face)
        assert len(seg.indices) > 0.6 * total
        # TLS normal error ≈ σ / (RMS in-plane extent · sqrt(n)); extent ≥ 2 m here: 5 standard errors + 1 mrad
        standard_error = sigma / (2.0 * math.sqrt(len(seg.indices)))
        assert angle_deg(seg.fit.normal, normals[face]) < math.degrees(1e-3 + 5.0 * standard_error)
        assert seg.fit.rms_m == pytest.approx(sigma, rel=0.10)
    for face in (0, 1):  # no fitted point lies within the buffer of the ridge (less the noise)
        seg, _ = segment_for(result, faces, face)
        assert ridge_distance[seg.indices].min() > buffer - 3 * sigma / math.sin(math.radians(pitch_deg))
    for face, downslope in ((0, ridge_azimuth_deg + 270.0), (1, ridge_azimuth_deg + 90.0)):
        fit = segment_for(result, faces, face)[0].fit
        assert fit.pitch_deg == pytest.approx(pitch_deg, abs=0.5)
        assert azimuth_difference(fit.azimuth_deg, downslope) == pytest.approx(0.0, abs=0.5)


def test_unclassified_points_are_still_split_into_planes():
    rng = np.random.default_rng(2)
    xyz, _cls, faces, normals, _ = gable_house(30.0, 20.0, 0.02, rng)
    result = extract_planes(xyz, None, edge_buffer_m=0.5)
    for face in (0, 1, 2):
        seg, share = segment_for(result, faces, face)
        assert share > 0.99 and angle_deg(seg.fit.normal, normals[face]) < 0.5


def test_extraction_is_deterministic():
    rng = np.random.default_rng(4)
    xyz, cls, *_ = gable_house(25.0, 30.0, 0.05, rng)
    first = extract_planes(xyz, cls)
    again = extract_planes(xyz.copy(), cls.copy())
    assert np.array_equal(first.labels, again.labels) and np.array_equal(first.used, again.used)
    assert [s.fit.rms_m for s in first.segments] == [s.fit.rms_m for s in again.segments]


def test_automatic_edge_buffer_is_half_the_point_spacing():
    rng = np.random.default_rng(6)
    xyz, cls, *_ = gable_house(30.0, 0.0, 0.01, rng, spacing=0.4)
    result = extract_planes(xyz, cls)
    assert result.edge_buffer_m == pytest.approx(0.5 * result.spacing_m)
    assert 0.1 < result.spacing_m < 0.4


def test_too_few_points_give_no_planes():
    result = extract_planes(ORIGIN + np.random.default_rng(0).normal(size=(10, 3)), np.full(10, 6))
    assert result.segments == [] and not result.used.any() and (result.labels == -1).all()


# --- the simulated calibration field -------------------------------------------------------------

ROOF_MIN_POINTS = 200  # roofs with fewer truth points are too thinly sampled to compare fits on


@pytest.fixture(scope="module")
def calibration_run(tmp_path_factory):
    """A 3 s flight at 500 m over the calibration field (both georeferencing models)."""
    from flightsim.engine.run import simulate_to_directory

    cfg = RunConfig()
    cfg.flight.duration_s = 3.0
    cfg = validate(cfg)
    directory = tmp_path_factory.mktemp("calibration")
    summary = simulate_to_directory(cfg, directory)
    return cfg, directory, summary


def roof_comparison(calibration_run, model):
    """Per well-sampled roof: the scene plane, the truth-mode fit and the matched blind segment."""
    cfg, directory, summary = calibration_run
    scene = build_scene(cfg)
    batch, _ = read_points(sorted((directory / model).glob("*.las")))
    xyz = np.column_stack([batch.x, batch.y, batch.z])
    buffer = summary["edge_buffer_m"]
    start = time.perf_counter()
    result = extract_planes(xyz, batch.classification, edge_buffer_m=buffer)
    elapsed = time.perf_counter() - start
    beyond = batch.edge_distance_m >= np.float32(buffer)
    rows = []
    for plane in scene.planes:
        truth_points = (batch.plane_id == plane.id) & beyond
        if plane.kind != "roof" or truth_points.sum() < ROOF_MIN_POINTS:
            continue
        truth = fit_points(xyz[truth_points])
        matches = [s for s in result.segments if np.bincount(batch.plane_id[s.indices] + 1).argmax() - 1 == plane.id]
        assert len(matches) == 1, f"roof {plane.id} ({truth.n} points) matched by {len(matches)} segments"
        seg = matches[0]
        purity = np.mean(batch.plane_id[seg.indices] == plane.id)
        rows.append((plane, truth, seg.fit, purity))
    return rows, elapsed, len(xyz)


def azimuth_difference(a, b) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def test_exact_model_roofs_match_the_scene(calibration_run):
    rows, elapsed, n = roof_comparison(calibration_run, "exact")
    assert len({round(p.pitch_deg) for p, *_ in rows}) >= 5  # roofs of several pitches
    for plane, truth, blind, purity in rows:
        assert purity > 0.99, plane.id
        assert blind.pitch_deg == pytest.approx(plane.pitch_deg, abs=0.05), plane.id
        assert azimuth_difference(blind.azimuth_deg, plane.azimuth_deg) == pytest.approx(0.0, abs=0.05), plane.id
        assert blind.rms_m < 1e-3 and abs(blind.rms_m - truth.rms_m) < 1e-4  # mm-quantised LAS coordinates
    print(f"\nblind extraction, exact model: {n} points in {elapsed:.2f} s")


def test_nominal_model_roofs_match_truth_mode(calibration_run):
    """The nominal model's distortion tilts the fitted roofs (up to ~1° here, even by plane id):
    blind fits must agree with the truth-mode fits of the same roofs."""
    rows, elapsed, n = roof_comparison(calibration_run, "nominal")
    assert len({round(p.pitch_deg) for p, *_ in rows}) >= 5
    for plane, truth, blind, purity in rows:
        assert purity > 0.98, plane.id
        assert blind.pitch_deg == pytest.approx(truth.pitch_deg, abs=0.5), plane.id
        assert azimuth_difference(blind.azimuth_deg, truth.azimuth_deg) == pytest.approx(0.0, abs=0.5), plane.id
        assert blind.rms_m == pytest.approx(truth.rms_m, rel=0.10), plane.id
        assert truth.rms_m > 0.005  # the distortion is there to be measured
    print(f"\nblind extraction, nominal model: {n} points in {elapsed:.2f} s")
