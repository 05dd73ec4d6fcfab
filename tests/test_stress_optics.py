"""Grazing and critical rays: fans pushed past total internal reflection, wedges a hair short of
the critical angle, rays nearly parallel to a surface and beams that miss (SPEC §4, §5).

The reference is float64 NumPy (``reference_optics``) with the prism angle of each pulse from
exact rational arithmetic; the simulator must agree on which beams reflect internally, place the
beams that exit within a millimetre of where their float64 ray meets the surface, count every
other beam, and never let a NaN or an infinity reach an output.
"""
import math
from fractions import Fraction

import laspy
import numpy as np
import pytest

import reference_optics as ref
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.run import simulate_to_directory
from flightsim.engine.tracer import Tracer
from flightsim.engine.readouts.points import Points

MM = 1e-3
N_BK7 = 1.5066
CRITICAL_DEG = math.degrees(math.asin(1.0 / N_BK7))


def config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in {"scene.name": "plane", "output.models": "exact,nominal", **settings}.items():
        set_value(cfg, key.replace("__", "."), value)
    return validate(cfg)


def simulate(cfg: RunConfig):
    """(scene, trajectory, counts, returns) of a one-line run; returns concatenated over the chunks."""
    scene = build_scene(cfg)
    (trajectory,) = flight_trajectories(cfg, scene)
    chunks = []
    counts = Tracer(cfg, scene, [trajectory]).run(Points(), chunks.append)
    cat = lambda get: np.concatenate([get(c) for c in chunks])  # noqa: E731
    returns = {
        "pulse": cat(lambda c: c.pulse), "beam": cat(lambda c: c.beam), "range": cat(lambda c: c.range_m),
        "face": cat(lambda c: c.face), "scan_angle": cat(lambda c: c.scan_angle_deg),
        "cos_incidence": cat(lambda c: c.cos_incidence),
        **{model: cat(lambda c, m=model: c.points[m]) for model in cfg.output.models},
    }
    return scene, trajectory, counts, returns


def reference_rays(cfg: RunConfig, trajectory, scene, n_pulses: int):
    """Float64 local exit points and directions (pulses, beams, 3), and the TIR mask and its margin
    n·sin θ2' − 1 (pulses, beams), of the first ``n_pulses`` pulses along ``trajectory``."""
    s, fan = cfg.risley, cfg.fan
    t0 = trajectory.start_time
    position, rotation = trajectory.interpolate(t0 + np.arange(n_pulses) / s.prf_hz)
    origin = scene.world_to_local(position)
    s1 = ref.fan_directions(fan.array, fan.spacing_mrad * 1e-3)
    s2, _ = ref.refract_tangential(s1, np.array([0.0, 0.0, 1.0]), 1.0, s.refractive_index)
    apex = math.radians(s.apex_angle_deg)
    step = Fraction(s.rotation_hz) / Fraction(s.prf_hz)
    turns0 = Fraction(s.rotation_hz) * Fraction(t0)
    starts, directions, tir, margin = [], [], [], []
    for k in range(n_pulses):
        turns = turns0 + k * step
        phi = 2 * math.pi * ((float(turns - math.floor(turns)) + math.radians(s.phase0_deg) / (2 * math.pi)) % 1.0)
        s3, exit_point, reflected = ref.prism_exit(s1, phi, s.refractive_index, apex, s.thickness_mm * 1e-3)
        starts.append(origin[k] + exit_point @ rotation[k].T)
        directions.append(s3 @ rotation[k].T)
        tir.append(reflected)
        margin.append(s.refractive_index * np.sin(ref.angle_between(s2, ref.back_normal(phi, apex))) - 1.0)
    return np.array(starts), np.array(directions), np.array(tir), np.array(margin)


def ground_hits(scene, starts, directions):
    """Where float64 rays meet the plane of the scene's plane 0 (local [m]), and the incidence cosine."""
    plane = scene.planes[0]
    along = directions @ plane.normal
    t = ((plane.point - starts) @ plane.normal) / along
    return starts + t[..., None] * directions, np.abs(along), t


def check_counts_and_finite(counts, returns, models):
    assert counts.beams_fired == counts.returns + counts.tir_dropped + counts.misses
    assert len(returns["pulse"]) == counts.returns
    for key, values in returns.items():
        assert np.isfinite(values).all(), key
    for model in models:
        assert np.isfinite(returns[model]).all()


@pytest.mark.parametrize("optics", ["float64", "float32"])
def test_fan_pushed_past_total_internal_reflection(optics):
    # 12×12 at 30 mrad through a wedge 1.5° short of the critical angle: about 40 % of the beams reflect
    cfg = config(fan__array=12, fan__spacing_mrad=30.0, risley__apex_angle_deg=CRITICAL_DEG - 1.5,
                 flight__altitude_m=300.0, flight__duration_s=0.03, run__optics=optics)
    scene, trajectory, counts, returns = simulate(cfg)
    check_counts_and_finite(counts, returns, cfg.output.models)
    starts, directions, tir, margin = reference_rays(cfg, trajectory, scene, counts.pulses)
    assert 0.2 < tir.mean() < 0.8
    decided = np.abs(margin) > (1e-12 if optics == "float64" else 1e-5)
    assert decided.mean() > 0.99
    # the simulator drops exactly the beams float64 reflects (where float rounding can decide)
    returned = np.zeros_like(tir)
    returned[returns["pulse"], returns["beam"]] = True
    assert not np.any(returned & tir & decided)
    assert counts.misses == 0 and np.array_equal(~returned[decided], tir[decided])
    assert counts.tir_dropped == counts.beams_fired - counts.returns
    if optics == "float64":  # the beams that exit are placed where their exact ray meets the ground
        hits, _, _ = ground_hits(scene, starts[returns["pulse"], returns["beam"]],
                                 directions[returns["pulse"], returns["beam"]])
        assert np.linalg.norm(returns["exact"] - hits, axis=1).max() <= MM


def test_wedge_a_hundredth_of_a_degree_short_of_the_critical_angle(tmp_path):
    # the on-axis beam leaves Σ2 within 0.2° of grazing; the small fan's outer beams reflect
    cfg = config(fan__array=3, fan__spacing_mrad=0.2, risley__apex_angle_deg=CRITICAL_DEG - 0.01,
                 flight__altitude_m=200.0, flight__duration_s=0.05, output__position_error=True)
    assert cfg.risley.cone_half_angle_deg > 45.0
    summary = simulate_to_directory(cfg, tmp_path)
    scene, trajectory, counts, returns = simulate(cfg)
    check_counts_and_finite(counts, returns, cfg.output.models)
    assert summary["tir_dropped"] == counts.tir_dropped > 0 and summary["points"]["exact"] == counts.returns > 0
    starts, directions, tir, _ = reference_rays(cfg, trajectory, scene, counts.pulses)
    assert counts.tir_dropped == tir.sum()
    hits, _, _ = ground_hits(scene, starts[returns["pulse"], returns["beam"]],
                             directions[returns["pulse"], returns["beam"]])
    assert np.linalg.norm(returns["exact"] - hits, axis=1).max() <= MM
    for model in ("exact", "nominal"):
        for tile in (tmp_path / model).glob("*.las"):
            las = laspy.read(tile)
            for name in ("x", "y", "z", "gps_time", "prism_angle", "range", "position_error"):
                assert np.isfinite(np.asarray(las[name], dtype=np.float64)).all(), name


@pytest.mark.parametrize("optics", ["float64", "float32"])
def test_rays_parallel_and_nearly_parallel_to_a_steep_slope(optics):
    # cone tan θ = 0.5 over a plane of slope 2 descending north: the beam that points north runs
    # exactly parallel to the ground (ray–plane denominator 0); its neighbours graze it far away
    cone = math.degrees(math.atan(0.5))
    cfg = config(scene__slope=2.0, scene__margin_m=8000.0, risley__cone_half_angle_deg=cone, fan__array=5,
                 flight__duration_s=0.2, run__optics=optics)
    scene, trajectory, counts, returns = simulate(cfg)
    check_counts_and_finite(counts, returns, cfg.output.models)
    assert counts.tir_dropped == 0 and counts.misses > 0  # beams at or above the slope never meet it
    plane = scene.planes[0]
    off_plane = np.abs((returns["exact"] - plane.point) @ plane.normal)  # every exact return lies on the slope ...
    assert off_plane.max() <= (MM if optics == "float64" else 5 * MM)
    starts, directions, _, _ = reference_rays(cfg, trajectory, scene, counts.pulses)
    hits, cos_incidence, t = ground_hits(scene, starts, directions)
    beyond = (t <= 0) | np.any(np.abs(hits[..., :2]) > scene.bounds()[1][0], axis=-1)
    assert counts.misses == beyond.sum()  # ... and the beams that miss are exactly those that run past it
    assert cos_incidence[~beyond].min() < 0.02  # some hit at less than 1.2° grazing
    returned = returns["pulse"], returns["beam"]
    assert np.allclose(returns["cos_incidence"], cos_incidence[returned], atol=1e-4)
    if optics == "float64":  # to the float32 storage of kilometre-scale local coordinates
        error = np.linalg.norm(returns["exact"] - hits[returned], axis=1)
        assert np.all(error <= MM + 2.0**-22 * np.abs(hits[returned]).max(axis=1))


def test_beams_that_never_reach_the_scene_are_counted_not_written(tmp_path):
    mesh = tmp_path / "far.obj"  # a pad 5 km east and a marker triangle at 0: the line flies over the gap
    mesh.write_text("v 5000 -30 0\nv 5060 -30 0\nv 5060 30 0\nv 5000 30 0\nv -5 -5 -100\nv 5 -5 -100\nv 0 5 -100\n"
                    "g ground\nf 1 2 3 4\ng deep\nf 5 6 7\n")
    for cull in (True, False):
        cfg = config(scene__name=str(mesh), flight__duration_s=0.1, run__cull=cull)
        summary = simulate_to_directory(cfg, tmp_path / f"cull_{cull}")
        assert summary["points"] == {"exact": 0, "nominal": 0}
        assert summary["beams_fired"] == summary["misses"] + summary["tir_dropped"]
        assert summary["pulses"] + summary.get("pulses_culled", 0) == 501
        assert summary["rms_m"] == {"exact": None, "nominal": None}
        assert not list((tmp_path / f"cull_{cull}").rglob("*.las"))
