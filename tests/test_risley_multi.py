"""The two- and three-prism Risley deflector (risley_n) on the device: rays against an independent float64 vector
refraction (Snell's law in tangential form, the scan phase in exact rational arithmetic), the thin-prism closed forms
of the Risley pair's patterns, the exact reduction to the single wedge, the sweep and simulate commands, bad input."""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest
import warp as wp

import flightsim
from flightsim.core.errors import InputError
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.instrument import risley_multi_model as model
from kernels import trace
from kernels.frames import ROW_ORIGIN, ROW_PHI, ROW_PULSE, ROW_ROT

FLOAT32_RAD = 5e-7  # the float32 production path: direction error bound [rad] (measured ~1e-8 on the CPU)
FLOAT64_RAD = 1e-12  # the float64 device optics [rad]
START_GPS = 450_000_000.123  # a line start whose rate × time is no whole number of turns


def _config(device: str, **overrides):
    base = {"instrument.deflector": "risley_n", "output.models": ["exact"], "scene.name": "plane",
            "flight.platform": "hover", "flight.altitude_m": 100.0, "flight.start_gps_time": START_GPS,
            "run.device": device}
    return flightsim.load_config(overrides={**base, **overrides})


# ---------------------------------------------------------------------------------------------
# an independent float64 model: the geometry of kernels/wedges.py's docstring, written again


def _snell(s: np.ndarray, n: np.ndarray, mu: float) -> np.ndarray:
    """Refraction with the tangential component scaled by μ = n_in/n_out and the normal one restoring unit length
    (n along propagation); NaN where it reflects totally."""
    tangential = mu * (s - np.sum(s * n, axis=-1, keepdims=True) * n)
    return tangential + np.sqrt(1.0 - np.sum(tangential * tangential, axis=-1, keepdims=True)) * n


def _meet(point, direction, plane_point, normal):
    """Where the ray point + t·direction meets the plane through plane_point of the given normal."""
    t = np.sum((plane_point - point) * normal, axis=-1, keepdims=True) / np.sum(direction * normal, axis=-1,
                                                                                   keepdims=True)
    return point + t * direction


def _reference(s1, phis, n_glass, apex, thickness, gaps):
    """(exit directions, exit points [m]) of unit directions s1 (..., 3) at prism angles phis (..., prisms)."""
    z = np.array([0.0, 0.0, 1.0])
    point, s, front = np.zeros(3), s1, 0.0
    for i, (n, a, d) in enumerate(zip(n_glass, apex, thickness)):
        s = _snell(s, z, 1.0 / n)
        normal = np.stack([math.sin(a) * np.cos(phis[..., i]), math.sin(a) * np.sin(phis[..., i]),
                           np.full_like(phis[..., i], math.cos(a))], -1)
        point = _meet(point, s, np.array([0.0, 0.0, front + d]), normal)
        s = _snell(s, normal, n)
        if i + 1 < len(n_glass):
            front += d + gaps[i]
            point = _meet(point, s, np.array([0.0, 0.0, front]), z)
    return s, point


def _prism_angles(cfg, t0: float, k: np.ndarray) -> np.ndarray:
    """φ_i = φ0_i + 2π·frac(f_i·(t0 + k/PRF)), the products formed exactly: (pulses, prisms) [rad]."""
    r = cfg.risley_n
    out = np.empty((len(k), r.prisms))
    for i, (f, phase0) in enumerate(zip(r.rotation_hz, r.phase0_deg)):
        for j, kk in enumerate(k):
            turns = Fraction(f) * (Fraction(t0) + Fraction(int(kk)) / Fraction(r.prf_hz))
            out[j, i] = math.radians(phase0) + 2 * math.pi * float(turns - math.floor(turns))
    return out


def _stack_args(cfg):
    r = cfg.risley_n
    return (r.refractive_index, [math.radians(a) for a in r.apex_angle_deg], [d * 1e-3 for d in r.thickness_mm],
            [g * 1e-3 for g in r.gap_mm])


def _rays(cfg, pulses: int, precise: bool = True):
    """(tracer, table columns, starts, directions) of the first ``pulses`` pulses, from the device's emit_rays."""
    scene = build_scene(cfg)
    tracer = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    table, n = tracer.first_chunk(pulses)
    vec = wp.vec3d if precise else wp.vec3f
    starts, directions = (wp.empty(n, dtype=vec, device=tracer.device) for _ in range(2))
    wp.launch(trace.emit_rays_kernel(tracer.instrument.kernel, precise=precise), n, inputs=[table, tracer.scan],
              outputs=[starts, directions], device=tracer.device)
    beams = tracer.beams_per_pulse
    shape = (n // beams, beams, 3)
    return (tracer, table.numpy()[:, : n // beams], starts.numpy().astype(np.float64).reshape(shape),
            directions.numpy().astype(np.float64).reshape(shape))


STACKS = {
    "two": {"risley_n.prisms": 2, "risley_n.rotation_hz": [37.5, -22.5], "risley_n.phase0_deg": [12.0, -40.0],
            "risley_n.apex_angle_deg": [14.0, 9.0], "risley_n.refractive_index": [1.5066, 1.72],
            "risley_n.thickness_mm": [8.0, 12.0], "risley_n.gap_mm": [4.0]},
    "three": {"risley_n.prisms": 3, "risley_n.rotation_hz": [37.5, -22.5, 7.5],
              "risley_n.phase0_deg": [12.0, -40.0, 100.0], "risley_n.apex_angle_deg": [8.0, 11.0, 6.0],
              "risley_n.refractive_index": [1.5066, 1.45, 1.8], "risley_n.thickness_mm": [8.0, 12.0, 5.0],
              "risley_n.gap_mm": [4.0, 6.0]},
}
FAN = {"fan.array": 3, "fan.spacing_mrad": 30.0, "risley_n.prf_hz": 433.0, "flight.duration_s": 0.3}


@pytest.mark.parametrize("name", list(STACKS))
def test_device_rays_match_float64_vector_refraction(device, name):
    cfg = _config(device, **FAN, **STACKS[name])
    tracer, t, starts, directions = _rays(cfg, 120)
    phis = _prism_angles(cfg, tracer.trajectories[0].start_time, t[ROW_PULSE])
    spread = np.ptp(np.mod(phis - phis[:, :1], 2 * np.pi), axis=0)
    assert len(t[ROW_PULSE]) == 120 and (spread[1:] > 5.0).all()  # relative angles all round the turn
    f_p = 7.5  # the scan phase turns at the rates' largest common divisor
    psi = [2 * math.pi * float((x := Fraction(f_p) * (Fraction(START_GPS) + Fraction(int(k)) / Fraction(433)))
                               - math.floor(x)) for k in t[ROW_PULSE]]
    assert np.allclose(t[ROW_PHI], psi, rtol=0, atol=1e-9)
    s3, exit_points = _reference(tracer.instrument.emitter.directions()[None], phis[:, None], *_stack_args(cfg))
    rot, origin = t[ROW_ROT:ROW_ROT + 9].T.reshape(-1, 3, 3), t[ROW_ORIGIN:ROW_ORIGIN + 3].T
    assert np.abs(directions - np.einsum("pij,pbj->pbi", rot, s3)).max() < FLOAT64_RAD
    assert np.abs(starts - origin[:, None] - np.einsum("pij,pbj->pbi", rot, exit_points)).max() < 1e-9
    assert np.abs(np.linalg.norm(exit_points[..., :2], axis=-1)).max() > 1e-3  # the exit points walk off the axis


def _simulated(cfg):
    """A run of ``cfg`` through the engine (float32 optics, ray cast, readout), every return kept with its true hit:
    (returns, (true hits, {model: points}) local [m], sensor origin [m] and R_local←sensor of each return, prism
    angles of each return, emitter beams)."""
    result = flightsim.simulate(cfg, with_truth=True)
    returns, scene = result.returns, result.scene
    assert result.stats["tir_dropped"] == result.stats["misses"] == 0 and len(returns.pulse) > 500
    tracer = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    line = tracer.trajectories[0]
    poses = tracer.poses64(line.line_id, 0, int(returns.pulse.max()) + 1).numpy()[returns.pulse]
    origin = np.asarray(poses["origin"], dtype=np.float64)
    rot = np.asarray(poses["rot"], dtype=np.float64).reshape(-1, 3, 3)
    phis = _prism_angles(cfg, line.start_time, returns.pulse)
    local = (scene.world_to_local(returns.true_points),
             {m: scene.world_to_local(p) for m, p in returns.points.items()})
    return returns, local, origin, rot, phis, tracer.instrument.emitter.directions()[returns.beam]


@pytest.mark.parametrize("name", list(STACKS))
def test_float32_production_path_points_along_the_float64_rays(device, name):
    """A run (float32 optics, the ray cast, the hit) against the reference ray: each true hit seen from the
    reference exit point lies along the reference direction."""
    cfg = _config(device, **FAN, **STACKS[name])
    _, (hits, _), origin, rot, phis, s1 = _simulated(cfg)
    s3, exit_points = _reference(s1, phis, *_stack_args(cfg))
    seen = hits - origin - np.einsum("pij,pj->pi", rot, exit_points)
    seen /= np.linalg.norm(seen, axis=-1, keepdims=True)
    error = np.linalg.norm(seen - np.einsum("pij,pj->pi", rot, s3), axis=-1)
    assert error.max() < FLOAT32_RAD, error.max()


def test_exact_model_georeferences_with_the_believed_prisms(device):
    """Truth with encoder zero errors, the processing believing other apexes, indices, thicknesses and gap: the true
    hit lies on the true ray, the exact model's point on the believed ray at the observed range."""
    errors = {"risley_n.encoder_arcsec": [0.0, 3600.0], "risley_n.believed_apex_angle_deg": [14.2, 8.9],
              "risley_n.believed_refractive_index": [1.51, 0.0], "risley_n.believed_thickness_mm": [8.5, 0.0],
              "risley_n.believed_gap_mm": [4.5]}
    cfg = _config(device, **FAN, **STACKS["two"], **errors)
    returns, (hits, points), origin, rot, phis, s1 = _simulated(cfg)
    true_s3, true_exit = _reference(s1, phis + np.radians([0.0, 1.0]), *_stack_args(cfg))
    r = cfg.risley_n
    believed = (r.believed_refractive_index, np.radians(r.believed_apex_angle_deg),
                np.array(r.believed_thickness_mm) * 1e-3, np.array(r.believed_gap_mm) * 1e-3)
    assert believed[0][1] == 1.72 and believed[2][1] == 12e-3  # 0 = the true value
    b_s3, b_exit = _reference(s1, phis, *believed)
    ranges = returns.range_m.astype(np.float64)[:, None]
    assert np.abs(hits - origin - np.einsum("pij,pj->pi", rot, true_exit + ranges * true_s3)).max() < 1e-4
    placed = origin + np.einsum("pij,pj->pi", rot, b_exit + ranges * b_s3)
    assert np.abs(points["exact"] - placed).max() < 1e-4 and np.abs(points["exact"] - hits).max() > 0.1


def _azimuths(device, apex, noise_arcsec):
    """Azimuth of the on-axis beam leaving the prisms [rad] over 2000 pulses: behind a plate (apex 0) a single wedge
    turns it to exactly its angle + 180°, so the difference between a noisy and a quiet run is that prism's noise."""
    cfg = _config(device, **{"fan.array": 1, "risley_n.prf_hz": 5000.0, "flight.duration_s": 0.5,
                             "risley_n.rotation_hz": [20.0, -13.0], "risley_n.apex_angle_deg": apex,
                             "risley_n.encoder_noise_arcsec": noise_arcsec, "run.seed": 11})
    _, t, _, directions = _rays(cfg, 2000)
    local = np.einsum("pji,pj->pi", t[ROW_ROT:ROW_ROT + 9].T.reshape(-1, 3, 3), directions[:, 0])
    return np.arctan2(local[:, 1], local[:, 0])


def test_encoder_noise_turns_each_prism_with_its_sigma_independently(device):
    sigma = 3600.0 * math.pi / (180.0 * 3600.0)  # 3600 arcsec [rad]
    noise = []
    for apex in ([10.0, 0.0], [0.0, 10.0]):
        diff = np.angle(np.exp(1j * (_azimuths(device, apex, 3600.0) - _azimuths(device, apex, 0.0))))
        assert abs(diff.mean()) < 4 * sigma / math.sqrt(len(diff)) and diff.std() == pytest.approx(sigma, rel=0.05)
        noise.append(diff)
    assert abs(np.corrcoef(noise[0], noise[1])[0, 1]) < 0.1  # the two prisms draw their own noise


def test_float64_model_module_matches_the_independent_reference():
    rng = np.random.default_rng(3)
    args = ([1.5066, 1.45, 1.8], [math.radians(a) for a in (8.0, 11.0, 6.0)], [8e-3, 12e-3, 5e-3], [4e-3, 6e-3])
    s1 = rng.normal(size=(50, 3)) * [0.03, 0.03, 0.0] + [0, 0, 1]
    s1 /= np.linalg.norm(s1, axis=-1, keepdims=True)
    phis = rng.uniform(0, 2 * np.pi, size=(50, 3))
    run = model.trace(model.Stack(*args), s1, phis)
    s3, points = _reference(s1, phis, *args)
    assert run.ok.all() and np.abs(run.directions - s3).max() < 1e-14 and np.abs(run.exit_points - points).max() < 1e-15


# ---------------------------------------------------------------------------------------------
# the Risley pair's patterns: two identical thin prisms against the first-order closed forms

THIN = {"fan.array": 1, "risley_n.prf_hz": 3600.0, "flight.duration_s": 0.25, "risley_n.apex_angle_deg": [2.0],
        "risley_n.refractive_index": [1.5066], "risley_n.thickness_mm": [5.0], "risley_n.gap_mm": [3.0]}
DELTA = (1.5066 - 1.0) * math.radians(2.0)  # first-order deviation of each prism, δ = (n − 1)·α [rad]


def _pattern(device, rates, phases, pulses):
    """(kernel pointing, first-order pointing, float64 exact pointing, prism angles): the exit direction's x, y in
    the sensor frame [rad], the first order being −δ·Σ (cos φ_i, sin φ_i) (each thin prism turns the beam by δ
    towards its thin edge, opposite the back face's tilt)."""
    cfg = _config(device, **THIN, **{"risley_n.rotation_hz": rates, "risley_n.phase0_deg": phases})
    tracer, t, _, directions = _rays(cfg, pulses, precise=False)
    rot = t[ROW_ROT:ROW_ROT + 9].T.reshape(-1, 3, 3)
    kernel = np.einsum("pji,pj->pi", rot, directions[:, 0])[:, :2]
    phis = _prism_angles(cfg, tracer.trajectories[0].start_time, t[ROW_PULSE])
    first = -DELTA * np.stack([np.cos(phis).sum(-1), np.sin(phis).sum(-1)], -1)
    exact, _ = _reference(np.array([0.0, 0.0, 1.0]), phis, *_stack_args(cfg))
    return kernel, first, exact[:, :2], phis


def _second_order(kernel, first, exact):
    """The first-order model's error bounded by the float64 exact trace (it must be of order δ², far below 2δ);
    the kernel must lie within it of the closed form."""
    bound = np.linalg.norm(exact - first, axis=-1).max()
    assert bound < 2.0 * DELTA ** 2 < 0.04 * DELTA
    assert np.linalg.norm(kernel - first, axis=-1).max() <= bound + 1e-6
    return bound + 1e-6


def test_co_rotating_in_phase_draws_a_circle_of_twice_the_deviation(device):
    kernel, first, exact, phis = _pattern(device, [20.0, 20.0], [30.0, 30.0], 180)
    bound = _second_order(kernel, first, exact)
    r = np.linalg.norm(kernel, axis=-1)
    assert np.abs(r - 2 * DELTA).max() <= bound
    azimuth = np.unwrap(np.arctan2(kernel[:, 1], kernel[:, 0]))  # turning with the prisms, π from their angle
    assert np.abs(azimuth - np.unwrap(phis[:, 0]) - np.pi - 2 * np.pi * np.round(
        (azimuth[0] - phis[0, 0] - np.pi) / (2 * np.pi))).max() < bound / DELTA


def test_co_rotating_in_anti_phase_stays_on_the_axis(device):
    kernel, first, exact, _ = _pattern(device, [20.0, 20.0], [30.0, 210.0], 180)
    bound = _second_order(kernel, first, exact)
    assert np.abs(first).max() < 1e-15 and np.linalg.norm(kernel, axis=-1).max() <= bound


def test_counter_rotating_at_equal_speeds_scans_a_line_four_deviations_long(device):
    kernel, first, exact, _ = _pattern(device, [20.0, -20.0], [90.0, 90.0], 180)
    bound = _second_order(kernel, first, exact)
    assert np.abs(kernel[:, 0]).max() <= bound  # the line lies along the sensor's y axis: (φ0_1 + φ0_2)/2 = 90°
    assert np.ptp(kernel[:, 1]) == pytest.approx(4 * DELTA, abs=2 * bound + 1e-5)


@pytest.mark.parametrize("rates, petals", [([20.0, -10.0], 3), ([30.0, 10.0], 2), ([25.0, -15.0], 8)])
def test_speed_ratio_draws_a_rose_with_the_ratio_s_petals(device, rates, petals):
    """r(t) = 2δ|cos((ω1 − ω2)t/2 + (φ0_1 − φ0_2)/2)|, closed after 1/f_p with |f1 − f2|/f_p petal tips."""
    f_p = math.gcd(*(int(f) for f in rates))
    period = int(3600 / f_p)
    kernel, first, exact, phis = _pattern(device, rates, [0.0, 50.0], period)
    bound = _second_order(kernel, first, exact)
    r = np.linalg.norm(kernel, axis=-1)
    closed = 2 * DELTA * np.abs(np.cos((phis[:, 0] - phis[:, 1]) / 2))
    assert np.abs(r - closed).max() <= bound
    tips = (r > np.roll(r, 1)) & (r >= np.roll(r, -1)) & (r > 1.5 * DELTA)
    assert tips.sum() == petals == abs(rates[0] - rates[1]) / f_p


# ---------------------------------------------------------------------------------------------
# exact reduction to the single wedge


def test_a_flat_second_prism_leaves_the_single_wedge_s_rays_shifted_by_the_plate(device):
    """Prism 2 with apex 0 is a plate: every ray of the single ``risley`` wedge (same pulses) keeps its direction and
    moves along it across the gap, then sideways through the plate as Snell's law says."""
    common = {"fan.array": 3, "fan.spacing_mrad": 30.0, "flight.duration_s": 0.3}
    single = flightsim.load_config(overrides={
        "output.models": ["exact"], "scene.name": "plane", "flight.platform": "hover", "flight.altitude_m": 100.0,
        "flight.start_gps_time": START_GPS, "run.device": device, "risley.prf_hz": 433.0, "risley.rotation_hz": 20.0,
        "risley.phase0_deg": 25.0, "risley.apex_angle_deg": 12.0, "risley.refractive_index": 1.5066,
        "risley.thickness_mm": 10.0, **common})
    double = _config(device, **common, **{
        "risley_n.prf_hz": 433.0, "risley_n.rotation_hz": [20.0, -60.0], "risley_n.phase0_deg": [25.0, 70.0],
        "risley_n.apex_angle_deg": [12.0, 0.0], "risley_n.refractive_index": [1.5066, 1.72],
        "risley_n.thickness_mm": [10.0, 7.0], "risley_n.gap_mm": [3.0]})
    _, t1, starts1, dirs1 = _rays(single, 80)
    _, t2, starts2, dirs2 = _rays(double, 80)
    assert np.array_equal(t1[:ROW_PHI], t2[:ROW_PHI]) and np.ptp(t1[ROW_PHI]) > 5.0  # the same poses
    assert np.abs(dirs2 - dirs1).max() < 1e-14
    rot, origin = t1[ROW_ROT:ROW_ROT + 9].T.reshape(-1, 3, 3), t1[ROW_ORIGIN:ROW_ORIGIN + 3].T
    exit1 = np.einsum("pji,pbj->pbi", rot, starts1 - origin[:, None])
    s3 = np.einsum("pji,pbj->pbi", rot, dirs1)
    z = np.array([0.0, 0.0, 1.0])
    front = _meet(exit1, s3, np.array([0.0, 0.0, 13e-3]), z)
    inside = _snell(s3, z, 1.0 / 1.72)
    back = _meet(front, inside, np.array([0.0, 0.0, 20e-3]), z)
    exit2 = np.einsum("pji,pbj->pbi", rot, starts2 - origin[:, None])
    assert np.abs(exit2 - back).max() < 1e-12
    shift = np.linalg.norm(np.cross(back - exit1, s3), axis=-1)  # the plate's sideways shift of the ray
    assert shift.max() > 1e-4


# ---------------------------------------------------------------------------------------------
# the commands


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "flightsim", *args], capture_output=True, text=True, timeout=600,
                          cwd=cwd)


def test_sweep_over_the_calibration_field_scores_the_prism_pair(tmp_path):
    run = _cli("sweep", "--set", "instrument.deflector=risley_n", "--set", "risley_n.rotation_hz=20,-13",
               "--altitudes", "500", "--duration", "0.4", "--out", str(tmp_path))
    assert run.returncode == 0, run.stderr
    with open(tmp_path / "sweep.csv", newline="") as fh:
        rows = {r["model"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {"exact", "nominal"}
    for row in rows.values():
        assert int(row["points"]) > 1000 and math.isfinite(float(row["rms_m"]))
    assert float(rows["exact"]["rms_m"]) < 1e-3 < float(rows["nominal"]["rms_m"])  # the fan's distortion
    base = json.loads((tmp_path / "sweep.json").read_text())["base"]
    assert base["instrument"]["deflector"] == "risley_n" and base["risley_n"]["rotation_hz"] == [20.0, -13.0]


def test_simulate_with_three_prisms_writes_las(tmp_path):
    import laspy

    run = _cli("simulate", "--set", "instrument.deflector=risley_n", "--set", "risley_n.prisms=3",
               "--set", "risley_n.rotation_hz=20,-20,7.5", "--duration", "0.3", "--out", str(tmp_path))
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    for name in ("exact", "nominal"):
        tiles = sorted((tmp_path / name).glob("*.las"))
        assert tiles and sum(laspy.read(p).header.point_count for p in tiles) == summary["points"][name] > 0
    assert "rotation_hz = [20.0, -20.0, 7.5]" in (tmp_path / "run.toml").read_text()


# ---------------------------------------------------------------------------------------------
# bad input


BAD = [
    ({"risley_n.prisms": 1}, "risley_n.prisms"),
    ({"risley_n.prisms": 4}, "risley_n.prisms"),
    ({"risley_n.prisms": 3}, "risley_n.rotation_hz"),  # two rates for three prisms
    ({"risley_n.gap_mm": [5.0, 5.0]}, "risley_n.gap_mm"),  # two gaps for one pair
    ({"risley_n.rotation_hz": [0.0, 0.0]}, "risley_n.rotation_hz"),  # nothing turns
    ({"risley_n.rotation_hz": [20.0, 6.666666667]}, "risley_n.rotation_hz"),  # no common period within MAX_TURNS
    ({"risley_n.rotation_hz": [999.999, 0.001]}, "risley_n.rotation_hz"),  # 999999 turns per pattern
    ({"risley_n.apex_angle_deg": [45.0]}, "risley_n.apex_angle_deg"),  # beyond the critical angle, 41.6°
    ({"risley_n.apex_angle_deg": [30.0]}, "risley_n.apex_angle_deg"),  # each passes alone, together they reflect
    ({"risley_n.refractive_index": [5.0]}, "risley_n.refractive_index"),
    ({"risley_n.thickness_mm": [0.0]}, "risley_n.thickness_mm"),
    ({"risley_n.prisms": 3, "risley_n.rotation_hz": [20.0, -20.0, 5.0], "risley_n.apex_angle_deg": [20.0],
      "risley_n.gap_mm": [0.0]}, "risley_n.gap_mm"),  # the second back face reaches past the third front face
    ({"risley_n.believed_refractive_index": [0.5]}, "risley_n.believed_refractive_index"),
    ({"risley_n.believed_apex_angle_deg": [60.0]}, "risley_n.believed_apex_angle_deg"),
    ({"risley_n.believed_gap_mm": [1.0, 1.0]}, "risley_n.believed_gap_mm"),
    ({"run.optics": "lut"}, "run.optics"),
]


@pytest.mark.parametrize("overrides, field", BAD, ids=[f"{f}-{i}" for i, (_, f) in enumerate(BAD)])
def test_bad_input_is_refused_naming_the_field(overrides, field):
    with pytest.raises(InputError, match=f"invalid {field} ="):
        flightsim.load_config(overrides={"instrument.deflector": "risley_n", **overrides})


def test_bad_input_exits_2_with_one_line(tmp_path):
    run = _cli("simulate", "--set", "instrument.deflector=risley_n", "--set", "risley_n.rotation_hz=0",
               "--out", str(tmp_path / "run"))
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "risley_n.rotation_hz" in run.stderr
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


def test_the_patterns_figure_regenerates(tmp_path):
    from flightsim.studies.risley_patterns import PATTERNS, SAMPLES, pattern_figure

    png, table = pattern_figure(tmp_path)
    assert png.stat().st_size > 10_000
    with open(table, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(PATTERNS) * (SAMPLES + 1)
    line = np.array([[float(r["x_exact_rad"]), float(r["y_exact_rad"])] for r in rows if r["panel"] == "1"])
    assert np.abs(line[:, 0]).max() < 0.01 * np.abs(line[:, 1]).max()  # the counter-rotating pair's line
