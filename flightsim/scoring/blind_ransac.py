"""RANSAC stages of blind plane extraction (:mod:`flightsim.scoring.blind`, steps 4 and 6): grown segments
that are not planar split into planes, and planes found among the points nothing grew into. The sampling
is seeded (``BlindParams.seed``), so results are deterministic."""
from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from flightsim.scoring.blind_neighbours import compact, group_indices
from flightsim.scoring.planes import fit_groups, fit_points


def split_non_planar(points, neighbours, normals, residual, labels, params) -> np.ndarray:
    """Re-segment by RANSAC each grown segment whose plane fits much worse than its points'
    own neighbourhoods (growing leaked across a ridge or a step)."""
    out = labels.copy()
    next_label = labels.max() + 1
    fits = fit_groups(points, labels)
    members_of = group_indices(labels)
    for fit in fits:
        member = members_of[fit.plane_id]
        scale = max(float(np.median(residual[member])), params.min_noise_m)
        if fit.rms_m <= params.planar_factor * scale or len(member) > params.ransac_max_points:
            continue
        tolerance = params.distance_factor * np.maximum(residual[member], params.min_noise_m)
        pieces = _ransac(points, neighbours, normals, member, tolerance,
                         math.cos(math.radians(params.ransac_angle_deg)), params)
        out[member] = np.where(pieces >= 0, pieces + next_label, -1)
        next_label += max(pieces.max() + 1, 0)
    return compact(out, params.min_points)


def leftover_planes(points, neighbours, normals, labels, noise, params) -> bool:
    """Planes among the points still unlabelled, by RANSAC alone (where the data are so sparse
    that every neighbourhood straddles an edge, nothing grows); labels them in place and says
    whether it found any. Only pieces as flat as the object's noise scale are kept."""
    leftover = np.flatnonzero(labels < 0)
    if len(leftover) < params.min_points or len(points) > params.ransac_max_points:
        return False
    tolerance = np.full(len(leftover), params.distance_factor * noise)
    pieces = _ransac(points, neighbours, normals, leftover, tolerance, 0.0, params)
    for fit in fit_groups(points[leftover], pieces):
        if fit.rms_m > params.planar_factor * noise:
            pieces[pieces == fit.plane_id] = -1
    pieces = compact(pieces, params.min_points)
    labels[leftover[pieces >= 0]] = pieces[pieces >= 0] + labels.max() + 1
    return bool(pieces.max(initial=-1) >= 0)


def _ransac(points, neighbours, normals, member, tolerance, cos_max, params) -> np.ndarray:
    """Sequential RANSAC on the points ``member``: a label per member (-1: none).

    Candidate planes, from seeded samples (deterministic): the tangent plane of a point and the
    plane through it and two of its neighbours. A member is an inlier of a plane when within
    its ``tolerance`` [m] of it and its normal within the angle of cosine ``cos_max`` of the
    plane's. The best candidate is refined by TLS fits of its inliers, cut to their largest
    connected piece in the neighbour graph, and taken out; then the next, for up to
    ``ransac_rounds`` planes.
    """
    rng = np.random.default_rng(params.seed)
    position = np.full(len(points), -1, dtype=np.int64)
    position[member] = np.arange(len(member))
    rows = position[neighbours[member]]  # neighbours as member positions, -1 outside
    p_all, q_all = points[member], normals[member]
    pieces = np.full(len(member), -1, dtype=np.int64)
    free = np.ones(len(member), dtype=bool)
    label = 0
    for _ in range(params.ransac_rounds):
        pool = np.flatnonzero(free)
        if len(pool) < params.min_points:
            break
        p, q, t = p_all[pool], q_all[pool], tolerance[pool]
        best, best_count = None, 0
        for h in rng.choice(pool, size=min(params.ransac_hypotheses, len(pool)), replace=False):
            for centroid, normal in _hypotheses(p_all, q_all, h, rows[h], free, rng):
                count = int(_inliers(p, q, centroid, normal, t, cos_max).sum())
                if count > best_count:
                    best, best_count = (centroid, normal), count
        if best is None or best_count < params.min_points:
            break
        first = inlier = _inliers(p, q, *best, t, cos_max)
        for _ in range(2):  # refine: fit the inliers, take the inliers of the fit
            fit = fit_points(p[inlier])
            inlier = _inliers(p, q, fit.centroid, fit.normal, t, cos_max)
            if inlier.sum() < 3:
                break
        piece = _largest_piece(pool[inlier], rows[pool[inlier]])
        if len(piece) < params.min_points:
            free[pool[first]] = False  # no connected plane here: leave these points out
            continue
        pieces[piece] = label
        free[piece] = False
        label += 1
    return pieces


def _hypotheses(p, q, h, row, free, rng) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate planes (point, unit normal) at member h: its tangent plane, and the plane
    through it and two random free neighbours when those are not collinear with it."""
    planes = [(p[h], q[h])]
    others = row[(row >= 0) & (row != h)]
    others = others[free[others]]
    if len(others) >= 2:
        i, j = rng.choice(others, size=2, replace=False)
        normal = np.cross(p[i] - p[h], p[j] - p[h])
        length = np.linalg.norm(normal)
        if length > 1e-12 * max(np.linalg.norm(p[i] - p[h]) * np.linalg.norm(p[j] - p[h]), 1e-300):
            planes.append((p[h], normal / length))
    return planes


def _inliers(p, q, centroid, normal, tolerance, cos_max) -> np.ndarray:
    """Points p (m, 3) with normals q (m, 3) within ``tolerance`` (m,) of the plane and whose
    normal is within the angle of cosine ``cos_max`` of the plane's."""
    return (np.abs((p - centroid) @ normal) <= tolerance) & (np.abs(q @ normal) >= cos_max)


def _largest_piece(chosen: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The largest connected subset of ``chosen`` (member positions) in the neighbour graph;
    ``rows`` (len(chosen), k) are their neighbours as member positions (-1 outside)."""
    if len(chosen) == 0:
        return chosen
    slot = np.full(max(int(rows.max()), int(chosen.max())) + 1, -1, dtype=np.int64)
    slot[chosen] = np.arange(len(chosen))
    j = np.where(rows >= 0, slot[np.maximum(rows, 0)], -1).ravel()
    i = np.repeat(np.arange(len(chosen)), rows.shape[1])
    ok = j >= 0
    graph = coo_matrix((np.ones(int(ok.sum()), dtype=np.int8), (i[ok], j[ok])), shape=(len(chosen), len(chosen)))
    _, component = connected_components(graph, directed=False)
    return chosen[component == np.bincount(component).argmax()]
