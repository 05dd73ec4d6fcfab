"""The height grid of a scene built on the device (:mod:`flightsim.scenes.height_grid`), bit for bit the
arrays of its NumPy build.

Steps (the grid's cell side chosen on the host from the counts):

1. :func:`triangle_boxes` — each triangle's xy(z) bounds and, by atomics, the extent of them all;
2. :func:`listing_counts` — how many cells each triangle's box meets, and their sum;
3. :func:`listings` — (cell, triangle) of every listing, triangle after triangle and row-major within
   one, at the triangle's place in the exclusive scan of the counts; a stable radix sort by cell then
   gives the NumPy build's stable argsort;
4. :func:`cell_counts` and a scan give each cell's first listing; :func:`cell_tops` the highest
   corner of each cell's triangles (−inf for none).

Cell indices are the host's arithmetic: clip(floor((value − origin) / cell), 0, n − 1) in float64.
"""
from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def _cell_index(value: wp.float64, origin: wp.float64, cell: wp.float64, n: int) -> int:
    """Cell of a coordinate along one axis [m], clipped to [0, n − 1]."""
    i = wp.floor((value - origin) / cell)
    return int(wp.clamp(i, wp.float64(0.0), wp.float64(n - 1)))


@wp.kernel
def triangle_boxes(
    vertices: wp.array(dtype=wp.vec3d),  # local [m]
    indices: wp.array(dtype=wp.int32),  # 3 vertex indices per triangle
    lowers: wp.array(dtype=wp.vec3d),  # out: per triangle, least x, y, z of its corners [m]
    uppers: wp.array(dtype=wp.vec3d),  # out: per triangle, greatest x, y, z of its corners [m]
    extent: wp.array(dtype=wp.float64),  # in/out (4,): least x, y of all lowers, greatest x, y of all uppers
):
    t = wp.tid()
    a = vertices[indices[3 * t]]
    b = vertices[indices[3 * t + 1]]
    c = vertices[indices[3 * t + 2]]
    lo = wp.min(wp.min(a, b), c)
    hi = wp.max(wp.max(a, b), c)
    lowers[t] = lo
    uppers[t] = hi
    wp.atomic_min(extent, 0, lo[0])
    wp.atomic_min(extent, 1, lo[1])
    wp.atomic_max(extent, 2, hi[0])
    wp.atomic_max(extent, 3, hi[1])


@wp.kernel
def listing_counts(
    lowers: wp.array(dtype=wp.vec3d),
    uppers: wp.array(dtype=wp.vec3d),
    x0: wp.float64,  # grid's lower-left corner [m]
    y0: wp.float64,
    cell: wp.float64,  # cell side [m]
    rows: int,
    cols: int,
    listed: wp.array(dtype=wp.int32),  # out: per triangle, cells its box meets
    total: wp.array(dtype=wp.int64),  # in/out (1,): their sum
):
    t = wp.tid()
    n_cols = _cell_index(uppers[t][0], x0, cell, cols) - _cell_index(lowers[t][0], x0, cell, cols) + 1
    n_rows = _cell_index(uppers[t][1], y0, cell, rows) - _cell_index(lowers[t][1], y0, cell, rows) + 1
    listed[t] = n_cols * n_rows
    wp.atomic_add(total, 0, wp.int64(n_cols * n_rows))


@wp.kernel
def listings(
    lowers: wp.array(dtype=wp.vec3d),
    uppers: wp.array(dtype=wp.vec3d),
    x0: wp.float64,
    y0: wp.float64,
    cell: wp.float64,
    rows: int,
    cols: int,
    offsets: wp.array(dtype=wp.int32),  # exclusive scan of the listing counts
    cells: wp.array(dtype=wp.int32),  # out: cell (row · cols + column) of each listing
    members: wp.array(dtype=wp.int32),  # out: triangle of each listing
):
    t = wp.tid()
    c_lo = _cell_index(lowers[t][0], x0, cell, cols)
    c_hi = _cell_index(uppers[t][0], x0, cell, cols)
    r_lo = _cell_index(lowers[t][1], y0, cell, rows)
    r_hi = _cell_index(uppers[t][1], y0, cell, rows)
    k = offsets[t]
    for r in range(r_lo, r_hi + 1):
        for c in range(c_lo, c_hi + 1):
            cells[k] = r * cols + c
            members[k] = t
            k += 1


@wp.kernel
def cell_counts(cells: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32)):
    """counts (zeroed) += 1 for the cell of every listing."""
    wp.atomic_add(counts, cells[wp.tid()], 1)


@wp.kernel
def cell_tops(
    start: wp.array(dtype=wp.int32),  # first listing of each cell (sorted by cell)
    counts: wp.array(dtype=wp.int32),  # listings of each cell
    members: wp.array(dtype=wp.int32),  # triangle of each listing, sorted by cell
    uppers: wp.array(dtype=wp.vec3d),
    top: wp.array(dtype=wp.float64),  # out: highest corner z of each cell's triangles [m]; −inf for none
):
    c = wp.tid()
    highest = wp.float64(-wp.inf)
    for i in range(start[c], start[c] + counts[c]):
        highest = wp.max(highest, uppers[members[i]][2])
    top[c] = highest
