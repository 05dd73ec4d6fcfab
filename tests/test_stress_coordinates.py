"""Large coordinates and late times: real UTM eastings and far-north northings, GPS times of 1e9 s
and hour-long flights lose nothing to float32 (SPEC §2, §4).

Every point is checked against an independent float64 model: from each return's pulse index and
beam, the trajectory, the SPEC's rotations, the prism angle in exact rational arithmetic and the
float64 NumPy optics of ``reference_optics`` give where the beam meets the ground; the
simulator's point (before the LAS 1 mm grid) may differ from it by at most 1 mm.
"""
import math
from fractions import Fraction

import laspy
import numpy as np
import pytest
import warp as wp

import reference_optics as ref
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.run import simulate_to_directory
from flightsim.engine.tracer import Tracer
from flightsim.engine.readouts.points import Points
from kernels import frames
from trajectories import PulseTiming
from trajectories.attitude import rotation_body_to_enu

MM = 1e-3
ZONES = {  # CRS, world origin of the scene [m]
    "utm48n": ("EPSG:32648", (409000.0, 3393000.0, 450.0)),
    "utm33n_far_north": ("EPSG:32633", (500000.0, 7000000.0, 120.0)),
}


def config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in settings.items():
        set_value(cfg, key.replace("__", "."), value)
    return validate(cfg)


def read_points(directory, model="exact") -> dict[str, np.ndarray]:
    """Every point of a model's tiles: xyz (world, float64) and the position_error extra."""
    tiles = [laspy.read(f) for f in sorted((directory / model).glob("*.las"))]
    cat = lambda get: np.concatenate([get(t) for t in tiles])  # noqa: E731
    return {
        "xyz": cat(lambda t: np.column_stack([t.x, t.y, t.z])),
        "position_error": cat(lambda t: np.asarray(t["position_error"])).astype(np.float64),
    }


def exact_phase(cfg: RunConfig, t0: float, k: int) -> float:
    """Prism angle of pulse k, φ0 + 2π·f_rot·(t0 + k/PRF) [rad] in [0, 2π), the turns in exact arithmetic.

    (From the pulse index, not the float64 pulse time: at 4.5e8 s that time is rounded to 6e-8 s,
    which at 20 Hz is 7.5e-6 rad, 1 cm on a 1.3 km scan circle.)
    """
    s = cfg.risley
    turns = Fraction(s.rotation_hz) * (Fraction(t0) + Fraction(k) / Fraction(s.prf_hz))
    return 2 * math.pi * ((float(turns - math.floor(turns)) + math.radians(s.phase0_deg) / (2 * math.pi)) % 1.0)


def reference_ground_points(cfg: RunConfig, trajectory, pulse: np.ndarray, beam: np.ndarray,
                            ground_height: float) -> np.ndarray:
    """Float64 world position where beam ``beam`` (i·n + j) of pulse ``pulse`` meets the horizontal ground [m]."""
    s, fan, f = cfg.risley, cfg.fan, cfg.flight
    rotation = rotation_body_to_enu(*np.radians([f.roll_deg, f.pitch_deg, f.heading_deg]))
    t0 = trajectory.start_time
    position, _ = trajectory.interpolate(t0 + pulse / s.prf_hz)
    s1_all = ref.fan_directions(fan.array, fan.spacing_mrad * 1e-3)
    apex = math.radians(s.apex_angle_deg)
    out = np.empty((len(pulse), 3))
    for k in range(len(pulse)):
        phi = exact_phase(cfg, t0, int(pulse[k]))
        s3, exit_point, tir = ref.prism_exit(s1_all[beam[k]][None], phi, s.refractive_index, apex,
                                             s.thickness_mm * 1e-3)
        assert not tir.any()
        start = position[k] + rotation @ exit_point[0]
        direction = rotation @ s3[0]
        out[k] = start + (ground_height - start[2]) / direction[2] * direction
    return out


@pytest.mark.parametrize("zone", sorted(ZONES))
@pytest.mark.parametrize("altitude", [500.0, 5000.0])
def test_exact_model_is_flat_and_every_point_within_a_millimetre_of_float64(tmp_path, zone, altitude):
    crs, origin = ZONES[zone]
    cfg = config(scene__name="plane", scene__crs=crs, scene__origin=list(origin), flight__altitude_m=altitude,
                 flight__duration_s=0.1, flight__heading_deg=30.0, flight__roll_deg=2.0, flight__pitch_deg=-1.5,
                 risley__phase0_deg=17.0, output__models="exact", output__position_error=True)
    # the LAS tiles: world coordinates on the 1 mm grid
    summary = simulate_to_directory(cfg, tmp_path)
    points = read_points(tmp_path)
    xyz = points["xyz"]
    assert len(xyz) == summary["points"]["exact"] == 9 * summary["pulses"] > 4000
    assert np.abs(xyz[:, :2] - origin[:2]).max() < 2000.0  # the points really carry the big coordinates
    assert np.abs(xyz[:, 2] - origin[2]).max() <= 2 * MM  # flat: the ground is at the origin's height
    centred = xyz - xyz.mean(axis=0)
    assert math.sqrt(np.linalg.eigvalsh(centred.T @ centred / len(xyz))[0]) < 2 * MM
    assert points["position_error"].max() <= MM
    # the same run's points before the 1 mm grid, each against the float64 model
    scene = build_scene(cfg)
    (trajectory,) = flight_trajectories(cfg, scene)
    chunks = []
    Tracer(cfg, scene, [trajectory]).run(Points(), chunks.append)
    pulse = np.concatenate([c.pulse for c in chunks])
    beam = np.concatenate([c.beam for c in chunks])
    world = scene.local_to_world(np.concatenate([c.points["exact"] for c in chunks]))
    expected = reference_ground_points(cfg, trajectory, pulse, beam, origin[2])
    assert len(world) == len(xyz)
    assert np.linalg.norm(world - expected, axis=1).max() <= MM


def las_fields(directory, model):
    """Per point, sorted by (gps_time, beam): xyz integers, the extra bytes and gps_time."""
    tiles = [laspy.read(f) for f in sorted((directory / model).glob("*.las"))]
    las = {name: np.concatenate([np.asarray(t[name]) for t in tiles])
           for name in ("X", "Y", "Z", "gps_time", "beam_row", "beam_col", "prism_angle", "range", "plane_id",
                        "intensity", "scan_angle", "classification")}
    offsets = np.concatenate([np.repeat(t.header.offsets[None], len(t.points), axis=0) for t in tiles])
    las["xyz_mm"] = np.rint(offsets * 1000).astype(np.int64) + np.column_stack([las["X"], las["Y"], las["Z"]])
    order = np.lexsort((las["beam_col"], las["beam_row"], las["gps_time"]))
    return {k: v[order] for k, v in las.items()}


@pytest.mark.parametrize("early, late", [(0.0, 450_000_000.0), (0.25, 1_000_000_000.25)])
def test_late_gps_time_gives_the_same_points_as_an_early_one_whole_turns_apart(tmp_path, early, late):
    """20 Hz × (late − early) is a whole number of turns: the same prism angles, so the same points."""
    assert (Fraction(late) - Fraction(early)) * 20 % 1 == 0
    runs = {}
    for name, start in (("early", early), ("late", late)):
        cfg = config(flight__start_gps_time=start, flight__duration_s=0.3, risley__phase0_deg=41.0,
                     instrument__errors="ranging", ranging__noise_m=0.02, run__seed=3)
        simulate_to_directory(cfg, tmp_path / name)
        runs[name] = {m: las_fields(tmp_path / name, m) for m in ("exact", "nominal")}
    for model in ("exact", "nominal"):
        a, b = runs["early"][model], runs["late"][model]
        assert len(a["gps_time"]) == len(b["gps_time"]) > 10000
        for name in a:
            if name not in ("gps_time", "X", "Y", "Z"):
                assert np.array_equal(a[name], b[name]), name
        offset = b["gps_time"] - a["gps_time"]
        assert np.abs(offset - (late - early)).max() <= np.spacing(late)  # float64 rounding of the late times


def test_device_prism_phase_stays_exact_at_the_end_of_an_hour(device):
    """kernels.frames.pulse_poses at pulse indices near 1 h after a late GPS start, against exact
    rational arithmetic: float64 phase within 1e-9 rad, the float32 angle only rounded."""
    prf, f_rot, phase0 = 5000.0, 20.0, math.radians(33.3)
    timing = PulseTiming(prf_hz=prf, rotation_hz=f_rot, phase0_rad=phase0)
    t0 = 1_234_567_890.123  # adjusted standard GPS time of the line's first pulse [s]
    hour = int(3600 * prf)
    first = hour - 4095
    d = device
    lines = frames.Lines()
    lines.times = wp.array([0.0, 3601.0], dtype=wp.float64, device=d)
    lines.positions = wp.array(np.zeros((2, 3)), dtype=wp.vec3d, device=d)
    lines.attitudes = wp.array(np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)), dtype=wp.quatd, device=d)
    lines.sample_start = wp.array([0], dtype=wp.int32, device=d)
    lines.sample_count = wp.array([2], dtype=wp.int32, device=d)
    lines.cycles0 = wp.array([timing.phase_cycles_at(t0)], dtype=wp.float64, device=d)
    lines.seed = wp.array([0], dtype=wp.int32, device=d)
    lines.boresight = wp.quatd(0.0, 0.0, 0.0, 1.0)
    lines.lever_arm = wp.vec3d(0.0, 0.0, 0.0)
    lines.pulse_period = timing.pulse_period_s
    lines.cycles_per_pulse = timing.cycles_per_pulse
    segments = frames.Segments()  # one segment: pulses first … first + 4095 of line 0
    segments.pulse_start = wp.array([0, 4096], dtype=wp.int32, device=d)
    segments.line = wp.array([0, 0], dtype=wp.int32, device=d)
    segments.first_pulse = wp.array([first, first], dtype=wp.int64, device=d)
    table = wp.empty((frames.POSE_ROWS, 4096), dtype=wp.float64, device=d)
    wp.launch(frames.pulse_poses, 4096, inputs=[lines, segments, 1], outputs=[table], device=d)
    phi64 = table.numpy()[frames.ROW_PHI]
    k = first + np.arange(4096)
    # exact: φ0 + 2π·f_rot·(t0 + k/PRF), every product and sum in rationals, reduced mod 2π only at the end
    start = Fraction(f_rot) * Fraction(t0)
    step = Fraction(f_rot) / Fraction(prf)
    exact = np.array([float((start + int(i) * step) % 1) for i in k])
    exact = 2 * np.pi * ((exact + phase0 / (2 * np.pi)) % 1.0)
    wrap = lambda a: np.angle(np.exp(1j * a))  # noqa: E731
    assert np.abs(wrap(phi64 - exact)).max() < 1e-9
    phi32 = phi64.astype(np.float32).astype(np.float64)  # what the float32 kernels take
    rounding = np.spacing(np.float32(2 * np.pi)).astype(np.float64) / 2  # half an ulp of float32 near 2π
    assert np.abs(wrap(phi32 - exact)).max() <= rounding + 1e-9
    assert rounding < 1e-6
    # the test can fail: the naive float64 product 2π·f_rot·t misses by far more than a microradian
    naive = np.mod(phase0 + 2 * np.pi * f_rot * (t0 + k / prf), 2 * np.pi)
    assert np.abs(wrap(naive - exact)).max() > 1e-6
