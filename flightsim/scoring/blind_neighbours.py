"""Point neighbourhoods and segment labels for blind plane extraction (:mod:`flightsim.scoring.blind`):
the k nearest neighbours of each point, its local plane (PCA normal and planarity residual [m]), and
the label arrays the stages pass on (-1: no segment; 0..S-1)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

_CHUNK = 100_000  # points per block of the batched neighbourhood PCA


@dataclass
class Neighbourhoods:
    """The k nearest neighbours of each point (itself first) and two of their distances."""

    index: np.ndarray  #: (n, k) int neighbour indices, column 0 the point itself
    nearest_m: np.ndarray  #: (n,) distance to the nearest other point [m]
    reach_m: np.ndarray  #: (n,) distance to the k-th nearest other point [m]


def neighbourhoods(points: np.ndarray, k: int) -> Neighbourhoods:
    """k nearest neighbours of every point (n ≥ 2) by a cKDTree on both cores."""
    k = min(k, len(points) - 1)
    distance, index = cKDTree(points).query(points, k=k + 1, workers=-1)
    return Neighbourhoods(index.astype(np.int64), distance[:, 1], distance[:, -1])


def restrict(near: Neighbourhoods, subset: np.ndarray) -> Neighbourhoods:
    """Neighbourhoods of the points ``subset``, renumbered within it; neighbours outside the subset
    are replaced by the point itself."""
    position = np.full(len(near.index), -1, dtype=np.int64)
    position[subset] = np.arange(len(subset))
    index = position[near.index[subset]]
    index = np.where(index >= 0, index, np.arange(len(subset))[:, None])
    return Neighbourhoods(index, near.nearest_m[subset], near.reach_m[subset])


def local_planes(points: np.ndarray, neighbours: np.ndarray, k_noise: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-point PCA of the neighbourhood (n, k), the point itself first.

    Returns unit normals (n, 3) with z ≥ 0, from all k neighbours, and the planarity residual
    (n,) [m], the RMS distance of the ``k_noise`` nearest from their own best plane: a local
    noise scale, small enough a neighbourhood not to straddle an edge where the data are dense.
    """
    normals = np.empty((len(points), 3))
    residual = np.empty(len(points))
    for start in range(0, len(points), _CHUNK):
        rows = slice(start, start + _CHUNK)
        block = points[neighbours[rows]]
        normal = _pca(block)[1][:, :, 0]
        normals[rows] = normal * np.where(normal[:, 2:3] >= 0.0, 1.0, -1.0)
        residual[rows] = np.sqrt(np.maximum(_pca(block[:, :k_noise + 1])[0][:, 0], 0.0))
    return normals, residual


def _pca(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and eigenvectors of the covariance of each neighbourhood (n, k, 3)."""
    block = block - block.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", block, block) / block.shape[1])


def group_indices(labels: np.ndarray) -> list[np.ndarray]:
    """Indices of each label 0..max (label order), by one stable sort."""
    if len(labels) == 0 or labels.max() < 0:
        return []
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(labels.max() + 2))
    return [order[bounds[g]:bounds[g + 1]] for g in range(labels.max() + 1)]


def compact(labels: np.ndarray, min_points: int) -> np.ndarray:
    """Drop labels with fewer than ``min_points`` points; renumber the rest 0..S-1, largest first."""
    out = np.full(len(labels), -1, dtype=np.int64)
    valid = labels >= 0
    if not valid.any():
        return out
    values, inverse, counts = np.unique(labels[valid], return_inverse=True, return_counts=True)
    order = np.lexsort((values, -counts))  # largest first, ties by old label
    rank = np.empty(len(values), dtype=np.int64)
    rank[order] = np.arange(len(values))
    out[valid] = np.where(counts[inverse] >= min_points, rank[inverse], -1)
    return out


def touching_pairs(labels: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct label pairs (a, b), a < b, of neighbouring points, and how many neighbour links
    join each pair."""
    a = np.repeat(labels, neighbours.shape[1] - 1)
    b = labels[neighbours[:, 1:].ravel()]
    touching = (a >= 0) & (b >= 0) & (a != b)
    pairs = np.sort(np.column_stack([a[touching], b[touching]]), axis=1)
    if len(pairs) == 0:
        return pairs.reshape(0, 2), np.zeros(0, dtype=np.int64)
    return np.unique(pairs, axis=0, return_counts=True)
