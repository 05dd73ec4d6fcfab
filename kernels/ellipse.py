"""ATL08's density filter: how many photons lie in each photon's ellipse, on points already scaled by the ellipse's
half axes and sorted by column, then height (flightsim.outputs.atl08.ellipse_counts makes the keys and runs it on the
CPU).

A point's key is ``column · span + (v − lowest v)``: its own column's points within ``band`` (just over 1) of its key
and the next column's within ``band`` of its key + ``span`` are the only ones that can lie within distance 1 of it.
Each pair is compared once, by its earlier point, in float64 as NumPy compares it (Δu² + Δv² ≤ 1: Warp's code makes
each operation a statement of its own, which the compiler does not fuse into a multiply-add), and counts for both.
One thread walks a column: the next column's candidates of its points move up with them, so a pointer finds them
without a search.
"""
from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def _near(ui: wp.float64, vi: wp.float64, uj: wp.float64, vj: wp.float64):
    """1 when (ui, vi) and (uj, vj) are within distance 1 of each other, else 0."""
    du = ui - uj
    dv = vi - vj
    return wp.where(du * du + dv * dv <= wp.float64(1.0), 1, 0)


@wp.kernel
def ellipse_pairs(key: wp.array(dtype=wp.float64), u: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64),
                  starts: wp.array(dtype=wp.int32), span: wp.float64, band: wp.float64,
                  counts: wp.array(dtype=wp.int32)):
    """Add to ``counts`` (each point's count, itself included beforehand) the pairs within distance 1 that the points
    of column run ``c`` (points starts[c] … starts[c + 1] − 1) make with the later points of their own column and with
    the next column's. The runs must be walked one after another (a run adds to the next one's counts: the CPU)."""
    c = wp.tid()
    n = key.shape[0]
    past = starts[c + 1]
    ahead = past  # the first point of the next column not below the current point's band there
    for i in range(starts[c], past):
        ui, vi, k = u[i], v[i], key[i]
        own, first, last = k + band, k + (span - band), k + (span + band)
        found = int(0)
        j = i + 1
        while j < past and key[j] <= own:
            near = _near(ui, vi, u[j], v[j])
            found += near
            counts[j] = counts[j] + near
            j += 1
        while ahead < n and key[ahead] < first:
            ahead += 1
        j = ahead
        while j < n and key[j] <= last:
            near = _near(ui, vi, u[j], v[j])
            found += near
            counts[j] = counts[j] + near
            j += 1
        counts[i] = counts[i] + found
