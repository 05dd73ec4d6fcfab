"""From photons to points: grid the photon events in the horizontal plane, histogram each cell's
heights and keep the cell's peak (seed: spad-fsm-small-body-lidar-paper.txt, Fig. 4a).

Per cell of side ``cell_m``: the heights are binned at ``bin_m``; the fullest pair of adjacent bins
is the cell's surface when it holds at least ``min_count`` photons and 5σ above the cell's background
per pair of bins (noise spreads over the whole gate, the echo piles up in one or two bins); the point
is the mean of the cell's photons within ``window_m`` of that pair's middle.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class GridPoints:
    """One point per accepted cell (local or world coordinates, as given) [m]."""

    points: np.ndarray  # (m, 3)
    cell: np.ndarray  # (m, 2) int64 column and row of each point's cell, from the photons' lowest x, y
    photons: np.ndarray  # (m,) photons averaged into each point
    peak: np.ndarray  # (m,) photons in the fullest bin
    cells: int  # cells holding any photon


def xy_cells(xyz: np.ndarray, cell_m: float) -> np.ndarray:
    """(n, 2) int64 column, row of each position's horizontal cell of side ``cell_m`` [m]."""
    xy = np.asarray(xyz, dtype=np.float64)[:, :2]
    return np.floor((xy - np.nanmin(xy, axis=0)) / cell_m).astype(np.int64)


def angle_cells(directions: np.ndarray, half_field_rad: float, cells: int) -> np.ndarray:
    """(n, 2) int64 column, row of each downward beam direction (n, 3) in a ``cells`` × ``cells`` grid of
    angles from nadir over ±``half_field_rad`` (atan of the east and north direction over the depth);
    −1 outside the field. Every photon of a beam falls in its beam's cell whatever its range."""
    d = np.asarray(directions, dtype=np.float64)
    angles = np.arctan2(d[:, :2], -d[:, 2:3])
    ij = np.floor((angles + half_field_rad) / (2.0 * half_field_rad) * cells).astype(np.int64)
    return np.where(((ij >= 0) & (ij < cells)).all(axis=1, keepdims=True), ij, -1)


def grid_points(xyz: np.ndarray, cells: np.ndarray, bin_m: float, min_count: int, window_m: float) -> GridPoints:
    """The surface points of photon positions ``xyz`` (n, 3) [m] gridded by ``cells`` (n, 2) int column and
    row (``xy_cells``, ``angle_cells``; negative: left out).

    The peak is the fullest pair of adjacent height bins (an echo straddling a bin edge stays whole);
    the point is the mean of the cell's photons within ``window_m`` of the pair's middle, then once more
    within ``window_m`` of that mean (so a window off the echo's centre does not clip it).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    ok = np.isfinite(xyz).all(axis=1) & (np.asarray(cells) >= 0).all(axis=1)
    xyz, ij = xyz[ok], np.asarray(cells, dtype=np.int64)[ok]
    empty = GridPoints(np.zeros((0, 3)), np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), 0)
    if len(xyz) == 0:
        return empty
    lo = xyz.min(axis=0)
    columns = ij[:, 0].max() + 1
    cell = ij[:, 1] * columns + ij[:, 0]
    zbin = np.floor((xyz[:, 2] - lo[2]) / bin_m).astype(np.int64)
    stride = zbin.max() + 2
    keys, counts = np.unique(cell * stride + zbin, return_counts=True)
    following = np.searchsorted(keys, keys + 1)
    has_next = (following < len(keys)) & (keys[np.minimum(following, len(keys) - 1)] == keys + 1)
    window = counts + np.where(has_next, counts[np.minimum(following, len(keys) - 1)], 0)
    key_cell = keys // stride
    order = np.lexsort((-window, key_cell))  # per cell, the fullest pair of bins first
    first = np.ones(len(order), dtype=bool)
    first[1:] = key_cell[order[1:]] != key_cell[order[:-1]]
    best = order[first]
    cells = len(best)
    # background rejection: the pair must beat the cell's own background by 5σ, and hold min_count
    in_cell = np.bincount(np.searchsorted(np.unique(key_cell), key_cell), weights=counts)
    background = 2.0 * np.maximum(in_cell - window[best], 0.0) / max(stride - 1, 1)
    best = best[window[best] >= np.maximum(min_count, background + 5.0 * np.sqrt(background))]
    if len(best) == 0:
        return GridPoints(empty.points, empty.cell, empty.photons, empty.peak, cells)
    best_cell = key_cell[best]
    index = np.minimum(np.searchsorted(best_cell, cell), len(best_cell) - 1)
    in_cell = best_cell[index] == cell
    centre = lo[2] + (keys[best] % stride + 1) * bin_m  # the pair's middle, then the mean of its window
    for _ in range(2):
        member = in_cell & (np.abs(xyz[:, 2] - centre[index]) <= window_m)
        n = np.bincount(index[member], minlength=len(best_cell))
        sums = np.stack([np.bincount(index[member], weights=xyz[member, k], minlength=len(best_cell))
                         for k in range(3)], axis=1)
        centre = np.where(n > 0, sums[:, 2] / np.maximum(n, 1), centre)
    ok = n > 0
    kept = best_cell[ok]
    return GridPoints(sums[ok] / n[ok, None], np.stack([kept % columns, kept // columns], axis=1), n[ok],
                      window[best][ok], cells)
