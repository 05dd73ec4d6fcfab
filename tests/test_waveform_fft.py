"""The waveforms' convolution with the pulse by overlap-save tile FFTs (``waveform.convolution = "fft"``) against
the float64 NumPy convolution of the same impulse trains and against the direct sums: the change1 preset over
the 0.20 slope and the flat plane, the error relative to each waveform's peak within a small factor of the direct
path's (both the float32 rounding of the output), exact zeros beyond the taps' reach of the touched span; a single
impulse gives the sampled pulse P(t) = P_max exp(−(t − τ/2)²/2σ²) (closed form); bad input."""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from flightsim.core.errors import InputError
from flightsim.engine.readouts.convolution import PulseConvolution, fft_size
from flightsim.engine.readouts.waveforms import Waveforms
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.instrument.waveform import WaveformDetector
from flightsim.studies.waveform import waveform_config
from kernels import waveform as kw

FLOAT32_HALF_ULP = 2.0 ** -24  # the float32 output's rounding, relative to the value


def _chunk(scene: str, device: str):
    """(impulse rows, spans, pulse taps, first lag) of one change1 shot over ``scene``, on the host (summed directly:
    the FFTs zero the trains as they read them)."""
    cfg = waveform_config(scene, device, **{"waveform.convolution": "direct"})
    mesh = build_scene(cfg)
    readout, kept = Waveforms(on_device=True), []

    def consume(found):
        b = readout.buffers
        kept.append((b.impulses.numpy()[:found.count].copy(), b.span.numpy()[:found.count].copy()))

    tracer = Tracer(cfg, mesh, flight_trajectories(cfg, mesh))
    tracer.run(readout, consume)
    impulses, span = kept[0]
    taps, first_lag = tracer.instrument.detector.pulse_taps("cpu")
    return impulses, span, taps.numpy(), first_lag


def _reference(row: np.ndarray, taps: np.ndarray, first_lag: int) -> np.ndarray:
    """out[i] = Σ_j row[j] taps[i − j − first_lag] in float64 (NumPy)."""
    full = np.convolve(row, taps)
    lag = np.arange(len(row)) - first_lag
    inside = (lag >= 0) & (lag < len(full))
    return np.where(inside, full[np.clip(lag, 0, len(full) - 1)], 0.0)


def _convolve(method: str, impulses: np.ndarray, span: np.ndarray, taps: np.ndarray, first_lag: int,
              device: str, left: list | None = None, **fft) -> np.ndarray:
    """The convolution's output rows; ``left`` gets the impulse trains as the launch left them."""
    pulse = PulseConvolution(method, wp.array(taps, dtype=wp.float64, device=device), first_lag, impulses.shape[1],
                             device, **fft)
    out = wp.empty(impulses.shape, dtype=wp.float32, device=device)
    out.fill_(7.0)  # launch zeroes its rows first
    trains = wp.array(impulses, dtype=wp.float64, device=device)
    pulse.launch(trains, wp.array(span, dtype=wp.int32, device=device), out, len(impulses))
    if left is not None:
        left.append(trains.numpy())
    return out.numpy()


@pytest.mark.parametrize("scene", ["slope", "flat"])
def test_fft_and_direct_against_the_float64_convolution(device, scene):
    impulses, span, taps, first_lag = _chunk(scene, device)
    assert len(taps) > 3000 and impulses.shape[1] == 32768 and np.all(span[:, 0] <= span[:, 1])
    errors = {}
    for method in ("direct", "fft"):  # every row by FFTs (direct_below=0), however narrow its span
        out = _convolve(method, impulses, span, taps, first_lag, device, **({"direct_below": 0} if method == "fft" else {}))
        worst = 0.0
        for row, got, (lo, hi) in zip(impulses, out, span):
            ref = _reference(row, taps, first_lag)
            worst = max(worst, np.abs(got - ref).max() / ref.max())
            reach = np.zeros(len(row), dtype=bool)
            reach[max(lo + first_lag, 0):hi + first_lag + len(taps)] = True
            assert np.all(got[~reach] == 0.0), method  # beyond the taps of the touched span: exactly 0
            assert np.all(got >= 0.0)
        errors[method] = worst
    assert errors["direct"] <= 1.5 * FLOAT32_HALF_ULP
    assert errors["fft"] <= max(2.0 * errors["direct"], 1.5 * FLOAT32_HALF_ULP), errors


def test_a_single_impulse_gives_the_sampled_pulse(device):
    """One unit impulse at sample j0: out[j0 + k] = P(k·dt) = P_max exp(−(k dt − τ/2)²/2σ²) for the lags k within
    ±8σ of τ/2 (the taps), 0 elsewhere; also with the impulse near either end of the row (the FFT blocks reach past
    the row's start and end)."""
    cfg = waveform_config("flat", device)
    taps, first_lag = WaveformDetector(cfg.waveform).pulse_taps("cpu")
    taps = taps.numpy()
    dt, fwhm, peak = cfg.waveform.sample_interval_s, cfg.waveform.pulse_fwhm_s, cfg.waveform.peak_power_w
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    samples = 32768
    for j0 in (100, 16000, samples - 50):
        row = np.zeros((1, samples))
        row[0, j0] = 1.0
        span = np.array([[j0, j0]], dtype=np.int32)
        k = np.arange(samples) - j0  # the lag of each sample [samples]; the pulse's ±8σ about τ/2 in whole samples:
        lags = (k >= math.floor((0.5 * fwhm - 8.0 * sigma) / dt)) & (k <= math.ceil((0.5 * fwhm + 8.0 * sigma) / dt))
        expected = np.where(lags, peak * np.exp(-0.5 * ((k * dt - 0.5 * fwhm) / sigma) ** 2), 0.0)
        for method in ("direct", "fft"):
            got = _convolve(method, row, span, taps, first_lag, device,
                            **({"direct_below": 0} if method == "fft" else {}))[0]
            assert np.all(got[~lags] == 0.0), (method, j0)
            assert np.abs(got - expected).max() <= 1.5 * FLOAT32_HALF_ULP * peak, (method, j0)


def test_the_kept_bins_are_where_a_gaussian_pulses_spectrum_falls_to_the_floor():
    """A Gaussian pulse of σ samples has the spectrum exp(−(2πσk/N)²/2): it falls to 1e-15 of its peak at
    k = N·√(2 ln 1e15)/(2πσ) (change1: σ = 297 samples, N = 8192: 36.5); a pulse cut at ±6.7σ leaks above the floor
    everywhere, so every bin is kept."""
    from flightsim.engine.readouts.convolution import kept_bins

    for sigma, n in ((297.0, 8192), (59.4, 4096), (20.0, 1024)):
        lags = np.arange(-int(8 * sigma), int(8 * sigma) + 1)
        expected = n * math.sqrt(2.0 * math.log(1e15)) / (2.0 * math.pi * sigma)
        assert kept_bins(np.exp(-0.5 * (lags / sigma) ** 2), n) == math.floor(expected), (sigma, n)
    short = np.exp(-0.5 * (np.arange(-200, 201) / 30.0) ** 2)
    assert kept_bins(short, 1024) == 512
    assert kept_bins(np.zeros(101), 256) == 128  # a pulse whose taps underflowed: every bin, no error


@pytest.mark.parametrize("scene", ["slope", "bump"])
def test_dropping_the_bins_beyond_the_floor_keeps_the_error(device, scene):
    """The FFTs with the pulse's spectrum cut at its float64 floor (fewer levels of butterflies) and with every bin
    both give the float64 convolution to the float32 output's rounding; the cut one differs from the other only in
    that rounding (the products it drops are ~1e-15 of the largest)."""
    settings = {"waveform.sample_interval_s": 5e-11, "waveform.samples": 2048} if scene == "bump" else {}
    cfg = waveform_config(scene, device, **settings, **{"waveform.convolution": "direct"})  # the trains kept
    mesh, readout, kept = build_scene(cfg), Waveforms(on_device=True), []
    Tracer(cfg, mesh, flight_trajectories(cfg, mesh)).run(
        readout, lambda found: kept.append((readout.buffers.impulses.numpy()[:found.count].copy(),
                                            readout.buffers.span.numpy()[:found.count].copy())))
    (impulses, span), = kept
    taps, first_lag = (a.numpy() if hasattr(a, "numpy") else a
                       for a in WaveformDetector(cfg.waveform).pulse_taps("cpu"))
    outs, keeps = {}, {}
    for name, floor in (("cut", {}), ("every bin", {"floor": 0.0})):
        pulse = PulseConvolution("fft", wp.array(taps, dtype=wp.float64, device=device), first_lag,
                                 impulses.shape[1], device, direct_below=0, **floor)
        keeps[name] = pulse.keep
        out = wp.zeros(impulses.shape, dtype=wp.float32, device=device)
        pulse.launch(wp.array(impulses, dtype=wp.float64, device=device), wp.array(span, dtype=wp.int32,
                                                                                  device=device), out, len(impulses))
        outs[name] = out.numpy().astype(np.float64)
    assert 0 < keeps["cut"] < pulse.n // 8 and keeps["every bin"] == -1  # change1: 36 of 8192; bump: 91 of 4096
    for name, out in outs.items():
        for row, got in zip(impulses, out):
            ref = _reference(row, taps, first_lag)
            assert np.abs(got - ref).max() <= 1.5 * FLOAT32_HALF_ULP * ref.max(), name
    assert np.abs(outs["cut"] - outs["every bin"]).max() <= 2.0 * FLOAT32_HALF_ULP * outs["every bin"].max()


def test_fft_sizes():
    """N is the smallest power of two that exceeds the taps and reaches the least asked for, or the row plus the
    taps − 1 if shorter (change1: 4759 taps, 32768 samples; gedi: ~100 taps, 1000 samples)."""
    assert fft_size(4759, 32768) == 8192 and fft_size(100, 32768) == 8192 and fft_size(8192, 32768) == 16384
    assert fft_size(103, 1000) == 2048 and fft_size(100, 32768, least=256) == 256 and fft_size(300, 9000, 256) == 512
    assert fft_size(10, 20) == 32


def test_a_small_fft_many_blocks_and_rows(device):
    """Random impulse trains over several rows, FFT size 1024 (many blocks per row, blocks cut by both ends of the
    row, a row with nothing touched) against the float64 convolution."""
    rng = np.random.default_rng(7)
    samples, taps_n, first_lag = 6000, 401, -150
    taps = np.exp(-0.5 * ((np.arange(taps_n) - 200) / 30.0) ** 2)
    rows, span = np.zeros((4, samples)), np.array([[10, 3000], [5900, 5999], [0, 0], [samples, -1]], dtype=np.int32)
    for r in range(3):
        lo, hi = span[r]
        rows[r, lo:hi + 1] = rng.random(hi - lo + 1)
    for least in (1024, 512):  # 512: each FFT makes 112 outputs, its pairs of blocks step less than the taps
        fft, left = {"fft_least": least, "block_dim": 64}, []
        out = _convolve("fft", rows, span, taps, first_lag, device, left, direct_below=0, **fft)
        for r in range(4):
            ref = _reference(rows[r], taps, first_lag)
            assert np.abs(out[r] - ref).max() <= 1.5 * FLOAT32_HALF_ULP * max(ref.max(), 1e-300)
            assert np.all(out[r][ref == 0.0] == 0.0)
        assert not left[0].any(), least  # every train the FFTs read is left zero
        # rows narrower than direct_below are the direct sums bit for bit (their trains left as they were), the
        # others the FFTs'
        mixed = _convolve("fft", rows, span, taps, first_lag, device, left, direct_below=200, **fft)
        direct = _convolve("direct", rows, span, taps, first_lag, device, left)
        assert np.array_equal(mixed[1:], direct[1:]) and np.array_equal(mixed[0], out[0])
        assert np.array_equal(left[1][1:], rows[1:]) and not left[1][0].any() and np.array_equal(left[2], rows)


@pytest.mark.parametrize("scene, settings", [("slope", {}), ("bump", {"waveform.sample_interval_s": 5e-11,
                                                                       "waveform.samples": 2048})])
def test_the_readout_runs_the_convolution_of_the_setting(device, scene, settings):
    """A whole run with waveform.convolution = fft gives the direct run's waveforms to the float32 rounding, exactly 0
    where they are beyond the reach (the second case: 951 taps, FFT size 4096 covering a row at once; inside the
    reach, where the pulse's tails fall below ~1e-16 of the peak, the FFT's rounding may leave 0 for a tiny sum)."""
    power = {}
    for method in ("direct", "fft"):
        cfg = waveform_config(scene, device, **settings, **{"waveform.convolution": method})
        mesh, parts = build_scene(cfg), []
        Tracer(cfg, mesh, flight_trajectories(cfg, mesh)).run(Waveforms(), parts.append)
        power[method] = np.concatenate([part.power_w for part in parts]).astype(np.float64)
    direct, fft = power["direct"], power["fft"]
    assert direct.shape == fft.shape and direct.max() > 0.0
    for d, f in zip(direct, fft):  # beyond the direct sums' first and last non-zero sample both are exactly 0
        touched = np.flatnonzero(d)
        outside = np.ones(len(d), dtype=bool)
        outside[touched.min():touched.max() + 1] = False
        assert np.all(f[outside] == 0.0) and np.all(f[d > 1e-12 * d.max()] > 0.0)
    assert np.abs(fft - direct).max() <= 2.0 * FLOAT32_HALF_ULP * direct.max()


@pytest.mark.parametrize("scene", ["slope", "flat"])
def test_a_chunk_clears_only_what_the_last_one_touched(device, scene, monkeypatch):
    """The impulse trains are zeroed once, then each chunk clears only the last chunk's touched spans: a run of one
    pulse per chunk gives every beam the waveform it gets when all pulses share the first chunk (bit for bit on the
    CPU: no stale impulse)."""
    from flightsim.engine.readouts import waveforms as readout_module

    power = {}
    for per_chunk in ("all", "one"):
        cfg = waveform_config(scene, device, **{"fixed.prf_hz": 1000.0, "flight.duration_s": 0.0035})  # 4 shots
        if per_chunk == "one":
            monkeypatch.setitem(readout_module.WAVEFORM_SAMPLES_PER_CHUNK, "cpu" if device == "cpu" else "cuda",
                                cfg.waveform.samples)
        mesh, parts = build_scene(cfg), []
        Tracer(cfg, mesh, flight_trajectories(cfg, mesh)).run(Waveforms(), parts.append)
        power[per_chunk] = np.concatenate([part.power_w for part in parts]).astype(np.float64)
        assert len(parts) == (4 if per_chunk == "one" else 1)
    assert power["one"].shape == power["all"].shape and power["all"].max() > 0.0
    if device == "cpu":
        assert np.array_equal(power["one"], power["all"])
    else:  # a GPU's float64 atomics add in any order
        assert np.abs(power["one"] - power["all"]).max() <= 2.0 * FLOAT32_HALF_ULP * power["all"].max()


def test_a_tracers_second_run_reuses_its_buffers_cleanly(device):
    """The waveform buffers are kept for a tracer's later runs: its second run starts on the impulse trains and
    power its first left (cleared within their spans and reach by its first chunk) and makes the same waveforms
    (bit for bit on the CPU)."""
    cfg = waveform_config("slope", device, **{"fixed.prf_hz": 1000.0, "flight.duration_s": 0.0015})  # 2 shots
    mesh = build_scene(cfg)
    tracer, power = Tracer(cfg, mesh, flight_trajectories(cfg, mesh)), []
    for _ in range(2):
        parts = []
        tracer.run(Waveforms(), parts.append)
        power.append(np.concatenate([part.power_w for part in parts]).astype(np.float64))
    assert power[0].max() > 0.0
    if device == "cpu":
        assert np.array_equal(power[0], power[1])
    else:  # a GPU's float64 atomics add in any order
        np.testing.assert_allclose(power[1], power[0], rtol=2.0 ** -22, atol=1e-14 * power[0].max())


def test_clear_impulses_zeroes_the_spans_of_the_narrow_rows(device):
    """kernels/waveform.py clear_impulses against NumPy (a span wider than its threads, 141 samples, among them):
    impulses zeroed over each row's span [lo, hi] if it is narrower than the given width, nothing else touched."""
    samples = 300
    span = np.array([[0, 5], [290, 299], [100, 100], [samples, -1], [40, 180]], dtype=np.int32)
    i, lo, hi = np.arange(samples)[None, :], span[:, :1], span[:, 1:]
    for narrower in (1 << 30, 10):
        impulses = wp.array(np.ones((len(span), samples)), dtype=wp.float64, device=device)
        wp.launch(kw.clear_impulses, (len(span), kw.CLEAR_THREADS),
                  inputs=[wp.array(span, dtype=wp.int32, device=device), narrower], outputs=[impulses], device=device)
        cleared = (i >= lo) & (i <= hi) & (hi - lo + 1 < narrower)
        np.testing.assert_array_equal(impulses.numpy(), np.where(cleared, 0.0, 1.0))
        assert cleared[4].any() == (narrower > 141)


def test_clear_power_zeroes_the_last_reach_outside_the_new_one(device):
    """kernels/waveform.py clear_power against NumPy: power zeroed over the reach of each row's last span [lo +
    first_lag, hi + first_lag + taps − 1] (within the row) less the reach of its new span (none from ``rows`` on),
    nothing else touched: new reaches to either side, inside, around, disjoint, empty; a row beyond ``rows``."""
    samples, first_lag, taps = 400, -7, 20
    last = np.array([[0, 5], [100, 250], [100, 250], [100, 250], [100, 250], [100, 250], [380, 399], [samples, -1],
                     [50, 60]], dtype=np.int32)
    new = np.array([[3, 3], [50, 150], [200, 300], [150, 160], [20, 300], [samples, -1], [10, 20], [5, 9],
                    [50, 60]], dtype=np.int32)
    rows = len(last) - 1  # the last row has no new span
    power = wp.array(np.ones((len(last), samples)), dtype=wp.float32, device=device)
    wp.launch(kw.clear_power, (len(last), kw.CLEAR_THREADS),
              inputs=[wp.array(last, dtype=wp.int32, device=device), wp.array(new, dtype=wp.int32, device=device),
                      rows, first_lag, taps], outputs=[power], device=device)
    i = np.arange(samples)[None, :]

    def reach(s):
        lo, hi = s[:, :1], s[:, 1:]
        return (i >= lo + first_lag) & (i <= hi + first_lag + taps - 1) & (hi >= lo)

    kept = reach(new) & (np.arange(len(last)) < rows)[:, None]
    expected = np.where(reach(last) & ~kept, 0.0, 1.0)
    np.testing.assert_array_equal(power.numpy(), expected)
    assert (expected == 0.0).sum(axis=1).tolist()[-1] == 11 + taps - 1 and expected[2, 93:192].min() == 0.0


def test_bad_convolution_is_one_line_input_error(tmp_path):
    with pytest.raises(InputError) as raised:
        waveform_config("flat", "cpu", **{"waveform.convolution": "fast"})
    assert "waveform.convolution" in str(raised.value) and "\n" not in str(raised.value)
    env = dict(os.environ, PYTHONPATH=os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "change1", "--set",
                           "waveform.convolution=fast", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, env=env, timeout=300)
    lines = [line for line in done.stderr.splitlines() if line.startswith("flightsim: error")]
    assert done.returncode == 2 and len(lines) == 1 and "waveform.convolution" in lines[0], done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "run").exists()


def test_the_convolve_kernel_of_the_setting_is_compiled_ahead():
    cfg = waveform_config("flat", "cpu", **{"waveform.convolution": "fft"})
    mesh = build_scene(cfg)
    tracer = Tracer(cfg, mesh, flight_trajectories(cfg, mesh))
    names = [k.key for k in Waveforms().kernels_needed(tracer)]
    assert any("convolve_fft" in name for name in names) and "split_spans" in names and kw.convolve.key in names
