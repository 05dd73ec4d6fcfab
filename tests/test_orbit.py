"""The orbit platform: circular two-body orbits against a numerical integration, the pass over the scene,
and 1″ of pointing at 500 km on the ground (seed: corner-cube-single-photon-calibration-patent.txt)."""
from __future__ import annotations

import math

import numpy as np
import pyproj
import pytest
from scipy.integrate import solve_ivp

from flightsim.cli import main
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.tracer import Tracer
from flightsim.platforms.orbit import BODIES, Orbit, earth_rotation, eccentric_anomaly, gcrs_to_itrs, kepler_state
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.readouts.points import Points

ARCSEC = math.pi / 648000


def _two_body(mu: float, state0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 3) positions of an independent numerical two-body integration (DOP853, rtol 1e-12) [m]."""
    ode = solve_ivp(lambda _, y: np.concatenate([y[3:], -mu * y[:3] / np.linalg.norm(y[:3]) ** 3]), (t[0], t[-1]),
                    state0, t_eval=t, rtol=1e-12, atol=1e-6, method="DOP853")
    return ode.y[:3].T


@pytest.mark.parametrize("body, perigee_altitude, e", [("earth", 500e3, 0.0), ("earth", 400e3, 0.05),
                                                       ("earth", 300e3, 0.6), ("moon", 100e3, 0.2)])
def test_kepler_orbit_matches_a_numerical_two_body_integration_over_one_orbit(body, perigee_altitude, e):
    b = BODIES[body]
    a = (b.radius_m + perigee_altitude) / (1.0 - e)
    orbit = Orbit(a, e, math.radians(92.0), 0.7, 1.1, 0.3)
    period = 2 * math.pi * math.sqrt(a ** 3 / b.mu)
    t = np.linspace(0.0, period, 400)
    position, velocity = kepler_state(b, orbit, t)
    numeric = _two_body(b.mu, np.concatenate([position[0], velocity[0]]), t)
    assert np.linalg.norm(numeric - position, axis=1).max() < 1.0
    r, v = np.linalg.norm(position, axis=1), np.linalg.norm(velocity, axis=1)
    assert v ** 2 / 2 - b.mu / r == pytest.approx(np.full(len(t), -b.mu / (2 * a)), rel=1e-12)  # vis-viva energy
    h = np.cross(position, velocity)
    assert np.linalg.norm(h, axis=1) == pytest.approx(np.full(len(t), math.sqrt(b.mu * a * (1 - e * e))), rel=1e-12)
    assert h / np.linalg.norm(h, axis=1, keepdims=True) == pytest.approx(
        np.tile([math.sin(0.7) * math.sin(math.radians(92)), -math.cos(0.7) * math.sin(math.radians(92)),
                 math.cos(math.radians(92))], (len(t), 1)), abs=1e-12)  # the plane of Ω, i
    perigee = -0.3 / math.sqrt(b.mu / a ** 3)  # M = 0
    apsides = np.linalg.norm(kepler_state(b, orbit, np.array([perigee, perigee + period / 2]))[0], axis=1)
    assert apsides == pytest.approx([a * (1 - e), a * (1 + e)], rel=1e-12)


def test_kepler_equation_is_solved_and_a_circle_is_the_closed_form():
    m = np.linspace(-40.0, 40.0, 2001)
    for e in (0.0, 0.3, 0.9, 0.999):
        anomaly = eccentric_anomaly(m, e)
        assert anomaly - e * np.sin(anomaly) == pytest.approx(m, abs=1e-13)
    b = BODIES["earth"]
    r = b.radius_m + 500e3
    t = np.linspace(-3000.0, 3000.0, 61)
    u = 0.3 + math.sqrt(b.mu / r ** 3) * t
    x, y = r * np.cos(u), r * np.sin(u)  # R3(−Ω)·R1(−i) of the circle, by hand
    i, node = math.radians(92.0), 0.7
    circle = np.column_stack([math.cos(node) * x - math.sin(node) * math.cos(i) * y,
                              math.sin(node) * x + math.cos(node) * math.cos(i) * y, math.sin(i) * y])
    assert np.array_equal(kepler_state(b, Orbit(r, 0.0, i, node, 0.0, 0.3), t)[0], circle)


def test_earth_rotation_from_astropy_turns_about_the_pole_at_the_sidereal_rate():
    """R_GCRS→ITRS of two epochs 1 h apart differ by R3(ω Δt) (precession, nutation and polar motion
    change by < 1e-7 rad in an hour), and the interpolated rotation matches astropy at any time."""
    t0 = 450_000_000.0
    r0, r1 = gcrs_to_itrs(np.array([t0, t0 + 3600.0]))
    turn = r1 @ r0.T
    angle = 7.2921150e-5 * 3600.0
    expected = np.array([[math.cos(angle), math.sin(angle), 0], [-math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    assert turn == pytest.approx(expected, abs=1e-6)
    assert r0 @ r0.T == pytest.approx(np.eye(3), abs=1e-14)
    times = t0 + np.array([0.0, 17.3, 600.0, 1799.9, 3600.0])
    assert earth_rotation(times) == pytest.approx(gcrs_to_itrs(times), abs=1e-10)


def _orbit_config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in {"instrument.deflector": "fixed", "fan.array": 1, "flight.platform": "orbit",
                       "flight.altitude_m": 500e3, "flight.duration_s": 0.2, "fixed.prf_hz": 50.0,
                       "instrument.max_range_m": 6e5, "scene.name": "plane", "output.models": ["exact"],
                       "instrument.errors": ["ranging", "pose"], **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


@pytest.mark.parametrize("e", [0.0, 0.1])
def test_the_pass_is_above_the_scene_origin_at_mid_run_at_the_vis_viva_speed(e):
    """With the perigee put at the pass (ω = the pass's argument of latitude u, sin u = sin φ / sin i), the
    speed there is √(μ (1 + e)/r) (vis-viva at perigee; in the Earth-fixed frame the rotation, ω r cos φ = 430 m/s
    eastward against a track 2.3° west of north, adds 0.4 %)."""
    lon, lat = pyproj.Transformer.from_crs("EPSG:32648", "EPSG:4326", always_xy=True).transform(409000.0, 3393000.0)
    above = np.array(pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
        lon, lat, 450.0 + 500e3))
    r = np.linalg.norm(above)
    u = math.degrees(math.asin(above[2] / r / math.sin(math.radians(92.0))))
    cfg = _orbit_config(**{"flight.eccentricity": e, "flight.perigee_arg_deg": u})
    scene = build_scene(cfg)
    (track,) = flight_trajectories(cfg, scene)
    mid = track.gps_time[0] + 0.1
    position = np.array([np.interp(mid, track.gps_time, track.position[:, k]) for k in range(3)])
    assert position - scene.origin == pytest.approx([0.0, 0.0, 500e3], abs=1e-3)
    speed = np.linalg.norm(np.diff(track.position, axis=0), axis=1) / np.diff(track.gps_time)
    assert speed == pytest.approx(math.sqrt(BODIES["earth"].mu * (1 + e) / r), rel=6e-3)


def test_one_arcsecond_of_pointing_moves_the_ground_point_by_h_tan_one_arcsecond():
    cfg = _orbit_config(**{"pose.boresight_arcsec": [1.0, 0.0, 0.0]})
    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene), with_truth=True)
    chunks = []
    counts = sim.run(Points(), chunks.append)
    assert counts.returns == counts.beams_fired == 11
    shift = np.concatenate([np.linalg.norm(c.points["exact"] - c.true_points, axis=1) for c in chunks])
    ranges = np.concatenate([c.range_m for c in chunks]).astype(np.float64)
    assert shift == pytest.approx(ranges * math.tan(ARCSEC), abs=1e-3)  # 2.424 m at 500 km: the patent's "about 2.5 m"
    assert 2.42 < shift.mean() < 2.43


def test_ranging_bias_adds_to_every_range():
    plain, biased = _orbit_config(), _orbit_config(**{"ranging.range_bias_m": 0.25})
    ranges = []
    for cfg in (plain, biased):
        scene = build_scene(cfg)
        chunks = []
        Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Points(), chunks.append)
        ranges.append(np.concatenate([c.range_m for c in chunks]).astype(np.float64))
    assert ranges[1] - ranges[0] == pytest.approx(np.full(11, 0.25), abs=0.04)  # float32 ranges near 500 km: 3 cm steps


def test_moon_pass_at_200_km():
    cfg = _orbit_config(**{"flight.body": "moon", "flight.altitude_m": 200e3, "flight.inclination_deg": 90.0,
                           "instrument.max_range_m": 3e5})
    scene = build_scene(cfg)
    chunks = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Points(), chunks.append)
    ranges = np.concatenate([c.range_m for c in chunks])
    assert len(ranges) == 11 and np.abs(ranges - 200e3).max() < 5.0  # the tangent plane drops ≤ 1 m over the pass


@pytest.mark.parametrize("args, field", [
    (["--set", "flight.inclination_deg=20"], "flight.inclination_deg"),  # the scene lies at 30.7°N
    (["--set", "flight.body=mars"], "flight.body"),
])
def test_bad_orbit_input_exits_2_naming_the_field(tmp_path, capsys, args, field):
    base = ["simulate", "--set", "flight.platform=orbit", "--set", "flight.altitude_m=500000", "--set",
            "instrument.max_range_m=600000", "--duration", "0.01"]
    assert main(base + args + ["--out", str(tmp_path / "o")]) == 2
    assert field in capsys.readouterr().err


_ROTATIONS = """
import sys
import numpy as np
from astropy.utils import iers
from flightsim.platforms.orbit import astropy_gcrs_to_itrs
if sys.argv[2] == "cached":  # the table must come from the cache entry: astropy parsing it fails
    iers.IERS_Auto.read = classmethod(lambda cls, *a, **k: (_ for _ in ()).throw(AssertionError("parsed")))
np.save(sys.argv[1], astropy_gcrs_to_itrs(3.5e8 + np.linspace(0.0, 600.0, 7)))
"""


def test_the_earth_orientation_table_from_the_cache_gives_the_same_rotations(tmp_path):
    """The IERS table astropy parses (0.4-0.6 s a process) is stored in the scene cache by the first run and read by
    the next: in fresh processes, the rotations from the stored table are those from the parsed one bit for bit;
    an entry cut short is ignored, parsed afresh and written again."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "FLIGHTSIM_CACHE": str(tmp_path / "cache")}

    def rotations(name: str, mode: str) -> np.ndarray:
        subprocess.run([sys.executable, "-c", _ROTATIONS, str(tmp_path / name), mode], env=env, check=True,
                       capture_output=True)
        return np.load(tmp_path / name)

    parsed = rotations("parsed.npy", "any")
    (entry,) = (tmp_path / "cache").glob("iers-*.h5")
    np.testing.assert_array_equal(rotations("cached.npy", "cached"), parsed)
    entry.write_bytes(entry.read_bytes()[:4096])
    np.testing.assert_array_equal(rotations("again.npy", "any"), parsed)
    assert entry.stat().st_size > 4096  # written again whole
    np.testing.assert_array_equal(rotations("cached2.npy", "cached"), parsed)


def test_a_run_without_the_scene_cache_leaves_the_earth_orientation_table_to_astropy(tmp_path, monkeypatch):
    """``run.scene_cache = false`` (USE_CACHE, set by the run around its trajectories): no entry read or written;
    with it, the first call writes one."""
    from astropy.utils import iers

    from flightsim.platforms.earth_orientation import USE_CACHE, use_cached_table

    monkeypatch.setattr(iers.IERS_Auto, "iers_table", None)
    token = USE_CACHE.set(False)
    try:
        use_cached_table(tmp_path)
    finally:
        USE_CACHE.reset(token)
    assert iers.IERS_Auto.iers_table is None and not list(tmp_path.iterdir())
    use_cached_table(tmp_path)
    assert iers.IERS_Auto.iers_table is not None and len(list(tmp_path.glob("iers-*.h5"))) == 1


def test_a_pass_flown_before_reads_astropys_rotations_from_the_cache(tmp_path, monkeypatch):
    """The GCRS → ITRS rotations of a set of times are worked out by astropy once and kept in the scene cache: the
    same times again are read back, astropy's bits, without asking astropy; other times, an entry cut short or of
    another key (the sources astropy's answer depends on) are worked out again; ``run.scene_cache = false`` neither
    reads nor writes."""
    from flightsim.platforms import earth_orientation as eo
    from flightsim.platforms.orbit import astropy_gcrs_to_itrs

    asked = []

    def rotations(times):
        asked.append(len(times))
        return astropy_gcrs_to_itrs(times)

    times = 3.5e8 + np.linspace(0.0, 600.0, 7)
    first = eo.cached_rotations(times, rotations, tmp_path)
    (entry,) = tmp_path.glob("rotations-*.npy")
    again = eo.cached_rotations(times.copy(), rotations, tmp_path)
    assert asked == [7] and again.dtype == np.float64 and again.shape == (7, 3, 3)
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(again, astropy_gcrs_to_itrs(times))
    eo.cached_rotations(times[:5], rotations, tmp_path)  # other times: another entry
    assert asked == [7, 5] and len(list(tmp_path.glob("rotations-*.npy"))) == 2
    entry.write_bytes(entry.read_bytes()[:300])  # cut short: worked out again, written whole
    np.testing.assert_array_equal(eo.cached_rotations(times, rotations, tmp_path), first)
    assert asked == [7, 5, 7] and entry.stat().st_size > 300
    monkeypatch.setattr(eo, "_sources", lambda: "another astropy")  # the key moved: the entry is not taken
    eo.cached_rotations(times, rotations, tmp_path)
    assert asked == [7, 5, 7, 7] and len(list(tmp_path.glob("rotations-*.npy"))) == 3
    token = eo.USE_CACHE.set(False)
    try:
        eo.cached_rotations(times, rotations, tmp_path / "off")
    finally:
        eo.USE_CACHE.reset(token)
    assert asked == [7, 5, 7, 7, 7] and not (tmp_path / "off").exists()
