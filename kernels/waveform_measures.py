"""Echo measures and Gaussian decomposition of many waveforms at once, on the device (float64): the batched form of
``flightsim.instrument.waveform_model.measure`` and ``decompose``, one launch per step for a whole chunk.

Every array is laid out sample (or parameter) first and waveform last, ``[j, w]``: with one thread per waveform the
threads of a warp read one sample of 32 waveforms side by side (coalesced).

0. :data:`echo_columns`: the waveforms, as they come one per row, into that layout on the device.
1. :data:`smooth_echoes` (one thread per sample and waveform): scipy.ndimage.gaussian_filter1d's correlation with
   its ``reflect`` extension, the taps added in the C code's order (centre, then the pairs from the outermost in).
2. :data:`echo_measures` (one thread per waveform): half-power, centroid and peak times, FWHM and RMS width.
3. :data:`chunk_extremes` and :data:`chunk_peaks` (one thread per PEAK_CHUNK samples of a waveform), then
   :data:`find_echo_peaks` (one thread per waveform): scipy.signal.find_peaks' local maxima (plateaus to their
   midpoint), their prominences over the whole waveform, those ≥ a share of the smoothed maximum kept, their
   widths at half the prominence (peak_widths, rel_height 0.5), and each kept peak's start parameters.
4. kernels/waveform_fit.py: a bounded Levenberg–Marquardt fit of the kept peaks' Gaussians, its sums over the samples
   spread over a thread per FIT_CHUNK samples of each waveform.
"""
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

MAX_PEAKS = wp.constant(8)  # Gaussians fitted on the device; a waveform with more is left to the host
MAX_ITERATIONS = wp.constant(200)  # Levenberg–Marquardt steps
LAMBDA_TRIES = wp.constant(20)  # damping increases (×10) per step before the fit is called converged
FWHM_PER_SIGMA = wp.constant(wp.float64(2.3548200450309493))  # 2√(2 ln 2)
GAIN_TOLERANCE = wp.constant(wp.float64(1.0e-15))  # a step gaining less than this share of the SSR ends the fit
UNDERFLOW = wp.constant(wp.float64(750.0))  # exp(−h) of h above this is 0 in float64

STATUS_CONVERGED = wp.constant(0)  # no step lowers the SSR any more, or the last lowered it by < GAIN_TOLERANCE
STATUS_ITERATIONS = wp.constant(1)  # MAX_ITERATIONS steps taken
STATUS_SKIPPED = wp.constant(-1)  # no peak, more than MAX_PEAKS, or a start amplitude < 0: not fitted


@wp.kernel
def echo_columns(rows: wp.array2d(dtype=Any), mean: wp.array(dtype=wp.float64),
                 columns: wp.array2d(dtype=wp.float64)):
    """The waveforms as they come, one per row (W, N) of float32 or float64 [W], less each one's noise ``mean`` (W,)
    [W] (0 for a noise-free waveform), as the float64 columns (N, W) the kernels read."""
    j, w = wp.tid()
    columns[j, w] = wp.float64(rows[w, j]) - mean[w]


# Both overloads made with the module, not by a first launch: a batch's parts launch from several threads, and an
# overload a launch makes changes the module under another thread's launch (Warp reads the new overload's launch
# metadata before it has hashed it: AttributeError 'tid_extent_limit_candidate')
wp.overload(echo_columns, {"rows": wp.array2d(dtype=wp.float32)})
wp.overload(echo_columns, {"rows": wp.array2d(dtype=wp.float64)})


@wp.func
def _reflect(i: int, n: int) -> int:
    """Sample of a line of ``n`` that index ``i`` reads under scipy.ndimage's ``reflect`` (d c b a | a b c d | d c b a)."""
    period = 2 * n
    m = i % period
    if m < 0:
        m = m + period
    if m >= n:
        m = period - 1 - m
    return m


@wp.func
def _time(t0: wp.float64, dt: wp.float64, j: int) -> wp.float64:
    """t0 + dt·j, sample j's time as the host forms it [s]."""
    return t0 + dt * wp.float64(j)


@wp.kernel
def smooth_echoes(echo: wp.array2d(dtype=wp.float64), group: wp.array(dtype=wp.int32),
                  radius: wp.array(dtype=wp.int32), taps: wp.array2d(dtype=wp.float64),
                  smooth: wp.array2d(dtype=wp.float64)):
    """Each waveform correlated with its group's Gaussian taps under the ``reflect`` extension [W].

    # In:
    echo    (N, W) received power, one waveform per column [W]
    group   (W,) row of ``radius`` and ``taps`` of each waveform
    radius  (G,) r of each kernel [samples]
    taps    (G, R + 1) one side of each kernel, w_0 … w_r (normalised over −r … r)
    # Out:
    smooth  (N, W) the smoothed waveforms [W]
    """
    i, w = wp.tid()
    n = echo.shape[0]
    g = group[w]
    r = radius[g]
    acc = echo[i, w] * taps[g, 0]
    for m in range(r):
        k = r - m
        below = i - k
        above = i + k
        if below < 0 or above >= n:  # the integer modulo only near the ends
            below = _reflect(below, n)
            above = _reflect(above, n)
        acc += (echo[below, w] + echo[above, w]) * taps[g, k]
    smooth[i, w] = acc


@wp.func
def _crossing(echo: wp.array2d(dtype=wp.float64), w: int, t0: wp.float64, dt: wp.float64, j: int,
              level: wp.float64) -> wp.float64:
    """Time where the echo crosses ``level`` between samples j and j + 1, linearly interpolated [s]."""
    tj = _time(t0, dt, j)
    a = echo[j, w]
    b = echo[j + 1, w]
    return tj + (level - a) / (b - a) * (_time(t0, dt, j + 1) - tj)


@wp.func
def _add(sum: wp.vec2d, v: wp.float64) -> wp.vec2d:
    """Neumaier's compensated sum: (sum, compensation) with v added."""
    s = sum[0]
    t = s + v
    c = sum[1]
    if wp.abs(s) >= wp.abs(v):
        c = c + ((s - t) + v)
    else:
        c = c + ((v - t) + s)
    return wp.vec2d(t, c)


@wp.kernel
def echo_measures(echo: wp.array2d(dtype=wp.float64), t0: wp.array(dtype=wp.float64), dt: wp.float64,
                  floor: wp.array(dtype=wp.float64), out: wp.array2d(dtype=wp.float64)):
    """Half-power, centroid and peak times, FWHM and RMS width of each waveform, and its maximum:
    ``waveform_model.measure`` (the centroid and RMS width over the samples from the first to the last above the
    noise floor; every measure NaN where none is).

    # In:
    echo  (N, W) received power less each waveform's noise mean [W] (:func:`echo_columns`)
    t0    (W,) time of each waveform's sample 0 [s]; dt: sample interval [s] (sample j at t0 + dt·j)
    floor (W,) each waveform's noise floor above its mean [W] (−∞: a noise-free waveform, measured whole)
    # Out:
    out   (7, W) half-power time [s], centroid time [s], peak time [s], FWHM [s], RMS width [s], maximum [W], and
          1 where the echo starts or ends above half its maximum (the host's measures then index out of the window)
    """
    w = wp.tid()
    n = echo.shape[0]
    start = t0[w]
    above = floor[w]
    top = echo[0, w]
    arg = int(0)
    lo = int(-1)
    hi = int(-1)
    for j in range(n):
        if echo[j, w] > top:
            top = echo[j, w]
            arg = j
        if echo[j, w] > above:
            if lo < 0:
                lo = j
            hi = j
    out[5, w] = top
    if lo < 0:  # nothing above the noise
        for k in range(5):
            out[k, w] = wp.float64(wp.nan)
        out[6, w] = wp.float64(0.0)
        return
    level = wp.float64(0.5) * top
    first = int(-1)
    last = int(-1)
    energy = wp.vec2d()
    moment = wp.vec2d()
    for j in range(n):
        e = echo[j, w]
        if e >= level:
            if first < 0:
                first = j
            last = j
        if j >= lo and j <= hi:
            energy = _add(energy, e)
            moment = _add(moment, _time(start, dt, j) * e)
    total = energy[0] + energy[1]
    centroid = (moment[0] + moment[1]) / total
    spread = wp.vec2d()
    for j in range(lo, hi + 1):
        d = _time(start, dt, j) - centroid
        spread = _add(spread, d * d * echo[j, w])
    edge = int(0)
    if first == 0 or last == n - 1:  # the echo starts or ends above half its maximum: the host's crossing reads
        edge = 1  # index −1 (the last sample) or n (IndexError); left to the host, the crossings read inside here
        first = 1
        last = n - 2
    half = _crossing(echo, w, start, dt, first - 1, level)
    j = wp.clamp(arg, 1, n - 2)
    y0 = echo[j - 1, w]
    y1 = echo[j, w]
    y2 = echo[j + 1, w]
    tj = _time(start, dt, j)
    out[0, w] = half
    out[1, w] = centroid
    out[2, w] = tj + wp.float64(0.5) * (y0 - y2) / (y0 - wp.float64(2.0) * y1 + y2) * (_time(start, dt, j + 1) - tj)
    out[3, w] = _crossing(echo, w, start, dt, last, level) - half
    out[4, w] = wp.sqrt((spread[0] + spread[1]) / total)
    out[6, w] = wp.float64(edge)


@wp.func
def _base(x: wp.array2d(dtype=wp.float64), w: int, peak: int, step: int):
    """Walking from ``peak`` by ``step`` (−1 or +1) until a higher sample or the line's end: (the lowest sample
    met, its index; the first one where several are lowest), scipy's base on that side."""
    n = x.shape[0]
    top = x[peak, w]
    lowest = top
    base = peak
    i = peak
    while i >= 0 and i <= n - 1:
        v = x[i, w]
        if v > top:
            break
        if v < lowest:
            lowest = v
            base = i
        i = i + step
    return lowest, base


@wp.func
def _prominence(x: wp.array2d(dtype=wp.float64), w: int, peak: int):
    """scipy's peak_prominences over the whole line: (prominence, left base, right base)."""
    left_min, left = _base(x, w, peak, -1)
    right_min, right = _base(x, w, peak, 1)
    return x[peak, w] - wp.max(left_min, right_min), left, right


@wp.func
def _width(x: wp.array2d(dtype=wp.float64), w: int, peak: int, prominence: wp.float64, left: int,
           right: int) -> wp.float64:
    """scipy's peak_widths at rel_height 0.5: the interpolated width [samples] at half the prominence."""
    height = x[peak, w] - prominence * wp.float64(0.5)
    i = peak
    while i > left:
        if height >= x[i, w]:
            break
        i = i - 1
    left_ip = wp.float64(i)
    if x[i, w] < height and x[i + 1, w] != x[i, w]:
        left_ip = left_ip + (height - x[i, w]) / (x[i + 1, w] - x[i, w])
    i = peak
    while i < right:
        if height >= x[i, w]:
            break
        i = i + 1
    right_ip = wp.float64(i)
    if x[i, w] < height and x[i - 1, w] != x[i, w]:
        right_ip = right_ip - (height - x[i, w]) / (x[i - 1, w] - x[i, w])
    return right_ip - left_ip


@wp.func
def _plateau_end(x: wp.array2d(dtype=wp.float64), w: int, i: int) -> int:
    """First sample after i (at most the last one) whose value differs from x[i] (scipy's _local_maxima_1d)."""
    ahead = i + 1
    last = x.shape[0] - 1
    while ahead < last:
        if x[ahead, w] != x[i, w]:
            break
        ahead = ahead + 1
    return ahead


PEAK_CHUNK = 256  # samples of the smoothed waveform a thread of chunk_extremes and chunk_peaks scans


@wp.kernel
def chunk_extremes(smooth: wp.array2d(dtype=wp.float64), extremes: wp.array3d(dtype=wp.float64)):
    """The highest (row 0) and lowest (row 1) sample of each chunk of PEAK_CHUNK samples of each smoothed waveform:
    extremes (2, chunks, W)."""
    chunk, w = wp.tid()
    first = chunk * PEAK_CHUNK
    top = smooth[first, w]
    bottom = top
    for j in range(first + 1, wp.min(first + PEAK_CHUNK, smooth.shape[0])):
        top = wp.max(top, smooth[j, w])
        bottom = wp.min(bottom, smooth[j, w])
    extremes[0, chunk, w] = top
    extremes[1, chunk, w] = bottom


@wp.kernel
def chunk_peaks(smooth: wp.array2d(dtype=wp.float64), extremes: wp.array3d(dtype=wp.float64),
                min_prominence: wp.float64, height: wp.array(dtype=wp.float64), kept: wp.array2d(dtype=wp.int32),
                found: wp.array3d(dtype=wp.int32), prominences: wp.array3d(dtype=wp.float64)):
    """The peaks of each chunk of PEAK_CHUNK samples of each smoothed waveform at least ``height`` high that stand out
    by ``min_prominence`` of its maximum: scipy.signal.find_peaks' local maxima (a plateau's midpoint, rounded down; a
    plateau belongs to the chunk where it starts; its ``height`` and ``prominence`` conditions) and their prominences
    over the whole waveform (peak_prominences).

    # In:
    smooth          (N, W) the smoothed waveforms [W]; extremes (2, chunks, W) chunk_extremes' output
    height          (W,) the least height of a peak [W] (−∞: any)
    # Out:
    kept            (chunks, W) the chunk's peaks standing out enough (only the first MAX_PEAKS are stored)
    found           (3·MAX_PEAKS, chunks, W) per peak in time order: its sample, left and right base
    prominences     (MAX_PEAKS, chunks, W) [W]
    """
    chunk, w = wp.tid()
    n = smooth.shape[0]
    top = extremes[0, 0, w]
    bottom = extremes[1, 0, w]
    for c in range(1, extremes.shape[1]):
        top = wp.max(top, extremes[0, c, w])
        bottom = wp.min(bottom, extremes[1, c, w])
    floor = min_prominence * top
    count = int(0)
    for i in range(wp.max(chunk * PEAK_CHUNK, 1), wp.min((chunk + 1) * PEAK_CHUNK, n - 1)):
        if smooth[i - 1, w] < smooth[i, w]:  # a plateau starts here (inside one, the sample before is as high)
            ahead = _plateau_end(smooth, w, i)
            if smooth[ahead, w] < smooth[i, w]:
                peak = (i + ahead - 1) // 2
                if smooth[peak, w] < height[w]:
                    continue
                prominence = smooth[peak, w] - bottom  # a bound: a maximum below it cannot stand out enough
                left = peak
                right = peak
                if prominence >= floor:
                    prominence, left, right = _prominence(smooth, w, peak)
                if prominence >= floor:
                    if count < MAX_PEAKS:
                        found[3 * count, chunk, w] = peak
                        found[3 * count + 1, chunk, w] = left
                        found[3 * count + 2, chunk, w] = right
                        prominences[count, chunk, w] = prominence
                    count = count + 1
    kept[chunk, w] = count


@wp.kernel
def find_echo_peaks(start: wp.array2d(dtype=wp.float64), smooth: wp.array2d(dtype=wp.float64),
                    t0: wp.array(dtype=wp.float64), dt: wp.float64, step: wp.array(dtype=wp.float64),
                    sigma: wp.float64, maximum: wp.array2d(dtype=wp.float64), kept: wp.array2d(dtype=wp.int32),
                    found: wp.array3d(dtype=wp.int32), prominences: wp.array3d(dtype=wp.float64),
                    count: wp.array(dtype=wp.int32), peaks: wp.array2d(dtype=wp.int32),
                    params: wp.array2d(dtype=wp.float64)):
    """Each waveform's peaks (chunk_peaks' over its chunks in order) and their start parameters.

    # In:
    start, smooth   (N, W) the waveforms the start amplitudes are read from (the echo, or the smoothed echo under
                    noise) and the smoothed waveforms [W]
    t0              (W,) time of sample 0 [s]; dt: sample interval [s]
    step            (W,) t_1 − t_0 of each waveform as the host forms it [s]
    sigma           σ of the pulse [s]
    maximum         (7, W) echo_measures' output (row 5: each waveform's maximum [W])
    kept, found, prominences: chunk_peaks' output
    # Out:
    count           (W,) peaks kept (may exceed MAX_PEAKS: only the first MAX_PEAKS are stored)
    peaks           (MAX_PEAKS, W) their samples, in time order
    params          (3·MAX_PEAKS, W) start (a, μ, s) of each: a in units of the maximum, μ and s in σ from t0
    """
    w = wp.tid()
    scale = maximum[5, w]
    total = int(0)
    for chunk in range(kept.shape[0]):
        in_chunk = kept[chunk, w]
        for q in range(wp.min(in_chunk, MAX_PEAKS)):
            k = total + q
            if k < MAX_PEAKS:
                peak = found[3 * q, chunk, w]
                width_s = _width(smooth, w, peak, prominences[q, chunk, w], found[3 * q + 1, chunk, w],
                                 found[3 * q + 2, chunk, w]) * step[w] / FWHM_PER_SIGMA
                spread = wp.sqrt(wp.max(width_s * width_s - sigma * sigma, wp.float64(0.0)))
                peaks[k, w] = peak
                params[3 * k, w] = start[peak, w] / scale
                params[3 * k + 1, w] = (_time(t0[w], dt, peak) - t0[w]) / sigma
                params[3 * k + 2, w] = wp.max(spread, wp.float64(0.5) * sigma) / sigma
        total = total + in_chunk
    count[w] = total
