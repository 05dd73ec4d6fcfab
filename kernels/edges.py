"""The edge buffer on the device: a grid marking the cells a plane boundary may come near, and the distance of a
point to the nearest plane-boundary segment (a BVH query), capped."""
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.struct
class EdgeGrid:
    """A grid over the scene's x–y extent marking the cells a plane boundary may come within the
    edge cap of; a return in an unmarked cell is at least the cap from every boundary, so the
    boundary query is skipped for it."""

    near: wp.array2d(dtype=wp.uint8)  # [ix, iy]: 1 where a boundary may be within the cap
    origin: wp.vec2f  # lower corner of cell (0, 0) [m, local]
    inv_cell: wp.float32  # 1 / cell side [1/m]


@wp.func
def _segment_distance(p: Any, a: Any, b: Any):
    """Distance from point p to the segment a–b (2-D or 3-D) [m]."""
    ab = b - a
    u = wp.clamp(wp.dot(p - a, ab) / wp.max(wp.dot(ab, ab), type(ab[0])(1.0e-20)), type(ab[0])(0.0),
                 type(ab[0])(1.0))
    return wp.length(p - (a + u * ab))


@wp.kernel
def mark_near_cells(
    seg_a: wp.array(dtype=wp.vec3f),  # boundary segments [m, local]
    seg_b: wp.array(dtype=wp.vec3f),
    cap: wp.float32,  # [m]
    # Out:
    grid: EdgeGrid,
):
    """Mark every cell a boundary segment may come within ``cap`` of, one thread per segment.

    The x–y distance never exceeds the 3-D one, and no point of a cell is farther than half its
    diagonal from its centre, so a cell whose centre is at least cap + half a diagonal (and a
    rounding margin) from the segment's x–y projection is at least ``cap`` from the segment.
    """
    k = wp.tid()
    a = wp.vec2f(seg_a[k][0], seg_a[k][1])
    b = wp.vec2f(seg_b[k][0], seg_b[k][1])
    cell = 1.0 / grid.inv_cell
    reach = cap + 0.7072 * cell + 1.0e-3 * (cap + cell)
    nx = grid.near.shape[0]
    ny = grid.near.shape[1]
    x0 = wp.max(int(wp.floor((wp.min(a[0], b[0]) - reach - grid.origin[0]) * grid.inv_cell)), 0)
    x1 = wp.min(int(wp.floor((wp.max(a[0], b[0]) + reach - grid.origin[0]) * grid.inv_cell)), nx - 1)
    y0 = wp.max(int(wp.floor((wp.min(a[1], b[1]) - reach - grid.origin[1]) * grid.inv_cell)), 0)
    y1 = wp.min(int(wp.floor((wp.max(a[1], b[1]) + reach - grid.origin[1]) * grid.inv_cell)), ny - 1)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            centre = grid.origin + wp.vec2f((float(ix) + 0.5) * cell, (float(iy) + 0.5) * cell)
            if _segment_distance(centre, a, b) < reach:
                grid.near[ix, iy] = wp.uint8(1)


@wp.func
def near_boundary(grid: EdgeGrid, p: wp.vec3f):
    """False where the edge grid shows p at least the edge cap from every plane boundary."""
    ix = int(wp.floor((p[0] - grid.origin[0]) * grid.inv_cell))
    iy = int(wp.floor((p[1] - grid.origin[1]) * grid.inv_cell))
    if ix >= 0 and iy >= 0 and ix < grid.near.shape[0] and iy < grid.near.shape[1]:
        return grid.near[ix, iy] != wp.uint8(0)
    return True


@wp.func
def boundary_distance(boundary: wp.uint64, seg_a: wp.array(dtype=wp.vec3f), seg_b: wp.array(dtype=wp.vec3f),
                       p: wp.vec3f, cap: wp.float32):
    """Distance from p to the nearest plane-boundary segment, at most ``cap`` [m].

    Only segments whose boxes overlap the cube of half side ``cap`` around p are visited, then
    the exact point–segment distance is taken.
    """
    best = cap
    extent = wp.vec3f(cap, cap, cap)
    query = wp.bvh_query_aabb(boundary, p - extent, p + extent)
    k = int(0)
    while wp.bvh_query_next(query, k):
        best = wp.min(best, _segment_distance(p, seg_a[k], seg_b[k]))
    return best
