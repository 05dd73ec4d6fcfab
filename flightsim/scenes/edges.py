"""Plane boundaries of a scene and the edge buffer that keeps plane scoring off them (SPEC §9).

A point whose true hit lies within the edge buffer of its plane's boundary is left out of the
plane fits: near an edge a real footprint straddles two surfaces, and a distorted point may
land on the neighbouring one. The kernels measure that distance exactly, visiting only the
boundary segments listed for the point's cell of the edge grid (every segment that may come within the buffer
of a point of the cell; kernels/edges.py).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # only named in annotations: a Scene calls this module (Scene.boundary_segments)
    from flightsim.scenes.scene import Scene

_VERTEX_KEY_M = 1e-6  # vertices closer than this count as one when matching edges [m]


_LOW_BITS_TABLE = 1 << 20
"""Entries of the table that narrows the search for the few lone edges' records (a power of two)."""
_PACKED_KEYS = 2**63 - 1
"""Largest edge key that packs into an int64 (beyond it, edges are grouped row by row)."""
_HASH_MULTIPLIERS = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], dtype=np.uint64)
"""Odd 64-bit multipliers of the row hash in :func:`_row_groups` (the golden ratio's and xxHash's primes)."""


def _sorted_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, starts) of an integer table (R, ≤ 3): an order that puts equal rows side by side, and
    whether each row in that order differs from the one before it (starts a group of equal rows).

    Rows are sorted by a 64-bit hash (one sort instead of a lexicographic sort's one per column). Should
    two different rows share a hash (which the check below always finds), the table is sorted
    lexicographically instead, so the groups are exact either way."""
    columns = rows.T.astype(np.uint64)
    hashes = columns[0] * _HASH_MULTIPLIERS[0]
    for column, multiplier in zip(columns[1:], _HASH_MULTIPLIERS[1:]):
        hashes ^= hashes >> np.uint64(29)
        hashes += column * multiplier
    order = np.argsort(hashes)
    ordered = hashes[order]
    starts = np.ones(len(rows), dtype=bool)
    starts[1:] = ordered[1:] != ordered[:-1]
    later = np.flatnonzero(~starts)  # rows whose hash equals the previous row's: the rows must be equal too
    if not np.array_equal(rows[order[later]], rows[order[later - 1]]):
        order = np.lexsort(rows.T[::-1])
        ordered = rows[order]
        starts[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    return order, starts


def _lone_rows(rows: np.ndarray) -> np.ndarray:
    """Indices, ascending, of the rows of an integer table (R, ≤ 3) that equal no other row."""
    order, starts = _sorted_rows(rows)
    ends = np.append(starts[1:], True)
    return np.sort(order[starts & ends])


def _vertex_ids(vertices: np.ndarray) -> np.ndarray:
    """An id per vertex, 0 … (distinct positions − 1): vertices share an id when their coordinates
    rounded to _VERTEX_KEY_M are equal."""
    order, starts = _sorted_rows(np.round(vertices / _VERTEX_KEY_M).astype(np.int64))
    ids = np.empty(len(vertices), dtype=np.int64)
    ids[order] = np.cumsum(starts) - 1
    return ids


def _lone_edges(plane: np.ndarray, lo: np.ndarray, hi: np.ndarray, n_ids: int) -> np.ndarray:
    """Indices, ascending, of the edge records (plane, lo, hi) that occur once: each packed into one
    int64 and sorted (a table too wide to pack: grouped row by row)."""
    n_planes = int(plane.max()) + 1 if len(plane) else 1
    if n_planes * n_ids * n_ids > _PACKED_KEYS:
        return _lone_rows(np.column_stack([plane, lo, hi]))
    keys = (plane.astype(np.int64) * n_ids + lo) * n_ids + hi
    ordered = np.sort(keys)
    same = ordered[1:] == ordered[:-1]
    once = np.ones(len(keys), dtype=bool)
    once[1:] &= ~same
    once[:-1] &= ~same
    lone = ordered[once]
    if len(lone) == 0:
        return np.zeros(0, dtype=np.int64)
    # their records: those whose key's low bits some lone key has (a small table), then a binary search
    low = np.zeros(_LOW_BITS_TABLE, dtype=bool)
    low[lone & (_LOW_BITS_TABLE - 1)] = True
    candidates = np.flatnonzero(low[keys & (_LOW_BITS_TABLE - 1)])
    at = np.minimum(np.searchsorted(lone, keys[candidates]), len(lone) - 1)
    return candidates[lone[at] == keys[candidates]]


def boundary_segments(scene: Scene) -> np.ndarray:
    """(S, 2, 3) local end points [m] of every edge that bounds a plane, in triangle order (edges 0→1 of
    every triangle, then 1→2, then 2→0).

    An edge bounds plane p when exactly one triangle of p uses it, vertices matched by position (so
    duplicated vertices do not create false boundaries). Degenerate edges are skipped.
    """
    ids = _vertex_ids(scene.vertices)
    a, b = scene.triangles.T.ravel(), np.roll(scene.triangles, -1, axis=1).T.ravel()
    id_a, id_b = ids[a], ids[b]
    lo, hi = np.minimum(id_a, id_b), np.maximum(id_a, id_b)
    keep = np.flatnonzero(lo != hi)
    lone = keep[_lone_edges(np.tile(scene.plane_id, 3)[keep], lo[keep], hi[keep], int(ids.max()) + 1)]
    return np.stack([scene.vertices[a[lone]], scene.vertices[b[lone]]], axis=1)
