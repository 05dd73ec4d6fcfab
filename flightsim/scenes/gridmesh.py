"""Triangles of a height grid: two per cell, or the leaves of an error-bounded quadtree.

Nodes are numbered row-major (row i from north to south, column j from west to east), node
i·cols + j. A triangle is kept when its three corners are finite (NaN = nodata: the mesh has a
hole); only blocks without nodata merge.

Simplification (``tolerance_m`` > 0): square blocks of 2^k cells, aligned on the grid, merge
bottom-up as a quadtree. A block merges when its four child blocks merged (so it has no nodata)
and one plane P lies within ±tolerance/2 of every node in it: the residuals r of its least-squares
plane satisfy max r − min r ≤ tolerance (P is that plane shifted to the residuals' mid-range).
A merged block (a leaf) is triangulated as a fan from its centre node to every leaf corner lying
on its boundary, so neighbouring leaves of different sizes share every edge: no T-junctions, the
mesh is as watertight as the full grid. Both the full grid's surface and the fan interpolate
nodes of the block, so each lies within tolerance/2 of P and the simplified surface is within
``tolerance_m`` (vertically) of the full-resolution one everywhere.
"""
from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def grid_triangles(heights: np.ndarray, tolerance_m: float = 0.0) -> np.ndarray:
    """(T, 3) int32 node indices of the triangles over ``heights`` (rows, cols) [m], counter-clockwise
    seen from above; two per cell when ``tolerance_m`` is 0, else the simplified quadtree's; a triangle
    with a non-finite corner is left out."""
    rows, cols = heights.shape
    finite = np.isfinite(heights)
    if tolerance_m <= 0.0:
        triangles = _cell_triangles(np.arange((rows - 1) * (cols - 1)), cols)
    else:
        triangles = _simplified(heights, finite, tolerance_m)
    return triangles if finite.all() else triangles[finite.ravel()[triangles].all(axis=1)]


def _simplified(heights: np.ndarray, finite: np.ndarray, tolerance_m: float) -> np.ndarray:
    """Triangles of the quadtree's leaves: cells (two triangles each) and fans of merged blocks."""
    rows, cols = heights.shape
    valid = finite[1:, :-1] & finite[1:, 1:] & finite[:-1, 1:] & finite[:-1, :-1]
    leaves = _quadtree_leaves(heights, valid, tolerance_m)
    corners = np.zeros((rows, cols), dtype=bool)
    for size, (bi, bj) in leaves:
        for di in (0, size):
            for dj in (0, size):
                corners[bi * size + di, bj * size + dj] = True
    cells = leaves[0][1]
    parts = [_cell_triangles(cells[0] * (cols - 1) + cells[1], cols)]
    parts += [_fan_triangles(size, bi * size, bj * size, corners) for size, (bi, bj) in leaves[1:] if len(bi)]
    return np.concatenate(parts)


def _cell_triangles(cells: np.ndarray, cols: int) -> np.ndarray:
    """Two triangles (SW, SE, NE) and (SW, NE, NW) of each cell index (row · (cols − 1) + col)."""
    cells = cells.astype(np.int32)  # grids hold fewer than 2³¹ nodes (dem.MAX_DEM_NODES)
    n = len(cells)
    triangles = np.empty((2 * n, 3), dtype=np.int32)
    nw = triangles[n:, 2]  # the cell's north-west node, written in place
    np.floor_divide(cells, cols - 1, out=nw)
    nw += cells
    triangles[:, 0] = np.tile(nw + cols, 2)  # south-west
    triangles[:n, 1] = triangles[:n, 0] + 1  # south-east
    triangles[:n, 2] = nw + 1  # north-east
    triangles[n:, 1] = triangles[:n, 2]
    return triangles


def _quadtree_leaves(heights: np.ndarray, valid: np.ndarray, tolerance_m: float) -> list:
    """[(size, (block rows, block cols))] of the leaves per level: size 1, 2, 4, … cells."""
    merged = [valid]
    size = 2
    while (heights.shape[0] - 1) // size and (heights.shape[1] - 1) // size:
        below = merged[-1]
        nr, nc = below.shape[0] // 2, below.shape[1] // 2
        children = below[:2 * nr, :2 * nc].reshape(nr, 2, nc, 2).all(axis=(1, 3))
        merged.append(_flat_blocks(heights, children, size, tolerance_m))
        if not merged[-1].any():
            break
        size *= 2
    leaves = []
    for level, blocks in enumerate(merged):
        parent = np.zeros(blocks.shape, dtype=bool)
        if level + 1 < len(merged):
            up = merged[level + 1]
            parent[:2 * up.shape[0], :2 * up.shape[1]] = np.repeat(np.repeat(up, 2, axis=0), 2, axis=1)
        leaf = ~parent if level == 0 else blocks & ~parent  # every cell not merged (nodata: no triangles)
        leaves.append((2 ** level, np.nonzero(leaf)))
    return leaves


def _flat_blocks(heights: np.ndarray, candidates: np.ndarray, size: int, tolerance_m: float) -> np.ndarray:
    """Which ``candidates`` blocks of ``size`` cells have least-squares plane residuals spanning ≤ tolerance."""
    flat = np.zeros(candidates.shape, dtype=bool)
    bi, bj = np.nonzero(candidates)
    if len(bi) == 0:
        return flat
    windows = sliding_window_view(heights, (size + 1, size + 1))[::size, ::size]
    z = windows[bi, bj].astype(np.float64)  # (B, size + 1, size + 1)
    u = np.arange(size + 1) - size / 2.0  # offsets from the block centre [cells]
    second = (size + 1) * np.sum(u * u)
    slope_e = np.einsum("bij,j->b", z, u) / second
    slope_s = np.einsum("bij,i->b", z, u) / second
    residual = z - z.mean(axis=(1, 2))[:, None, None] - slope_e[:, None, None] * u - slope_s[:, None, None] * u[:, None]
    flat[bi, bj] = residual.max(axis=(1, 2)) - residual.min(axis=(1, 2)) <= tolerance_m
    return flat


def _fan_triangles(size: int, row0: np.ndarray, col0: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Fans of the leaves of ``size`` ≥ 2 cells with north-west nodes (row0, col0): the centre node to each
    pair of consecutive ``corners`` nodes met walking the boundary counter-clockwise from the south-west."""
    cols = corners.shape[1]
    t = np.arange(size)
    walk_r = np.concatenate([np.full(size, size), size - t, np.zeros(size, int), t])
    walk_c = np.concatenate([t, np.full(size, size), size - t, np.zeros(size, int)])
    rr, cc = row0[:, None] + walk_r, col0[:, None] + walk_c
    leaf, step = np.nonzero(corners[rr, cc])
    node = rr[leaf, step] * cols + cc[leaf, step]
    first = np.flatnonzero(np.r_[True, leaf[1:] != leaf[:-1]])
    last = np.r_[first[1:], len(leaf)] - 1
    following = np.arange(1, len(leaf) + 1)
    following[last] = first
    centre = (row0 + size // 2) * cols + col0 + size // 2
    return np.column_stack([centre[leaf], node, node[following]]).astype(np.int32)
