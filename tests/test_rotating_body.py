"""A spacecraft hovering over a spinning small body (flight.body_rotation_period_s), against independent
float64 geometry: the hover held in inertial space, rotated into the body frame by R_y(−ωt)."""
from __future__ import annotations

import math

import numpy as np
import pytest

import flightsim
from flightsim.cli import main
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.config_io import load_toml, to_toml
from flightsim.core.errors import InputError
from flightsim.engine.tracer import Tracer
from flightsim.platforms import rotating_body
from flightsim.engine.world import build_scene, flight_trajectories

A, C = 250.0, 120.2  # the ellipsoid scene's semi-axes along local x and y, z [m]
PERIOD = 60.0  # the fastest spin allowed [s]: the hardest case for the sampling
ALTITUDE = 200.0  # above the north pole [m]: clear of the a-axis ends sweeping 250 m from the axis
OMEGA = 2.0 * math.pi / PERIOD


def _config(**fields) -> RunConfig:
    """A staring single beam hovering over the ellipsoid scene for a quarter turn and a bit."""
    cfg = RunConfig()
    cfg.scene.name = "ellipsoid"
    cfg.flight.platform = "hover"
    cfg.flight.altitude_m = ALTITUDE
    cfg.flight.duration_s = 16.0
    cfg.flight.body_rotation_period_s = PERIOD
    cfg.instrument.deflector = "fixed"
    cfg.fan.array = 1
    cfg.fixed.prf_hz = 7.0  # not a multiple of the sample rate: pulses fall between samples
    cfg.output.models = ("exact",)
    for key, value in fields.items():
        section, name = key.split("__")
        setattr(getattr(cfg, section), name, value)
    return validate(cfg)


def _spin(angle: float) -> np.ndarray:
    """R_y(angle), right-handed about +y (independent of the code under test)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _body_to_enu(roll: float, pitch: float, heading: float) -> np.ndarray:
    """R_body→ENU = M·Rz(heading)·Ry(pitch)·Rx(roll), body x forward, y right, z down (SPEC §2)."""
    cr, sr, cp, sp, ch, sh = (f(a) for a in (roll, pitch, heading) for f in (math.cos, math.sin))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[ch, -sh, 0], [sh, ch, 0], [0, 0, 1]])
    return np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]]) @ rz @ ry @ rx


def _hover_point(scene, cfg, t: float) -> np.ndarray:
    """Inertial (= body frame at t = 0) local position of the sensor t seconds in [m]."""
    lo, hi = scene.bounds()
    f = cfg.flight
    return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, scene.ground_z + f.altitude_m - f.descent_mps * t])


def _simulator(cfg):
    scene = build_scene(cfg)
    return scene, Tracer(cfg, scene, flight_trajectories(cfg, scene))


@pytest.mark.parametrize("fields", [{}, {"flight__descent_mps": 2.0},
                                    {"flight__heading_deg": 90.0, "flight__roll_deg": 3.0, "flight__pitch_deg": -2.0}])
def test_device_poses_follow_the_rotated_hover(fields):
    """Every pulse's sensor origin from the simulator's own pose kernel is R_y(−ωt)·p(t) within 1 mm;
    its attitude is R_y(−ωt)·R₀ (heading 90°: the body x axis passes the vertical)."""
    cfg = _config(**{"fixed__prf_hz": 50.0, **fields})
    scene, sim = _simulator(cfg)
    count = int(cfg.flight.duration_s * cfg.fixed.prf_hz)
    poses = sim.poses64(1, 0, count).numpy()
    f = cfg.flight
    r0 = _body_to_enu(*np.radians([f.roll_deg, f.pitch_deg, f.heading_deg]))
    for k in range(count):
        t = k / cfg.fixed.prf_hz
        spin = _spin(-OMEGA * t)
        origin = np.asarray(poses[k]["origin"], dtype=np.float64)
        assert np.linalg.norm(origin - spin @ _hover_point(scene, cfg, t)) <= 1e-3, t
        rot = np.asarray(poses[k]["rot"], dtype=np.float64).reshape(3, 3)
        assert np.abs(rot - spin @ r0).max() < 1e-9, t


def test_level_boresight_points_at_the_body_centre():
    """The level sensor's axis (body z) points from the hover through the body's centre plane: at
    R_y(−ωt)·(x₀, y₀, 0), the spin axis' point beneath the hover (x₀, y₀: the scene's bounds centre,
    0.3 m off the body centre for the rough ellipsoid), within 1e-6 rad, at every pulse."""
    cfg = _config(fixed__prf_hz=50.0)
    scene, sim = _simulator(cfg)
    poses = sim.poses64(1, 0, 800).numpy()
    x0, y0, _ = _hover_point(scene, cfg, 0.0)
    for k, pose in enumerate(poses):
        target = _spin(-OMEGA * k / cfg.fixed.prf_hz) @ np.array([x0, y0, 0.0])
        origin = np.asarray(pose["origin"], dtype=np.float64)
        axis = np.asarray(pose["rot"], dtype=np.float64).reshape(3, 3)[:, 2]
        to_target = (target - origin) / np.linalg.norm(target - origin)
        assert math.atan2(np.linalg.norm(np.cross(axis, to_target)), axis @ to_target) < 1e-6, k
    assert math.hypot(x0, y0) < 1.0 and abs(math.atan2(math.hypot(x0, y0), C + ALTITUDE)) < 2e-3


def test_trajectory_chords_stay_within_a_millimetre_and_the_bound_is_tight():
    """Between samples (worst: the midpoints) the interpolated position is within 1 mm of the circle,
    and not much closer: the sample count follows the sagitta bound, not a blanket oversampling."""
    cfg = _config(flight__duration_s=60.0)
    scene = build_scene(cfg)
    (trajectory,) = flight_trajectories(cfg, scene)
    t = trajectory.gps_time
    mid = (t[:-1] + t[1:]) / 2.0
    position, _ = trajectory.interpolate(mid)
    local = scene.world_to_local(position)
    elapsed = mid - cfg.flight.start_gps_time
    exact = np.array([_spin(-OMEGA * e) @ _hover_point(scene, cfg, e) for e in elapsed])
    error = np.linalg.norm(local - exact, axis=1)
    assert error.max() <= 1e-3
    assert error.max() > 0.9e-3
    rho = np.hypot(*_hover_point(scene, cfg, 0.0)[[0, 2]])
    assert len(t) - 1 == math.ceil(2 * math.pi / math.sqrt(8e-3 / rho))  # one turn at Δθ = √(8·1 mm/ρ)


def test_attitude_angles_reproduce_the_rotation_through_gimbal_lock():
    """Roll, pitch, heading of R_y(θ)·R₀ in the trajectory convention, unwrapped, for a heading of 90°
    (body x swings through the vertical) and of 20°."""
    theta = np.concatenate([np.linspace(-7.0, 7.0, 4001), [math.pi / 2, -math.pi / 2]])
    for heading in (90.0, 20.0):
        r0 = _body_to_enu(*np.radians([3.0, -2.0, heading]))
        x = r0[:, 0]
        lock = math.atan2(-x[0], x[2])  # the angle that turns body x to the vertical
        angles = np.concatenate([theta, lock + np.array([0.0, 1e-12, math.pi])])
        rotations = np.array([_spin(a) @ r0 for a in angles])
        euler = rotating_body.attitude_angles(rotations)
        rebuilt = np.array([_body_to_enu(*e) for e in euler])
        assert np.abs(rebuilt - rotations).max() < 1e-14
        steps = np.abs(np.diff(euler[:4001], axis=0))  # along θ: no 2π jumps (π at the lock, heading 90°)
        assert steps[:, [0, 2]].max() < (math.pi + 0.01 if heading == 90.0 else 0.01)


def _ray_ellipsoid(origin: np.ndarray, direction: np.ndarray, axes: np.ndarray) -> float:
    """Distance [m] along the unit ``direction`` from ``origin`` to the ellipsoid Σ(x_i/a_i)² = 1 (closed form)."""
    o, d = origin / axes, direction / axes
    qa, qb, qc = d @ d, o @ d, o @ o - 1.0
    return float((-qb - math.sqrt(qb * qb - qa * qc)) / qa)


def _ray_mesh(origin: np.ndarray, direction: np.ndarray, scene) -> float:
    """Nearest hit [m] of the ray on the scene's triangles (Möller–Trumbore, float64, every triangle)."""
    v0, v1, v2 = (scene.vertices[scene.triangles[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    s = origin - v0
    u = np.einsum("ij,ij->i", s, p) / det
    q = np.cross(s, e1)
    v = (q @ direction) / det
    t = np.einsum("ij,ij->i", e2, q) / det
    hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return float(t[hit].min())


def test_ranges_follow_the_spinning_ellipsoid():
    """Ranges of a staring beam over a quarter turn: at t = 0 the pole (range H), at t = P/4 the a-axis
    end (range c + H − a = 70.2 m); within the roughness of the closed-form ellipsoid, and within 2 mm
    (1 mm chord + float32 tracing) of an independent float64 ray cast on the scene's triangles."""
    cfg = _config(fixed__prf_hz=4.0)  # pulse 60 fires at exactly P/4
    result = flightsim.simulate(cfg)
    scene = result.scene
    assert len(result.returns.pulse) == result.counts.pulses > 60  # every pulse hits the body, none culled
    vertices = scene.vertices
    radius = np.linalg.norm(vertices, axis=1)
    unit = vertices / radius[:, None]
    rough = np.abs(radius - 1.0 / np.sqrt(((unit / np.array([A, C, C])) ** 2).sum(axis=1)))
    for k, range_m in zip(result.returns.pulse, result.returns.range_m):
        t = k / cfg.fixed.prf_hz
        spin = _spin(-OMEGA * t)
        origin, direction = spin @ _hover_point(scene, cfg, t), spin @ np.array([0.0, 0.0, -1.0])
        smooth = _ray_ellipsoid(origin, direction, np.array([A, C, C]))
        near = np.linalg.norm(vertices - (origin + smooth * direction), axis=1) < 10.0
        assert abs(range_m - smooth) <= rough[near].max() + 0.05, t  # facets ≤ 4 m over R ≥ 58 m: sag ≤ 3.5 cm
        assert abs(range_m - _ray_mesh(origin, direction, scene)) <= 2e-3, t
    ranges = dict(zip(result.returns.pulse.tolist(), result.returns.range_m.tolist()))
    assert ranges[0] == pytest.approx(ALTITUDE, abs=2.5)  # the roughness stays within 5 RMS (test_smallbody_scene)
    assert ranges[60] == pytest.approx(C + ALTITUDE - A, abs=2.5)


def test_zero_period_is_the_plain_hover():
    cfg = _config(flight__body_rotation_period_s=0.0)
    (trajectory,) = flight_trajectories(cfg, build_scene(cfg))
    assert len(trajectory.gps_time) == 2 and np.all(trajectory.position[0] == trajectory.position[1])


def test_toml_and_set_round_trip(tmp_path):
    cfg = _config(flight__body_rotation_period_s=19440.0)
    path = tmp_path / "run.toml"
    path.write_text(to_toml(cfg))
    assert validate(load_toml(path)).flight.body_rotation_period_s == 19440.0
    out = tmp_path / "run"
    args = ["simulate", "--scene", "ellipsoid", "--altitude", "200", "--duration", "0.01",
            "--set", "flight.platform=hover", "--set", "flight.body_rotation_period_s=19440", "--out", str(out)]
    assert main(args) == 0
    assert "body_rotation_period_s = 19440.0" in (out / "run.toml").read_text()


@pytest.mark.parametrize("value", ["-5", "nan", "inf", "30", "2e7"])
def test_bad_periods_name_the_field(tmp_path, capsys, value):
    args = ["simulate", "--set", "flight.platform=hover", "--set", f"flight.body_rotation_period_s={value}",
            "--out", str(tmp_path / "run")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "flight.body_rotation_period_s" in err and "[0, 1e+07] s; 0 = not rotating, else at least 60 s" in err


def test_a_period_needs_the_hover(tmp_path, capsys):
    args = ["simulate", "--set", "flight.body_rotation_period_s=19440", "--out", str(tmp_path / "run")]
    assert main(args) == 2
    assert "flight.body_rotation_period_s = 19440.0" in capsys.readouterr().err
    cfg = _config()
    set_value(cfg, "flight.trajectory", "t.csv")
    with pytest.raises(InputError, match="flight.trajectory"):  # a hover flies no trajectory file
        validate(cfg)


def test_body_sweeping_into_the_sensor_is_refused():
    cfg = _config(flight__altitude_m=100.0)  # the a-axis ends sweep 250 m from the axis; the sensor is at 220 m
    with pytest.raises(InputError, match="flight.altitude_m"):
        flight_trajectories(cfg, build_scene(cfg))


def test_too_many_samples_are_refused():
    cfg = _config(flight__altitude_m=50000.0, flight__duration_s=36000.0)
    with pytest.raises(InputError, match="flight.duration_s"):
        flight_trajectories(cfg, build_scene(cfg))
