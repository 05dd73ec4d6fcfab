"""Echo measures and Gaussian decomposition of a chunk of waveforms on the device: the batched form of
:func:`flightsim.instrument.waveform_model.measure` and :func:`~flightsim.instrument.waveform_model.decompose`
(kernels/waveform_measures.py, kernels/waveform_fit.py), for the writer's ``waveform.processing = "device"``.

The steps are the host functions', in the same float64 operations where the order is theirs to copy:
- the smoothing is scipy.ndimage.gaussian_filter1d's (σ/Δt samples, truncate 4, ``reflect``): its taps are formed
  here by scipy's own formula, per distinct Δt = t_1 − t_0 of the chunk, and added in its C loop's order;
- the peaks are scipy.signal.find_peaks' (local maxima, plateaus to their midpoint) with prominence ≥ 5 % of the
  smoothed maximum (and, under receiver noise, at least the noise floor times the smoothing's gain high), their
  widths peak_widths' at rel_height 0.5, and the start parameters and bounds decompose's;
- the fit is a bounded Levenberg–Marquardt (kernels/waveform_fit.py) where decompose calls curve_fit (scipy's
  trust-region-reflective): both minimise the same sum of squares from the same start within the same bounds.
  The device's ends at float64 rounding, scipy's at a 1e-8 relative change of the cost, so their parameters differ
  by what that gap allows (docs/waveform-processing.md).
- The centroid's and RMS width's sums are compensated (Neumaier) where NumPy's are pairwise: they agree to a few
  units in the last place.

A waveform with more than MAX_PEAKS peaks, or none, or a peak on a negative sample (a start amplitude outside the
bound a ≥ 0, which curve_fit refuses) is not fitted on the device: its components are the host's (``decompose``), so
the result is the host's there too (a ValueError for the last two, as on the host). So are the measures of an echo
that starts or ends above half its maximum (where the host's indexing leaves the window).

On the CPU a batch's parts are launched from up to CPU_THREADS threads at once: Warp runs a CPU launch on the
thread that makes it, with Python's lock released, so the parts use as many cores; every waveform is worked out by
the same operations whatever part it falls in (``tests/test_waveform_batch.py``).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.process_map import usable_cores
from flightsim.core.warp_runtime import compile_ahead
from flightsim.instrument import waveform_model as model
from kernels import waveform_fit as kf
from kernels import waveform_measures as km

MAX_PEAKS = int(km.MAX_PEAKS)
BATCH_SAMPLES = {"cpu": 1 << 24, "cuda": 1 << 26}  # samples per launch (W·N): the float64 echo and its smoothing
# take 8 bytes each (128 MiB each on the CPU, 512 MiB on a GPU: 2048 change1 waveforms, 67,108 GEDI ones)
MEASURES = ("half_power_s", "centroid_s", "peak_s", "fwhm_s", "rms_width_s")
FIT_ROUNDS = 8  # rounds of the fit between two checks of whether any fit goes on
CPU_THREADS = 16  # the most threads that launch a batch's parts at once on the CPU
CPU_PART = 64  # the fewest waveforms in a part when the CPU's threads share a batch


@dataclass(frozen=True)
class Batch:
    """Measures and components of W waveforms: ``measures`` name → (W,) [s]; ``time_s``, ``amplitude_w``,
    ``sigma_s`` (W, K) the components in time order (NaN-padded; K ≥ the most any waveform has); ``count`` (W,);
    ``ssr`` (W,) the device fit's sum of squared residuals in units of the maximum² (NaN where the host fitted);
    ``status`` (W,) kernels.waveform_measures STATUS_*; ``steps`` (W,) Levenberg–Marquardt steps; ``peaks``
    (W, MAX_PEAKS) the samples of the first MAX_PEAKS peaks found, −1-padded."""

    measures: dict[str, np.ndarray]
    time_s: np.ndarray
    amplitude_w: np.ndarray
    sigma_s: np.ndarray
    count: np.ndarray
    ssr: np.ndarray
    status: np.ndarray
    steps: np.ndarray
    peaks: np.ndarray

    def ranges_m(self, system: model.WaveformSystem) -> dict[str, np.ndarray]:
        """Half-power, centroid and peak ranges [m] as :func:`~flightsim.instrument.waveform_model.measure` reads them."""
        m, centre = self.measures, 0.5 * system.pulse_fwhm_s
        return {"half_power_range_m": 0.5 * model.C * m["half_power_s"],
                "centroid_range_m": 0.5 * model.C * (m["centroid_s"] - centre),
                "peak_range_m": 0.5 * model.C * (m["peak_s"] - centre)}


def smoothing_taps(sigma_s: float, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(group of each waveform, radius of each group [samples], one-sided taps (G, R + 1)) of
    gaussian_filter1d(·, σ/Δt) for each waveform's Δt, by scipy's formula (``_gaussian_kernel1d``, truncate 4)."""
    unique, group = np.unique(steps, return_inverse=True)
    radii, rows = [], []
    for step in unique:
        weights = model.smoothing_weights(float(sigma_s / step))
        radius = len(weights) // 2
        radii.append(radius)
        rows.append(weights[radius:])
    taps = np.zeros((len(rows), max(radii) + 1))
    for g, row in enumerate(rows):
        taps[g, :len(row)] = row
    return group.astype(np.int32), np.array(radii, np.int32), taps


def process(system: model.WaveformSystem, t0_s: np.ndarray, echo_w: np.ndarray, device: str,
            min_prominence: float = 0.05, noise: tuple[np.ndarray, np.ndarray] | None = None) -> Batch:
    """Measures and Gaussian components of the waveforms ``echo_w`` (W, N) [W], row w's sample j at
    t0_s[w] + Δt·j [s] (Δt = ``system.sample_interval_s``), computed on ``device``; in launches of at most
    BATCH_SAMPLES samples. ``noise``: each waveform's noise (mean, floor) [W] (``waveform_model.window_noise``), or
    None for noise-free waveforms (``waveform_model.measure``)."""
    echo_w = np.asarray(echo_w)
    t0_s = np.asarray(t0_s, dtype=np.float64)
    if noise is not None:
        noise = np.array(noise, dtype=np.float64)
    cpu = str(device).startswith("cpu")
    per = max(1, BATCH_SAMPLES["cpu" if cpu else "cuda"] // max(echo_w.shape[1], 1))
    threads = min(CPU_THREADS, usable_cores()) if cpu else 1
    if threads > 1:
        per = min(per, max(CPU_PART, -(-len(echo_w) // threads)))

    def part(lo: int) -> dict[str, np.ndarray]:
        return _launch(system, t0_s[lo:lo + per], echo_w[lo:lo + per], None if noise is None else noise[:, lo:lo + per],
                       device, min_prominence)

    parts = _map_parts(part, range(0, len(echo_w), per), threads, device)
    return _host_fallback(system, t0_s, echo_w, noise, _joined(parts), min_prominence)


def kernels() -> list:
    """The kernels :func:`process` launches."""
    return [km.echo_columns, km.smooth_echoes, km.echo_measures, km.chunk_extremes, km.chunk_peaks,
            km.find_echo_peaks, kf.start_fits, kf.advance_fits, kf.evaluate_kernel(kf.FEW_GAUSSIANS),
            kf.evaluate_kernel(MAX_PEAKS)]


def _map_parts(part, starts: range, threads: int, device: str) -> list[dict[str, np.ndarray]]:
    """``part(lo)`` of each start, in order: from up to ``threads`` threads (their modules loaded first, so no
    thread compiles), or in this one."""
    if threads <= 1 or len(starts) <= 1:
        return [part(lo) for lo in starts]
    compile_ahead(device, kernels())
    with ThreadPoolExecutor(min(threads, len(starts)), thread_name_prefix="waveform-parts") as pool:
        return list(pool.map(part, starts))


def _launch(system, t0_s, echo_w, noise, device, min_prominence) -> dict[str, np.ndarray]:
    """One launch of each kernel over W waveforms: their raw outputs on the host. ``noise``: (2, W) mean and floor
    [W], or None (noise-free: mean 0, floor −∞, no height for a peak to reach, fits started from the echo)."""
    dt, sigma = system.sample_interval_s, model.pulse_sigma_s(system)
    n_wave, n = echo_w.shape
    steps = (t0_s + dt) - t0_s  # t_1 − t_0 as the host forms the time base
    if noise is None:
        mean, floor, height = np.zeros(n_wave), np.full(n_wave, -np.inf), np.full(n_wave, -np.inf)
    else:  # the heights decompose asks of a smoothed maximum, formed as it forms them
        mean, floor = noise
        unique, group = np.unique(steps, return_inverse=True)  # a gain per distinct Δt, not per waveform
        height = floor * np.array([model.smoothing_gain(sigma / step) for step in unique])[group]
    group, radius, taps = smoothing_taps(sigma, steps)
    arr = lambda a, dtype=wp.float64: wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)  # noqa: E731
    t0, step = arr(t0_s), arr(steps)
    rows = echo_w if echo_w.dtype in (np.float32, np.float64) else echo_w.astype(np.float64)
    echo = wp.empty((n, n_wave), dtype=wp.float64, device=device)  # transposed on the device, not the host
    wp.launch(km.echo_columns, dim=(n, n_wave), inputs=[arr(rows, wp.float32 if rows.dtype == np.float32 else
                                                            wp.float64), arr(mean)], outputs=[echo], device=device)
    smooth = wp.empty((n, n_wave), dtype=wp.float64, device=device)
    wp.launch(km.smooth_echoes, dim=(n, n_wave), inputs=[echo, arr(group, wp.int32), arr(radius, wp.int32),
                                                        arr(taps)], outputs=[smooth], device=device)
    out = wp.empty((7, n_wave), dtype=wp.float64, device=device)
    wp.launch(km.echo_measures, dim=n_wave, inputs=[echo, t0, wp.float64(dt), arr(floor)], outputs=[out],
              device=device)
    p = 3 * MAX_PEAKS
    count = wp.zeros(n_wave, dtype=wp.int32, device=device)
    peaks = wp.zeros((MAX_PEAKS, n_wave), dtype=wp.int32, device=device)
    params = wp.zeros((p, n_wave), dtype=wp.float64, device=device)
    echo_peaks(echo if noise is None else smooth, smooth, t0, dt, step, sigma, min_prominence, arr(height), out, count,
               peaks, params)
    del smooth
    ssr = wp.zeros(n_wave, dtype=wp.float64, device=device)
    status = wp.zeros((2, n_wave), dtype=wp.int32, device=device)
    _fit(echo, t0, dt, step, sigma, out, count, params, ssr, status, device)
    return {"out": out.numpy().T, "count": count.numpy(), "peaks": peaks.numpy().T, "params": params.numpy().T,
            "ssr": ssr.numpy(), "status": status.numpy().T, "t0": t0_s}


def echo_peaks(start: wp.array, smooth: wp.array, t0: wp.array, dt: float, step: wp.array, sigma: float,
               min_prominence: float, height: wp.array, out: wp.array, count: wp.array, peaks: wp.array,
               params: wp.array) -> None:
    """The peaks of the smoothed waveforms ``smooth`` (N, W) at least ``height`` (W,) [W] high and standing out by
    ``min_prominence`` of their maximum, and their start parameters (amplitudes from ``start`` (N, W) at the peaks),
    into ``count``, ``peaks`` and ``params`` (kernels/waveform_measures.py: a thread per PEAK_CHUNK samples of a
    waveform finds its chunk's peaks, a thread per waveform keeps the first MAX_PEAKS)."""
    n, n_wave = smooth.shape
    device, chunks = smooth.device, -(-n // km.PEAK_CHUNK)
    extremes = wp.empty((2, chunks, n_wave), dtype=wp.float64, device=device)
    wp.launch(km.chunk_extremes, (chunks, n_wave), inputs=[smooth], outputs=[extremes], device=device)
    kept = wp.empty((chunks, n_wave), dtype=wp.int32, device=device)
    found = wp.empty((3 * MAX_PEAKS, chunks, n_wave), dtype=wp.int32, device=device)
    prominences = wp.empty((MAX_PEAKS, chunks, n_wave), dtype=wp.float64, device=device)
    wp.launch(km.chunk_peaks, (chunks, n_wave), inputs=[smooth, extremes, wp.float64(min_prominence), height],
              outputs=[kept, found, prominences], device=device)
    wp.launch(km.find_echo_peaks, n_wave, inputs=[start, smooth, t0, wp.float64(dt), step, wp.float64(sigma), out,
                                                  kept, found, prominences], outputs=[count, peaks, params],
              device=device)


def _fit(echo, t0, dt, step, sigma, out, count, params, ssr, status, device) -> None:
    """The Gaussians of ``params`` fitted in place (kernels/waveform_fit.py): rounds of one SSR evaluation per going
    fit, until none goes on (checked every FIT_ROUNDS rounds) or the most rounds a fit can take have passed."""
    n, n_wave = echo.shape
    p, chunks = 3 * MAX_PEAKS, -(-n // kf.FIT_CHUNK)
    most = min(int(count.numpy().max(initial=0)), MAX_PEAKS)  # the most Gaussians a waveform fits
    m = 3 * most
    evaluate = kf.evaluate_kernel(kf.FEW_GAUSSIANS if most <= kf.FEW_GAUSSIANS else MAX_PEAKS)
    zeros = lambda shape, dtype=wp.float64: wp.zeros(shape, dtype=dtype, device=device)  # noqa: E731
    state = kf.FitState()
    state.phase, state.accepted, state.tries, state.steps = (zeros(n_wave, wp.int32) for _ in range(4))
    state.cost, state.gain, state.lam = (zeros(n_wave) for _ in range(3))
    sums = kf.ChunkSums()
    sums.ssr, sums.grad, sums.normal = zeros((chunks, n_wave)), zeros((max(m, 1), chunks, n_wave)), \
        zeros((max(m * (m + 1) // 2, 1), chunks, n_wave))
    trial, grad, delta = (zeros((p, n_wave)) for _ in range(3))
    normal, chol = zeros((p, p, n_wave)), zeros((p, p, n_wave))
    free = zeros((p, n_wave), wp.int32)
    wp.launch(kf.start_fits, n_wave, inputs=[count, params, state], outputs=[status], device=device)
    rounds = 1 + int(km.MAX_ITERATIONS) * (int(km.LAMBDA_TRIES) + 1)  # a fit's evaluations at the most
    left, going = wp.array([rounds], dtype=wp.int32, device=device), wp.ones(1, dtype=wp.int32, device=device)
    # a round's two launches and the check's two, their arguments packed once (every round passes the same): ~20 µs
    # a round on the host instead of ~85 where the host launches them (two CPU cores; profile-experiments.md 97)
    def record(kernel, dim, inputs: list, outputs: tuple = ()) -> wp.Launch:
        return wp.launch(kernel, dim, inputs=inputs, outputs=list(outputs), device=device, record_cmd=True)

    one_round = (record(evaluate, (chunks, n_wave), [echo, t0, wp.float64(dt), wp.float64(sigma), out, count, params,
                                                      trial, state, sums]),
                 record(kf.advance_fits, n_wave, [echo, t0, wp.float64(dt), step, wp.float64(sigma), count, sums,
                                                  chunks, state, params, trial, normal, chol, grad, delta, free],
                        [ssr, status]))
    check = (record(kf.clear_going, 1, [FIT_ROUNDS, left, going]), record(kf.mark_going, n_wave, [state, left, going]))
    _while_going(going, one_round * FIT_ROUNDS + check, device)


def _while_going(going: wp.array, launches: tuple, device) -> None:
    """``launches`` in turn while ``going`` (1,) holds a nonzero value (their last ones set it). On a GPU with
    conditional graph nodes (CUDA 12.4+): one CUDA graph on a stream of its own, no host work or wait between the
    checks, none behind other threads' work on the device's stream; otherwise from the host, which reads ``going``
    after each pass."""
    device = wp.get_device(device)
    if not (device.is_cuda and wp.is_conditional_graph_supported()):
        wp.capture_while(going, lambda: [launch.launch() for launch in launches])
        return
    stream = wp.Stream(device)
    stream.wait_stream(device.stream)
    wp.capture_begin(stream=stream)
    try:
        wp.capture_while(going, lambda: [launch.launch(stream) for launch in launches], stream=stream)
    finally:
        graph = wp.capture_end(stream=stream)
    wp.capture_launch(graph, stream=stream)
    device.stream.wait_stream(stream)


def _joined(parts: list[dict]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def _host_fallback(system, t0_s, echo_w, noise, raw, min_prominence) -> Batch:
    """The Batch of the kernels' outputs, components sorted by time; rows the device did not fit (the module's
    docstring) decomposed by the host instead."""
    sigma, n = model.pulse_sigma_s(system), len(t0_s)
    a, mu, s = (raw["params"][:, i::3] for i in range(3))
    fitted = raw["status"][:, 0] != km.STATUS_SKIPPED
    width = max(MAX_PEAKS, int(raw["count"].max(initial=0)))
    comp = np.full((3, n, width), np.nan)
    used = fitted[:, None] & (np.arange(MAX_PEAKS)[None, :] < raw["count"][:, None])
    time_s = t0_s[:, None] + mu * sigma
    order = np.argsort(np.where(used, time_s, np.inf), axis=1, kind="stable")  # sorted(), as decompose
    parts = np.stack([time_s, a * raw["out"][:, 5:6], s * sigma])
    comp[:, :, :MAX_PEAKS] = np.where(used, np.take_along_axis(parts, order[None], axis=2), np.nan)
    offsets = system.sample_interval_s * np.arange(echo_w.shape[1])  # the writer's time base, row by row
    count = raw["count"].astype(np.int64)
    for w in np.flatnonzero(~fitted):
        parts = model.decompose(system, t0_s[w] + offsets, echo_w[w].astype(np.float64), min_prominence,
                                None if noise is None else tuple(noise[:, w]))
        comp[:, w, :len(parts)] = np.array([(g.time_s, g.amplitude_w, g.sigma_s) for g in parts]).T
        count[w] = len(parts)
    measures = {name: raw["out"][:, i].copy() for i, name in enumerate(MEASURES)}
    for w in np.flatnonzero(raw["out"][:, 6] != 0.0):  # an echo above half its maximum at an end: the host's
        m = model.measure(system, t0_s[w] + offsets, echo_w[w].astype(np.float64),  # measures (IndexError, there)
                          None if noise is None else tuple(noise[:, w]))
        for name in MEASURES:
            measures[name][w] = getattr(m, name)
    peaks = np.where(np.arange(MAX_PEAKS)[None, :] < raw["count"][:, None], raw["peaks"], -1)
    return Batch(measures, comp[0], comp[1], comp[2], count, np.where(fitted, raw["ssr"], np.nan),
                 raw["status"][:, 0], raw["status"][:, 1], peaks)
