"""The terrestrial laser scanner (vz2000 preset: tripod platform, panoramic deflector, discrete returns with the
datasheet's range noise) against independent float64 closed forms: the azimuth/elevation grid of its directions,
ranges to a plane, and the statistics of its range noise; bad input."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from flightsim import api


def _cfg(device: str, **overrides):
    """The vz2000 preset over the flat ``plane`` scene, a small sector, noise off unless overridden."""
    base = {"scene.name": "plane", "panoramic.vertical_deg": [-40.0, -5.0], "panoramic.vertical_step_deg": 0.5,
            "panoramic.azimuth_deg": [-20.0, 20.0], "panoramic.azimuth_step_deg": 0.5, "flight.position_m": [0.0, 0.0],
            "flight.altitude_m": 2.5, "flight.heading_deg": 30.0, "ranging.noise_m": 0.0,
            "ranging.channel_delay_m": 0.0, "run.device": device, "run.seed": 11}
    base.update(overrides)
    cfg = api.load_config(instrument="vz2000", overrides=base)
    p = cfg.panoramic
    cfg.flight.duration_s = (p.scan_pulses - 0.5) / p.measurement_rate_hz  # one scan: pulses 0 … n − 1
    return cfg


def _angles(k, lo_deg, step_deg, start_deg, az_step_deg, per_line):
    """Independent float64: elevation and azimuth [rad] of pulse k (continuous head rotation)."""
    k = np.asarray(k, dtype=np.float64)
    i = np.mod(k, per_line)
    return np.radians(lo_deg + i * step_deg), np.radians(start_deg + az_step_deg * k / per_line)


def test_scan_grid_counts():
    cfg = _cfg("cpu")
    assert (cfg.panoramic.per_line, cfg.panoramic.lines) == (71, 81)  # 35° / 0.5° + 1, 40° / 0.5° + 1


def test_directions_match_the_azimuth_elevation_grid(device):
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    cfg = _cfg(device, **{"panoramic.vertical_deg": [-40.0, 60.0], "panoramic.azimuth_deg": [-180.0, 180.0],
                          "panoramic.vertical_step_deg": 1.0, "panoramic.azimuth_step_deg": 7.0})
    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    n = cfg.panoramic.scan_pulses
    _, directions = (a.numpy().astype(np.float64) for a in sim.sample_rays(n))
    elev, az = _angles(np.arange(len(directions)), -40.0, 1.0, -180.0, 7.0, 101)
    heading = np.radians(30.0) + az  # clockwise from grid north
    expected = np.column_stack([np.cos(elev) * np.sin(heading), np.cos(elev) * np.cos(heading), np.sin(elev)])
    assert len(directions) == n == 101 * 52
    assert np.abs(directions - expected).max() < 2e-6  # float32 rays


def _plane_run(device: str, **overrides):
    cfg = _cfg(device, **overrides)
    result = api.simulate(cfg)
    r = result.returns
    p = cfg.panoramic
    elev, _ = _angles(r.pulse, p.vertical_deg[0], p.vertical_step_deg, p.azimuth_deg[0], p.azimuth_step_deg,
                      p.per_line)
    return cfg, r, 2.5 / np.sin(-elev)  # the origin 2.5 m above flat ground


def test_ranges_to_a_plane_match_the_closed_form(device):
    cfg, r, expected = _plane_run(device)
    assert len(r.range_m) == cfg.panoramic.scan_pulses  # every measurement below the horizon meets the ground
    assert np.abs(r.range_m - expected).max() < 2e-4
    ground = r.points["exact"][:, 2]
    assert np.abs(ground - ground[0]).max() < 1e-3


def test_range_noise_has_the_datasheet_accuracy_and_precision(device):
    """Bias 8 mm and σ 5 mm (the datasheet's accuracy and precision as numbers): the mean within 5 standard
    errors, the variance within chi-square bounds, the share inside ±1σ within binomial bounds."""
    bias, sigma = 0.008, 0.005
    cfg, r, expected = _plane_run(device, **{"panoramic.vertical_step_deg": 0.1, "panoramic.azimuth_step_deg": 0.1,
                                             "ranging.noise_m": sigma, "ranging.range_bias_m": bias})
    e = r.range_m - expected
    n = len(e)
    assert n > 100_000
    assert abs(e.mean() - bias) < 5.0 * sigma / math.sqrt(n)
    chi = (n - 1) * e.var(ddof=1) / sigma ** 2
    assert stats.chi2.ppf(1e-6, n - 1) < chi < stats.chi2.ppf(1 - 1e-6, n - 1)
    inside = int(np.sum(np.abs(e - bias) < sigma))
    p = stats.norm.cdf(1.0) - stats.norm.cdf(-1.0)
    assert stats.binom.ppf(1e-6, n, p) <= inside <= stats.binom.ppf(1 - 1e-6, n, p)


@pytest.mark.parametrize("setting, field", [
    ("panoramic.vertical_deg=10,5", "panoramic.vertical_deg"),
    ("panoramic.vertical_deg=-100,0", "panoramic.vertical_deg"),
    ("panoramic.vertical_step_deg=0", "panoramic.vertical_step_deg"),
    ("panoramic.azimuth_step_deg=-1", "panoramic.azimuth_step_deg"),
    ("panoramic.azimuth_deg=0,400", "panoramic.azimuth_deg"),
    ("flight.altitude_m=-1", "flight.altitude_m"),
    ("flight.roll_deg=100", "flight.roll_deg"),
    ("flight.position_m=1", "flight.position_m"),
])
def test_bad_tls_input_exits_2_naming_the_field(tmp_path, setting, field):
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "vz2000", "--set", setting,
                          "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], run.stderr
    assert not (tmp_path / "o").exists()


def test_simulate_writes_las(tmp_path):
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "vz2000", "--scene", "sandbox",
                          "--set", "panoramic.vertical_step_deg=0.5", "--set", "panoramic.azimuth_step_deg=0.5",
                          "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert list((tmp_path / "o" / "exact").glob("*.las"))
