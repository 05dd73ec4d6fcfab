"""Merging and assignment stages of blind plane extraction (:mod:`flightsim.scoring.blind`, steps 5 and
6): neighbouring segments merged where their joint plane fits about as well as their separate ones, and
every point given to the nearest plane among its neighbours' segments."""
from __future__ import annotations

import numpy as np

from flightsim.scoring.blind_neighbours import compact, group_indices, touching_pairs
from flightsim.scoring.planes import fit_groups, group_moments


def merge(points, neighbours, labels, noise, gap, params) -> np.ndarray:
    """Merge neighbouring segments whose joint plane fits about as well as their separate ones,
    or as well as the object's noise scale (the distortion can offset or tilt the parts of one
    plane seen from different scan positions by that much).

    Neighbouring: touching (neighbour links) or with bounding boxes less than ``gap`` [m] apart,
    which bridges the gaps of the scan pattern. Candidate pairs are tried best fit first.
    """
    count, centroid, covariance = group_moments(points, labels)
    moments = [(int(count[s]), centroid[s], covariance[s]) for s in range(len(count))]
    parent = list(range(len(count)))

    def root(s: int) -> int:
        while parent[s] != s:
            parent[s] = parent[parent[s]]
            s = parent[s]
        return s

    floor = params.min_noise_m**2
    touching, _ = touching_pairs(labels, neighbours)
    pairs = np.unique(np.concatenate([touching, _close_pairs(points, labels, gap)]), axis=0)
    ratio = [_variance(_combine(moments[s], moments[t])) / max(_variance(moments[s]), _variance(moments[t]), floor)
             for s, t in pairs.tolist()]
    for s, t in pairs[np.argsort(ratio, kind="stable")]:
        rs, rt = root(int(s)), root(int(t))
        if rs == rt:
            continue
        joint = _combine(moments[rs], moments[rt])
        pooled = (moments[rs][0] * _variance(moments[rs]) + moments[rt][0] * _variance(moments[rt])) / joint[0]
        if _variance(joint) <= params.merge_factor**2 * max(pooled, noise**2) + floor:
            parent[rt] = rs
            moments[rs] = joint
    roots = np.array([root(s) for s in range(len(count))])
    return compact(np.where(labels >= 0, roots[np.maximum(labels, 0)], -1), params.min_points)


def _close_pairs(points: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """Label pairs (a, b), a < b, whose bounding boxes are less than ``gap`` [m] apart."""
    members_of = group_indices(labels)
    lo = np.array([points[m].min(axis=0) if len(m) else [np.inf] * 3 for m in members_of]).reshape(-1, 3) - 0.5 * gap
    hi = np.array([points[m].max(axis=0) if len(m) else [-np.inf] * 3 for m in members_of]).reshape(-1, 3) + 0.5 * gap
    overlap = np.all((lo[:, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[:, None, :]), axis=2)
    a, b = np.nonzero(np.triu(overlap, k=1))
    return np.column_stack([a, b]).astype(np.int64)


def _combine(a: tuple, b: tuple) -> tuple:
    """Exact union of two (count, centroid, centred covariance) moment sets."""
    n = a[0] + b[0]
    centroid = (a[0] * a[1] + b[0] * b[1]) / n
    covariance = sum(m[0] * (m[2] + np.outer(m[1] - centroid, m[1] - centroid)) for m in (a, b)) / n
    return n, centroid, covariance


def _variance(m: tuple) -> float:
    """Mean squared orthogonal residual of the TLS plane of a moment set [m²]."""
    return float(max(np.linalg.eigvalsh(m[2])[0], 0.0))


def assign(points, neighbours, labels, params) -> np.ndarray:
    """Give each point to the nearest plane among its own and its neighbours' segments, within
    ``distance_factor`` × that segment's RMS. Repeated, this sheds points of another surface,
    however few (each pass re-fits without the points the last one shed)."""
    count = labels.max() + 1
    if count <= 0:
        return labels
    normal = np.zeros((count + 1, 3))
    offset = np.zeros(count + 1)
    tolerance = np.full(count + 1, -1.0)  # the sentinel row `count` accepts nothing
    for f in fit_groups(points, labels):
        s = f.plane_id
        normal[s], offset[s] = f.normal, f.normal @ f.centroid
        tolerance[s] = params.distance_factor * max(f.rms_m, params.min_noise_m)
    candidates = np.where(labels[neighbours] >= 0, labels[neighbours], count)
    distance = np.empty(candidates.shape)
    for c in range(candidates.shape[1]):
        s = candidates[:, c]
        distance[:, c] = np.abs(np.einsum("ij,ij->i", points, normal[s]) - offset[s])
        distance[distance[:, c] > tolerance[s], c] = np.inf
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(points))
    chosen = candidates[rows, best]
    return np.where(np.isfinite(distance[rows, best]), chosen, -1)
