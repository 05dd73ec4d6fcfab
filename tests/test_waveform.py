"""The waveform detector on the device against closed forms and the float64 reference model (seed:
large-footprint-echo-waveform-patent.txt): flat echo = the pulse delayed by 2(H + Δ)/c, the slope's
RMS width, energy = the lidar equation, and bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from flightsim.cli import main
from flightsim.engine.tracer import Tracer
from flightsim.instrument import waveform_model as model
from flightsim.instrument.waveform_surfaces import PlaneSurface
from flightsim.instrument.waveform import system
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.studies.waveform import waveform_config
from flightsim.engine.readouts.waveforms import Waveforms

C = 299_792_458.0
H = 200e3
ALPHA = 3e-4
SMALL = {"waveform.n_rings": 24, "waveform.n_sectors": 48, "waveform.sample_interval_s": 5e-11,
         "waveform.samples": 8192}
E2 = math.exp(-2.0)


def _shot(scene: str, device: str = "cpu", **settings):
    cfg = waveform_config(scene, device, **{**SMALL, **settings})
    scene_mesh = build_scene(cfg)
    parts = []
    Tracer(cfg, scene_mesh, flight_trajectories(cfg, scene_mesh)).run(Waveforms(), parts.append)
    (chunk,) = parts
    times = chunk.window_start_s[0] + cfg.waveform.sample_interval_s * np.arange(cfg.waveform.samples)
    return cfg, times, chunk.power_w[0].astype(np.float64), chunk.received[0]


def _moments(times, power):
    """(energy-weighted mean time, RMS width) [s]."""
    mean = np.sum(times * power) / np.sum(power)
    return mean, math.sqrt(np.sum((times - mean) ** 2 * power) / np.sum(power))


def test_flat_echo_is_the_pulse_delayed_by_the_nadir_and_the_footprint_spread():
    cfg, times, power, _ = _shot("flat")
    sigma = 7e-9 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    assert model.fwhm_s(times, power) == pytest.approx(7e-9, rel=1e-3)
    mean, rms = _moments(times, power)
    assert rms == pytest.approx(sigma, rel=1e-3)
    # the truncated Gaussian's mean of H(1/cos φ − 1) ≈ ρ²/2H: Δ = Hα²(1 − 3e⁻²)/(4(1 − e⁻²))
    spread = H * ALPHA ** 2 * (1 - 3 * E2) / (4 * (1 - E2))
    assert spread == pytest.approx(3.0914e-3, rel=1e-4)
    assert mean - 3.5e-9 == pytest.approx(2 * (H + spread) / C, abs=1e-12)  # 1 ps of the 20.6 ps spread


def test_slope_widens_the_echo_by_the_footprint_across_the_slope():
    s = 0.2
    cfg, times, power, _ = _shot("slope")
    sigma_p = 7e-9 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    # RMS across-slope extent of exp(−2ρ²/R²) truncated at ρ = R = Hα: σ_x² = (R²/4)(1 − 3e⁻²)/(1 − e⁻²)
    sigma_x = math.sqrt((H * ALPHA) ** 2 / 4 * (1 - 3 * E2) / (1 - E2))
    _, rms = _moments(times, power)
    assert rms == pytest.approx(math.hypot(sigma_p, 2 * s * sigma_x / C), rel=0.01)
    untruncated = math.hypot(sigma_p, 2 * s * (H * ALPHA / 2) / C)  # σ_x = R/2 without the edge: 40 ns
    assert abs(rms / untruncated - 1) > 0.15


def test_received_energy_is_the_lidar_equation_and_the_echo_matches_the_reference():
    cfg, times, power, received = _shot("flat")
    # flat ground at normal incidence: P_r / P_s = π f D² /(4 H²) (eq. 1, every other factor 1)
    lidar = math.pi * 1.0 * 1.0 / (4 * H ** 2)
    assert received[0] == pytest.approx(lidar, rel=1e-3)
    assert received[1] == 0.0
    sys = system(cfg.waveform, altitude_m=H)
    rets = model.sample_returns(sys, model.footprint(sys), PlaneSurface(0.0))
    assert received[0] == pytest.approx(rets.gain.sum(), rel=1e-9)
    reference = model.echo_analytic(sys, rets, times)
    dt, sigma = cfg.waveform.sample_interval_s, model.pulse_sigma_s(sys)
    assert np.abs(power - reference).max() <= (dt / sigma) ** 2 / 8 * reference.max() + 1e-6 * reference.max()
    energy = np.sum(power) * dt  # ∫P_r dt = (P_r/P_s) × pulse energy A = √(2π) σ P_max
    assert energy == pytest.approx(lidar * math.sqrt(2 * math.pi) * sigma * 0.05, rel=1e-3)


def test_more_subrays_converge_on_the_fine_echo():
    _, times, fine, _ = _shot("slope", **{"waveform.n_rings": 64, "waveform.n_sectors": 128})
    errors = []
    for rings in (8, 16, 32):
        _, t, coarse, _ = _shot("slope", **{"waveform.n_rings": rings, "waveform.n_sectors": 2 * rings})
        assert np.array_equal(t, times)
        errors.append(np.abs(coarse - fine).max() / fine.max())
    assert errors[0] > 2.5 * errors[1] > 6.0 * errors[2]  # about second order in the ring width


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a GPU")
def test_cpu_and_gpu_waveforms_agree():
    _, t_cpu, cpu, _ = _shot("slope")
    _, t_gpu, gpu, _ = _shot("slope", device="cuda")
    assert np.array_equal(t_cpu, t_gpu)
    assert np.abs(cpu - gpu).max() <= 1e-6 * cpu.max()  # float32 output; atomics sum in any order


@pytest.mark.parametrize("key, value, field", [
    ("waveform.half_divergence_rad", "0", "waveform.half_divergence_rad"),
    ("waveform.pulse_fwhm_s", "0", "waveform.pulse_fwhm_s"),
    ("waveform.sample_interval_s", "1e-8", "waveform.sample_interval_s"),
    ("waveform.n_rings", "0", "waveform.n_rings"),
    ("waveform.scheme", "spiral", "waveform.scheme"),
])
def test_bad_waveform_input_exits_2_naming_the_field(tmp_path, capsys, key, value, field):
    assert main(["waveform", "--set", f"{key}={value}", "--out", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert field in err and "Traceback" not in err
    assert not (tmp_path / "w").exists()


E_ELECTRON = 6.62607015e-34 * C / (1064e-9 * 0.4)  # J per photo-electron at the defaults


def test_background_shot_noise_is_poisson_and_thermal_noise_gaussian():
    dt = SMALL["waveform.sample_interval_s"]
    background = 20 * E_ELECTRON / dt  # 20 photo-electrons per sample
    _, times, power, _ = _shot("flat", **{"waveform.shot_noise": True, "waveform.background_w": background})
    quiet = power[:3000] * dt / E_ELECTRON  # far before the echo: background alone, in electrons
    assert np.allclose(quiet, np.round(quiet), atol=1e-3)  # whole photo-electrons
    n = quiet.size
    assert abs(quiet.mean() - 20) < 4 * math.sqrt(20 / n)
    assert abs(quiet.var() / 20 - 1) < 4 * math.sqrt(2 / n)  # Poisson: variance = mean
    sigma = 1e-15
    _, _, noisy, _ = _shot("flat", **{"waveform.thermal_noise_w": sigma})
    _, _, clean, _ = _shot("flat")
    d = (noisy - clean)[:3000]
    assert abs(d.mean()) < 4 * sigma / math.sqrt(d.size)
    assert abs(d.std() / sigma - 1) < 4 / math.sqrt(2 * d.size)
    _, _, again, _ = _shot("flat", **{"waveform.thermal_noise_w": sigma})
    assert np.array_equal(again, noisy)  # same seed, same noise
    _, _, other, _ = _shot("flat", **{"waveform.thermal_noise_w": sigma, "run.seed": 7})
    assert not np.array_equal(other, noisy)


def test_digitiser_codes_and_clipping():
    _, _, clean, _ = _shot("flat")
    top = clean.max()
    _, _, coded, _ = _shot("flat", **{"waveform.bits": 8, "waveform.full_scale_w": 0.8 * top})
    lsb = 0.8 * top / 255
    codes = coded / lsb
    assert np.allclose(codes, np.round(codes), atol=1e-4)
    assert codes.max() == pytest.approx(255, abs=1e-3)  # the peak clips at full scale
    assert np.abs(coded - np.clip(clean, 0, 0.8 * top)).max() <= 0.5 * lsb * (1 + 1e-5)


def test_bits_without_full_scale_exit_2(tmp_path, capsys):
    assert main(["waveform", "--set", "waveform.bits=12", "--out", str(tmp_path / "w")]) == 2
    assert "waveform.full_scale_w" in capsys.readouterr().err


def test_risley_array_runs_with_the_waveform_detector_and_writes_returns(tmp_path):
    import laspy

    from flightsim.engine.config import RunConfig, set_value, validate
    from flightsim.engine.run import simulate_to_directory

    cfg = RunConfig()
    for key, value in {"instrument.detector": "waveform", "scene.name": "plane", "fan.array": 2,
                       "flight.duration_s": 0.002, "waveform.half_divergence_rad": 1.5e-4, "waveform.n_rings": 4,
                       "waveform.n_sectors": 8, "waveform.sample_interval_s": 5e-11, "waveform.samples": 1024}.items():
        set_value(cfg, key, value)
    summary = simulate_to_directory(validate(cfg), tmp_path / "r")
    assert summary["waveforms"] == summary["beams_fired"] == 4 * summary["pulses"]
    las = laspy.read(tmp_path / "r" / "returns.las")
    assert len(las.points) == summary["waveforms"]  # one Gaussian per beam on the plane
    assert np.abs(np.asarray(las.z) - cfg.scene.origin[2]).max() < 0.01  # on the plane (world height of local 0)


def test_receiver_response_widens_the_echo_and_keeps_its_energy():
    _, times, plain, _ = _shot("flat")
    tau_r = 4e-9
    _, _, read, _ = _shot("flat", **{"waveform.receiver_fwhm_s": tau_r})
    assert model.fwhm_s(times, read) == pytest.approx(math.hypot(7e-9, tau_r), rel=1e-3)  # Gaussians add in quadrature
    assert read.sum() == pytest.approx(plain.sum(), rel=1e-6)
    assert _moments(times, read)[0] == pytest.approx(_moments(times, plain)[0], abs=1e-13)  # no delay
