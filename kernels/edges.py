"""The edge buffer on the device: a grid marking the cells a plane boundary may come near, and the distance of a
point to the nearest plane-boundary segment, capped, over the segments listed for the coarser cell holding it."""
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


LIST_CELLS = wp.constant(4)  # cells per side of a list cell (EdgeGrid): a list cell holds 16 of the grid's cells


@wp.struct
class EdgeGrid:
    """A grid over the scene's x–y extent marking the cells a plane boundary may come within the
    edge cap of; a return in an unmarked cell is at least the cap from every boundary, so the
    boundary query is skipped for it. Over the same origin, list cells of LIST_CELLS × LIST_CELLS
    cells each list the segments that may come within the cap of a point in them (compressed rows:
    cell (i, j)'s segment ids are ``listed[offsets[i·ny + j] : offsets[i·ny + j + 1]]``)."""

    near: wp.array2d(dtype=wp.uint8)  # [ix, iy]: 1 where a boundary may be within the cap
    origin: wp.vec2f  # lower corner of cell (0, 0) [m, local]
    inv_cell: wp.float32  # 1 / cell side [1/m]
    list_shape: wp.vec2i  # list cells along x and y
    offsets: wp.array(dtype=wp.int32)  # list cells + 1: where each list cell's segment ids start in ``listed``
    listed: wp.array(dtype=wp.int32)  # segment ids, list cell by list cell


@wp.func
def _segment_distance(p: Any, a: Any, b: Any):
    """Distance from point p to the segment a–b (2-D or 3-D) [m]."""
    ab = b - a
    u = wp.clamp(wp.dot(p - a, ab) / wp.max(wp.dot(ab, ab), type(ab[0])(1.0e-20)), type(ab[0])(0.0),
                 type(ab[0])(1.0))
    return wp.length(p - (a + u * ab))


@wp.func
def _cell_range(a: wp.vec2f, b: wp.vec2f, reach: wp.float32, origin: wp.vec2f, inv_cell: wp.float32, nx: int,
                ny: int):
    """(x0, x1, y0, y1): the cells, of side 1 / ``inv_cell`` from ``origin``, of the segment a–b's x–y box widened by
    ``reach`` [m], clipped to nx × ny."""
    x0 = wp.max(int(wp.floor((wp.min(a[0], b[0]) - reach - origin[0]) * inv_cell)), 0)
    x1 = wp.min(int(wp.floor((wp.max(a[0], b[0]) + reach - origin[0]) * inv_cell)), nx - 1)
    y0 = wp.max(int(wp.floor((wp.min(a[1], b[1]) - reach - origin[1]) * inv_cell)), 0)
    y1 = wp.min(int(wp.floor((wp.max(a[1], b[1]) + reach - origin[1]) * inv_cell)), ny - 1)
    return x0, x1, y0, y1


@wp.func
def _reach(cap: wp.float32, cell: wp.float32):
    """How far from a cell's centre a segment may be and still come within ``cap`` of a point of the cell (side
    ``cell``): x–y distances never exceed 3-D ones, and no point of a cell is farther than half its diagonal from
    its centre (with a rounding margin) [m]."""
    return cap + 0.7072 * cell + 1.0e-3 * (cap + cell)


@wp.func
def _near_centre(a: wp.vec2f, b: wp.vec2f, origin: wp.vec2f, cell: wp.float32, ix: int, iy: int, reach: wp.float32):
    """Whether the x–y segment a–b passes within ``reach`` of the centre of cell (ix, iy)."""
    centre = origin + wp.vec2f((float(ix) + 0.5) * cell, (float(iy) + 0.5) * cell)
    return _segment_distance(centre, a, b) < reach


@wp.func
def _xy(p: wp.vec3f):
    return wp.vec2f(p[0], p[1])


MARK = wp.constant(0)  # near_cells' steps: mark the grid's cells
COUNT = wp.constant(1)  # ... count each list cell's segments
WRITE = wp.constant(2)  # ... write them (after the counts' exclusive scan into grid.offsets)


@wp.kernel
def near_cells(
    seg_a: wp.array(dtype=wp.vec3f),  # boundary segments [m, local]
    seg_b: wp.array(dtype=wp.vec3f),
    cap: wp.float32,  # [m]
    grid: EdgeGrid,
    step: wp.int32,  # MARK, COUNT or WRITE
    # In and out (COUNT, WRITE): per list cell, the segments counted or written so far (zeroed before each step)
    filled: wp.array(dtype=wp.int32),
):
    """The cells each boundary segment may come within ``cap`` of (:func:`_reach`), one thread per segment: marked
    in grid.near (MARK), or the list cells, where the segment is counted (COUNT) and then listed (WRITE). A list
    cell's ids come in no set order; the distance query's minimum does not depend on it."""
    k = wp.tid()
    a = _xy(seg_a[k])
    b = _xy(seg_b[k])
    inv = grid.inv_cell
    nx = grid.near.shape[0]
    ny = grid.near.shape[1]
    if step != MARK:
        inv = grid.inv_cell / float(LIST_CELLS)
        nx = grid.list_shape[0]
        ny = grid.list_shape[1]
    cell = 1.0 / inv
    reach = _reach(cap, cell)
    x0, x1, y0, y1 = _cell_range(a, b, reach, grid.origin, inv, nx, ny)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            if _near_centre(a, b, grid.origin, cell, ix, iy, reach):
                if step == MARK:
                    grid.near[ix, iy] = wp.uint8(1)
                else:
                    c = ix * ny + iy
                    n = wp.atomic_add(filled, c, 1)
                    if step == WRITE:
                        grid.listed[grid.offsets[c] + n] = k


@wp.func
def near_boundary(grid: EdgeGrid, p: wp.vec3f):
    """False where the edge grid shows p at least the edge cap from every plane boundary."""
    ix = int(wp.floor((p[0] - grid.origin[0]) * grid.inv_cell))
    iy = int(wp.floor((p[1] - grid.origin[1]) * grid.inv_cell))
    if ix >= 0 and iy >= 0 and ix < grid.near.shape[0] and iy < grid.near.shape[1]:
        return grid.near[ix, iy] != wp.uint8(0)
    return True


@wp.func
def boundary_distance(grid: EdgeGrid, seg_a: wp.array(dtype=wp.vec3f), seg_b: wp.array(dtype=wp.vec3f),
                      p: wp.vec3f, cap: wp.float32):
    """Distance from p to the nearest plane-boundary segment, at most ``cap`` [m] (the cap the grid was built for).

    Only the segments listed for p's list cell are visited (every segment that may come within ``cap`` of it),
    then the exact point–segment distance is taken; beyond the list cells (which cover the scene and the cap
    around it) every segment is farther than ``cap``.
    """
    best = cap
    inv = grid.inv_cell / float(LIST_CELLS)
    fx = (p[0] - grid.origin[0]) * inv
    fy = (p[1] - grid.origin[1]) * inv
    nx = grid.list_shape[0]
    ny = grid.list_shape[1]
    if fx >= 0.0 and fy >= 0.0 and fx < float(nx) and fy < float(ny):  # as floats: no overflow, NaN out
        c = wp.min(int(fx), nx - 1) * ny + wp.min(int(fy), ny - 1)
        for i in range(grid.offsets[c], grid.offsets[c + 1]):
            k = grid.listed[i]
            best = wp.min(best, _segment_distance(p, seg_a[k], seg_b[k]))
    return best
