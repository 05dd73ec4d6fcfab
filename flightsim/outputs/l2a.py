"""GEDI L2A-like elevation and height metrics from full waveforms (NumPy and SciPy only).

Sources: the GEDI L1/L2 waveform ATBD (Hofton & Blair 2019, "Algorithm Theoretical Basis Document for GEDI
Transmit and Receive Waveform Processing for L1 and L2 Products", v1.0), the GEDI L2A data dictionary for the
names, and for the sensitivity Hancock et al. 2019 ("The GEDI simulator", Earth and Space Science 6) as coded in
the GEDI simulator (``gediMetric.c``: ``findBlairSense``, ``gaussThresholds``).

Per waveform (sample 0 is bin0, the first received and the highest; elevations are linear in the sample index
between ``elevation_bin0`` and ``elevation_lastbin``, and so are latitude and longitude):

1. **Noise**: mean m and standard deviation σ of the first and last ``noise_samples`` samples pooled (GEDI
   L1B reports them from the waveform's noise-only part), or as given.
2. **Smoothing**: a Gaussian of σ = ``smoothing_sigmas`` × the pulse σ (GEDI's setting group a1 smooths with
   6.5 samples of 1 ns, about the GEDI pulse's σ; a1's values here are those of the GEDI L2A user guide's
   table of algorithm setting groups).
3. **Signal start and end**: the first sample of the smoothed waveform above m + ``front_threshold``·σ is the
   signal start (the highest return), the last above m + ``back_threshold``·σ the signal end; crossings
   interpolated linearly between samples. The thresholds are GEDI a1's front 3σ and back 6σ, with the raw
   waveform's σ (as GEDI's thresholds use L1B's noise σ; the smoothed noise is several times smaller). A
   threshold never falls below ``noise_floor`` × the smoothed peak above m: only a noise-free waveform (σ = 0)
   meets that floor.
4. **Modes**: the maxima of the smoothed waveform (its derivative crossing zero from + to −) between signal
   start and end and above the front threshold; ``num_detectedmodes`` counts them.
5. **Gaussian decomposition**: the waveform minus m over the signal (± 3 pulse σ) fitted by a sum of one
   Gaussian per mode (SciPy's bounded Trust Region Reflective least squares with ``x_scale="jac"``, analytic
   Jacobian; amplitudes ≥ 0, widths ≥ half the pulse σ), started from the modes; the waveforms with as many modes
   are fitted together (:mod:`flightsim.core.trf_batch`: each the fit ``scipy.optimize.least_squares`` makes of
   it alone, to the fit's tolerances). The **lowest mode** (the ground) is the lowest fitted component whose
   smoothed peak would clear the front threshold; ``elev_lowestmode``, ``lat_lowestmode``, ``lon_lowestmode``
   are at its centre. GEDI a1 takes the lowest mode's location from the smoothed waveform's zero crossing; the
   fit removes the pull of a nearby canopy mode and of the smoothing.
6. **RH**: ``rh[k]`` (k = 0…100 %) is the height above the lowest mode's centre where the energy of the
   waveform minus m, accumulated upwards from the signal end (trapezoids between samples), reaches k % of the
   energy between signal end and start: rh0 is the signal end, rh100 the signal start (``elev_highestreturn``).
   As in GEDI, energy below the lowest mode's centre counts, so rh1… are negative over bare ground (about
   half the ground return lies below its centre).
7. **Sensitivity** (Hancock et al. 2019; GEDI's "maximum canopy cover that can be penetrated"):
   1 − (n_N + n_S)·σ·√(2π)·σ_eff / E, the energy of the weakest ground return the thresholds would still find,
   amplitude (n_N + n_S)·σ and width σ_eff = √(σ_pulse² + (2·σ_footprint·tan 2°/c)²) (a 2° slope across the
   footprint), over the waveform's energy E = Σ(w − m) (all in samples). n_N = Φ⁻¹(1 − p_FA·0.15/30): a false
   alarm probability ``p_false_alarm`` per 30 m of 0.15 m bins; n_S = Φ⁻¹(1 − ``p_miss``): 3.48 + 1.28 with
   the simulator's 0.05 and 0.1. Clipped to [0, 1] (0 when E ≤ 0, 1 when σ = 0).
8. **quality_flag** = 1 where a signal was found and sensitivity ≥ ``min_sensitivity`` (GEDI: 0.9 over land;
   GEDI's flag also weighs surface and DEM checks that a simulation has no use for).

Shots without a signal have ``quality_flag`` 0, ``num_detectedmodes`` 0 and :data:`FILL` in every elevation,
position and rh. ``energy_total`` is Σ(w − m)·dt over the whole waveform [W·s when w is in W].
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.special import ndtri

from flightsim.core.errors import InputError, positive
from flightsim.core.process_map import ProcessMap, by_pieces, map_rows, row_chunks
from flightsim.core.settings import Settings, check_settings, setting
from flightsim.core.trf_batch import least_squares_batch
from flightsim.instrument.waveform_model import end_noise

C = 299_792_458.0  # speed of light [m/s]
FILL = -9999.0  # elevations, positions and rh of a shot without a signal
RH_LEVELS = 101  # rh0 … rh100
TRUTH_PIECE_ROWS = 256  # the fewest profiles in a piece of truth_rh's work on threads
_BIN_M, _WINDOW_M = 0.15, 30.0  # the sensitivity's false-alarm window: 30 m of 0.15 m bins (GEDI simulator)
_FIT_PAD = 3.0  # the fit window reaches this many pulse σ beyond signal start and end
_MIN_WIDTH = 0.5  # least fitted width [pulse σ]
_SLAB_VALUES = 1 << 19  # the batched fit takes waveforms in slabs of about this many Jacobian values


_GEOLOCATION = ("elevation_bin0", "elevation_lastbin", "latitude_bin0", "longitude_bin0", "latitude_lastbin",
                "longitude_lastbin")  # l2a_metrics' per-shot positions, in its arguments' order


@dataclass
class L2ASettings(Settings):
    """GEDI L2A waveform interpretation, algorithm setting group a1."""

    table: ClassVar[str] = "l2a"
    front_threshold: float = setting(3.0, "signal start: smoothed waveform above noise mean + this many σ", "σ",
                                     range=(0.0, 100.0))
    back_threshold: float = setting(6.0, "signal end: smoothed waveform above noise mean + this many σ", "σ",
                                    range=(0.0, 100.0))
    smoothing_sigmas: float = setting(1.0, "σ of the Gaussian smoothing, in pulse σ", range=(0.0, 100.0),
                                      lo_open=True)
    noise_samples: int = setting(64, "samples at each end of a waveform that give its noise mean and σ",
                                 range=(2, 1 << 20))
    noise_floor: float = setting(1e-6, "least threshold above the noise mean, a fraction of the smoothed peak",
                                 range=(0.0, 1.0), lo_open=True)
    footprint_sigma_m: float = setting(5.5, "footprint σ in the sensitivity's ground return width", "m",
                                       range=(0.0, 1e4))
    p_false_alarm: float = setting(0.05, "sensitivity: false alarm probability per 30 m", range=(0.0, 1.0),
                                   lo_open=True)
    p_miss: float = setting(0.1, "sensitivity: probability of missing the weakest ground", range=(0.0, 1.0),
                            lo_open=True)
    min_sensitivity: float = setting(0.9, "quality_flag needs a sensitivity of at least this", range=(0.0, 1.0))
    max_modes: int = setting(20, "most modes fitted per waveform (GEDI rx_max_mode_count)", range=(1, 200))


@dataclass(frozen=True)
class _Shots:
    """Validated input: waveforms minus their noise mean, noise σ and smoothed waveforms (sample units)."""

    y: np.ndarray  # (S, N) waveform − noise mean
    sigma: np.ndarray  # (S,) noise σ
    smooth: np.ndarray  # (S, N) smoothed y
    pulse: float  # pulse σ [samples]
    kernel: float  # σ of the smoothing [samples]


def l2a_metrics(rx, dt_s: float, elevation_bin0, elevation_lastbin, latitude_bin0, longitude_bin0,
                latitude_lastbin, longitude_lastbin, pulse_sigma_s: float, noise: tuple | None = None,
                settings: L2ASettings | None = None, workers: ProcessMap | None = None) -> dict[str, np.ndarray]:
    """GEDI L2A metrics of S waveforms of N samples (the module docstring gives the algorithm).

    Args:
        rx: (S, N) received waveforms [W or any linear unit], finite; sample 0 is bin0 (the highest).
        dt_s: sample interval [s], > 0.
        elevation_bin0, elevation_lastbin: (S,) elevation of the first and last sample [m], bin0 higher.
        latitude_bin0, longitude_bin0, latitude_lastbin, longitude_lastbin: (S,) their positions [deg].
        pulse_sigma_s: σ of the transmitted pulse [s], > 0.
        noise: (mean, σ) of the noise, each a number or (S,) [rx units]; None: from the waveforms' ends.
        settings: :class:`L2ASettings` (GEDI a1 by default).
        workers: worker processes (:class:`~flightsim.core.process_map.ProcessMap`) to spread the waveforms over,
            a chunk of rows each (the same results: every metric is a row's own); None: this process.

    Returns: GEDI L2A names, (S,) arrays unless stated: ``rh`` (S, 101) [m], ``elev_lowestmode``,
    ``elev_highestreturn`` [m], ``lat_lowestmode``, ``lon_lowestmode``, ``lat_highestreturn``,
    ``lon_highestreturn`` [deg], ``num_detectedmodes`` (uint8), ``sensitivity``, ``quality_flag`` (uint8),
    ``energy_total`` [rx units · s]; float64 elsewhere, :data:`FILL` where no signal.
    """
    s = settings if settings is not None else L2ASettings()
    check_settings("l2a", s)
    if workers is not None:
        return _spread(rx, dt_s, pulse_sigma_s, noise, s, workers, elevation_bin0=elevation_bin0,
                       elevation_lastbin=elevation_lastbin, latitude_bin0=latitude_bin0, longitude_bin0=longitude_bin0,
                       latitude_lastbin=latitude_lastbin, longitude_lastbin=longitude_lastbin)
    shots, dt = _prepare(rx, dt_s, pulse_sigma_s, noise, s)
    geo = _geometry(len(shots.y), elevation_bin0=elevation_bin0, elevation_lastbin=elevation_lastbin,
                    latitude_bin0=latitude_bin0, longitude_bin0=longitude_bin0, latitude_lastbin=latitude_lastbin,
                    longitude_lastbin=longitude_lastbin)
    front, back = _thresholds(shots, s)
    start, end, found = _signal_bounds(shots.smooth, front, back)
    shot, loc = _modes(shots.smooth, front, start, end)
    count = np.bincount(shot, minlength=len(shots.y))
    found &= count > 0
    ground = _lowest_modes(shots, shot, loc, start, end, front, found, s.max_modes)
    out = _positions(geo, shots.y.shape[1], ground, start, found)
    out["rh"] = _rh(shots.y, geo["elevation_bin0"], geo["elevation_lastbin"], start, end, out["elev_lowestmode"],
                    found)
    out["num_detectedmodes"] = np.where(found, np.minimum(count, 255), 0).astype(np.uint8)
    energy = shots.y.sum(axis=1)
    out["sensitivity"] = _sensitivity(energy, shots.sigma, shots.pulse, dt, s)
    out["quality_flag"] = (found & (out["sensitivity"] >= s.min_sensitivity)).astype(np.uint8)
    out["energy_total"] = energy * dt
    return out


def _spread(rx, dt_s: float, pulse_sigma_s: float, noise, s: L2ASettings, workers: ProcessMap,
            **geolocation) -> dict[str, np.ndarray]:
    """:func:`l2a_metrics` of the waveforms cut into chunks of rows, each worked out by a worker (the input checked
    here first, so that an error names the whole input), the chunks' metrics joined in order."""
    w, _, _, noise = _checked(rx, dt_s, pulse_sigma_s, noise, s)
    n = len(w)
    geo = _geometry(n, **geolocation)
    chunks = [(w[c], dt_s, *(geo[name][c] for name in _GEOLOCATION), pulse_sigma_s,
               None if noise is None else (noise[0][c], noise[1][c]), s) for c in row_chunks(n, workers)]
    parts = map_rows(l2a_metrics, chunks, workers)
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def truth_rh(profile, elevation_bin0, elevation_lastbin, ground_elevation) -> np.ndarray:
    """(S, 101) rh [m] of noise-free energy profiles above the true ground, for the product's truth group.

    rh[k] is the height above ``ground_elevation`` where the profile's energy, accumulated upwards from its
    lowest non-zero sample (trapezoids), reaches k % of the whole (rh0: that sample; rh100: the highest
    non-zero sample); :data:`FILL` for a profile without energy.

    Args:
        profile: (S, N) received energy per sample without noise, ≥ 0, finite; sample 0 the highest.
        elevation_bin0, elevation_lastbin: (S,) elevation of the first and last sample [m], bin0 higher.
        ground_elevation: (S,) the true ground elevation [m].
    """
    p = _waveforms(profile, "profile")
    if p.min() < 0.0:
        raise InputError("profile", f"minimum {p.min():g}", "energies >= 0")
    geo = _geometry(len(p), elevation_bin0=elevation_bin0, elevation_lastbin=elevation_lastbin,
                    ground_elevation=ground_elevation)
    return np.concatenate(by_pieces(len(p), lambda rows: _truth_rows(p[rows], {k: v[rows] for k, v in geo.items()}),
                                    least=TRUTH_PIECE_ROWS))


def _truth_rows(p: np.ndarray, geo: dict[str, np.ndarray]) -> np.ndarray:
    """:func:`truth_rh` of some profiles (each row's rh its own, whatever rows lie beside it: :func:`_rh`)."""
    lit = p > 0.0
    start, end = np.argmax(lit, axis=1), p.shape[1] - 1 - np.argmax(lit[:, ::-1], axis=1)
    return _rh(p, geo["elevation_bin0"], geo["elevation_lastbin"], start.astype(np.float64), end.astype(np.float64),
               geo["ground_elevation"], lit.any(axis=1))


# --- input -----------------------------------------------------------------------------------------


def _waveforms(values, name: str) -> np.ndarray:
    """``values`` as (S, N) finite float64 with S >= 1 and N >= 3."""
    try:
        w = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(name, type(values).__name__, "an (S, N) array of numbers") from None
    if w.ndim != 2 or w.shape[0] < 1 or w.shape[1] < 3:
        raise InputError(name, f"shape {w.shape}", "(S, N) with S >= 1 shots and N >= 3 samples")
    if not np.isfinite(w).all():
        raise InputError(name, f"{np.count_nonzero(~np.isfinite(w))} non-finite samples", "finite samples")
    return w


def _column(name: str, value, n: int) -> np.ndarray:
    """A number or (n,) values as (n,) finite float64."""
    try:
        a = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,))
    except (TypeError, ValueError):
        raise InputError(name, f"shape {np.shape(value)}", f"a number or ({n},) finite values") from None
    if not np.isfinite(a).all():
        raise InputError(name, "a non-finite value", f"({n},) finite values")
    return a.astype(np.float64)


def _geometry(n: int, **columns) -> dict[str, np.ndarray]:
    """Per-shot columns, each (n,) finite; bin0 above the last bin."""
    out = {}
    for name, value in columns.items():
        if np.shape(value) != (n,):
            raise InputError(name, f"shape {np.shape(value)}", f"({n},), one value per waveform")
        out[name] = _column(name, value, n)
    if not (out["elevation_bin0"] > out["elevation_lastbin"]).all():
        raise InputError("elevation_lastbin", "not below elevation_bin0", "each last bin lower than its bin0 [m]")
    return out


def _prepare(rx, dt_s, pulse_sigma_s, noise, s: L2ASettings) -> tuple[_Shots, float]:
    """The waveforms minus their noise mean, the noise σ and the smoothed waveforms; the sample interval."""
    w, dt, pulse, noise = _checked(rx, dt_s, pulse_sigma_s, noise, s)
    mean, sigma = end_noise(w, s.noise_samples) if noise is None else noise
    y = w - mean[:, None]
    kernel = s.smoothing_sigmas * pulse
    return _Shots(y, sigma, gaussian_filter1d(y, kernel, axis=1, mode="nearest"), pulse, kernel), dt


def _checked(rx, dt_s, pulse_sigma_s, noise, s: L2ASettings) -> tuple[np.ndarray, float, float, tuple | None]:
    """(waveforms (S, N) float64, sample interval [s], pulse σ [samples], the noise given as two (S,) arrays or None),
    every input checked."""
    w = _waveforms(rx, "rx")
    dt = positive("dt_s", dt_s)
    pulse = positive("pulse_sigma_s", pulse_sigma_s) / dt
    if noise is not None:
        return w, dt, pulse, _noise(noise, len(w))
    if w.shape[1] < 2 * s.noise_samples + 1:
        raise InputError("rx", f"shape {w.shape}",
                         f"N > 2·l2a.noise_samples = {2 * s.noise_samples} samples, or give noise")
    return w, dt, pulse, None


def _noise(noise, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The noise (mean, σ) given, each a number or (n,) values, as two (n,) finite float64 arrays, σ >= 0."""
    if not isinstance(noise, (tuple, list)) or len(noise) != 2:
        raise InputError("noise", noise, "(mean, σ): numbers or (S,) arrays")
    mean, sigma = _column("noise mean", noise[0], n), _column("noise σ", noise[1], n)
    if sigma.min() < 0.0:
        raise InputError("noise σ", sigma.min(), "σ >= 0")
    return mean, sigma


# --- signal, modes, lowest mode --------------------------------------------------------------------


def _thresholds(shots: _Shots, s: L2ASettings) -> tuple[np.ndarray, np.ndarray]:
    """Front and back thresholds above the noise mean (S,), each at least noise_floor × the smoothed peak."""
    floor = s.noise_floor * np.maximum(shots.smooth.max(axis=1), 0.0)
    return (np.maximum(s.front_threshold * shots.sigma, floor),
            np.maximum(s.back_threshold * shots.sigma, floor))


def _crossing(sm: np.ndarray, rows: np.ndarray, i: np.ndarray, j: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Fractional sample between i and j = i ± 1 where the row's smoothed waveform crosses ``level``."""
    a, b = sm[rows, i], sm[rows, j]
    frac = np.where(b != a, (level - a) / np.where(b != a, b - a, 1.0), 0.0)
    return i + np.clip(frac, 0.0, 1.0) * (j - i)


def _signal_bounds(sm, front, back) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signal start (first smoothed sample above front) and end (last above back), fractional; found."""
    above_f, above_b = sm > front[:, None], sm > back[:, None]
    found = above_f.any(axis=1) & above_b.any(axis=1)
    rows, last = np.arange(len(sm)), sm.shape[1] - 1
    i0 = np.argmax(above_f, axis=1)
    i1 = last - np.argmax(above_b[:, ::-1], axis=1)
    start = _crossing(sm, rows, i0, np.maximum(i0 - 1, 0), front)
    end = _crossing(sm, rows, i1, np.minimum(i1 + 1, last), back)
    return start, end, found


def _modes(sm, front, start, end) -> tuple[np.ndarray, np.ndarray]:
    """(shot, fractional sample) of every maximum of the smoothed waveforms above the front threshold and
    within the signal, in order of shot then sample; the sample refined by a parabola through three."""
    d = np.diff(sm, axis=1)
    peak = np.zeros(sm.shape, dtype=bool)
    peak[:, 1:-1] = (d[:, :-1] > 0.0) & (d[:, 1:] <= 0.0)
    index = np.arange(sm.shape[1])[None, :]
    peak &= (sm > front[:, None]) & (index >= np.floor(start)[:, None]) & (index <= np.ceil(end)[:, None])
    shot, i = np.nonzero(peak)
    left, mid, right = sm[shot, i - 1], sm[shot, i], sm[shot, i + 1]
    curve = left - 2.0 * mid + right
    offset = np.where(curve < 0.0, 0.5 * (left - right) / np.where(curve < 0.0, curve, -1.0), 0.0)
    return shot, i + np.clip(offset, -0.5, 0.5)


def _lowest_modes(shots: _Shots, shot, loc, start, end, front, found, max_modes: int) -> np.ndarray:
    """Fractional sample of each waveform's lowest mode after the Gaussian fit (NaN where no signal)."""
    ground = np.full(len(shots.y), np.nan)
    rows = np.flatnonzero(found)
    if not len(rows):
        return ground
    bounds = np.searchsorted(shot, np.arange(len(shots.y) + 1))
    modes = [_strongest(shots.smooth[k], loc[bounds[k]:bounds[k + 1]], max_modes) for k in rows]
    first = np.maximum(0.0, np.floor(start[rows] - _FIT_PAD * shots.pulse)).astype(np.int64)
    stop = np.minimum(shots.y.shape[1], np.ceil(end[rows] + _FIT_PAD * shots.pulse).astype(np.int64) + 1)
    samples = first[:, None] + np.arange((stop - first).max())
    inside = samples < stop[:, None]
    windows = np.where(inside, shots.y[rows[:, None], np.minimum(samples, shots.y.shape[1] - 1)], 0.0)
    ground[rows] = _fit_rows(windows, first, stop, modes, shots.pulse, shots.kernel, front[rows])
    return ground


def _fit_rows(windows, first, stop, modes: list, pulse: float, kernel: float, front) -> np.ndarray:
    """The lowest detectable component of a Gaussian fit to each waveform's samples ``first`` … ``stop`` − 1
    (``windows``: those samples, zero beyond; the pulse's and the smoothing's σ ``pulse``, ``kernel`` [samples])
    started from its ``modes`` [samples]; the rows with as many modes solved together (a module-level function: a
    worker process runs it on a chunk of rows)."""
    count = np.array([len(m) for m in modes])
    ground = np.empty(len(windows))
    for m in np.unique(count):
        rows = np.flatnonzero(count == m)
        for part in np.array_split(rows, -(-len(rows) * (stop - first)[rows].max() * 3 * m // _SLAB_VALUES)):
            centres = np.array([modes[i] for i in part])
            ground[part] = _fit_lowest(windows[part], first[part], stop[part], centres, pulse, kernel, front[part])
    return ground


def _strongest(smooth: np.ndarray, modes: np.ndarray, max_modes: int) -> np.ndarray:
    """At most ``max_modes`` of a waveform's modes: the strongest in the smoothed waveform, and always the lowest."""
    if len(modes) <= max_modes:
        return modes
    strongest = np.argsort(smooth[np.rint(modes[:-1]).astype(int)])[::-1][:max_modes - 1]
    return np.append(np.sort(modes[strongest]), modes[-1])


def _fit_lowest(windows: np.ndarray, first: np.ndarray, stop: np.ndarray, modes: np.ndarray, pulse: float,
                kernel: float, front: np.ndarray) -> np.ndarray:
    """(G,) lowest detectable fitted centre [samples] of G waveforms with m ``modes`` each (G, m), fitted over their
    samples ``first`` … ``stop`` − 1 (``windows``: those samples, zero beyond); the lowest mode where no component
    would be detected."""
    g, m = modes.shape
    window = stop - first
    target = windows[:, :window.max()]
    samples = first[:, None] + np.arange(target.shape[1])
    inside = samples < stop[:, None]
    peak = np.take_along_axis(windows, np.rint(modes).astype(np.int64) - first[:, None], axis=1)
    p0 = np.concatenate([np.maximum(peak, front[:, None]), modes, np.full((g, m), pulse)], axis=1)
    lower = np.concatenate([np.zeros((g, m)), np.repeat(first[:, None], m, axis=1),
                            np.full((g, m), _MIN_WIDTH * pulse)], axis=1).astype(np.float64)
    upper = np.concatenate([np.full((g, m), np.inf), np.repeat(stop[:, None] - 1, m, axis=1),
                            np.repeat(window[:, None], m, axis=1)], axis=1).astype(np.float64)
    fit = least_squares_batch(_Gaussians(samples.astype(np.float64), inside, target), np.clip(p0, lower, upper),
                              lower, upper, window)
    amp, centre, width = fit[:, :m], fit[:, m:2 * m], fit[:, 2 * m:]
    seen = amp * width / np.hypot(width, kernel) > front[:, None]  # its peak in the smoothed waveform
    return np.where(seen.any(axis=1), np.max(np.where(seen, centre, -np.inf), axis=1), modes[:, -1])


class _Gaussians:
    """Sums of m Gaussians a_k exp(−u²/2), u = (x − c_k)/w_k, at each waveform's samples ``x`` (G, L) (``inside``
    its window) minus its ``target`` (zero beyond the window), for the batched fit: residuals and their transposed
    Jacobian at parameters p = (a, c, w) (k, 3m) of the waveforms ``rows``, zero beyond each window. The Gaussians
    of the last residuals are kept for a Jacobian asked at their points (the same values as worked out anew)."""

    def __init__(self, x: np.ndarray, inside: np.ndarray, target: np.ndarray):
        self.x, self.inside, self.target = x, inside, target
        self._rows, self._p, self._terms = None, None, None

    def _at(self, p: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, ...]:
        m = p.shape[1] // 3
        amp, centre, width = p[:, :m, None], p[:, m:2 * m, None], p[:, 2 * m:, None]
        if self._rows is not None:
            kept = np.searchsorted(self._rows, rows)
            if kept.max(initial=0) < len(self._rows) and np.array_equal(self._rows[kept], rows) \
                    and np.array_equal(self._p[kept], p):
                return amp, width, self._terms[0][kept], self._terms[1][kept]
        u = (self.x[rows][:, None, :] - centre) / width
        return amp, width, u, np.exp(-0.5 * u * u) * self.inside[rows][:, None, :]

    def residual(self, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        amp, _, u, e = self._at(p, rows)
        self._rows, self._p, self._terms = rows.copy(), p.copy(), (u, e)
        return (amp * e).sum(axis=1) - self.target[rows]

    def jacobian(self, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        amp, width, u, e = self._at(p, rows)
        m = amp.shape[1]
        out = np.empty((len(rows), 3 * m, u.shape[2]))
        out[:, :m] = e
        by_centre = np.multiply(amp * e, u / width, out=out[:, m:2 * m])  # a e u / w
        np.multiply(by_centre, u, out=out[:, 2 * m:])  # a e u² / w
        return out


# --- positions, rh, sensitivity --------------------------------------------------------------------


def _at(geo: dict, n: int, name: str, sample: np.ndarray) -> np.ndarray:
    """Column ``name``_bin0 … ``name``_lastbin interpolated at fractional samples."""
    first, last = geo[f"{name}_bin0"], geo[f"{name}_lastbin"]
    return first + (last - first) * sample / (n - 1)


def _positions(geo: dict, n: int, ground: np.ndarray, start: np.ndarray, found: np.ndarray) -> dict:
    """Elevation, latitude and longitude of the lowest mode and of the highest return; FILL where no signal."""
    g, top = np.where(found, ground, 0.0), np.where(found, start, 0.0)
    out = {}
    for tag, sample in (("lowestmode", g), ("highestreturn", top)):
        out[f"elev_{tag}"] = _at(geo, n, "elevation", sample)
        out[f"lat_{tag}"] = _at(geo, n, "latitude", sample)
        out[f"lon_{tag}"] = _at(geo, n, "longitude", sample)
    return {name: np.where(found, value, FILL) for name, value in out.items()}


def _rh(y, elevation_bin0, elevation_lastbin, start, end, ground, found) -> np.ndarray:
    """(S, 101) heights [m] above ``ground`` where the energy of y between ``end`` and ``start`` (fractional
    samples), accumulated upwards in trapezoids between samples, reaches 0 … 100 %; FILL where not found. The
    sums run over the samples that hold every found window (the same sums: the rest adds zeros)."""
    s, n = y.shape
    if not found.any():
        return np.full((s, RH_LEVELS), FILL)
    first = int(np.ceil(start[found]).min())
    last = max(int(np.floor(end[found]).max()), first + 1)
    first = min(first, last - 1)
    index = np.arange(first, last + 1)[None, :]
    inside = (index >= np.ceil(start)[:, None]) & (index <= np.floor(end)[:, None])
    pair = inside[:, :-1] & inside[:, 1:]
    window = y[:, first:last + 1]
    step = np.where(pair, 0.5 * (window[:, :-1] + window[:, 1:]), 0.0)
    upward = np.cumsum(step[:, ::-1], axis=1)  # column r: the energy from the bottom up to sample last-1-r
    total = upward[:, -1]
    found = found & (total > 0.0)
    share = np.clip(np.maximum.accumulate(upward / np.where(found, total, 1.0)[:, None], axis=1), 0.0, 1.0)
    share = np.concatenate([np.zeros((s, 1)), share], axis=1)  # column r: sample last-r
    width = share.shape[1]
    levels = np.arange(1, RH_LEVELS - 1) / (RH_LEVELS - 1)
    r = np.clip(_first_reaching(share, levels), 1, width - 1)
    lo, hi = np.take_along_axis(share, r - 1, axis=1), np.take_along_axis(share, r, axis=1)
    frac = np.where(hi > lo, (levels[None, :] - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0)
    sample = (n - 1) - (r + (n - 1 - last) - 1 + np.clip(frac, 0.0, 1.0))
    edges = np.column_stack([np.where(found, end, 0.0), sample, np.where(found, start, 0.0)])
    heights = _elevation_at(elevation_bin0, elevation_lastbin, n, edges) - ground[:, None]
    return np.where(found[:, None], heights, FILL)


def _first_reaching(share: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """(S, L) per row of ``share`` (S, W), non-decreasing along each row, the first column whose value reaches each of
    the sorted ``levels`` (L,): the count of the row's values below the level (W where none reaches it), exactly, a
    row's answer whatever rows lie beside it. Each value is placed among the levels (its count of levels at or
    below it), and a row's counts of values per place, summed, count the values below each level."""
    s, w = share.shape
    place = np.searchsorted(levels, share, side="right")  # value j lies below level k exactly where k >= place[j]
    per_place = np.bincount((place + (len(levels) + 1) * np.arange(s)[:, None]).ravel(),
                            minlength=s * (len(levels) + 1)).reshape(s, -1)
    return np.cumsum(per_place, axis=1)[:, :len(levels)]


def _elevation_at(bin0: np.ndarray, lastbin: np.ndarray, n: int, sample: np.ndarray) -> np.ndarray:
    """(S, k) elevations [m] at fractional samples (S, k), linear between the samples' elevations, which are
    linear from ``bin0`` to ``lastbin`` over the n samples."""
    i = np.clip(np.floor(sample).astype(np.int64), 0, n - 2)
    t = sample - i
    rise = (lastbin - bin0)[:, None]
    return (1.0 - t) * (bin0[:, None] + rise * (i / (n - 1))) + t * (bin0[:, None] + rise * ((i + 1) / (n - 1)))


def _sensitivity(energy, sigma, pulse: float, dt: float, s: L2ASettings) -> np.ndarray:
    """Hancock et al. (2019) beam sensitivity of each waveform (energy and σ in samples, pulse σ in samples)."""
    n_noise = ndtri(1.0 - s.p_false_alarm * _BIN_M / _WINDOW_M)
    n_signal = ndtri(1.0 - s.p_miss)
    spread = 2.0 * s.footprint_sigma_m * math.tan(math.radians(2.0)) / C / dt  # footprint on a 2° slope [samples]
    width = math.hypot(pulse, spread)
    weakest = (n_noise + n_signal) * sigma * math.sqrt(2.0 * math.pi) * width
    value = 1.0 - weakest / np.where(energy > 0.0, energy, 1.0)
    return np.where(energy > 0.0, np.clip(value, 0.0, 1.0), np.where(sigma > 0.0, 0.0, 1.0))
