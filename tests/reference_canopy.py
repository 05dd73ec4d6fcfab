"""An independent float64 NumPy walk of a ray through a voxel grid, for checking :mod:`kernels.canopy`.

No stepping: the segment is clipped to the grid's box, every crossing of a voxel plane inside it is
listed, the crossings are sorted, and each interval between two successive ones is one voxel, the one
holding the interval's midpoint. Intervals of zero length (several planes crossed at once: an edge or a
corner) are dropped.

The conventions are those :mod:`kernels.canopy` documents: the box is closed; along an axis the ray is
parallel to (|component| < 1e-290) it stays in the layer holding its start coordinate, the upper layer
where that lies on a face and the last layer on the box's upper face.
"""
from __future__ import annotations

import numpy as np

PARALLEL = 1.0e-290


def clip_to_box(lower, cell, dims, start, direction, t0: float, t1: float) -> tuple[float, float] | None:
    """(ta, tb) of the segment start + t·direction, t in [t0, t1], inside the closed box of the grid; None
    when it misses the box or meets it for zero length."""
    lower, cell, start, direction = (np.asarray(v, dtype=np.float64) for v in (lower, cell, start, direction))
    upper = lower + np.asarray(dims, dtype=np.float64) * cell
    ta, tb = float(t0), float(t1)
    for a in range(3):
        if abs(direction[a]) < PARALLEL:
            if not lower[a] <= start[a] <= upper[a]:
                return None
            continue
        ends = sorted(((lower[a] - start[a]) / direction[a], (upper[a] - start[a]) / direction[a]))
        ta, tb = max(ta, ends[0]), min(tb, ends[1])
    if not ta < tb:
        return None
    return ta, tb


def walk(lower, cell, dims, start, direction, t0: float, t1: float) -> list[tuple[tuple[int, int, int], float, float]]:
    """The voxels the segment crosses, in order: ((ix, iy, iz), t_in, t_out) each, t_out > t_in."""
    lower, cell, start, direction = (np.asarray(v, dtype=np.float64) for v in (lower, cell, start, direction))
    dims = np.asarray(dims, dtype=np.int64)
    clipped = clip_to_box(lower, cell, dims, start, direction, t0, t1)
    if clipped is None:
        return []
    ta, tb = clipped
    crossings = [np.array([ta, tb])]
    for a in range(3):
        if abs(direction[a]) < PARALLEL:
            continue
        planes = lower[a] + np.arange(dims[a] + 1, dtype=np.float64) * cell[a]
        t = (planes - start[a]) / direction[a]
        crossings.append(t[(t > ta) & (t < tb)])
    t = np.unique(np.concatenate(crossings))
    t_in, t_out = t[:-1], t[1:]
    keep = t_out > t_in
    t_in, t_out = t_in[keep], t_out[keep]
    middle = 0.5 * (t_in + t_out)
    index = np.empty((len(middle), 3), dtype=np.int64)
    for a in range(3):
        coordinate = start[a] + middle * direction[a] if abs(direction[a]) >= PARALLEL else np.full(len(middle), start[a])
        index[:, a] = np.clip(np.floor((coordinate - lower[a]) / cell[a]), 0, dims[a] - 1)
    return [(tuple(int(i) for i in index[k]), float(t_in[k]), float(t_out[k])) for k in range(len(middle))]


def optical_depth(lad, lower, cell, start, direction, t0: float, t1: float, g: float) -> float:
    """g · Σ lad · length over the voxels of the segment (a unit direction: lengths in metres)."""
    lad = np.asarray(lad, dtype=np.float64)
    return g * sum(lad[v] * (b - a) for v, a, b in walk(lower, cell, lad.shape, start, direction, t0, t1))
