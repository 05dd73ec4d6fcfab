"""ATL08-like land and vegetation heights from photons (NumPy and SciPy; the density filter's counts a Warp kernel on
the CPU): each photon classified as ground, canopy, top of canopy or noise, then statistics per along-track segment
of ``segment_m`` (100 m).

After the ICESat-2 ATL08 ATBD (Neuenschwander & Pitts, "Algorithm Theoretical Basis Document for Land and
Vegetation Along-Track Products (ATL08)", Release 002 and later), §4 "Algorithm implementation", simplified:

1. **Signal** (ATBD §4.3, DRAGANN, simplified): a photon is dense (ATL08's ``d_flag``) when more other photons
   lie within the ellipse (Δx/``dragann_along_m``)² + (Δh/``dragann_height_m``)² ≤ 1 than the background
   puts there with probability ``dragann_p`` (Poisson). The background density is that of each along-track
   window of ``dragann_window_m``: the mean count of its height bins of ``dragann_bin_m`` over the photons'
   height range, leaving out the bins above median + 3·√(median + 1) (the signal, which must fill less than
   half the range, as in an ATL03 telemetry band), per metre along and in height. DRAGANN instead picks its
   radius and threshold from the histogram of neighbour counts. The ellipse is long (100 m × 3 m) so that a
   canopy's top, where half the ellipse is empty, still stands out of a daytime background; the price is
   that a canopy gap shorter than about 50 m along track passes for canopy. Signal photons are the dense
   ones and those of ATL03 ``signal_conf_ph`` ≥ ``min_signal_conf`` (ATL03's confidence misses much of a
   canopy, which is spread over its height); the rest are noise (0). The filter runs twice: on the heights, then on
   the heights above the trend of a first ground surface (step 2) of the photons it found (the ATBD de-trends the
   photons too): on sloping ground an ellipse level with the horizon holds only a short stretch of the ground
   (20 m of a 15 % slope), too few photons of a dim ground to stand out.
2. **Ground surface** (ATBD §4.9–4.12: the ground is the lowest dense surface of the signal photons, found in
   along-track windows, filtered, smoothed and refined; :mod:`flightsim.outputs.atl08_ground` says how): in each
   window of ``window_m`` the lowest cluster of ``cluster_photons`` signal photons within ``cluster_m`` (heights
   above a least-squares trend over ``trend_m``, so a slope does not spread the cluster); a floor with no other
   floor near it is background below the ground; a floor more than ``object_height_m`` above the envelope of
   slope ``relief_slope`` the other floors allow is a canopy window whose few ground photons made no cluster;
   the surface is linear between the remaining floors, median filtered over ``smooth_windows``, then ``refinements``
   passes re-estimate each window as the median of the photons within ±``search_m``/2ʲ of it. Under a closed
   canopy over dim ground the lowest photons of many windows are leaves; taking a low percentile of each window
   (as this classifier did before) put the ground there, metres up in the canopy.
3. **Ground** (ATBD §4.13 "refine ground estimates"): photons within ±buffer of the surface, the buffer
   ``ground_sigmas`` × the robust σ of the signal photons just below it (1.4826 × the median of |h − surface|
   over those within ``search_m`` below: a half-normal's median is 0.6745 σ; canopy lies only above the
   ground), clipped to [``min_buffer_m``, ``max_buffer_m``]. Signal photons further below are noise.
4. **Canopy** (ATBD §4.11–4.14): signal photons above the buffer and at most ``max_canopy_m`` above the
   surface that are dense (step 1's test) among the photons above the buffer alone, in along-track distance
   and height above the surface (the ATBD's canopy filter: without it, background photons just above the
   ground band pass for canopy, the ground photons filling their ellipses).
   **Top of canopy** (3): the canopy photons at or above the ``toc_percentile`` (95th) of the canopy heights
   above ground in each along-track window of ``toc_window_m`` (the ATBD finds an upper-envelope surface).
5. **Segments** (ATBD §4.15): segment j holds the photons with ⌊along/segment_m⌋ = j (along-track distance
   from the line's start, as ATL03's ``dist_ph_along``); a segment is reported when it holds a classified
   photon. ``h_te_mean``, ``h_te_median``: ground photon heights; ``h_canopy`` (98th percentile),
   ``h_mean_canopy``, ``canopy_openness`` (standard deviation): the heights above the surface of the canopy
   and top-of-canopy photons; counts of each class; ``latitude``, ``longitude``, ``delta_time`` interpolated
   along track at the segment's middle. ``segment_id_beg``/``_end`` are the first and last ATL03 20 m segment
   (id ⌊along/20 m⌋ + 1) the segment spans. Terrain (canopy) values need ``min_ground_photons``
   (``min_canopy_photons``) photons, else they hold :data:`FILL` (ATL08's fill value); terrain values also need
   more ground photons than the background (step 1's, over the ground band's height and the segment) puts in the
   band but with the chance ``dragann_p``: a segment without ground photons, its ground surface interpolated from
   the segments around it, reports no terrain height (its canopy height, above that surface, it does).

Per photon: ``classed_pc_flag`` (ATL08: 0 noise, 1 ground, 2 canopy, 3 top of canopy), ``ph_h`` (height above
the surface [m], FILL when no surface), ``ph_segment_id`` (its ATL03 20 m segment), ``d_flag`` (1: dense, step 1).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import warp as wp

from flightsim.core.errors import InputError, positive
from flightsim.core.poisson import upper_quantile
from flightsim.core.settings import Settings, check_settings, setting
from flightsim.core.warp_runtime import init_warp
from flightsim.outputs.atl08_ground import ground_surface, group_percentile, trend_of
from kernels.ellipse import ellipse_pairs

NOISE, GROUND, CANOPY, TOP_OF_CANOPY = 0, 1, 2, 3
FILL = float(np.finfo(np.float32).max)  # ATL08's _FillValue of its float32 heights
ATL03_SEGMENT_M = 20.0
SEGMENT_COLUMNS = ("segment_id_beg", "segment_id_end", "latitude", "longitude", "delta_time", "n_seg_ph",
                   "h_te_mean", "h_te_median", "n_te_photons", "h_canopy", "h_mean_canopy", "canopy_openness",
                   "n_ca_photons", "n_toc_photons")
PHOTON_COLUMNS = ("classed_pc_flag", "classed_pc_indx", "ph_h", "ph_segment_id", "d_flag", "delta_time")


@dataclass
class ATL08Settings(Settings):
    """ATL08-like photon classification and segment statistics."""

    table: ClassVar[str] = "atl08"
    min_signal_conf: int = setting(2, "photons of signal_conf_ph at least this are signal", range=(0, 4))
    dragann_along_m: float = setting(50.0, "density filter: along-track half axis", "m", range=(0.0, 1e3),
                                     lo_open=True)
    dragann_height_m: float = setting(1.5, "density filter: height half axis", "m", range=(0.0, 1e3), lo_open=True)
    dragann_window_m: float = setting(200.0, "along-track window of the background density", "m",
                                      range=(0.0, 1e5), lo_open=True)
    dragann_bin_m: float = setting(2.0, "height bin of the background density", "m", range=(0.0, 1e3),
                                   lo_open=True)
    dragann_p: float = setting(1e-3, "density filter: chance that background alone is called dense",
                               range=(0.0, 1.0), lo_open=True)
    window_m: float = setting(10.0, "along-track window of the ground surface", "m", range=(0.0, 1e4), lo_open=True)
    cluster_photons: int = setting(3, "ground: photons of a window's lowest cluster", range=(1, 1000))
    cluster_m: float = setting(1.0, "ground: height band of a window's lowest cluster (plus the slope's rise)", "m",
                               range=(0.0, 100.0), lo_open=True)
    ground_slope: float = setting(0.2, "ground: steepest slope along track the surface follows untouched",
                                  range=(0.0, 10.0))
    trend_m: float = setting(200.0, "ground: along-track span of the trend the floors are taken relative to", "m",
                             range=(0.0, 1e5), lo_open=True)
    relief_slope: float = setting(0.05, "ground: steepest slope of the ground relative to the trend", range=(0.0, 10.0))
    object_height_m: float = setting(1.0, "ground: a floor this much above the relief_slope envelope is canopy", "m",
                                     range=(0.0, 100.0))
    refinements: int = setting(3, "passes re-estimating the surface from the photons near it", range=(0, 20))
    search_m: float = setting(3.0, "half height of the first refinement's band (halved each pass)", "m",
                              range=(0.0, 1e3), lo_open=True)
    smooth_windows: int = setting(3, "median filter of the surface over this many windows", range=(1, 101))
    ground_sigmas: float = setting(2.5, "ground buffer: this many robust σ of the ground photons", range=(0.0, 100.0))
    min_buffer_m: float = setting(0.3, "least ground buffer", "m", range=(0.0, 100.0))
    max_buffer_m: float = setting(3.0, "largest ground buffer", "m", range=(0.0, 100.0))
    max_canopy_m: float = setting(60.0, "signal photons higher than this above the ground are noise", "m",
                                  range=(0.0, 1e3), lo_open=True)
    toc_window_m: float = setting(5.0, "along-track window of the top of canopy", "m", range=(0.0, 1e4),
                                  lo_open=True)
    toc_percentile: float = setting(95.0, "top of canopy: canopy photons at or above this percentile", "%",
                                    range=(0.0, 100.0))
    min_ground_photons: int = setting(5, "fewest ground photons for a segment's terrain heights", range=(1, 1e6))
    min_canopy_photons: int = setting(5, "fewest canopy photons for a segment's canopy heights", range=(1, 1e6))

    def check(self, context=None) -> None:
        if self.min_buffer_m > self.max_buffer_m:
            raise InputError("atl08.min_buffer_m", self.min_buffer_m, f"<= atl08.max_buffer_m = {self.max_buffer_m}")


def atl08_segments(along_track_m, h_ph, lat, lon, signal_conf_ph, delta_time, segment_m: float = 100.0,
                   settings: ATL08Settings | None = None, threads: int = 1) -> dict[str, np.ndarray]:
    """ATL08-like classification and segments of one beam's photons (the module docstring gives the method).

    Args:
        along_track_m: (n,) along-track distance of each photon from the line's start [m], finite, >= 0.
        h_ph: (n,) photon heights [m] (ellipsoidal or local: the segments' terrain heights are in the same).
        lat, lon: (n,) photon latitude, longitude [deg].
        signal_conf_ph: (n,) integer ATL03 confidence (-2 … 4).
        delta_time: (n,) time of each photon's shot [s].
        segment_m: along-track length of a segment [m], > 0 (ATL08: 100 m).
        settings: :class:`ATL08Settings`.
        threads: threads the density filter's counts may use (:func:`ellipse_counts`; the same values on any).

    Returns: ``{"land_segments": {...}, "signal_photons": {...}}`` as ATL08 groups them: the
    :data:`SEGMENT_COLUMNS`, (m,) arrays, one per reported segment in along-track order (heights float64 with
    :data:`FILL`, counts and ids int32); the :data:`PHOTON_COLUMNS`, (n,) arrays in input order
    (``classed_pc_flag``, ``d_flag`` int8; ``classed_pc_indx`` the photon's 1-based index in the input, int32 —
    ATL08's counts within its ATL03 20 m segment; ``ph_h`` float64; ``ph_segment_id`` int32; ``delta_time``).
    """
    s = settings if settings is not None else ATL08Settings()
    check_settings("atl08", s)
    x, h, la, lo, conf, t = _photons(along_track_m, h_ph, lat, lon, signal_conf_ph, delta_time)
    seg_m = positive("segment_m", segment_m, "m")
    dense, window, lam = _dense(x, h, conf, s, threads)
    signal = dense | (conf >= s.min_signal_conf)
    cls, ph_h, band = _classify(x, h, signal, window, lam, s, threads)
    photons = {"classed_pc_flag": cls, "classed_pc_indx": np.arange(1, len(x) + 1, dtype=np.int32), "ph_h": ph_h,
               "ph_segment_id": (np.floor(x / ATL03_SEGMENT_M) + 1).astype(np.int32),
               "d_flag": dense.astype(np.int8), "delta_time": t}
    return {"land_segments": _segments(x, h, la, lo, t, cls, ph_h, band, seg_m, s), "signal_photons": photons}


# --- input -----------------------------------------------------------------------------------------


def _photons(along, h, lat, lon, conf, t) -> tuple[np.ndarray, ...]:
    """The photon columns checked: (n,) each, finite, along-track >= 0, confidence integers in [-2, 4]."""
    n = np.shape(along)[0] if np.ndim(along) == 1 else -1
    out = []
    for name, value in (("along_track_m", along), ("h_ph", h), ("lat", lat), ("lon", lon), ("delta_time", t)):
        try:
            column = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(name, type(value).__name__, "(n,) numbers, one per photon") from None
        if column.ndim != 1 or len(column) != n:
            raise InputError(name, f"shape {column.shape}", f"({max(n, 0)},), one value per photon")
        if not np.isfinite(column).all():
            raise InputError(name, f"{np.count_nonzero(~np.isfinite(column))} non-finite values", "finite values")
        out.append(column)
    if n and out[0].min() < 0.0:
        raise InputError("along_track_m", out[0].min(), "distances >= 0 [m] from the line's start")
    c = np.asarray(conf)
    if c.shape != (n,) or (n and (c.dtype.kind not in "iu" or c.min() < -2 or c.max() > 4)):
        raise InputError("signal_conf_ph", f"shape {c.shape}, dtype {c.dtype}", f"({n},) integers in [-2, 4]")
    x, h, la, lo, t = out
    return x, h, la, lo, c.astype(np.int64), t


# --- classification --------------------------------------------------------------------------------


def _expected(window, x, h, s: ATL08Settings) -> np.ndarray:
    """Per along-track window (:func:`_windows`, each photon's): the mean count of background photons in a photon's
    ellipse there."""
    if not len(x):
        return np.zeros(0)
    return _background(window, x, h, s) * math.pi * s.dragann_along_m * s.dragann_height_m


def _windows(x, s: ATL08Settings) -> np.ndarray:
    """Each photon's along-track window of dragann_window_m, numbered 0, 1, … over the windows holding photons (the
    ranks ``np.unique``'s inverse gives: from a count of the windows where they span few more than the photons, else
    by ``np.unique``'s sort)."""
    if not len(x):
        return np.zeros(0, dtype=np.int64)
    cell = np.floor(x / s.dragann_window_m)
    cell -= cell.min()
    if cell.max() > 4 * len(x) + 1024:  # photons far apart: a count would be mostly empty windows
        return np.unique(cell, return_inverse=True)[1].reshape(-1)
    cell = cell.astype(np.int64)
    return (np.cumsum(np.bincount(cell) > 0) - 1)[cell]


def _limit(lam: np.ndarray, s: ATL08Settings) -> np.ndarray:
    """The counts a Poisson background of mean ``lam`` exceeds with the chance dragann_p (one per distinct mean)."""
    means, index = np.unique(lam, return_inverse=True)
    return upper_quantile(s.dragann_p, means)[index.reshape(-1)]


def _dense(x, h, conf, s: ATL08Settings, threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which photons the density filter finds dense (step 1: in heights above the trend of a first ground surface
    of the photons dense in their heights, or of ATL03 confidence); each photon's window and each window's
    background count in an ellipse there."""
    window = _windows(x, s)
    lam = _expected(window, x, h, s)
    first = (_neighbours(x, h, s, threads) > _limit(lam, s)[window]) | (conf >= s.min_signal_conf)
    if not first.any():
        return first, window, lam
    centres, surface = ground_surface(x[first], h[first], s)
    above = h - np.interp(x, centres, trend_of(surface, np.ones(len(surface), dtype=bool), s))
    lam = _expected(window, x, above, s)
    return _neighbours(x, above, s, threads) > _limit(lam, s)[window], window, lam


def _neighbours(x, h, s: ATL08Settings, threads: int) -> np.ndarray:
    """How many other of the photons lie in each one's ellipse: (Δx/a)² + (Δh/b)² ≤ 1 for the half axes a, b
    (:func:`ellipse_counts` on ``threads``)."""
    return ellipse_counts(x / s.dragann_along_m, h / s.dragann_height_m, threads) - 1


CELL = 1.0 + 2.0 ** -20  # ellipse_counts' column width and search band [half axes]: just over 1, so that two points
# whose distance rounds to 1 or less are in the same or neighbouring columns and within the band whatever the rounding


def ellipse_counts(u: np.ndarray, v: np.ndarray, threads: int = 1) -> np.ndarray:
    """For each point (u, v) (scaled by the ellipse's half axes) the points, itself included, with
    (u − u')² + (v − v')² ≤ 1 in float64: the count ``scipy.spatial.cKDTree.query_ball_point(r=1,
    return_length=True)`` gives, in a twentieth of its time on one core (an ATLAS beam). The points are cut into
    columns of width :data:`CELL` in u and sorted by column, then v (one float64 key, the columns apart by more than
    twice the band searched); a Warp kernel on the CPU (:func:`kernels.ellipse.ellipse_pairs`) walks the columns,
    comparing each pair once, by its earlier point: against the later points of its own column within the band (just
    over 1) above its v and the points of the next column within the band around its v; a pair found counts for
    both. On ``threads`` > 1 threads (Warp's CPU kernels and NumPy's sorts let go of Python's lock) the sort and the
    walk are shared out (:func:`_key_order`, :func:`_walked`): the same counts, whatever order ties take."""
    n = len(u)
    if not n:
        return np.zeros(0, dtype=np.int64)
    column = np.floor(u / CELL)
    column -= column.min()
    low = v.min()
    span = float(v.max() - low) + 4.0 * CELL  # a column's key range and more than twice the band between columns
    key = column * span + (v - low)
    order = _key_order(key, column, threads)
    key, column = key[order], column[order]
    band = CELL + 8.0 * float(np.spacing(key[-1]))  # a pair's key difference is its v difference within 5 ulps
    starts = np.flatnonzero(np.r_[True, column[1:] != column[:-1], True]).astype(np.int32)  # the columns' runs
    out = np.empty(n, dtype=np.int64)
    out[order] = _walked(key, u[order], v[order], starts, span, band, threads)
    return out


def _key_order(key: np.ndarray, column: np.ndarray, threads: int) -> np.ndarray:
    """An order sorting ``key``: NumPy's argsort, or on ``threads`` > 1 the points cut into as many bands of whole
    columns (every key of a band below the next band's: a column's keys span less than ``span``), each band sorted
    on a thread of its own."""
    if threads < 2:
        return np.argsort(key)
    band = np.minimum(column * (threads / (column.max() + 1.0)), threads - 1).astype(np.uint8)
    grouped = np.argsort(band, kind="stable")
    edges = np.searchsorted(band[grouped], np.arange(threads + 1))
    bands = [grouped[a:b] for a, b in zip(edges[:-1], edges[1:])]
    with ThreadPoolExecutor(threads, thread_name_prefix="atl08") as pool:
        return np.concatenate(list(pool.map(lambda part: part[np.argsort(key[part])], bands)))


def _walked(key, u, v, starts: np.ndarray, span: float, band: float, threads: int) -> np.ndarray:
    """Each sorted point's count (itself included) by :func:`kernels.ellipse.ellipse_pairs`, its column runs
    ``starts`` cut into up to ``threads`` ranges walked side by side, each adding into counts of its own (a range's
    last column adds to the next range's first), then summed."""
    init_warp()
    runs = len(starts) - 1
    cuts = np.linspace(0, runs, max(1, min(threads, runs)) + 1).astype(np.int64)
    points = [wp.array(a, dtype=wp.float64, device="cpu") for a in (key, u, v)]

    def walk(k: int) -> np.ndarray:
        counts = (wp.ones if k == 0 else wp.zeros)(len(key), dtype=wp.int32, device="cpu")  # each point itself once
        wp.launch(ellipse_pairs, int(cuts[k + 1] - cuts[k]), inputs=[*points, starts[cuts[k]:cuts[k + 1] + 1], span,
                                                                     band], outputs=[counts], device="cpu")
        return counts.numpy()

    if len(cuts) == 2:
        return walk(0)
    wp.load_module(ellipse_pairs.module, device="cpu")  # loaded once, before the threads launch it
    with ThreadPoolExecutor(len(cuts) - 1, thread_name_prefix="atl08") as pool:
        return sum(pool.map(walk, range(len(cuts) - 1)))


def _background(window, x, h, s: ATL08Settings) -> np.ndarray:
    """Background photons per m² (along × height) of each window, from the counts of its height bins: their
    mean after dropping the bins above median + 3·√(median + 1), which hold the signal."""
    count = int(window.max()) + 1
    low, high = _extremes(window, h, count)
    bins = np.maximum(np.ceil((high - low) / s.dragann_bin_m).astype(np.int64), 1)
    k = np.minimum(((h - low[window]) / s.dragann_bin_m).astype(np.int64), bins[window] - 1)
    width = int(bins.max())
    counts = np.bincount(window * width + k, minlength=count * width).reshape(count, width).astype(np.float64)
    counts[np.arange(width)[None, :] >= bins[:, None]] = np.nan  # past a window's height span
    median = np.nanmedian(counts, axis=1)
    counts[counts > (median + 3.0 * np.sqrt(median + 1.0))[:, None]] = np.nan
    first, last = _extremes(window, x, count)
    length = np.clip(last - first, 1.0, s.dragann_window_m)
    return np.nanmean(counts, axis=1) / (s.dragann_bin_m * length)


def _extremes(group, values, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Least and greatest value of each group 0 … count-1 (every group non-empty)."""
    low, high = np.full(count, np.inf), np.full(count, -np.inf)
    np.minimum.at(low, group, values)
    np.maximum.at(high, group, values)
    return low, high


def _classify(x, h, signal, window, lam, s: ATL08Settings, threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """classed_pc_flag (int8), height above the ground surface (FILL where no signal photon exists) and the
    background photons per metre along track in the ground band around each photon; ``window``, ``lam``: each
    photon's window and each window's mean background count in the density filter's ellipse."""
    cls = np.zeros(len(x), dtype=np.int8)
    if not signal.any():
        return cls, np.full(len(x), FILL), np.zeros(len(x))
    centres, surface = ground_surface(x[signal], h[signal], s)
    rel = h - np.interp(x, centres, surface)
    buffer = _ground_buffer(rel[signal], s)
    cls[signal & (np.abs(rel) <= buffer)] = GROUND
    above = rel > buffer
    cls[signal & above & (rel <= s.max_canopy_m)] = CANOPY
    sparse = _neighbours(x[above], rel[above], s, threads) <= _limit(lam, s)[window[above]]  # above the ground only
    cls[np.flatnonzero(above)[sparse & (cls[above] == CANOPY)]] = NOISE
    _mark_top_of_canopy(x, rel, cls, s)
    return cls, rel, lam[window] * 2.0 * buffer / (math.pi * s.dragann_along_m * s.dragann_height_m)


def _ground_buffer(rel: np.ndarray, s: ATL08Settings) -> float:
    """Half height of the ground band [m]: ground_sigmas robust σ of the signal photons just below the surface."""
    below = -rel[(rel <= 0.0) & (rel >= -s.search_m)]
    sigma = 1.4826 * float(np.median(below)) if len(below) else 0.0
    return float(np.clip(s.ground_sigmas * sigma, s.min_buffer_m, s.max_buffer_m))


def _mark_top_of_canopy(x, rel, cls, s: ATL08Settings) -> None:
    """Canopy photons at or above the toc_percentile of their window's canopy heights become top of canopy."""
    canopy = np.flatnonzero(cls == CANOPY)
    if not len(canopy):
        return
    window = np.floor(x[canopy] / s.toc_window_m).astype(np.int64)
    first = window.min()
    level, _ = group_percentile(window - first, rel[canopy], s.toc_percentile, int(window.max() - first) + 1)
    cls[canopy[rel[canopy] >= level[window - first]]] = TOP_OF_CANOPY


# --- segments --------------------------------------------------------------------------------------


def _segments(x, h, lat, lon, t, cls, rel, band, seg_m: float, s: ATL08Settings) -> dict[str, np.ndarray]:
    """The SEGMENT_COLUMNS of the segments holding a classified photon; ``band``: per photon, the background photons
    per metre along track in the ground band (terrain needs more ground photons than that puts in a segment but
    with the chance dragann_p)."""
    segment = np.floor(x / seg_m).astype(np.int64)
    ids = np.unique(segment[cls > NOISE])
    if not len(ids):
        return {name: np.zeros(0, np.int32 if name.startswith(("n_", "segment_id")) else np.float64)
                for name in SEGMENT_COLUMNS}
    group = np.searchsorted(ids, segment)
    member = np.isin(segment, ids)
    m = len(ids)
    ground, canopy = member & (cls == GROUND), member & (cls >= CANOPY)
    out = {"segment_id_beg": (np.floor(ids * seg_m / ATL03_SEGMENT_M) + 1).astype(np.int32),
           "segment_id_end": np.ceil((ids + 1) * seg_m / ATL03_SEGMENT_M).astype(np.int32)}
    order = np.argsort(x, kind="stable")
    middle = (ids + 0.5) * seg_m
    for name, values in (("latitude", lat), ("longitude", lon), ("delta_time", t)):
        out[name] = np.interp(middle, x[order], values[order])
    out["n_seg_ph"] = np.bincount(group[member], minlength=m).astype(np.int32)
    out["n_te_photons"] = np.bincount(group[ground], minlength=m).astype(np.int32)
    out["n_ca_photons"] = np.bincount(group[member & (cls == CANOPY)], minlength=m).astype(np.int32)
    out["n_toc_photons"] = np.bincount(group[member & (cls == TOP_OF_CANOPY)], minlength=m).astype(np.int32)
    noise = np.bincount(group[member], weights=band[member], minlength=m) / np.maximum(out["n_seg_ph"], 1) * seg_m
    enough_te = (out["n_te_photons"] >= s.min_ground_photons) & (out["n_te_photons"] > upper_quantile(s.dragann_p, noise))
    enough_ca = out["n_ca_photons"] + out["n_toc_photons"] >= s.min_canopy_photons
    mean, _ = _group_moments(group[ground], h[ground], m)
    out["h_te_mean"] = np.where(enough_te, mean, FILL)
    out["h_te_median"] = np.where(enough_te, group_percentile(group[ground], h[ground], 50.0, m)[0], FILL)
    mean, std = _group_moments(group[canopy], rel[canopy], m)
    out["h_canopy"] = np.where(enough_ca, group_percentile(group[canopy], rel[canopy], 98.0, m)[0], FILL)
    out["h_mean_canopy"] = np.where(enough_ca, mean, FILL)
    out["canopy_openness"] = np.where(enough_ca, std, FILL)
    return out


def _group_moments(group, values, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (population) of each group's values; 0 for an empty group."""
    size = np.maximum(np.bincount(group, minlength=count), 1)
    mean = np.bincount(group, weights=values, minlength=count) / size
    square = np.bincount(group, weights=(values - mean[group]) ** 2, minlength=count) / size
    return mean, np.sqrt(square)
