"""The highest surface per cell of a coarse grid over a scene, built once, and the height queries that use it.

Cell (row i, column j) covers local x in [x0 + j·cell_m, x0 + (j+1)·cell_m) and y in
[y0 + i·cell_m, y0 + (i+1)·cell_m) [m]. A triangle is listed in every cell its xy bounding box meets
(closed), and a cell's ``top`` is the highest vertex of its triangles, so ``top`` is never below the
surface anywhere over the cell (−inf where the cell holds no triangle). Queries read the few cells
under a rectangle or a point, so their cost does not grow with the number of triangles:

- :meth:`HeightGrid.top_bound`: a cheap upper bound of the surface over a rectangle;
- :meth:`HeightGrid.tops`: the exact highest point over rectangles, refined from the triangles of
  only those cells whose top can beat the best height found so far;
- :meth:`HeightGrid.ground_height`: the highest surface straight under points.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from flightsim.core.process_map import by_pieces

TRIANGLES_PER_CELL = 4.0
"""Cell size target: about this many triangles' worth of area per cell."""

MAX_CELLS_PER_SIDE = 2048
"""Largest grid side [cells]."""

MAX_LISTED_PER_TRIANGLE = 16.0
"""The cell size grows until the triangles are listed at most this many times each, on average."""

LISTINGS_PER_BLOCK = 1 << 20
"""(point, listed triangle) pairs :meth:`HeightGrid.ground_height` tests at a time."""


@dataclass(frozen=True)
class HeightGrid:
    """Highest surface z per cell and the triangles listed in each cell (local coordinates [m]).

    Attributes:
        x0, y0: local x, y of the grid's lower-left corner [m].
        cell_m: cell side [m].
        top: (rows, columns) highest vertex z of each cell's triangles [m]; −inf for an empty cell.
        start: (rows·columns + 1,) cell c lists triangles members[start[c]:start[c + 1]].
        members: triangle indices, cell after cell.
        vertices, triangles: the mesh, (V, 3) [m] and (T, 3) indices (the scene's arrays, not copies).
    """

    x0: float
    y0: float
    cell_m: float
    top: np.ndarray
    start: np.ndarray
    members: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray

    @classmethod
    def build(cls, vertices: np.ndarray, triangles: np.ndarray, device: str | None = None) -> "HeightGrid":
        """The grid of a mesh: vertices (V, 3) [m], triangles (T, 3) indices; built with NumPy, or on a Warp
        ``device`` ("cpu", "cuda:0", …: :mod:`kernels.height_grid`, the same arrays)."""
        arrays = _numpy_grid(vertices, triangles) if device is None else _device_grid(vertices, triangles, device)
        return cls(*arrays, vertices, triangles)

    def arrays(self) -> dict[str, np.ndarray]:
        """The grid's own arrays (not the mesh), for :meth:`from_arrays`."""
        return {"origin_cell": np.array([self.x0, self.y0, self.cell_m]), "top": self.top, "start": self.start,
                "members": self.members}

    @classmethod
    def from_arrays(cls, arrays, vertices: np.ndarray, triangles: np.ndarray) -> "HeightGrid":
        """The grid stored by :meth:`arrays` for this mesh; ValueError when the arrays cannot be its grid."""
        x0, y0, cell = (float(v) for v in arrays["origin_cell"])
        top, start, members = arrays["top"], arrays["start"], arrays["members"]
        fits = (top.ndim == 2 and start.shape == (top.size + 1,) and members.ndim == 1 and cell > 0.0
                and start[0] == 0 and start[-1] == len(members) and np.all(np.diff(start) >= 0)
                and (len(members) == 0 or (members.min() >= 0 and members.max() < len(triangles))))
        if not fits:
            raise ValueError("stored height grid does not fit the mesh")
        return cls(x0, y0, cell, top, start, members, vertices, triangles)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return self.top.shape

    def top_bound(self, xmin: float, ymin: float, xmax: float, ymax: float) -> float:
        """An upper bound [m] of the surface's height over the closed rectangle; −inf where no triangle is near."""
        cells = self._cells(xmin, ymin, xmax, ymax)
        return -math.inf if cells is None else float(self.top[cells].max())

    def tops(self, rectangles) -> np.ndarray:
        """Highest local z [m] of the surface over each closed rectangle (xmin, ymin, xmax, ymax) (R, 4) [m];
        −inf where none. Exact for planar triangles (see :func:`highest_over`)."""
        rects = np.asarray(rectangles, dtype=np.float64).reshape(-1, 4)
        return np.array([self._exact_top(*rect) for rect in rects], dtype=np.float64).reshape(len(rects))

    def ground_height(self, x, y) -> np.ndarray:
        """Highest surface z [m] straight under each point (x, y) [m] (any matching shapes); NaN where
        no triangle lies under the point (outside the scene, a hole). Walls (vertical triangles) are
        not ground. The points go in blocks of at most LISTINGS_PER_BLOCK (point, listed triangle) pairs
        (~0.1 kB of temporaries each: an ALS tile of 1e7 points over a 1 m ground grid lists ~1.2e8)."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        px, py = x.reshape(-1), y.reshape(-1)
        rows, cols = self.shape
        col = np.floor((px - self.x0) / self.cell_m)
        row = np.floor((py - self.y0) / self.cell_m)
        inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
        cell = np.where(inside, row * cols + col, 0).astype(np.int64)
        count = np.where(inside, self.start[cell + 1] - self.start[cell], 0)
        listed = np.cumsum(count)
        best = np.full(len(px), -np.inf)
        first = 0
        while first < len(px):
            done = listed[first - 1] if first else 0
            last = max(int(np.searchsorted(listed, done + LISTINGS_PER_BLOCK, side="right")), first + 1)
            block = slice(first, last)
            best[block] = self._highest_under(px[block], py[block], cell[block], count[block])
            first = last
        return np.where(np.isfinite(best), best, np.nan).reshape(x.shape)

    def _highest_under(self, px: np.ndarray, py: np.ndarray, cell: np.ndarray, count: np.ndarray) -> np.ndarray:
        """Highest z [m] of the triangles listed in each point's cell that lie under it; −inf where none."""
        point = np.repeat(np.arange(len(px)), count)
        k = np.arange(len(point)) - np.repeat(np.cumsum(count) - count, count)
        terms = self._terms[self.members[self.start[cell[point]] + k]].T
        height, under = _height_at(terms, px[point], py[point])
        best = np.full(len(px), -np.inf)
        np.maximum.at(best, point[under], height[under])
        return best

    @cached_property
    def _terms(self) -> np.ndarray:
        """(T, 11) :func:`_triangle_terms` of every triangle, worked out once, in pieces of the triangles on threads."""
        terms = np.empty((len(self.triangles), 11))

        def piece(rows: slice) -> None:
            terms[rows] = _triangle_terms(self.vertices[self.triangles[rows]]).T

        by_pieces(len(self.triangles), piece)
        return terms

    def _cells(self, xmin: float, ymin: float, xmax: float, ymax: float) -> tuple[slice, slice] | None:
        """(row, column) slices of the cells that meet the closed rectangle, None if none."""
        rows, cols = self.shape
        c0, c1 = math.floor((xmin - self.x0) / self.cell_m), math.floor((xmax - self.x0) / self.cell_m)
        r0, r1 = math.floor((ymin - self.y0) / self.cell_m), math.floor((ymax - self.y0) / self.cell_m)
        if c1 < 0 or r1 < 0 or c0 >= cols or r0 >= rows:
            return None
        return slice(max(r0, 0), min(r1, rows - 1) + 1), slice(max(c0, 0), min(c1, cols - 1) + 1)

    def _exact_top(self, xmin: float, ymin: float, xmax: float, ymax: float) -> float:
        """Highest z over the closed rectangle: the triangles of the highest cell first, then those of
        every cell whose top is above the best height found."""
        cells = self._cells(xmin, ymin, xmax, ymax)
        if cells is None:
            return -math.inf
        rows, cols = self.shape
        r, c = np.meshgrid(np.arange(rows)[cells[0]], np.arange(cols)[cells[1]], indexing="ij")
        ids, bounds = (r * cols + c).reshape(-1), self.top[cells].reshape(-1)
        ids, bounds = ids[np.isfinite(bounds)], bounds[np.isfinite(bounds)]
        best = -math.inf
        for pick in (np.argmax(bounds) if len(bounds) else None, None):
            chosen = ids[[pick]] if pick is not None else ids[bounds > best]
            if len(chosen) == 0:
                break
            best = max(best, self._top_of(chosen, xmin, ymin, xmax, ymax))
        return best

    def _top_of(self, cells: np.ndarray, xmin: float, ymin: float, xmax: float, ymax: float) -> float:
        """Highest z over the rectangle of the triangles listed in ``cells``."""
        count = self.start[cells + 1] - self.start[cells]
        k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        triangles = np.unique(self.members[np.repeat(self.start[cells], count) + k])
        corners = self.vertices[self.triangles[triangles]]
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        over = (hi[:, 0] >= xmin) & (lo[:, 0] <= xmax) & (hi[:, 1] >= ymin) & (lo[:, 1] <= ymax)
        if not np.any(over):
            return -math.inf
        return highest_over(corners[over], hi[over, 2], xmin, ymin, xmax, ymax)


def _numpy_grid(vertices: np.ndarray, triangles: np.ndarray) -> tuple:
    """(x0, y0, cell_m, top, start, members) of a mesh's grid, with NumPy."""
    (lo_x, hi_x), (lo_y, hi_y), (_, hi_z) = (_extent(vertices[:, axis], triangles) for axis in range(3))
    x0, y0 = float(lo_x.min()), float(lo_y.min())
    boxes = {}

    def listed_total(cell: float, rows: int, cols: int) -> int:
        c_lo, c_hi = _index(lo_x, x0, cell, cols), _index(hi_x, x0, cell, cols)
        r_lo, r_hi = _index(lo_y, y0, cell, rows), _index(hi_y, y0, cell, rows)
        n_cols = c_hi - c_lo + 1
        boxes.update(c_lo=c_lo, r_lo=r_lo, n_cols=n_cols, listed=n_cols.astype(np.int64) * (r_hi - r_lo + 1))
        return int(boxes["listed"].sum())

    cell, rows, cols, _ = _grid_shape(float(hi_x.max()) - x0, float(hi_y.max()) - y0, len(triangles), listed_total)
    cell_of, members = _listing(boxes["c_lo"], boxes["r_lo"], boxes["n_cols"], boxes["listed"], cols)
    order = np.argsort(cell_of, kind="stable")
    cell_of, members = cell_of[order], members[order]
    start = np.searchsorted(cell_of, np.arange(rows * cols + 1))
    top = np.full(rows * cols, -np.inf)
    filled = np.flatnonzero(start[1:] > start[:-1])
    top[filled] = np.maximum.reduceat(hi_z[members], start[filled])
    return x0, y0, cell, top.reshape(rows, cols), start, members


def _device_grid(vertices: np.ndarray, triangles: np.ndarray, device: str) -> tuple:
    """(x0, y0, cell_m, top, start, members) of a mesh's grid, built on a Warp device: the arrays of
    :func:`_numpy_grid`."""
    import warp as wp

    from flightsim.core.warp_runtime import resolve_device, to_host
    from kernels import height_grid as kg

    d, n = resolve_device(device), len(triangles)
    indices = wp.array(np.ascontiguousarray(triangles, dtype=np.int32).ravel(), dtype=wp.int32, device=d)
    lowers, uppers = wp.empty(n, dtype=wp.vec3d, device=d), wp.empty(n, dtype=wp.vec3d, device=d)
    extent = wp.array([np.inf, np.inf, -np.inf, -np.inf], dtype=wp.float64, device=d)
    wp.launch(kg.triangle_boxes, n, inputs=[wp.array(vertices, dtype=wp.vec3d, device=d), indices],
              outputs=[lowers, uppers, extent], device=d)
    x0, y0, x1, y1 = (float(v) for v in to_host(extent))
    listed, total = wp.empty(n, dtype=wp.int32, device=d), wp.zeros(1, dtype=wp.int64, device=d)

    def listed_total(cell: float, rows: int, cols: int) -> int:
        total.zero_()
        wp.launch(kg.listing_counts, n, inputs=[lowers, uppers, wp.float64(x0), wp.float64(y0), wp.float64(cell),
                                                rows, cols], outputs=[listed, total], device=d)
        return int(to_host(total)[0])

    cell, rows, cols, count = _grid_shape(x1 - x0, y1 - y0, n, listed_total)  # `listed`: the last grid tried
    if 2 * count >= 2**31:  # beyond int32 listings: the NumPy build
        return _numpy_grid(vertices, triangles)
    offsets = wp.empty(n, dtype=wp.int32, device=d)
    wp.utils.array_scan(listed, offsets, inclusive=False)
    cells, members = wp.empty(2 * count, dtype=wp.int32, device=d), wp.empty(2 * count, dtype=wp.int32, device=d)
    wp.launch(kg.listings, n, inputs=[lowers, uppers, wp.float64(x0), wp.float64(y0), wp.float64(cell), rows, cols,
                                      offsets], outputs=[cells, members], device=d)
    wp.utils.radix_sort_pairs(cells, members, count, end_bit=max(1, (rows * cols - 1).bit_length()))
    counts, start = wp.zeros(rows * cols, dtype=wp.int32, device=d), wp.empty(rows * cols, dtype=wp.int32, device=d)
    wp.launch(kg.cell_counts, count, inputs=[cells], outputs=[counts], device=d)
    wp.utils.array_scan(counts, start, inclusive=False)
    top = wp.empty(rows * cols, dtype=wp.float64, device=d)
    wp.launch(kg.cell_tops, rows * cols, inputs=[start, counts, members, uppers], outputs=[top], device=d)
    sorted_members = wp.empty(count, dtype=wp.int32, device=d)
    wp.copy(sorted_members, members, count=count)
    return (x0, y0, cell, top.numpy().reshape(rows, cols), np.append(start.numpy().astype(np.int64), count),
            sorted_members.numpy())


def _grid_shape(width: float, height: float, n_triangles: int, listed_total) -> tuple[float, int, int, int]:
    """(cell side [m], rows, columns, listings) of the grid over a width × height [m] extent: about
    TRIANGLES_PER_CELL triangles' share of the area per cell, widened while the triangles would be listed
    more than MAX_LISTED_PER_TRIANGLE times each on average (``listed_total(cell, rows, cols)``: the
    listings of a candidate grid)."""
    cell = _cell_size(width, height, n_triangles)
    while True:
        rows, cols = int(height // cell) + 1, int(width // cell) + 1
        total = listed_total(cell, rows, cols)
        if total <= MAX_LISTED_PER_TRIANGLE * n_triangles or max(rows, cols) == 1:
            return cell, rows, cols, total
        cell *= math.sqrt(total / (MAX_LISTED_PER_TRIANGLE * n_triangles)) * 1.01


def _cell_size(width: float, height: float, n_triangles: int) -> float:
    """Cell side [m]: about TRIANGLES_PER_CELL triangles' share of the area, at most MAX_CELLS_PER_SIDE a side."""
    extent = max(width, height)
    if extent <= 0.0:
        return 1.0
    area = max(width, extent / MAX_CELLS_PER_SIDE) * max(height, extent / MAX_CELLS_PER_SIDE)
    return max(math.sqrt(area * TRIANGLES_PER_CELL / n_triangles), extent / (MAX_CELLS_PER_SIDE - 1))


def _index(value: np.ndarray, origin: float, cell: float, n: int) -> np.ndarray:
    """Cell index along one axis of each coordinate, clipped to [0, n − 1] (int32)."""
    return np.clip(np.floor((value - origin) / cell), 0, n - 1).astype(np.int32)


def _extent(values: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least and greatest of one vertex coordinate ``values`` (V,) over each triangle's corners, (T,) each."""
    a, b, c = (values[triangles[:, k]] for k in range(3))
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def _listing(c_lo: np.ndarray, r_lo: np.ndarray, n_cols: np.ndarray, listed: np.ndarray,
             cols: int) -> tuple[np.ndarray, np.ndarray]:
    """(cell, triangle) of every listing: triangle t in the ``listed[t]`` cells of its box, whose lowest
    row and column are ``r_lo[t]``, ``c_lo[t]`` and which is ``n_cols[t]`` cells wide."""
    triangle = np.repeat(np.arange(len(listed), dtype=np.int32), listed)
    k = np.arange(len(triangle), dtype=np.int64) - np.repeat(np.cumsum(listed) - listed, listed)
    width = n_cols[triangle]
    cell = (r_lo[triangle] + k // width).astype(np.int64) * cols + c_lo[triangle] + k % width
    return cell, triangle


def _height_under(corners: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z [m] of each triangle (m, 3, 3) at (x, y) (m,), and whether the point lies in the triangle's
    (non-degenerate) xy projection, edges included."""
    return _height_at(_triangle_terms(corners), x, y)


def _triangle_terms(corners: np.ndarray) -> np.ndarray:
    """(11, m) of triangles (m, 3, 3): the first corner x0, y0, z0, the xy edges to the others (ex1, ey1, ex2, ey2),
    the determinant of the edges (1 for a degenerate xy projection), z1 − z0, z2 − z0, and 1.0 where degenerate."""
    x0, y0, z0 = corners[:, 0, 0], corners[:, 0, 1], corners[:, 0, 2]
    ex1, ey1 = corners[:, 1, 0] - x0, corners[:, 1, 1] - y0
    ex2, ey2 = corners[:, 2, 0] - x0, corners[:, 2, 1] - y0
    det = ex1 * ey2 - ey1 * ex2
    flat = np.abs(det) <= 1e-12 * (ex1 * ex1 + ey1 * ey1 + ex2 * ex2 + ey2 * ey2)
    return np.stack([x0, y0, z0, ex1, ey1, ex2, ey2, np.where(flat, 1.0, det), corners[:, 1, 2] - z0,
                     corners[:, 2, 2] - z0, flat.astype(np.float64)])


def _height_at(terms: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z [m] of each triangle (its :func:`_triangle_terms`, (11, m)) at (x, y) (m,), and whether the point lies in
    the triangle's (non-degenerate) xy projection, edges included."""
    x0, y0, z0, ex1, ey1, ex2, ey2, det, dz1, dz2, flat = terms
    px, py = x - x0, y - y0
    w1 = (px * ey2 - py * ex2) / det
    w2 = (ex1 * py - ey1 * px) / det
    under = (flat == 0.0) & (w1 >= -1e-12) & (w2 >= -1e-12) & (w1 + w2 <= 1.0 + 1e-12)
    return z0 + w1 * dz1 + w2 * dz2, under


def highest_over(corners: np.ndarray, tops: np.ndarray, xmin: float, ymin: float, xmax: float,
                 ymax: float) -> float:
    """Highest z [m] of triangles ``corners`` (T, 3, 3) over the closed rectangle; −inf if none reaches it.

    Exact for planar triangles: the highest point of a triangle over the rectangle is a corner of
    their intersection (a triangle vertex inside the rectangle, a triangle edge crossing a rectangle
    side, or a rectangle corner inside the triangle), so a large sloped triangle counts only as high
    as it rises over the rectangle. ``tops`` (T,) are the triangles' highest z, used to skip those
    that cannot beat the best so far.
    """
    tol = 1e-9 * (1.0 + max(abs(xmin), abs(ymin), abs(xmax), abs(ymax)))
    x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
    inside = (x >= xmin - tol) & (x <= xmax + tol) & (y >= ymin - tol) & (y <= ymax + tol)
    best = float(np.max(np.where(inside, z, -np.inf)))
    rest = tops > best
    if not np.any(rest):
        return best
    x, y, z = x[rest], y[rest], z[rest]
    candidates = [best]
    # triangle edges crossing the lines x = xmin, xmax (within [ymin, ymax]) and y = ymin, ymax
    a, b = np.array([0, 1, 2]), np.array([1, 2, 0])
    for u, v, line, v_lo, v_hi in ((x, y, xmin, ymin, ymax), (x, y, xmax, ymin, ymax),
                                   (y, x, ymin, xmin, xmax), (y, x, ymax, xmin, xmax)):
        du = u[:, b] - u[:, a]
        s = (line - u[:, a]) / np.where(du != 0.0, du, 1.0)
        cross = (du != 0.0) & (s >= 0.0) & (s <= 1.0)
        at = v[:, a] + s * (v[:, b] - v[:, a])
        cross &= (at >= v_lo - tol) & (at <= v_hi + tol)
        candidates.append(np.max(np.where(cross, z[:, a] + s * (z[:, b] - z[:, a]), -np.inf), initial=-np.inf))
    # rectangle corners inside a triangle's (non-degenerate) projection
    corners = np.stack([x, y, z], axis=-1)
    for cx, cy in ((xmin, ymin), (xmin, ymax), (xmax, ymin), (xmax, ymax)):
        height, under = _height_under(corners, np.full(len(x), cx), np.full(len(x), cy))
        candidates.append(np.max(np.where(under, height, -np.inf), initial=-np.inf))
    return float(max(candidates))
