"""ATL03's signal finder: each photon's neighbour counts, one thread per along-track segment (the algorithm is
flightsim.scoring.signal_finder's, which runs this on the CPU).

The photons come sorted by segment, then height: segment j's heights are ``hs[bounds[j]:bounds[j + 1]]``, ascending.
A photon's counts are taken over sorted runs, a pointer per bound and run: as the segment's photons go up in height,
so does each bound, and each pointer only moves up. A count over [lo, hi] is the values ≤ hi less those < lo, as
``np.searchsorted`` gives them (the bounds worked out in float64 as NumPy works them out).
"""
from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def _below(hs: wp.array(dtype=wp.float64), p: int, end: int, value: wp.float64):
    """The first index from p on (up to ``end``) whose value is >= ``value``."""
    while p < end and hs[p] < value:
        p += 1
    return p


@wp.func
def _through(hs: wp.array(dtype=wp.float64), p: int, end: int, value: wp.float64):
    """The first index from p on (up to ``end``) whose value is > ``value``."""
    while p < end and hs[p] <= value:
        p += 1
    return p


@wp.func
def _add_window(hs: wp.array(dtype=wp.float64), a: int, b: int, first: int, end: int, half: wp.float64, sign: int,
                counts: wp.array(dtype=wp.int32)):
    """Add ``sign`` × how many of the sorted run first … end − 1 lie in [h − half, h + half] to counts[i], for each
    photon i of a … b − 1 (heights h = hs[i], ascending)."""
    lo = first
    hi = first
    for i in range(a, b):
        h = hs[i]
        lo = _below(hs, lo, end, h - half)
        hi = _through(hs, hi, end, h + half)
        counts[i] = counts[i] + sign * (hi - lo)


@wp.kernel
def segment_counts(hs: wp.array(dtype=wp.float64), bounds: wp.array(dtype=wp.int32),
                   pool_lo: wp.array(dtype=wp.int32), pool_hi: wp.array(dtype=wp.int32), inner: wp.float64,
                   outer: wp.float64, half: wp.float64, ring: wp.array(dtype=wp.int32),
                   others: wp.array(dtype=wp.int32), band: wp.array2d(dtype=wp.float64)):
    """Per photon of segment j: ``ring``, its pool's photons (segments pool_lo[j] … pool_hi[j] − 1) with heights in
    [h − outer, h + outer] but not in [h − inner, h + inner]; ``others``, its segment's other photons in
    [h − half, h + half]; per segment ``band`` (2, m): the pool's least and greatest height."""
    j = wp.tid()
    a = bounds[j]
    b = bounds[j + 1]
    for i in range(a, b):
        ring[i] = 0
        others[i] = -1
    low = hs[bounds[pool_lo[j]]]
    high = hs[bounds[pool_lo[j]]]
    for r in range(pool_lo[j], pool_hi[j]):
        first = bounds[r]
        end = bounds[r + 1]
        low = wp.min(low, hs[first])
        high = wp.max(high, hs[end - 1])
        _add_window(hs, a, b, first, end, outer, 1, ring)
        _add_window(hs, a, b, first, end, inner, -1, ring)
    band[0, j] = low
    band[1, j] = high
    _add_window(hs, a, b, a, b, half, 1, others)
