"""Pose errors (boresight error, POS noise) and the Risley prism encoder's errors on the device,
against closed forms in float64 computed from the true points and the believed poses."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightsim.core.constants import ARCSEC
from flightsim.engine.config import RunConfig, copy_config, validate
from flightsim.studies.budget import Frame

PULSES = 400
CENTRE = 4  # the on-axis beam of the 3×3 fan


@pytest.fixture(scope="module")
def frame() -> Frame:
    cfg = RunConfig()
    cfg.scene.name = "plane"
    cfg.flight.duration_s = 0.1
    cfg.output.models = ("exact",)
    cfg.run.cull = False
    return Frame(cfg, pulses=PULSES)


POSE_FIELDS = ("boresight_arcsec", "position_noise_m", "attitude_noise_arcsec")


def _run(frame: Frame, **errors):
    cfg = copy_config(frame.cfg)
    cfg.instrument.errors = ("pose",)
    cfg.parts["pose"] = dataclasses.replace(cfg.pose, **{k: v for k, v in errors.items() if k in POSE_FIELDS})
    cfg.parts["risley"] = dataclasses.replace(cfg.risley, **{k: v for k, v in errors.items() if k not in POSE_FIELDS})
    deviation, truth, sim = frame.local_deviations(validate(cfg))
    origin, rot = frame.poses(sim)
    pulse = np.arange(PULSES).repeat(frame.beams)
    return deviation, truth, origin[pulse], rot[pulse]


def test_boresight_error_turns_every_ray_about_the_sensor_origin(frame):
    angles = (40.0, -25.0, 60.0)  # roll, pitch, yaw [arcsec]
    deviation, truth, origin, rot = _run(frame, boresight_arcsec=angles)
    mount = Rotation.from_euler("ZYX", [a * ARCSEC for a in angles[::-1]]).as_matrix()
    # believed − true = R (Mᵀ − I) Rᵀ (T − O): the processing places the sensor-frame vector without M
    v = np.einsum("nji,nj->ni", rot, truth - origin)
    expected = np.einsum("nij,nj->ni", rot, v @ mount - v)
    assert np.abs(expected).max() > 0.1  # the test sees centimetres to decimetres
    assert np.abs(deviation - expected).max() < 2e-4  # float32 points


def test_position_noise_shifts_each_pulse_as_one(frame):
    sigma = 0.05
    deviation, *_ = _run(frame, position_noise_m=sigma)
    per_pulse = deviation.reshape(PULSES, frame.beams, 3)
    assert np.abs(per_pulse - per_pulse[:, :1]).max() < 1e-4  # every beam of a pulse shares the offset
    shifts = per_pulse[:, 0]
    n = len(shifts)
    assert np.abs(shifts.mean(axis=0)).max() < 4 * sigma / math.sqrt(n)
    assert shifts.std(axis=0) == pytest.approx([sigma] * 3, rel=5 / math.sqrt(2 * n))


def test_attitude_noise_rotates_about_the_sensor_origin(frame):
    sigma = 60.0 * ARCSEC
    deviation, truth, origin, _ = _run(frame, attitude_noise_arcsec=60.0)
    v = truth - origin  # to first order Δ = −a × v, a isotropic: var Δ_i = σ²(|v|² − v_i²)
    scaled = deviation / np.sqrt(np.sum(v * v, axis=1, keepdims=True) - v * v)
    assert scaled.std(axis=0) == pytest.approx([sigma] * 3, rel=5 / math.sqrt(2 * PULSES))
    assert np.abs(scaled.mean(axis=0)).max() < 5 * sigma / math.sqrt(PULSES)


def test_position_and_attitude_noise_are_independent(frame):
    deviation, truth, origin, _ = _run(frame, position_noise_m=0.05, attitude_noise_arcsec=60.0)
    v = truth - origin
    expected = np.sqrt(0.05 ** 2 + (60.0 * ARCSEC) ** 2 * (np.sum(v * v, axis=1, keepdims=True) - v * v))
    scaled = deviation / expected  # unit normal on every axis when the six draws are independent
    assert scaled.std(axis=0) == pytest.approx([1.0] * 3, rel=5 / math.sqrt(2 * PULSES))
    shifts = _run(frame, position_noise_m=0.05)[0][::frame.beams]
    assert np.abs(np.corrcoef(shifts.T)[np.triu_indices(3, 1)]).max() < 4 / math.sqrt(PULSES)


def _azimuth_turn(deviation, truth, origin):
    """Signed turn [rad] about the vertical through the sensor from the true to the processed point."""
    a = (truth - origin)[:, :2]
    b = a + deviation[:, :2]
    return np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.sum(a * b, axis=1))


def test_encoder_zero_error_turns_the_on_axis_beam_about_the_vertical(frame):
    deviation, truth, origin, _ = _run(frame, encoder_arcsec=120.0)
    centre = slice(CENTRE, None, frame.beams)
    d, t, o = deviation[centre], truth[centre], origin[centre]
    assert np.abs(d[:, 2]).max() < 1e-4  # a turn about the vertical keeps the height (level flight)
    rho = np.linalg.norm((t - o)[:, :2], axis=1)
    assert np.linalg.norm(d[:, :2], axis=1) == pytest.approx(2 * rho * math.sin(120.0 * ARCSEC / 2), abs=1e-4)
    # the prism stands 120″ past its reading; the processing, believing the reading, turns the point back
    assert _azimuth_turn(d, t, o) == pytest.approx(np.full(PULSES, 120.0 * ARCSEC), abs=2e-6)


def test_encoder_noise_has_its_sigma(frame):
    deviation, truth, origin, _ = _run(frame, encoder_noise_arcsec=30.0)
    centre = slice(CENTRE, None, frame.beams)
    turn = _azimuth_turn(deviation[centre], truth[centre], origin[centre])
    assert turn.std() == pytest.approx(30.0 * ARCSEC, rel=5 / math.sqrt(2 * PULSES))


def test_risley_budget_monte_carlo_agrees_with_its_linearisation():
    from flightsim.studies import risley_budget as rb

    cfg = rb.frame_config(turns=1)
    small = Frame(cfg, pulses=250)
    det = rb.deterministic(small)
    draws = 400
    mc = rb.monte_carlo(small, draws, seed=3)
    linear = rb.linearised_sigma(det)
    assert (mc.hits == draws).all()
    tolerance = 4.0 / math.sqrt(2 * (draws - 1))
    for k in range(3):
        assert abs(np.median(mc.std[:, k] / linear[:, k]) - 1.0) < tolerance, k
    # the roll error alone moves every point across track by H·tan(ε) to first order (level flight)
    assert det["roll"]["table"]["X"][0] == pytest.approx(500.0 * math.tan(18.0 * ARCSEC), rel=0.01)


@pytest.mark.parametrize("args, field", [
    (["budget", "--instrument", "lidar9", "--out", "OUT"], "--instrument"),
    (["simulate", "--set", "pose.boresight_arcsec=1,2", "--out", "OUT"], "pose.boresight_arcsec"),
    (["simulate", "--set", "pose.position_noise_m=-1", "--out", "OUT"], "pose.position_noise_m"),
    (["simulate", "--set", "risley.encoder_arcsec=20", "--set", "run.optics=lut", "--out", "OUT"], "run.optics"),
    (["simulate", "--instrument", "change3", "--set", "risley.encoder_arcsec=20", "--out", "OUT"],
     "risley.encoder_arcsec"),
])
def test_bad_error_input_exits_2_naming_the_field(tmp_path, args, field):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "flightsim", *[str(tmp_path / "o") if a == "OUT" else a for a in args]],
                         capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], run.stderr
