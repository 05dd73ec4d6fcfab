"""The simulator end to end: config → kernels → LAS tiles → plane RMS (SPEC §5, §6, §8, §10)."""
import json
import math

import laspy
import numpy as np
import pytest

import reference_optics as ref
from flightsim.engine.config import RunConfig, config_dict, set_value, validate
from flightsim.engine.config_io import load_toml
from flightsim.engine.run import STAGES, simulate_to_directory
from flightsim.engine.readouts.points import Points


def config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in settings.items():
        set_value(cfg, key.replace("__", "."), value)
    return validate(cfg)


def read_model(directory, model):
    """All points of one model's tiles, in world coordinates, float64."""
    files = sorted((directory / model).glob("*.las"))
    las = [laspy.read(f) for f in files]
    xyz = np.concatenate([np.column_stack([l.x, l.y, l.z]) for l in las])
    return xyz, las


def tls_rms(xyz: np.ndarray) -> float:
    """Orthogonal-residual RMS of a total-least-squares plane, two-pass float64."""
    centred = xyz - xyz.mean(axis=0)
    return float(np.sqrt(np.linalg.eigvalsh(centred.T @ centred / len(xyz))[0]))


def nominal_plane_rms_reference(altitude, n, spacing, duration, prf=5000.0, f_rot=20.0, speed=200 / 3.6):
    """Independent float64 model of the seed paper's altitude study over flat ground."""
    n_glass = 1.5066
    apex = math.atan2(math.sin(math.radians(15)), n_glass - math.cos(math.radians(15)))
    t = np.arange(int(round(duration * prf)) + 1) / prf
    points = []
    s1 = ref.fan_directions(n, spacing)
    for k, tk in enumerate(t):
        phi = 2 * np.pi * f_rot * tk
        s3, _, _ = ref.prism_exit(s1, phi, n_glass, apex, 0.01)
        nominal = ref.nominal_directions(n, spacing, phi, n_glass, apex)
        r = altitude / s3[:, 2]  # sensor frame z is down; ground at depth = altitude
        p = r[:, None] * nominal
        p[:, 0] += speed * tk
        points.append(p)
    return tls_rms(np.concatenate(points))


@pytest.mark.parametrize("altitude", [500.0, 5000.0])
def test_exact_model_is_flat_in_utm_coordinates(tmp_path, device, altitude):
    cfg = config(scene__name="plane", flight__altitude_m=altitude, flight__duration_s=0.5, run__device=device)
    summary = simulate_to_directory(cfg, tmp_path)
    xyz, tiles = read_model(tmp_path, "exact")
    assert xyz[:, 0].min() > 4.0e5 and xyz[:, 1].min() > 3.3e6  # real UTM values went through the kernels
    assert len(xyz) == summary["points"]["exact"] == summary["pulses"] * 9
    assert tls_rms(xyz) < 0.002
    # ground is at the scene origin height, and points lie on the scan circle of radius h·tan15°
    assert abs(np.median(xyz[:, 2]) - 450.0) < 0.002
    radius = np.hypot(xyz[:, 0] - xyz[:, 0].mean(), xyz[:, 1] - xyz[:, 1].mean())
    assert abs(np.median(radius) - altitude * math.tan(math.radians(15))) < 0.02 * altitude


def test_nominal_model_reproduces_the_seed_paper_at_500_m(tmp_path):
    cfg = config(scene__name="plane", flight__altitude_m=500.0, flight__duration_s=1.0)
    summary = simulate_to_directory(cfg, tmp_path)
    xyz, _ = read_model(tmp_path, "nominal")
    rms = tls_rms(xyz)
    expected = nominal_plane_rms_reference(500.0, 3, 2.314e-3, 1.0)
    assert rms == pytest.approx(expected, rel=0.02)
    assert rms == pytest.approx(0.05, rel=0.10)  # seed paper: 0.0498 m
    assert summary["rms_m"]["nominal"] == pytest.approx(rms, rel=1e-3)
    assert summary["rms_m"]["exact"] < 0.001


def test_tiles_hold_what_the_summary_says_with_the_las_conventions(tmp_path):
    cfg = config(flight__duration_s=0.4, output__position_error=True)
    summary = simulate_to_directory(cfg, tmp_path)
    for model in ("exact", "nominal"):
        xyz, tiles = read_model(tmp_path, model)
        assert len(xyz) == summary["points"][model] == sum(summary["tiles"][model].values())
        for las in tiles:
            h = las.header
            assert (h.version.major, h.version.minor, h.point_format.id) == (1, 4, 6)
            assert np.allclose(h.scales, 0.001) and h.offsets[0] % 500 == 0 and h.offsets[1] % 500 == 0
            assert h.parse_crs().to_epsg() == 32648
            assert set(las.point_format.extra_dimension_names) >= {
                "beam_row", "beam_col", "prism_angle", "range", "plane_id", "position_error"}
            t = np.asarray(las.gps_time)
            assert 450_000_000.0 <= t.min() and t.max() <= 450_000_000.0 + 0.4 + 1e-6
            assert set(np.unique(las.classification)) <= {2, 6, 11}
            assert np.asarray(las.point_source_id).max() == 1
    xyz, tiles = read_model(tmp_path, "exact")
    error = np.concatenate([np.asarray(t["position_error"]) for t in tiles])
    assert error.max() < 0.002  # exact model: numerical noise only
    assert summary["beams_fired"] == 9 * summary["pulses"]
    assert summary["beams_fired"] == summary["points"]["exact"] + summary["tir_dropped"] + summary["misses"]
    stages = summary["stages_s"]
    assert tuple(stages) == STAGES and min(stages.values()) >= 0.0
    assert stages["trace"] >= summary["wall_s"] - 1e-3  # the traced chunks lie within the trace stage


def test_run_toml_reproduces_the_run(tmp_path):
    cfg = config(flight__duration_s=0.2, fan__array=4)
    first = simulate_to_directory(cfg, tmp_path / "a")
    again = validate(load_toml(tmp_path / "a" / "run.toml"))
    assert config_dict(again) == config_dict(cfg)
    second = simulate_to_directory(again, tmp_path / "b")
    assert first["points"] == second["points"] and first["rms_m"] == second["rms_m"]
    for name in first["tiles"]["nominal"]:
        assert (tmp_path / "a/nominal" / name).read_bytes() == (tmp_path / "b/nominal" / name).read_bytes()


def test_total_internal_reflection_is_counted_and_never_emits_nan(tmp_path):
    # the apex is 1° short of the critical angle: the wide fan's far side reflects internally
    apex = math.degrees(math.asin(1 / 1.5066)) - 1.0
    cfg = config(scene__name="plane", flight__duration_s=0.1, fan__array=9, fan__spacing_mrad=30.0,
                 risley__apex_angle_deg=apex, flight__altitude_m=300.0)
    summary = simulate_to_directory(cfg, tmp_path)
    assert 0 < summary["tir_dropped"] < summary["beams_fired"]
    xyz, _ = read_model(tmp_path, "nominal")
    assert np.isfinite(xyz).all() and len(xyz) == summary["points"]["nominal"]
    assert summary["beams_fired"] == summary["points"]["nominal"] + summary["tir_dropped"] + summary["misses"]


def test_beams_that_miss_a_small_mesh_are_counted(tmp_path):
    mesh = tmp_path / "strip.obj"  # a 200 m wide strip under the line: the 134 m scan circle overhangs it
    mesh.write_text("v -100 -300 0\nv 100 -300 0\nv 100 300 0\nv -100 300 0\ng ground\nf 1 2 3 4\n")
    cfg = config(scene__name=str(mesh), flight__duration_s=0.2)
    summary = simulate_to_directory(cfg, tmp_path / "out")
    assert summary["misses"] > 0 and summary["points"]["exact"] > 0
    assert summary["beams_fired"] == summary["points"]["exact"] + summary["misses"]
    summary_file = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary_file["misses"] == summary["misses"]


def test_edge_distances_equal_a_brute_force_over_every_boundary_segment():
    """The kernels' capped distance to the nearest plane boundary (edge grid + listed segments) against
    an exhaustive float64 search over every boundary segment of the calibration field."""
    from flightsim.studies.bench_common import simulator, workload
    from flightsim.scenes.edges import boundary_segments

    sim = simulator(workload("cpu", 3, 6e4), with_truth=True)
    cap = sim.edge_buffer_m
    chunks = []
    sim.run(Points(), chunks.append)
    got = np.concatenate([c.edge_distance_m for c in chunks]).astype(np.float64)
    points = np.concatenate([c.true_points for c in chunks])
    segments = boundary_segments(sim.scene)
    a, ab = segments[:, 0], segments[:, 1] - segments[:, 0]
    want = np.empty(len(points))
    for start in range(0, len(points), 2000):
        p = points[start:start + 2000, None, :]
        u = np.clip(np.einsum("psk,sk->ps", p - a, ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
        want[start:start + 2000] = np.linalg.norm(p - (a + u[..., None] * ab), axis=2).min(axis=1)
    want = np.minimum(want, cap)
    assert 0.005 < np.mean(want < cap) < 0.5  # the run has points on both sides of the cap
    assert np.abs(got - want).max() < 1e-4  # float32 points and segments, coordinates of a few hundred m
    assert 0.0 < sim.scan.edge_grid.near.numpy().mean() < 0.2  # most of the field skips the query


def test_fallback_boxes_are_the_triangle_bounds_padded_by_the_used_corners_extent():
    """The fallback BVH's boxes: each triangle's bounds widened by 1e-6·(1 + the largest |coordinate| of a
    corner some triangle uses), an unused far vertex left out, computed here in numpy."""
    import dataclasses

    from flightsim.engine.meshes import SceneMeshes
    from flightsim.scenes.calibration import calibration_scene
    from flightsim.scenes.scene import DEFAULT_CRS

    scene = calibration_scene(300.0, np.array([409000.0, 3393000.0, 450.0]), DEFAULT_CRS)
    scene = dataclasses.replace(scene, vertices=np.vstack([scene.vertices, [[1e5, -2e5, 3e4]]]))
    meshes = SceneMeshes(scene, "cpu")
    corners = scene.vertices.astype(np.float32)[scene.triangles]
    pad = np.float32(1e-6 * (1.0 + np.abs(corners).max()))
    assert 1e-4 < pad < 1e-3  # the far vertex would make it 2e-1
    assert np.array_equal(meshes._padded_boxes[0].numpy(), corners.min(axis=1) - pad)
    assert np.array_equal(meshes._padded_boxes[1].numpy(), corners.max(axis=1) + pad)


@pytest.mark.parametrize("block", [32, 4])
def test_replica_totals_add_every_copy_of_the_sums_in_float64(block):
    import warp as wp

    from flightsim.scoring.reduction import replica_totals
    from kernels.statistics import vec6d

    rng = np.random.default_rng(3)
    replicas, models, groups = 9, 2, 5
    counts = rng.integers(0, 1 << 40, (replicas, models, groups))
    first = rng.normal(0.0, 1e3, (replicas, models, groups, 3))
    second = rng.normal(0.0, 1e6, (replicas, models, groups, 6))
    sums = [wp.array(counts, dtype=wp.int64, device="cpu"), wp.array(first, dtype=wp.vec3d, device="cpu"),
            wp.array(second, dtype=vec6d, device="cpu")]
    count, s, ss = replica_totals(sums, block)
    expected_s, expected_ss = np.zeros((models, groups, 3)), np.zeros((models, groups, 6))
    for lo in range(0, replicas, block):  # each block of replicas in order from its first, then the blocks in order
        block_s, block_ss = np.zeros((models, groups, 3)), np.zeros((models, groups, 6))
        for r in range(lo, min(lo + block, replicas)):
            block_s = block_s + first[r]
            block_ss = block_ss + second[r]
        expected_s, expected_ss = expected_s + block_s, expected_ss + block_ss
    assert np.array_equal(count, counts.sum(axis=0))
    assert np.array_equal(s, expected_s) and np.array_equal(ss, expected_ss)
