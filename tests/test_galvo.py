"""The Chang'e-3 galvo imager on the device: rays against independent float64 reflection math, the
error sources against their closed forms, Monte Carlo against first-order propagation, bad input."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from flightsim.core.constants import ARCSEC
from flightsim.engine.config import validate
from flightsim.engine.config_io import preset_config
from flightsim.instrument import galvo_model
from flightsim.studies.budget import Frame, frame_config, monte_carlo, with_errors

C = 299_792_458.0
COLUMNS = 8  # a thinned raster keeps the CPU runs short: 17 strips × 8 columns × 16 channels


@pytest.fixture(scope="module")
def frame() -> Frame:
    return Frame(frame_config(columns=COLUMNS))


def _reflect(s, n):
    return s - 2.0 * np.sum(s * n, axis=-1, keepdims=True) * n


def _reference_rays(b, e, delta, gamma, theta):
    """Independent float64 two-mirror trace (the geometry of kernels/galvo.py's docstring)."""
    s = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], axis=-1)
    n1 = np.stack([np.cos(3 * np.pi / 4 - delta), np.sin(3 * np.pi / 4 - delta), np.zeros_like(delta)], axis=-1)
    n2 = np.stack([np.zeros_like(gamma), np.cos(3 * np.pi / 4 - gamma), np.sin(3 * np.pi / 4 - gamma)], axis=-1)
    source = np.array([-b, -e, 0.0])
    q1 = source + (np.sum(n1 * (np.array([0.0, -e, 0.0]) - source), axis=-1) / np.sum(n1 * s, axis=-1))[..., None] * s
    s2 = _reflect(s, n1)
    q2 = q1 + (np.sum(n2 * -q1, axis=-1) / np.sum(n2 * s2, axis=-1))[..., None] * s2
    return q2, _reflect(s2, n2)


def _raster(k, strips, columns, h_half, v_half):
    strip, column = np.divmod(k % (strips * columns), columns)
    column = np.where(strip % 2 == 1, columns - 1 - column, column)
    return (-h_half + 2 * h_half * column / (columns - 1), -v_half + 2 * v_half * strip / (strips - 1),
            np.where(strip % 2 == 1, -1.0, 1.0))


def test_device_rays_match_float64_reflection_and_the_double_angle_law(frame):
    sim = frame.simulator(frame.cfg)
    starts, directions = (a.numpy().astype(np.float64) for a in sim.sample_rays(frame.pulses * frame.beams))
    rot = frame.sensor_rotation(sim)
    origin = np.asarray(sim.poses64(frame.trajectories[0].line_id, 0, 1).numpy()[0]["origin"], dtype=np.float64)
    k = np.arange(frame.pulses).repeat(frame.beams)
    channel = np.tile(np.arange(frame.beams), frame.pulses)
    g = frame.cfg.galvo
    delta, gamma, _ = _raster(k, g.strips, g.columns, math.radians(g.field_deg[0]) / 4, math.radians(g.field_deg[1]) / 4)
    theta = np.asarray(frame.cfg.channels.angles_mrad)[channel] * 1e-3
    exit_ref, dir_ref = _reference_rays(g.b_mm * 1e-3, g.e_mm * 1e-3, delta, gamma, theta)
    angle = np.linalg.norm(np.cross(directions @ rot, dir_ref), axis=1)  # sin of the angle between them
    assert angle.max() < 2e-6  # float32 rays
    assert np.abs((starts - origin) @ rot - exit_ref).max() < 3e-5  # float32 local coordinates ~100 m
    # the central ray obeys the double-angle law: (sin 2δ, cos 2δ sin 2γ, cos 2δ cos 2γ)
    _, central = _reference_rays(0.05, 0.02, delta, gamma, np.zeros_like(delta))
    closed = np.stack([np.sin(2 * delta), np.cos(2 * delta) * np.sin(2 * gamma), np.cos(2 * delta) * np.cos(2 * gamma)], 1)
    assert np.abs(central - closed).max() < 1e-12
    # the field: central-ray corners at ±15° horizontally and vertically
    assert math.degrees(np.arcsin(closed[:, 0]).max()) == pytest.approx(15.0, abs=1e-9)


def test_horizontal_encoder_error_flips_sign_between_strips(frame):
    b1 = 42.9
    deviation, truth = frame.deviations(with_errors(frame.cfg, b1_arcsec=b1))
    per_pulse = deviation.reshape(frame.pulses, frame.beams, 3)
    strip0, strip1 = per_pulse[:COLUMNS, 8, 0], per_pulse[COLUMNS:2 * COLUMNS, 8, 0][::-1]  # same physical column
    # the true mirror is turned +B1 on even strips: the beam went further to +x than the processing believes
    assert np.all(strip0 < 0) and np.all(strip1 > 0)
    r = np.linalg.norm(truth.reshape(frame.pulses, frame.beams, 3)[:COLUMNS, 8], axis=1)
    # a mirror turned by B1 turns the beam by 2·B1: |ΔX| ≈ 2·B1·R to first order (the beam's tilt changes it a little)
    assert np.abs(strip0) == pytest.approx(2 * b1 * ARCSEC * r, rel=0.05)


def _range_errors(frame, **errors):
    deviation, truth = frame.deviations(with_errors(frame.cfg, **errors))
    unit = truth / np.linalg.norm(truth, axis=1, keepdims=True)
    return np.sum(deviation * unit, axis=1), np.linalg.norm(truth, axis=1)


@pytest.mark.parametrize("errors, sigma", [
    ({"tdc_bin_s": 1.25e-10}, C / 2 * 1.25e-10 / math.sqrt(6)),  # σ_n ≈ 0.77 cm
    ({"jitter_s": 2e-11}, C / 2 * math.sqrt(2) * 2e-11),  # σ_j ≈ 0.42 cm
    ({"rise_time_s": 7e-9, "snr": 31.0, "cfd_fraction": 0.3}, C / 2 * 7e-9 / 31 * math.sqrt(1.09)),  # σ_ie
    ({"tdc_bin_s": 1.25e-10, "jitter_s": 2e-11}, C / 2 * math.sqrt(1.25e-10 ** 2 / 6 + 2 * 2e-11 ** 2)),
])
def test_each_random_ranging_error_has_its_formula_sigma(frame, errors, sigma):
    error, _ = _range_errors(frame, **errors)
    n = error.size
    assert abs(error.mean()) < 4 * sigma / math.sqrt(n)
    assert error.std() == pytest.approx(sigma, rel=4 / math.sqrt(2 * n) + 2e-3)  # + float32 points (~10 µm)


def test_mirror_angle_noises_are_independent_with_their_sigma(frame):
    sigma = 60.0 * ARCSEC
    deviation, _ = frame.deviations(with_errors(frame.cfg, h_noise_arcsec=60.0, v_noise_arcsec=60.0))
    centre = deviation.reshape(frame.pulses, frame.beams, 3)[:, 8]  # one channel: one draw per pulse
    n = len(centre)
    assert abs(np.corrcoef(centre[:, 0], centre[:, 1])[0, 1]) < 4 / math.sqrt(n)
    # a mirror turned by ε turns the beam by 2ε: about 2·σ·100 m on the plane, near the centre of the field
    assert centre[:, 0].std() == pytest.approx(2 * sigma * 100.0, rel=0.2)
    assert centre[:, 1].std() == pytest.approx(2 * sigma * 100.0, rel=0.2)


def test_clock_drift_and_channel_delays_are_systematic(frame):
    error, r = _range_errors(frame, clock_drift=2e-6)
    assert np.abs(error - 2e-6 * r).max() < 3e-5  # ε = R·e_df, 0.2 mm at 100 m, within float32 rounding
    cfg = with_errors(frame.cfg, channel_delay_m=0.05)
    error, _ = _range_errors(frame, channel_delay_m=0.05)
    per_channel = error.reshape(frame.pulses, frame.beams)
    assert np.abs(per_channel - per_channel[0]).max() < 3e-5  # one constant per channel
    from flightsim.instrument.ranging import RangingErrors

    assert per_channel[0] == pytest.approx(RangingErrors(cfg.ranging, cfg.run.seed).channel_delays(frame.beams),
                                           abs=3e-5)


def test_monte_carlo_agrees_with_first_order_propagation(frame):
    draws = 400
    mc = monte_carlo(frame, draws, seed=1)
    cfg = frame.cfg
    sig = {"b1": 42.9 * ARCSEC, "b2": 42.9 * ARCSEC, "b3": 42.9 * ARCSEC, "c1": 94.5 * ARCSEC, "n_h": 0.0,
           "n_v": 0.0, "range": 0.0}
    analytic = galvo_model.analytic_sigma(frame.geometry, sig, cfg.flight.altitude_m)
    assert (mc.hits == draws).all()
    tolerance = 4.0 / math.sqrt(2 * (draws - 1))
    for k in range(3):
        big = analytic[:, k] > 1e-4  # slots where the axis moves by more than 0.1 mm
        ratio = np.median(mc.std[big, k] / analytic[big, k])
        assert abs(ratio - 1.0) < tolerance, (k, ratio)


@pytest.mark.parametrize("setting, field", [
    ("instrument.deflector=prisms", "instrument.deflector"),
    ("galvo.aperture_mm=2", "galvo.aperture_mm"),
    ("galvo.c1_arcsec=5000", "galvo.c1_arcsec"),
    ("galvo.b2_arcsec=12 arcsec", "galvo.b2_arcsec"),
    ("galvo.field_deg=30,95", "galvo.field_deg"),
    ("output.models=exact,nominal", "output.models"),
])
def test_bad_instrument_input_exits_2_naming_the_field(tmp_path, setting, field):
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "change3", "--set", setting,
                          "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], run.stderr
    assert not (tmp_path / "out").exists()


def test_galvo_errors_are_refused_on_the_risley_instrument():
    from flightsim.engine.config import RunConfig
    from flightsim.core.errors import InputError

    cfg = RunConfig()
    cfg.galvo.b1_arcsec = 10.0
    with pytest.raises(InputError, match="galvo.b1_arcsec"):
        validate(cfg)


def test_preset_is_the_papers_instrument():
    cfg = validate(preset_config("change3"))
    assert cfg.channels.angles_mrad == tuple(float(17 - 2 * i) for i in range(1, 17))
    assert cfg.galvo.strips * cfg.galvo.columns / cfg.galvo.frame_s == pytest.approx(43520.0)
