"""Waveform ranging on the device (kernels/waveform_measures.py, waveform_fit.py; flightsim/instrument/waveform_batch.py)
against SciPy and the host's float64 reference (waveform_model.measure, decompose): the smoothing against
scipy.ndimage.gaussian_filter1d, the peaks against scipy.signal.find_peaks and peak_widths, the measures and the
fitted Gaussians against the host's over simulated runs (change1: flat, slope, bump; GEDI: plane, point-cloud forest)
and synthetic sums of Gaussians with noise, and waveforms.h5 written with waveform.processing = "device" against
"host"."""
from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest
import warp as wp
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks, peak_widths

from flightsim.cli import main
from flightsim.instrument import waveform_model as model
from flightsim.instrument.waveform_batch import MAX_PEAKS, echo_peaks, process, smoothing_taps
from flightsim.studies import waveform_processing as study
from kernels import waveform_fit as kf
from kernels import waveform_measures as km

TIME_ULPS = 8  # measures' times [s]: within 8 units in the last place of the echo's time (operation order, FMA)
RMS_REL = 1e-13  # the RMS width: relative (its sums are compensated on the device, pairwise in NumPy)
GEDI = model.WaveformSystem(pulse_fwhm_s=1.5e-8, sample_interval_s=1e-9)


def _columns(a: np.ndarray, device: str) -> wp.array:
    return wp.array(np.ascontiguousarray(np.asarray(a, dtype=np.float64).T), dtype=wp.float64, device=device)


@pytest.mark.parametrize("samples, sd", [(300, 2.3), (300, 6.37), (2000, 29.7), (12, 5.0)])
def test_smoothing_is_gaussian_filter1d(device, samples, sd):
    rng = np.random.default_rng(samples)
    echo = rng.random((5, samples)) * np.exp(-0.5 * ((np.arange(samples) - samples / 2) / (samples / 8)) ** 2)
    steps = np.array([1.0, 1.0, 1.0 + 2e-16, 1.0, 1.0 + 2e-16])  # two Δt: two kernels, as t_1 − t_0 may round
    group, radius, taps = smoothing_taps(sd, steps)
    out = wp.empty((samples, 5), dtype=wp.float64, device=device)
    wp.launch(km.smooth_echoes, dim=(samples, 5), inputs=[_columns(echo, device), wp.array(group, device=device),
                                                          wp.array(radius, device=device), wp.array(taps, device=device)],
              outputs=[out], device=device)
    got = out.numpy().T
    want = np.array([gaussian_filter1d(echo[w], sd / steps[w]) for w in range(5)])
    if device == "cpu":  # the C loop's order of additions: the same float64 values
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-16 * want.max())


def _plateaus(waveforms: int, samples: int, seed: int) -> np.ndarray:
    """Smooth-ish lines quantised to 1/40 of their maximum: flat-topped peaks (plateaus) of 1 to many samples."""
    rng = np.random.default_rng(seed)
    i = np.arange(samples)
    line = np.zeros((waveforms, samples))
    for w in range(waveforms):
        for _ in range(rng.integers(1, 7)):
            line[w] += rng.uniform(0.05, 1.0) * np.exp(-0.5 * ((i - rng.uniform(0, samples)) / rng.uniform(3, 40)) ** 2)
    return np.round(line / line.max(axis=1, keepdims=True) * 40.0) / 40.0


@pytest.mark.parametrize("waveforms, samples", [(40, 500), (20, 2000)])  # 2 and 8 chunks of PEAK_CHUNK samples
def test_peaks_are_find_peaks_with_plateaus_and_widths_are_peak_widths(device, waveforms, samples):
    x, sigma, dt = _plateaus(waveforms, samples, 5), 2.0, 0.5
    n_wave = len(x)
    t0, steps = np.zeros(n_wave), np.full(n_wave, dt)
    maximum = np.zeros((7, n_wave))
    maximum[5] = x.max(axis=1)
    count = wp.zeros(n_wave, dtype=wp.int32, device=device)
    peaks = wp.zeros((MAX_PEAKS, n_wave), dtype=wp.int32, device=device)
    params = wp.zeros((3 * MAX_PEAKS, n_wave), dtype=wp.float64, device=device)
    smooth = _columns(x, device)
    echo_peaks(smooth, smooth, wp.array(t0, dtype=wp.float64, device=device), dt,
               wp.array(steps, dtype=wp.float64, device=device), sigma, 0.05,
               wp.array(np.full(n_wave, -np.inf), dtype=wp.float64, device=device),
               wp.array(maximum, dtype=wp.float64, device=device), count, peaks, params)
    count, peaks, params = count.numpy(), peaks.numpy().T, params.numpy().T
    plateaus = 0
    for w in range(n_wave):
        want, _ = find_peaks(x[w], prominence=0.05 * x[w].max())
        plateaus += int(np.sum(x[w][want] == x[w][want + 1]))
        assert count[w] == len(want)
        k = min(len(want), MAX_PEAKS)
        np.testing.assert_array_equal(peaks[w, :k], want[:k])
        width = peak_widths(x[w], want[:k], rel_height=0.5)[0] * dt / model.FWHM_PER_SIGMA
        s0 = np.maximum(np.sqrt(np.maximum(width * width - sigma * sigma, 0.0)), 0.5 * sigma) / sigma
        np.testing.assert_allclose(params[w, 2:3 * k:3], s0, rtol=1e-14)
        np.testing.assert_array_equal(params[w, 0:3 * k:3], x[w][want[:k]] / x[w].max())
        np.testing.assert_allclose(params[w, 1:3 * k:3], want[:k] * dt / sigma, rtol=1e-15)
    assert plateaus > 0  # the lines do hold flat-topped peaks


def _assert_equivalent(c: dict) -> None:
    """The module docstring's tolerances over one set's comparison (flightsim.studies.waveform_processing.compare)."""
    for name in ("half_power_s", "centroid_s", "peak_s", "fwhm_s"):
        assert c[f"{name}_ulps"] <= TIME_ULPS, (name, c)
    assert c["rms_width_s_rel"] <= RMS_REL, c
    assert c["peaks_differ"] == 0, c
    assert c["ssr_ratio_max"] <= 1.0 + study.SSR_SLACK, c
    assert c["q_over_gap_max"] <= 1.0, c
    assert c["host_fitted"] == 0, c


@pytest.mark.parametrize("system, waveforms, samples, seed", [(GEDI, 60, 1000, 11),
                                                              (model.WaveformSystem(sample_interval_s=5e-11), 6, 4096, 12)])
def test_synthetic_sums_of_gaussians_match_scipy(device, system, waveforms, samples, seed):
    _, _, t0, echo = study.synthetic("s", system, waveforms, samples, seed)
    c = study.compare(system, t0, echo, device)
    _assert_equivalent(c)
    assert c["components"] > waveforms  # several Gaussians per waveform on average


@pytest.mark.parametrize("scene", ["flat", "slope", "bump"])
def test_change1_waveforms_match_scipy(device, scene):
    _, system, t0, echo = study.simulated(scene, device, "change1", scene, **{"fixed.prf_hz": 20.0,
                                                                              "flight.duration_s": 0.1})
    _assert_equivalent(study.compare(system, t0, echo, device))


def test_gedi_plane_and_forest_waveforms_match_scipy(device):
    for name, system, t0, echo in (study.simulated("plane", device, "gedi", "flat", **{"flight.duration_s": 0.03}),
                                   study.simulated("forest", device, "gedi", str(study.CLOUD),
                                                   study.FOREST_CENTRES[:4])):
        c = study.compare(system, t0, echo, device)
        _assert_equivalent(c)
    assert c["components"] > c["waveforms"]  # the forest's canopy and ground


def test_six_gaussians_are_fitted_on_the_device_as_scipy_fits_them(device):
    """More Gaussians than kernels.waveform_fit.FEW_GAUSSIANS: the fit's per-thread sums sized for MAX_PEAKS."""
    sigma = model.pulse_sigma_s(GEDI)
    times = 1.3e-3 + 1e-9 * np.arange(1500)
    centres = times[0] + np.array([150.0, 330.0, 560.0, 760.0, 1010.0, 1290.0]) * 1e-9
    widths = sigma * np.array([1.0, 1.6, 1.2, 2.0, 1.1, 1.4])
    heights = np.array([0.5, 1.0, 0.35, 0.8, 0.6, 0.45])
    echo = np.sum(heights[:, None] * np.exp(-0.5 * ((times[None, :] - centres[:, None]) / widths[:, None]) ** 2),
                  axis=0)
    echo = (echo + np.random.default_rng(5).normal(0.0, 0.005, len(times))).astype(np.float32).astype(np.float64)
    c = study.compare(GEDI, times[:1], echo[None, :], device)
    _assert_equivalent(c)
    assert c["components"] == 6


def test_more_peaks_than_the_device_fits_are_decomposed_by_the_host(device):
    sigma = model.pulse_sigma_s(GEDI)
    times = 1.3e-3 + 1e-9 * np.arange(1200)
    centres = times[0] + np.linspace(100, 1100, MAX_PEAKS + 2) * 1e-9
    echo = np.sum(np.exp(-0.5 * ((times[None, :] - centres[:, None]) / sigma) ** 2), axis=0)
    b = process(GEDI, times[:1], echo[None, :], device)
    host = model.decompose(GEDI, times, echo)
    assert b.status[0] == km.STATUS_SKIPPED and b.count[0] == MAX_PEAKS + 2 == len(host)
    np.testing.assert_array_equal(b.time_s[0], [g.time_s for g in host])
    np.testing.assert_array_equal(b.amplitude_w[0], [g.amplitude_w for g in host])


def test_a_batch_in_parts_on_the_cpus_threads_is_the_batch_in_one_part(monkeypatch):
    """On the CPU a batch is cut into parts launched from several threads (waveform_batch.CPU_THREADS): 60 GEDI-like
    waveforms of one to five Gaussians (parts with the few-Gaussians fit and parts with MAX_PEAKS'), some under
    noise, in four parts of 15 on four threads (at most CPU_THREADS and the usable cores), are every measure,
    component and status of the batch in one part."""
    import flightsim.instrument.waveform_batch as wb

    _, system, t0, echo = study.synthetic("s", GEDI, 60, 1000, 31)
    rng = np.random.default_rng(9)
    samples = np.arange(1000)[None, None, :]
    centres = np.array([100.0, 250.0, 400.0, 550.0, 700.0, 850.0])[None, :, None] + rng.uniform(-20, 20, (5, 6, 1))
    widths = model.pulse_sigma_s(GEDI) / 1e-9 * rng.uniform(1.0, 1.8, (5, 6, 1))
    echo[20:25] = np.sum(rng.uniform(0.3, 1.0, (5, 6, 1)) * np.exp(-0.5 * ((samples - centres) / widths) ** 2), axis=1)
    echo = echo + np.where(np.arange(60)[:, None] % 3 == 0, rng.normal(0.0, 0.002, echo.shape), 0.0)
    mean, floor = model.window_noise(echo)
    monkeypatch.setattr(wb, "usable_cores", lambda: 1)
    whole = process(system, t0, echo, "cpu", noise=(mean, floor))
    monkeypatch.setattr(wb, "usable_cores", lambda: 7)
    monkeypatch.setattr(wb, "CPU_THREADS", 4)
    monkeypatch.setattr(wb, "CPU_PART", 8)
    launched = []
    launch = wb._launch
    monkeypatch.setattr(wb, "_launch", lambda *a: launched.append(len(a[1])) or launch(*a))
    parts = process(system, t0, echo, "cpu", noise=(mean, floor))
    assert launched == [15] * 4
    assert whole.count.max() > kf.FEW_GAUSSIANS >= whole.count.min() > 0  # both sizes of the fit's sums
    _assert_same_batch(parts, whole)


FRESH_PARTS = """
import numpy as np, warp as wp
import flightsim.instrument.waveform_batch as wb
from flightsim.core.warp_runtime import compile_ahead
from flightsim.studies import waveform_processing as study
from flightsim.instrument import waveform_model as model
system = model.WaveformSystem(pulse_fwhm_s=1.5e-8, sample_interval_s=1e-9)
_, _, t0, echo = study.synthetic("s", system, 16, 1000, 3)
compile_ahead("cpu", wb.kernels())
wb.CPU_PART, wb.CPU_THREADS = 4, 4
wb.usable_cores = lambda: 4
changed = []
mark = wp.Module.mark_modified
wp.Module.mark_modified = lambda self, *a, **k: changed.append(self.name) or mark(self, *a, **k)
for rows in (echo.astype(np.float32), echo):
    wb.process(system, t0, rows, "cpu")
print(sorted(set(changed)))
"""


def test_a_batch_s_parts_on_threads_launch_only_kernels_made_before_them():
    """The CPU's threads launch a batch's parts at once: a kernel made by a first launch (a generic kernel's
    overload for float32 or float64 waveforms) would change its module under another thread's launch (Warp then
    reads the overload's launch metadata before hashing it, and fails now and then). In a fresh process, after
    compile_ahead of waveform_batch.kernels(), parts of float32 and float64 waveforms on four threads change no
    module."""
    out = subprocess.run([sys.executable, "-c", FRESH_PARTS], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout + out.stderr


def _assert_same_batch(a, b) -> None:
    for name in ("time_s", "amplitude_w", "sigma_s", "count", "ssr", "status", "steps", "peaks"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name, value in b.measures.items():
        np.testing.assert_array_equal(a.measures[name], value, err_msg=name)


def test_the_fits_checked_every_round_or_seldom_from_the_host_or_in_a_graph_are_the_same(device, monkeypatch):
    """Whether any fit goes on is checked every waveform_batch.FIT_ROUNDS rounds, on a GPU inside one CUDA graph
    (a conditional loop on a stream of its own), else from the host: a check every round or every 5, and on a GPU the
    host's loop instead of the graph, give every number of the default (rounds past a fit's end leave it as it is)."""
    import flightsim.instrument.waveform_batch as wb

    _, _, t0, echo = study.synthetic("s", GEDI, 40, 1000, 13)
    graphs = []
    capture_launch = wp.capture_launch
    monkeypatch.setattr(wp, "capture_launch", lambda *a, **k: graphs.append(a) or capture_launch(*a, **k))
    default = process(GEDI, t0, echo, device)
    assert len(graphs) == (1 if device.startswith("cuda") and wp.is_conditional_graph_supported() else 0)
    # fits of one to four Gaussians ending after 3 to 18 steps: the early ones go through many rounds after their end
    assert default.count.max() > 1 and default.steps.min() >= 3 and default.steps.max() >= 4 * default.steps.min()
    for rounds in (1, 5):
        monkeypatch.setattr(wb, "FIT_ROUNDS", rounds)
        _assert_same_batch(process(GEDI, t0, echo, device), default)
    monkeypatch.setattr(wp, "is_conditional_graph_supported", lambda: False)
    _assert_same_batch(process(GEDI, t0, echo, device), default)


def test_noisy_waveforms_are_decomposed_less_their_noise_mean_as_on_the_host(device):
    """Under receiver noise (mean, floor) the device decomposes each waveform less its noise mean, counting only the
    smoothed maxima above the floor scaled to the smoothing and starting each fit from the smoothed height, as
    ``decompose`` does: the same peaks, fits equivalent by the module's measure, and no component in noise alone."""
    _, system, t0, echo = study.synthetic("s", GEDI, 30, 1000, 22)
    rng = np.random.default_rng(6)
    echo = np.vstack([echo + 0.2, 0.2 + rng.normal(0.0, 0.01, (3, 1000))])  # a background; three of noise alone
    t0 = np.append(t0, t0[:3])
    mean, floor = model.window_noise(echo)
    b = process(system, t0, echo, device, noise=(mean, floor))
    times = t0[:, None] + system.sample_interval_s * np.arange(1000)[None, :]
    for w in range(len(echo)):
        host = model.decompose(system, times[w], echo[w], noise=(mean[w], floor[w]))
        assert b.count[w] == len(host), w
        if host:
            device_parts = np.column_stack([b.time_s[w, :len(host)], b.amplitude_w[w, :len(host)],
                                            b.sigma_s[w, :len(host)]])
            ratio, q, _ = study.agreement(system, times[w], echo[w] - mean[w],
                                          [(g.time_s, g.amplitude_w, g.sigma_s) for g in host], device_parts)
            assert ratio <= 1.0 + study.SSR_SLACK and q <= 1.0, (w, ratio, q)
    assert b.count[:30].min() >= 1 and not b.count[30:].any()


CASES = {"gedi plane": (["simulate", "--instrument", "gedi", "--set", "flight.duration_s=0.03"], GEDI),
         "gedi plane, noisy": (["simulate", "--instrument", "gedi", "--set", "flight.duration_s=0.03", "--set",
                                "waveform.thermal_noise_w=2e-9"], GEDI),
         "change1 slope": (["waveform", "--scene", "slope", "--set", "fixed.prf_hz=20", "--set", "flight.duration_s=0.2"],
                           model.WaveformSystem())}


def _run(tmp_path, name: str, args: list[str], device: str, *extra: str):
    out = tmp_path / name
    assert main([*args, "--device", device, *extra, "--out", str(out)]) == 0
    return h5py.File(out / "waveforms.h5")


@pytest.mark.parametrize("case", list(CASES))
def test_waveforms_h5_with_device_processing_is_the_hosts(tmp_path, device, case):
    args, system = CASES[case]
    host = _run(tmp_path, "host", args, device, "--set", "waveform.processing=host")
    dev = _run(tmp_path, "device", args, device)  # the default
    names = []
    host.visit(lambda n: names.append(n) if isinstance(host[n], h5py.Dataset) else None)
    assert names and sorted(names) == sorted(n for n in names if n in dev)
    ranging = {"ranging/" + n for n in ("range_halfpower_m", "range_centroid_m", "range_peak_m", "fwhm_s",
                                        "rms_width_s", "component_range_m", "component_amplitude_w",
                                        "component_sigma_s")}
    for n in names:
        if n.split("/", 1)[1] not in ranging:
            _assert_same_run(host[n][()], dev[n][()], device, n)
    g, d = host["BEAM0000"], dev["BEAM0000"]
    for n in ("range_halfpower_m", "range_centroid_m", "range_peak_m"):  # c·t/2 of times within TIME_ULPS
        ulp = np.spacing(np.abs(g[f"ranging/{n}"][()]))
        assert np.all(np.abs(g[f"ranging/{n}"][()] - d[f"ranging/{n}"][()]) <= 2 * TIME_ULPS * ulp), n
    np.testing.assert_allclose(d["ranging/fwhm_s"][()], g["ranging/fwhm_s"][()], rtol=1e-9)
    np.testing.assert_allclose(d["ranging/rms_width_s"][()], g["ranging/rms_width_s"][()], rtol=RMS_REL)
    _assert_components(system, g, d, noisy="noisy" in case)


def _assert_same_run(a: np.ndarray, b: np.ndarray, device: str, name: str) -> None:
    """The same dataset of two runs of one command: bit for bit on the CPU. On a GPU, whose float64 atomics add a
    sample's sub-ray echoes in any order, and the FFT convolution carries a last-bit difference of one impulse into
    every output of its block at the FFT's rounding (~ε·log₂N of the block's largest output), which also rounds
    some float32 samples to their neighbours: floating-point values to two float32 units in their last place or
    1e-14 of the dataset's largest magnitude (the slope case on an H100: 1,236 of 163,840 samples differ, by at most
    1.3e-15 of the peak, in the echo's far tails)."""
    if device == "cpu" or not np.issubdtype(a.dtype, np.floating):
        np.testing.assert_array_equal(a, b, err_msg=name)
    else:
        np.testing.assert_allclose(b, a, rtol=2.0 ** -22, atol=1e-14 * float(np.nanmax(np.abs(a), initial=0.0)),
                                   err_msg=name)


def _assert_components(system, g, d, noisy: bool) -> None:
    """The file's components against each other by the fit's own measure (study.agreement), shot by shot; under
    receiver noise against the waveforms less their noise mean, which the Gaussians were fitted to."""
    n = int(g["rx_sample_count"][0])
    rx, t0 = g["rxwaveform"][()].reshape(-1, n).astype(np.float64), g["rx_window_start_s"][()]
    if noisy:
        rx = rx - model.window_noise(rx)[0][:, None]
    centre = 0.5 * system.pulse_fwhm_s
    for w in range(len(t0)):
        k = int(g["ranging/n_components"][w])
        parts = [np.column_stack([f["ranging/component_range_m"][w, :k] * 2.0 / model.C + centre,
                                  f["ranging/component_amplitude_w"][w, :k], f["ranging/component_sigma_s"][w, :k]])
                 for f in (g, d)]
        times = t0[w] + system.sample_interval_s * np.arange(n)
        ratio, q, _ = study.agreement(system, times, rx[w], *parts)
        assert ratio <= 1.0 + study.SSR_SLACK and q <= 1.0, (w, ratio, q)


def test_bad_processing_exits_2_naming_the_field(tmp_path, capsys):
    assert main(["simulate", "--instrument", "gedi", "--set", "waveform.processing=gpu", "--out",
                 str(tmp_path / "bad")]) == 2
    line = capsys.readouterr().err.strip().splitlines()
    assert len(line) == 1 and "waveform.processing" in line[0] and "host, device" in line[0], line
    assert not (tmp_path / "bad").exists()


def test_a_peak_on_a_negative_sample_fails_as_on_the_host(device):
    times = 1.3e-3 + 1e-9 * np.arange(1000)
    i = np.arange(1000)
    echo = np.exp(-0.5 * ((i - 300) / 6.37) ** 2) + 0.2 * np.exp(-0.5 * ((i - 700) / 40.0) ** 2)
    echo[699:702] += [0.125, -0.25, 0.125]  # the smoothed peak stays at 700, now a negative sample: a start below 0
    with pytest.raises(ValueError, match="bounds"):
        model.decompose(GEDI, times, echo)
    with pytest.raises(ValueError, match="bounds"):
        process(GEDI, times[:1], echo[None, :], device)


def test_an_echo_above_half_its_maximum_at_an_end_is_measured_as_on_the_host(device):
    times = 1.3e-3 + 1e-9 * np.arange(1000)
    i = np.arange(1000)
    starts_high = np.exp(-0.5 * ((i - 5) / 20.0) ** 2) + 0.5 * np.exp(-0.5 * ((i - 600) / 8.0) ** 2)
    b = process(GEDI, times[:1], starts_high[None, :], device)
    host = model.measure(GEDI, times, starts_high)  # its first crossing interpolates from the last sample (index −1)
    for name in ("half_power_s", "centroid_s", "peak_s", "fwhm_s"):
        assert abs(b.measures[name][0] - getattr(host, name)) <= TIME_ULPS * np.spacing(times[-1]), name
    with pytest.raises(IndexError):
        model.measure(GEDI, times, starts_high[::-1].copy())
    with pytest.raises(IndexError):
        process(GEDI, times[:1], starts_high[None, ::-1].copy(), device)


def test_noisy_waveforms_are_measured_above_their_noise_floor_as_on_the_host(device):
    """With each waveform's noise (mean, floor): the device's measures are the host's (waveform_model.measure) within
    the module's tolerances, all finite where an echo stands above the floor, all NaN in both where none does."""
    _, system, t0, echo = study.synthetic("s", GEDI, 30, 1000, 21)
    echo = np.vstack([echo + 0.2, 0.2 + np.random.default_rng(4).normal(0.0, 0.01, (1, 1000))])  # a background
    t0 = np.append(t0, t0[0])
    mean, floor = model.window_noise(echo)
    floor[-1] = 1.0  # the last: noise alone, its floor out of reach
    b = process(system, t0, echo, device, noise=(mean, floor))
    times = t0[:, None] + system.sample_interval_s * np.arange(1000)[None, :]
    host = [model.measure(system, times[w], echo[w], (mean[w], floor[w])) for w in range(len(echo))]
    for name in ("half_power_s", "centroid_s", "peak_s", "fwhm_s", "rms_width_s"):
        want = np.array([getattr(m, name) for m in host])
        assert np.isnan(want[-1]) and np.isnan(b.measures[name][-1]) and np.isfinite(want[:-1]).all(), name
        if name == "rms_width_s":
            np.testing.assert_allclose(b.measures[name][:-1], want[:-1], rtol=RMS_REL)
        else:
            assert np.all(np.abs(b.measures[name][:-1] - want[:-1]) <= TIME_ULPS * np.spacing(times[:-1, -1])), name
    assert b.count[-1] == 0 and np.isnan(b.time_s[-1]).all()  # no components in noise alone
