"""The ground surface of the ATL08-like classifier (:mod:`flightsim.outputs.atl08`, step 2), from the signal photons
alone: the lowest dense surface, found so that a closed canopy over dim ground is not taken for the ground.

After the ATL08 ATBD (Neuenschwander & Pitts, §4.9–4.13: the ground is the lowest surface of the signal photons,
found in along-track windows, filtered of what stands above it, smoothed, then refined within a buffer):

1. **Floors**: the signal photons in along-track windows of ``window_m``; in each, the lowest cluster: the lowest
   photon with ``cluster_photons`` − 1 others within ``cluster_m`` above it; the window's floor is the median of
   those ``cluster_photons`` heights. A lone photon below the ground (background the signal finder let through)
   is no cluster; a window without a cluster has no floor (where no window has one, each window's lowest photon).
2. **Trend**: per window the least-squares line through the floors within ±``trend_m``/2 along track, taken at
   the window (one-sided at the ends of the line, so a slope goes on). Steps 1 and 3 are done twice: first with
   the floors of the heights themselves (their band widened by ``ground_slope`` × ``window_m``, a slope's rise
   across a window) and the trend of all of them, then with the floors of the heights above that trend and the
   trend of the floors step 3 kept: the canopy no longer lifts it.
3. **Rejected floors**, in the heights above the trend: a floor with no other floor within ±``trend_m``/2 along
   track that lies within ``object_height_m`` + ``relief_slope`` × their distance of it is no surface (a cluster
   of background far below the ground would otherwise pull the ground down to it); a floor more than
   ``object_height_m`` above the lowest surface of slope ``relief_slope`` that the other floors allow,
   min over j of (floor_j + ``relief_slope`` × |distance|), is raised: a window whose ground photons were too
   few for a cluster, so that its lowest cluster lay in the canopy. The ground is the lowest dense surface:
   a canopy window stands above the ground windows beside it, a ground window does not stand above anything.
   A canopy window further than (its floor's height above the ground − ``object_height_m``) / ``relief_slope``
   (80 m for leaves from 5 m up) from every window with a ground cluster cannot be told from a rise of the
   ground, and stays.
4. **Surface**: the kept floors, linear in between (beyond the end ones the trend, through the end one), median
   filtered over ``smooth_windows``; then ``refinements`` passes each re-estimate every window as the median of
   the signal photons within ±``search_m``/2ʲ of the surface (j = 0, 1, …; in heights above the surface, so a
   slope does not widen the band) and smooth again. The surface is linear between window centres.

Nothing here uses a photon's truth: only its along-track position, height and signal classification.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

from flightsim.core.radix import by_key_then_value


def ground_surface(x: np.ndarray, h: np.ndarray, s) -> tuple[np.ndarray, np.ndarray]:
    """Window centres [m along track] and the ground surface there [m] of the signal photons ``x``, ``h`` (m,
    non-empty); ``s`` the :class:`flightsim.outputs.atl08.ATL08Settings`."""
    x0 = x.min()
    window = np.floor((x - x0) / s.window_m).astype(np.int64)
    count = int(window.max()) + 1
    centres = x0 + (np.arange(count) + 0.5) * s.window_m
    floors, ground = _floors(window, h, count, s, s.cluster_m + s.ground_slope * s.window_m)
    for _ in range(2):  # the trend of every floor, then of the ground floors alone
        trend = trend_of(floors, ground, s)
        residual, found = _floors(window, h - np.interp(x, centres, trend), count, s, s.cluster_m)
        valid = supported(centres, residual, found, s)
        ground = valid & ~raised(centres, residual, valid, s.relief_slope, s.object_height_m)
        ground = ground if ground.any() else found  # too few windows to judge
        floors = trend + residual
    surface = _smoothed(trend, residual, ground, s.smooth_windows)
    for j in range(s.refinements):
        rel = h - np.interp(x, centres, surface)
        near = np.abs(rel) <= s.search_m / 2.0 ** j
        offset, found = group_percentile(window[near], rel[near], 50.0, count)
        if found.any():
            surface = _smoothed(surface, offset, found, s.smooth_windows)
    return centres, surface


def _floors(window: np.ndarray, h: np.ndarray, count: int, s, band: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`window_floors` with cluster_photons; where no window has a cluster, each window's lowest photon."""
    floors, valid = window_floors(window, h, count, s.cluster_photons, band)
    return (floors, valid) if valid.any() else _lowest(window, h, count)


def trend_of(floors: np.ndarray, valid: np.ndarray, s) -> np.ndarray:
    """Per window: the least-squares line through the valid floors within ±trend_m/2 along track, at the window
    (one-sided near the ends: a slope goes on); the mean where too few, interpolated where none."""
    count = len(floors)
    half = max(int(round(s.trend_m / s.window_m / 2.0)), 1)
    i = np.arange(count, dtype=np.float64)
    lo, hi = np.maximum(np.arange(count) - half, 0), np.minimum(np.arange(count) + half + 1, count)
    w, f = valid.astype(np.float64), np.where(valid, floors, 0.0)

    def spans(v):
        total = np.concatenate([[0.0], np.cumsum(v)])
        return total[hi] - total[lo]

    s0, s1, s2, t0, t1 = (spans(v) for v in (w, w * i, w * i * i, w * f, w * i * f))
    su, suu, tu = s1 - i * s0, s2 - 2.0 * i * s1 + i * i * s0, t1 - i * t0  # about the window itself
    det = s0 * suu - su * su
    line = (s0 >= 3) & (det > 1e-9 * np.maximum(s0 * suu, 1.0))
    value = np.where(line, (suu * t0 - su * tu) / np.where(line, det, 1.0), t0 / np.maximum(s0, 1.0))
    return _filled(value, s0 > 0)


def window_floors(window: np.ndarray, h: np.ndarray, count: int, k: int, band: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per window 0 … count-1: the median height of its lowest cluster (the lowest photon with k − 1 others within
    ``band`` [m] above it, and those k photons) and whether it has one."""
    floors, valid = np.zeros(count), np.zeros(count, dtype=bool)
    if len(h) < k:
        return floors, valid
    order = by_key_then_value(window, h)
    hs, ws = h[order], window[order]
    start = np.arange(len(hs) - k + 1)
    seeds = start[(ws[start + k - 1] == ws[start]) & (hs[start + k - 1] - hs[start] <= band)]
    first_windows, first = np.unique(ws[seeds], return_index=True)  # seeds ascend: the lowest seed of each window
    lowest = seeds[first]
    floors[first_windows] = np.median(hs[lowest[:, None] + np.arange(k)[None, :]], axis=1)
    valid[first_windows] = True
    return floors, valid


def supported(centres: np.ndarray, floors: np.ndarray, valid: np.ndarray, s) -> np.ndarray:
    """Which valid windows have another valid floor within ±trend_m/2 along track that lies within object_height_m
    + relief_slope × their distance of theirs: a floor of its own (background below the ground) is not a surface."""
    half = max(int(round(s.trend_m / s.window_m / 2.0)), 1)
    found = np.zeros(len(floors), dtype=bool)
    for shift in range(1, min(half, len(floors) - 1) + 1):
        near = valid[shift:] & valid[:-shift] & (np.abs(floors[shift:] - floors[:-shift])
                                                  <= s.object_height_m + s.relief_slope * shift * s.window_m)
        found[shift:] |= near
        found[:-shift] |= near
    return valid & found


def raised(centres: np.ndarray, floors: np.ndarray, valid: np.ndarray, slope: float, rise: float) -> np.ndarray:
    """Which valid windows (``centres`` ascending [m]) have a floor more than ``rise`` [m] above the lowest surface
    of slope ``slope`` that the valid floors allow there: min over j of floor_j + slope·|centre_i − centre_j|."""
    big = np.finfo(np.float64).max / 4.0
    f = np.where(valid, floors, big)
    from_left = np.minimum.accumulate(f - slope * centres) + slope * centres
    from_right = np.minimum.accumulate((f + slope * centres)[::-1])[::-1] - slope * centres
    return valid & (floors - np.minimum(from_left, from_right) > rise)


def _lowest(window: np.ndarray, h: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Each window's lowest height, and whether it has any."""
    low = np.full(count, np.inf)
    np.minimum.at(low, window, h)
    valid = np.isfinite(low)
    return np.where(valid, low, 0.0), valid


def _filled(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The values with the invalid ones interpolated linearly from the valid (held flat beyond the ends)."""
    index = np.arange(len(values))
    return np.interp(index, index[valid], values[valid])


def _smoothed(base: np.ndarray, offset: np.ndarray, valid: np.ndarray, size: int) -> np.ndarray:
    """Per window base + offset where valid; between valid windows linear, beyond the end ones the base plus the end
    one's offset (a slope goes on); median filtered over ``size`` windows."""
    index = np.flatnonzero(valid)
    surface = np.interp(np.arange(len(base)), index, (base + offset)[index])
    surface[:index[0]] = base[:index[0]] + offset[index[0]]
    surface[index[-1] + 1:] = base[index[-1] + 1:] + offset[index[-1]]
    return median_filter(surface, size=size, mode="nearest")


def group_percentile(group, values, q: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The q-th percentile (linear, as numpy's default) of the values of each group 0 … count-1, and whether the
    group has any (0 where not)."""
    order = by_key_then_value(group, values)
    v = values[order]
    size = np.bincount(group, minlength=count)
    valid = size > 0
    start = np.cumsum(size) - size
    position = start + (q / 100.0) * np.maximum(size - 1, 0)
    lo = np.minimum(np.floor(position).astype(np.int64), max(len(v) - 1, 0))
    hi = np.minimum(lo + 1, start + size - 1)
    frac = position - np.floor(position)
    if not len(v):
        return np.zeros(count), valid
    result = (1.0 - frac) * v[lo] + frac * v[np.maximum(hi, 0)]
    return np.where(valid, result, 0.0), valid
