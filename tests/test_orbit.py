"""The orbit platform: circular two-body orbits against a numerical integration, the pass over the scene,
and 1″ of pointing at 500 km on the ground (seed: corner-cube-single-photon-calibration-patent.txt)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from flightsim.cli import main
from flightsim.core.config import RunConfig, set_value, validate
from flightsim.engine.simulate import Simulator
from flightsim.platforms.orbit import BODIES, kepler_circular
from flightsim.platforms.plan import build_scene, flight_trajectories

ARCSEC = math.pi / 648000


@pytest.mark.parametrize("body, altitude", [("earth", 500e3), ("moon", 200e3)])
def test_circular_orbit_matches_a_numerical_two_body_integration_over_one_orbit(body, altitude):
    b = BODIES[body]
    r = b.radius_m + altitude
    period = 2 * math.pi * math.sqrt(r ** 3 / b.mu)
    t = np.linspace(0.0, period, 200)
    kepler = kepler_circular(b, r, math.radians(92.0), 0.7, 0.3, t)
    v0 = (kepler_circular(b, r, math.radians(92.0), 0.7, 0.3, np.array([1e-3]))[0]
          - kepler_circular(b, r, math.radians(92.0), 0.7, 0.3, np.array([-1e-3]))[0]) / 2e-3
    ode = solve_ivp(lambda _, y: np.concatenate([y[3:], -b.mu * y[:3] / np.linalg.norm(y[:3]) ** 3]), (0.0, period),
                    np.concatenate([kepler[0], v0]), t_eval=t, rtol=1e-12, atol=1e-6, method="DOP853")
    assert np.linalg.norm(ode.y[:3].T - kepler, axis=1).max() < 1.0
    assert np.linalg.norm(kepler, axis=1) == pytest.approx(r, rel=1e-12)


def _orbit_config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in {"instrument.deflector": "fixed", "sensor.array": 1, "flight.platform": "orbit",
                       "flight.altitude_m": 500e3, "flight.duration_s": 0.2, "sensor.prf_hz": 50.0,
                       "sensor.max_range_m": 6e5, "scene.name": "plane", "output.models": ["exact"], **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def test_the_pass_is_above_the_scene_origin_at_mid_run_and_points_nadir():
    cfg = _orbit_config()
    scene = build_scene(cfg)
    (track,) = flight_trajectories(cfg, scene)
    mid = track.gps_time[0] + 0.1
    position = np.array([np.interp(mid, track.gps_time, track.position[:, k]) for k in range(3)])
    assert position - scene.origin == pytest.approx([0.0, 0.0, 500e3], abs=1e-3)
    speed = np.linalg.norm(np.diff(track.position, axis=0), axis=1) / np.diff(track.gps_time)
    b = BODIES["earth"]
    assert speed == pytest.approx(math.sqrt(b.mu / np.linalg.norm(position - scene.origin + [0, 0, b.radius_m])), rel=5e-3)


def test_one_arcsecond_of_pointing_moves_the_ground_point_by_h_tan_one_arcsecond():
    cfg = _orbit_config(**{"errors.boresight_arcsec": [1.0, 0.0, 0.0]})
    scene = build_scene(cfg)
    sim = Simulator(cfg, scene, flight_trajectories(cfg, scene), with_truth=True)
    chunks = []
    counts = sim.run(chunks.append)
    assert counts.returns == counts.beams_fired == 11
    shift = np.concatenate([np.linalg.norm(c.points["exact"] - c.true_points, axis=1) for c in chunks])
    ranges = np.concatenate([c.range_m for c in chunks]).astype(np.float64)
    assert shift == pytest.approx(ranges * math.tan(ARCSEC), abs=1e-3)  # 2.424 m at 500 km: the patent's "about 2.5 m"
    assert 2.42 < shift.mean() < 2.43


def test_ranging_bias_adds_to_every_range():
    plain, biased = _orbit_config(), _orbit_config(**{"errors.range_bias_m": 0.25})
    ranges = []
    for cfg in (plain, biased):
        scene = build_scene(cfg)
        chunks = []
        Simulator(cfg, scene, flight_trajectories(cfg, scene)).run(chunks.append)
        ranges.append(np.concatenate([c.range_m for c in chunks]).astype(np.float64))
    assert ranges[1] - ranges[0] == pytest.approx(np.full(11, 0.25), abs=0.04)  # float32 ranges near 500 km: 3 cm steps


def test_moon_pass_at_200_km():
    cfg = _orbit_config(**{"flight.body": "moon", "flight.altitude_m": 200e3, "flight.inclination_deg": 90.0,
                           "sensor.max_range_m": 3e5})
    scene = build_scene(cfg)
    chunks = []
    Simulator(cfg, scene, flight_trajectories(cfg, scene)).run(chunks.append)
    ranges = np.concatenate([c.range_m for c in chunks])
    assert len(ranges) == 11 and np.abs(ranges - 200e3).max() < 5.0  # the tangent plane drops ≤ 1 m over the pass


@pytest.mark.parametrize("args, field", [
    (["--set", "flight.inclination_deg=20"], "flight.inclination_deg"),  # the scene lies at 30.7°N
    (["--set", "flight.body=mars"], "flight.body"),
])
def test_bad_orbit_input_exits_2_naming_the_field(tmp_path, capsys, args, field):
    base = ["simulate", "--set", "flight.platform=orbit", "--set", "flight.altitude_m=500000", "--set",
            "sensor.max_range_m=600000", "--duration", "0.01"]
    assert main(base + args + ["--out", str(tmp_path / "o")]) == 2
    assert field in capsys.readouterr().err
