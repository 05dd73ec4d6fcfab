"""The photon-counting detector on the device against Poisson statistics, the dead-time closed form
and the lidar equation in float64."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import warp as wp
from scipy.special import gammainc

from flightsim.core.errors import InputError
from flightsim.instrument.photon import PhotonSettings as PhotonConfig
from flightsim.instrument.photon import check_settings, detect, detector_struct, first_photon_bias_s, sigma_t
from kernels import normal, photon

C = 299_792_458.0
SLOTS = 20_000
GATE = (5.0, 305.0)  # [m]: a 2 µs gate
T0 = 2 * 150.0 / C  # echo from 150 m


def _settings(**kw) -> PhotonConfig:
    return dataclasses.replace(PhotonConfig(gate_m=GATE, noise_hz=0.0, dead_time_s=0.0, max_events=64), **kw)


def test_signal_counts_are_poisson_with_the_expected_mean():
    n = 3.0
    d = detect(_settings(), np.full(SLOTS, n), np.full(SLOTS, T0), seed=1)
    counts = d.counts.astype(float)
    assert abs(counts.mean() - n) < 4 * math.sqrt(n / SLOTS)
    assert counts.var(ddof=1) / counts.mean() == pytest.approx(1.0, abs=4 * math.sqrt(2 / SLOTS))
    times = d.times[d.times > 0]
    sigma = sigma_t(_settings())
    assert abs(times.mean() - T0) < 4 * sigma / math.sqrt(times.size)
    assert times.std() == pytest.approx(sigma, rel=4 / math.sqrt(2 * times.size))
    assert d.signal[d.times > 0].all()


def test_tdc_bins_keep_the_range_unbiased():
    """A 250 ps TDC: each time reads its bin centre; over echoes at random phases the mean error is 0
    (within a tenth of a bin) and the spread adds bin²/12."""
    rng = np.random.default_rng(5)
    t0 = T0 + rng.uniform(0, 2.5e-10, SLOTS)
    s = _settings(tdc_bin_s=2.5e-10)
    d = detect(s, np.full(SLOTS, 2.0), t0, seed=6)
    kept = np.arange(64)[None, :] < d.counts[:, None]
    error = (d.times - t0[:, None])[kept]
    assert np.allclose((d.times[kept] / 2.5e-10) % 1.0, 0.5, atol=1e-6)
    assert abs(error.mean()) < 2.5e-11
    assert error.std() == pytest.approx(math.sqrt(sigma_t(s) ** 2 + 2.5e-10 ** 2 / 12), rel=0.03)


@pytest.mark.parametrize("n", [0.3, 1.0, 3.0])
def test_first_photon_pile_up_bias_matches_its_integral(n):
    """Dead time longer than the echo: only the first photo-electron counts, so the echo reads early."""
    s = _settings(dead_time_s=1e-7, max_events=1)
    d = detect(s, np.full(SLOTS, n), np.full(SLOTS, T0), seed=11)
    t = d.times[d.counts > 0, 0] - T0
    expected = first_photon_bias_s(n, sigma_t(s))
    assert expected < 0
    assert abs(t.mean() - expected) < 4 * t.std() / math.sqrt(t.size)
    assert (d.counts > 0).mean() == pytest.approx(1 - math.exp(-n), abs=4 * math.sqrt(0.25 / SLOTS))


def test_first_photon_bias_is_the_trapezoid_rule_bit_for_bit():
    """The pile-up bias of an array of strengths at once: each value the bits of NumPy's trapezoid rule over the same
    nodes, written out here as its formula reads (the calibration's pins and atl03.h5's table rest on them)."""
    from scipy.special import ndtr

    def plain(n, sigma_s):
        z = np.linspace(-10.0, 10.0, 200_001)
        density = n * (np.exp(-z**2 / 2.0) / np.sqrt(2.0 * np.pi)) * np.exp(-n * ndtr(z))
        return float(np.trapezoid(z * density, z) / np.trapezoid(density, z)) * sigma_s

    n = np.concatenate([np.random.default_rng(5).uniform(0.0, 40.0, 40), [1e-9, 0.1, 16.0, 900.0]]).reshape(4, 11)
    got = first_photon_bias_s(n, 1.3e-10)
    assert got.shape == (4, 11)
    assert np.array_equal(got, [[plain(k, 1.3e-10) for k in row] for row in n])
    assert isinstance(first_photon_bias_s(2.0, 1.3e-10), float)
    assert first_photon_bias_s(2.0, 1.3e-10) == plain(2.0, 1.3e-10)


def test_dead_time_saturation_matches_the_closed_form():
    """Background only, rate r over a gate T, non-paralyzable dead time τ, live at the gate's opening:
    the k-th detection comes at (k − 1)τ + Gamma(k, r), so E[N] = Σ_k P(k, r (T − (k − 1)τ))."""
    rate, tau = 2e7, 5e-8
    s = _settings(noise_hz=rate, dead_time_s=tau)
    gate = 2 * (GATE[1] - GATE[0]) / C
    d = detect(s, np.zeros(SLOTS), np.full(SLOTS, T0), seed=2)
    k = np.arange(1, 200)
    room = np.maximum(gate - (k - 1) * tau, 0.0)
    expected = float(np.sum(np.where(room > 0, gammainc(k, rate * room), 0.0)))
    assert rate * gate == pytest.approx(40.0, rel=1e-3) and expected < 25.0  # deep in saturation
    counts = d.counts.astype(float)
    assert abs(counts.mean() - expected) < 4 * counts.std() / math.sqrt(SLOTS)
    gaps = np.diff(d.times, axis=1)[(d.times[:, 1:] > 0)]
    assert gaps.min() >= tau * (1 - 1e-12)


def test_the_bound_of_detections_per_pulse_holds_at_saturation_and_is_tight():
    """A saturated echo (30 photo-electrons) behind a 50 ns dead time longer than the echo, and 5e4 Hz of
    background over the 2 µs gate: the mean detections stay below one plus the gate's mean background
    counts, within a few of its hundredths; with no dead time the bound is the kept detections."""
    s = _settings(noise_hz=5e4, dead_time_s=5e-8, max_events=8)
    bound = 1.0 + 5e4 * 2.0 * (GATE[1] - GATE[0]) / C
    assert s.detections_per_pulse() == pytest.approx(bound, rel=1e-12)
    n = 5 * SLOTS  # the mean's σ 1e-3; the dead time takes ~6e-3 below the bound
    mean = detect(s, np.full(n, 30.0), np.full(n, T0), seed=4).counts.mean()
    assert bound - 0.02 < mean <= bound
    assert _settings(dead_time_s=0.0, max_events=8).detections_per_pulse() == 8.0


def test_background_only_histogram_is_flat():
    s = _settings(noise_hz=2e6)
    d = detect(s, np.zeros(SLOTS), np.full(SLOTS, T0), seed=3)
    times = d.times[np.arange(64)[None, :] < d.counts[:, None]]
    lo, hi = (2 * g / C for g in GATE)
    observed, _ = np.histogram(times, bins=50, range=(lo, hi))
    expected = times.size / 50
    chi2 = float(np.sum((observed - expected) ** 2 / expected))
    assert chi2 < 49 + 5 * math.sqrt(2 * 49)
    assert times.size / SLOTS == pytest.approx(2e6 * (hi - lo), rel=4 / math.sqrt(times.size))
    assert not d.signal.any()


def test_signal_flag_follows_the_intensities():
    n, rate = 2.0, 1e6
    d = detect(_settings(noise_hz=rate), np.full(SLOTS, n), np.full(SLOTS, T0), seed=4)
    kept = np.arange(64)[None, :] < d.counts[:, None]
    gate = 2 * (GATE[1] - GATE[0]) / C
    share = n / (n + rate * gate)
    flags = d.signal[kept].astype(float)
    assert flags.mean() == pytest.approx(share, abs=4 * math.sqrt(share * (1 - share) / flags.size))


def test_same_seed_same_photons_and_launch_splits_change_nothing():
    s = _settings(noise_hz=1e6, dead_time_s=2e-8)
    n, t0 = np.full(1000, 1.5), np.full(1000, T0)
    a, b = detect(s, n, t0, seed=9), detect(s, n, t0, seed=9)
    assert np.array_equal(a.times, b.times) and np.array_equal(a.counts, b.counts)
    half = detect(s, n[500:], t0[500:], seed=9, first_slot=500)
    assert np.array_equal(a.times[500:], half.times)
    assert not np.array_equal(a.times, detect(s, n, t0, seed=10).times)
    if wp.is_cuda_available():
        g = detect(s, n, t0, seed=9, device="cuda")
        assert np.array_equal(a.counts, g.counts) and np.allclose(a.times, g.times, rtol=0, atol=1e-15)


@wp.kernel
def _expected(det: photon.PhotonDetector, r: wp.array(dtype=wp.float64), cos_i: wp.array(dtype=wp.float64),
              rho: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = photon.expected_signal(det, r[i], cos_i[i], rho[i])


def test_expected_signal_is_the_lidar_equation():
    s = PhotonConfig(wavelength_nm=532.0, pulse_energy_j=2e-6, aperture_m=0.1, optics_transmission=0.6, pde=0.25)
    r = np.array([34.0, 100.0, 600.0])
    cos_i = np.array([1.0, 0.5, 0.9])
    rho = np.array([0.2, 0.2, 0.05])
    out = wp.zeros(3, dtype=wp.float64, device="cpu")
    wp.launch(_expected, 3, inputs=[detector_struct(s), *(wp.array(a, dtype=wp.float64, device="cpu") for a in (r, cos_i, rho))],
              outputs=[out], device="cpu")
    photons = 2e-6 / (6.62607015e-34 * C / 532e-9)  # photons in the pulse
    area = math.pi * 0.05 ** 2
    expected = photons * rho * cos_i / math.pi * area / r ** 2 * 0.6 * 0.25
    assert out.numpy() == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("field, value", [("pde", 0.0), ("pde", 1.2), ("noise_hz", -1.0), ("dead_time_s", float("nan")),
                                          ("gate_m", (600.0, 5.0)), ("max_events", 0)])
def test_bad_detector_settings_name_the_field(field, value):
    with pytest.raises(InputError, match=f"photon.{field}"):
        check_settings("photon", dataclasses.replace(PhotonConfig(), **{field: value}))


def test_traced_run_counts_the_lidar_equation_of_every_beam(tmp_path):
    """The galvo imager hovering 100 m over the plane, no background, no dead time: the signal photons
    of all beams are Poisson with mean Σ n_b, n_b the lidar equation at each beam's own range and
    incidence from the float64 reference trace; signal times of flight sit at 2R/c."""
    import h5py
    import subprocess
    import sys

    from flightsim.instrument import galvo_model
    from flightsim.instrument.galvo_model import GalvoGeometry

    frames, columns = 4, 8
    settings = ["instrument.detector=photon", f"galvo.columns={columns}", f"flight.duration_s={0.1 * frames}",
                "photon.noise_hz=0", "photon.dead_time_s=0", "photon.max_events=64", "photon.pulse_energy_j=2e-9",
                "ranging.channel_delay_m=0", "ranging.jitter_s=0", "ranging.tdc_bin_s=0", "ranging.rise_time_s=0",
                "ranging.clock_drift=0"]
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "change3", "--out",
                          str(tmp_path / "run"), *[a for s in settings for a in ("--set", s)]],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    with h5py.File(tmp_path / "run" / "photons.h5") as f:
        g = {k: v[:] for k, v in f["photons"].items()}
    assert (g["signal"] == 1).all()  # no background: every photon is signal
    assert np.allclose(g["range_m"], g["time_of_flight_s"] * C / 2, rtol=1e-15)

    geom = GalvoGeometry(strips=17, columns=columns)
    delta, gamma, _ = galvo_model.raster_angles(geom)
    start, ray = galvo_model.trace(geom, delta[:, None], gamma[:, None], np.arange(16)[None, :])
    r = (100.0 - start[..., 2]) / ray[..., 2]  # the plane lies 100 m down the optical axis
    photons = 2e-9 / (6.62607015e-34 * C / 532e-9)
    n = photons * 0.2 * ray[..., 2] / math.pi * (math.pi * 0.025 ** 2) / r ** 2 * 0.5 * 0.2
    import json

    pulses = json.loads((tmp_path / "run" / "summary.json").read_text())["pulses"]
    expected = n.sum(axis=1)[np.arange(pulses) % (17 * columns)].sum()
    assert abs(len(g["pulse"]) - expected) < 4 * math.sqrt(expected)
    frame_slot = (g["pulse"] % (17 * columns)) * 16 + g["pixel"]
    bias = g["range_m"] - r.reshape(-1)[frame_slot]
    sigma_r = sigma_t(PhotonConfig()) * C / 2
    assert abs(bias.mean()) < 4 * sigma_r / math.sqrt(bias.size) + 2e-5  # + float32 ranges of the trace
    assert bias.std() == pytest.approx(sigma_r, rel=0.05)
    # each photon placed on its believed beam at c·t/2 lies on the plane (z = scene origin H = 450 m)
    height = g["z"] - 450.0
    assert abs(height.mean()) < 4 * sigma_r / math.sqrt(height.size) + 2e-5
    assert height.std() < sigma_r


@pytest.mark.parametrize("args, field", [
    (["simulate", "--set", "instrument.detector=photon", "--set", "photon.pde=1.5"], "photon.pde"),
    (["simulate", "--set", "instrument.detector=photon", "--set", "photon.noise_hz=-5"], "photon.noise_hz"),
    (["simulate", "--set", "instrument.detector=photon", "--set", "photon.gate_m=600,5"], "photon.gate_m"),
    (["simulate", "--set", "instrument.detector=spad9"], "instrument.detector"),
    (["sweep", "--set", "instrument.detector=photon", "--altitudes", "500"], "instrument.detector"),
])
def test_bad_photon_input_exits_2_naming_the_field(tmp_path, args, field):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "flightsim", *args, "--out", str(tmp_path / "o")],
                         capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], run.stderr


def test_photon_chunks_kept_by_the_consumer_are_its_own():
    """A consumer may keep every chunk's photons: ten chunks of 20 pulses must hand over what one chunk of the whole
    run does (the detections are keyed by seed, line, pulse and beam, so chunking never changes them)."""
    import flightsim
    from flightsim.engine.readouts.photons import Photons
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    runs = []
    for chunk_pulses in (20, 0):
        cfg = flightsim.load_config(instrument="atlas", overrides={"flight.duration_s": 0.02,
                                                                   "run.chunk_pulses": chunk_pulses})
        scene = build_scene(cfg)
        parts = []
        Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Photons(), parts.append)
        pulse, beam, tof = (np.concatenate([getattr(p, k) for p in parts]) for k in ("pulse", "pixel",
                                                                                      "time_of_flight_s"))
        order = np.lexsort((tof, beam, pulse))
        runs.append((len(parts), pulse[order], beam[order], tof[order]))
    (chunks, *many), (_, *one) = runs
    assert chunks >= 10 and len(one[0]) > 1000
    for a, b in zip(many, one):
        assert np.array_equal(a, b)


@wp.kernel
def _normal_tails(x: wp.array(dtype=wp.float64), det: photon.PhotonDetector, cdf: wp.array(dtype=wp.float64),
                  rate: wp.array(dtype=wp.float64)):
    i = wp.tid()
    cdf[i] = normal.normal_cdf(x[i])
    rate[i] = photon.echo_rate(det, x[i] * det.sigma_t, wp.float64(0.0), wp.float64(1.0))


def test_the_normal_tails_are_the_float64_values_without_erfc_or_exp(device):
    """Φ(x) and the echo's rate φ(x)/σ against float64 libm (math.erfc, math.exp): beyond ±NORMAL_TAIL the sampler
    returns 0, 1 and 0 without evaluating them, which are exactly what they give there; inside, the tails' tiny
    values (x = ±10: Φ = 7.6e-24, φ = 7.7e-23) are still made, to float64 rounding."""
    xs = np.array([-1e6, -40.5, -40.0, -39.9, -37.0, -10.0, -1.0, 0.0, 2.5, 10.0, 39.9, 40.0, 40.5, 1e6])
    det = photon.PhotonDetector()
    det.sigma_t = 1.0e-9
    cdf, rate = (wp.zeros(len(xs), dtype=wp.float64, device=device) for _ in range(2))
    wp.launch(_normal_tails, len(xs), inputs=[wp.array(xs, dtype=wp.float64, device=device), det],
              outputs=[cdf, rate], device=device)
    expected_cdf = np.array([0.5 * math.erfc(-x / math.sqrt(2.0)) for x in xs])
    expected_rate = np.array([math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi) / det.sigma_t for x in xs])
    tail = np.abs(xs) >= float(normal.NORMAL_TAIL)
    assert np.array_equal(cdf.numpy()[tail], expected_cdf[tail]) and set(expected_cdf[tail]) == {0.0, 1.0}
    assert np.array_equal(rate.numpy()[tail], expected_rate[tail]) and not expected_rate[tail].any()
    # inside, to float64 rounding: the argument's rounding δ ≈ 1.1e-16 |x| moves erfc and exp in the tails by a
    # relative x·δx ≈ x² · 1.1e-16 (2e-13 at x = 37), whatever the implementation
    rtol = 1e-14 + 4.0 * xs[~tail] ** 2 * 2.2e-16
    assert np.all(np.abs(cdf.numpy()[~tail] - expected_cdf[~tail]) <= rtol * expected_cdf[~tail])
    assert np.all(np.abs(rate.numpy()[~tail] - expected_rate[~tail]) <= rtol * expected_rate[~tail])
    assert 0.0 < cdf.numpy()[xs == -10.0][0] < 1e-23 and 0.0 < rate.numpy()[xs == 10.0][0]
