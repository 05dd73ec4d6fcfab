"""Blind plane extraction: planar segments found from the points alone (SPEC §9).

This is what a user with real data does, using nothing the simulator knows: no plane ids, no
true edge distances. The steps, per ASPRS class:

1. **Objects.** Vegetation and noise classes are skipped. Ground, water and road points
   (classes 2, 9, 11) are one surface each; points of any other class (buildings, class 6, and
   unclassified data) are split into objects by horizontal connectivity: a radius graph on
   (x, y) and its connected components, so each building is processed on its own.
2. **Local planes.** Each point's normal and planarity residual come from a PCA of its k
   nearest neighbours of the same object.
3. **Region growing**, as connected components of a graph: two neighbouring points are
   linked when both neighbourhoods are planar (residual within a few noise scales), their
   normals agree and each lies near the other's tangent plane. The noise scale is estimated
   per object (median planarity residual), so the thresholds follow the point scatter, which
   grows with altitude and with the georeferencing model's distortion.
4. **Merging** of neighbouring segments that are coplanar: the pair's joint fit is hardly
   worse than their separate fits.
5. **Assignment.** Every point of the object (including the non-planar ones along ridges and
   eaves) goes to the neighbouring segment whose plane is nearest, if within tolerance; so a
   ridge splits where the two roof planes are equidistant.
6. **Edge buffer.** A segment's boundary points are those whose same-segment neighbours leave
   an angular gap of more than 90° around them in the plane (the point set ends there, at a
   free edge or against another segment). Boundary points, and points within the edge buffer
   of one, are left out of the fit.
7. **Final fit**: two-pass total least squares of the remaining points.

Everything is vectorised with numpy and scipy (cKDTree, sparse connected components); there is
no randomness, so results are deterministic.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from flightsim.planes import PlaneFit, fit_groups, fit_points

SKIPPED_CLASSES = frozenset({3, 4, 5, 7, 18})
"""ASPRS classes never searched for planes: low/medium/high vegetation, low and high noise."""

SURFACE_CLASSES = frozenset({2, 9, 11})
"""ASPRS classes taken as one continuous surface (ground, water, road), not split into objects."""

_MAX_GAP_RAD = 0.5 * math.pi  # an angular gap wider than this marks a boundary point
_CHUNK = 200_000  # points per block of the batched neighbourhood PCA


@dataclass(frozen=True)
class BlindParams:
    """Tuning of the blind extractor. Lengths in units of the estimated noise are dimensionless."""

    k: int = 24  #: neighbours for local normals and for growing
    max_angle_deg: float = 12.0  #: largest angle between the normals of two linked neighbours [deg]
    smooth_factor: float = 2.5  #: a point grows only if its planarity residual ≤ this × noise
    distance_factor: float = 4.0  #: tangent-plane and assignment tolerance, × noise
    merge_factor: float = 1.25  #: merge neighbours if their joint RMS ≤ this × their pooled RMS
    min_points: int = 30  #: smallest segment kept
    min_noise_m: float = 5e-4  #: floor of the noise scale (mm-quantised LAS coordinates) [m]
    planar_factor: float = 2.0  #: a grown segment is planar if its fit RMS ≤ this × its points' median residual
    ransac_angle_deg: float = 20.0  #: largest angle between a point's normal and a RANSAC plane's [deg]
    ransac_hypotheses: int = 256  #: candidate planes per RANSAC round
    ransac_max_points: int = 200_000  #: larger non-planar segments are left whole
    seed: int = 0  #: seed of the RANSAC sampling
    link_spacings: float = 3.0  #: object link radius in units of the neighbourhood radius
    assign_passes: int = 3  #: passes of nearest-plane assignment


@dataclass
class Segment:
    """One extracted plane."""

    id: int  #: index in BlindResult.segments
    classification: int  #: ASPRS class of its points
    members: np.ndarray  #: indices of every point assigned to it
    indices: np.ndarray  #: indices of the points used in the fit (members beyond the edge buffer)
    fit: PlaneFit  #: fit of ``indices``; ``fit.plane_id`` is the segment id


@dataclass
class BlindResult:
    """Segments, and per point: segment label (-1 none) and whether it was used in a fit."""

    segments: list[Segment]
    labels: np.ndarray  #: (n,) segment id of each point, -1 if unassigned
    used: np.ndarray  #: (n,) bool, the point is in some segment's fit
    edge_buffer_m: float  #: edge buffer applied [m]
    spacing_m: float  #: median nearest-neighbour distance [m]
    timings_s: dict = field(default_factory=dict)


def point_spacing_m(xyz: np.ndarray) -> float:
    """Median distance from a point to its nearest neighbour [m] (NaN for fewer than 2 points)."""
    if len(xyz) < 2:
        return float("nan")
    distance, _ = cKDTree(xyz).query(xyz, k=2, workers=-1)
    return float(np.median(distance[:, 1]))


def auto_edge_buffer_m(spacing_m: float) -> float:
    """Automatic edge buffer: half the typical point spacing [m] (the edge lies, on average,
    half a spacing beyond the outermost points)."""
    return 0.5 * spacing_m


def extract_planes(xyz: np.ndarray, classification: np.ndarray | None = None, edge_buffer_m: float | None = None,
                   params: BlindParams = BlindParams()) -> BlindResult:
    """Blind planar segments of a point cloud.

    Args:
        xyz: (n, 3) world or local coordinates [m], float64.
        classification: (n,) ASPRS classes; None treats all points as one unclassified set.
        edge_buffer_m: points within this distance of a segment's boundary are left out of its
            fit [m]; None: :func:`auto_edge_buffer_m` of the point spacing.
        params: tuning, see :class:`BlindParams`.
    """
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    points = points - (points.mean(axis=0) if n else 0.0)
    classes = np.ones(n, dtype=np.int64) if classification is None else np.asarray(classification, dtype=np.int64)
    spacing = point_spacing_m(points)
    buffer = auto_edge_buffer_m(spacing) if edge_buffer_m is None else float(edge_buffer_m)
    if not math.isfinite(buffer):
        buffer = 0.0
    labels = np.full(n, -1, dtype=np.int64)
    used = np.zeros(n, dtype=bool)
    segments: list[Segment] = []
    for cls in np.unique(classes):
        if int(cls) in SKIPPED_CLASSES:
            continue
        index = np.flatnonzero(classes == cls)
        groups = [index] if int(cls) in SURFACE_CLASSES else _objects(points[index], index, params)
        for group in groups:
            if len(group) < params.min_points:
                continue
            local_labels, local_used = _segment_object(points[group], buffer, params)
            for label in range(local_labels.max() + 1):
                members = group[local_labels == label]
                kept = group[(local_labels == label) & local_used]
                if len(kept) < 3:
                    continue
                seg_id = len(segments)
                fit = fit_points(points[kept], seg_id)
                segments.append(Segment(seg_id, int(cls), members, kept, fit))
                labels[members] = seg_id
                used[kept] = True
    return BlindResult(segments, labels, used, buffer, spacing)


def _objects(points: np.ndarray, index: np.ndarray, params: BlindParams) -> list[np.ndarray]:
    """Split points into objects by horizontal connectivity; return each object's indices."""
    if len(points) < params.min_points:
        return [index]
    k = min(params.k, len(points))
    distance, _ = cKDTree(points).query(points, k=k, workers=-1)
    radius = params.link_spacings * float(np.median(distance[:, -1]))
    pairs = cKDTree(points[:, :2]).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(points), len(points)))
    count, component = connected_components(graph, directed=False)
    order = np.argsort(component, kind="stable")
    bounds = np.searchsorted(component[order], np.arange(count + 1))
    return [index[order[bounds[c]:bounds[c + 1]]] for c in range(count)]


def local_planes(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point PCA of its neighbourhood: unit normals (n, 3) with z ≥ 0, and the RMS distance
    (n,) [m] of the neighbourhood from its own best plane (the planarity residual)."""
    normals = np.empty((len(points), 3))
    residual = np.empty(len(points))
    for start in range(0, len(points), _CHUNK):
        block = points[neighbours[start:start + _CHUNK]]
        block = block - block.mean(axis=1, keepdims=True)
        covariance = np.einsum("nki,nkj->nij", block, block) / block.shape[1]
        values, vectors = np.linalg.eigh(covariance)
        normal = vectors[:, :, 0]
        normals[start:start + _CHUNK] = normal * np.where(normal[:, 2:3] >= 0.0, 1.0, -1.0)
        residual[start:start + _CHUNK] = np.sqrt(np.maximum(values[:, 0], 0.0))
    return normals, residual


def _segment_object(points: np.ndarray, buffer: float, params: BlindParams) -> tuple[np.ndarray, np.ndarray]:
    """Segment one object; return per-point labels (-1 none, 0..S-1) and the used-in-fit mask."""
    n = len(points)
    k = min(params.k, n)
    _, neighbours = cKDTree(points).query(points, k=k, workers=-1)
    normals, residual = local_planes(points, neighbours)
    noise = max(float(np.median(residual)), params.min_noise_m)
    labels = _grow(points, neighbours, normals, residual, noise, params)
    labels = _split_non_planar(points, neighbours, normals, residual, labels, params)
    if labels.max() < 0:
        return labels, np.zeros(n, dtype=bool)
    labels = _merge(points, neighbours, labels, params)
    for _ in range(params.assign_passes):
        labels = _assign(points, neighbours, labels, noise, params)
    labels = _compact(labels, params.min_points)
    used = _beyond_edges(points, neighbours, labels, buffer)
    return labels, used


def _grow(points, neighbours, normals, residual, noise, params) -> np.ndarray:
    """Region growing as connected components of the graph of compatible neighbour pairs."""
    n, k = neighbours.shape
    smooth = residual <= params.smooth_factor * noise
    i = np.repeat(np.arange(n), k - 1)
    j = neighbours[:, 1:].ravel()
    ok = smooth[i] & smooth[j]
    i, j = i[ok], j[ok]
    cos_angle = np.abs(np.einsum("ij,ij->i", normals[i], normals[j]))
    offset = points[j] - points[i]
    tolerance = params.distance_factor * noise
    ok = ((cos_angle >= math.cos(math.radians(params.max_angle_deg)))
          & (np.abs(np.einsum("ij,ij->i", offset, normals[i])) <= tolerance)
          & (np.abs(np.einsum("ij,ij->i", offset, normals[j])) <= tolerance))
    graph = coo_matrix((np.ones(int(ok.sum()), dtype=np.int8), (i[ok], j[ok])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    component[~smooth] = -1
    return _compact(component, params.min_points)


def _split_non_planar(points, neighbours, normals, residual, labels, params) -> np.ndarray:
    """Re-segment by RANSAC every grown segment whose plane fits much worse than its points'
    neighbourhoods do (growing leaked across a ridge or a step)."""
    out = labels.copy()
    next_label = labels.max() + 1
    for fit in fit_groups(points, labels):
        member = np.flatnonzero(labels == fit.plane_id)
        scale = max(float(np.median(residual[member])), params.min_noise_m)
        if fit.rms_m <= params.planar_factor * scale or len(member) > params.ransac_max_points:
            continue
        pieces = _ransac(points, neighbours, normals, residual, member, params)
        out[member] = np.where(pieces >= 0, pieces + next_label, -1)
        next_label += max(pieces.max() + 1, 0)
    return _compact(out, params.min_points)


def _ransac(points, neighbours, normals, residual, member, params) -> np.ndarray:
    """Sequential RANSAC on the points ``member``: labels (len(member),), -1 for none.

    Candidate planes are the tangent planes of sampled points (seeded, so deterministic). A
    point is an inlier of a plane when within ``distance_factor`` × its own planarity residual
    of it and its normal within ``ransac_angle_deg``. The best candidate is refined by a TLS fit
    of its inliers, cut to their largest connected piece (the neighbour graph), and removed.
    """
    rng = np.random.default_rng(params.seed)
    n = len(points)
    pieces = np.full(len(member), -1, dtype=np.int64)
    local = np.full(n, -1, dtype=np.int64)
    local[member] = np.arange(len(member))
    tolerance = params.distance_factor * np.maximum(residual[member], params.min_noise_m)
    cos_max = math.cos(math.radians(params.ransac_angle_deg))
    free = np.ones(len(member), dtype=bool)
    for label in range(len(member)):
        pool = np.flatnonzero(free)
        if len(pool) < params.min_points:
            break
        seeds = rng.choice(pool, size=min(params.ransac_hypotheses, len(pool)), replace=False)
        p, q = points[member[pool]], normals[member[pool]]
        best, best_count = -1, 0
        for h in seeds:
            count = int(_inliers(p, q, points[member[h]], normals[member[h]], tolerance[pool], cos_max).sum())
            if count > best_count:
                best, best_count = h, count
        if best_count < params.min_points:
            break
        centroid, normal = points[member[best]], normals[member[best]]
        first = inlier = _inliers(p, q, centroid, normal, tolerance[pool], cos_max)
        for _ in range(2):  # refine: fit the inliers, collect the inliers of the fit
            if inlier.sum() < 3:
                break
            fit = fit_points(p[inlier])
            centroid, normal = fit.centroid, fit.normal
            inlier = _inliers(p, q, centroid, normal, tolerance[pool], cos_max)
        piece = _largest_piece(pool[inlier], neighbours[member[pool[inlier]]], local) if inlier.any() else pool[:0]
        if len(piece) < params.min_points:
            free[pool[first]] = False  # no connected plane here: drop these from the pool
            continue
        pieces[piece] = label
        free[piece] = False
    return pieces


def _inliers(p, q, centroid, normal, tolerance, cos_max) -> np.ndarray:
    """Points p (m, 3) with normals q (m, 3) within tolerance (m,) of the plane and of its normal."""
    return (np.abs((p - centroid) @ normal) <= tolerance) & (np.abs(q @ normal) >= cos_max)


def _largest_piece(chosen: np.ndarray, rows: np.ndarray, local: np.ndarray) -> np.ndarray:
    """The largest connected subset of ``chosen`` (indices into a member list) under the
    neighbour graph; ``rows`` are the chosen points' neighbour rows (object indices) and
    ``local`` maps object indices to member positions (-1 outside)."""
    position = np.full(local.max() + 2, -1, dtype=np.int64)
    position[chosen] = np.arange(len(chosen))
    j = local[rows[:, 1:]]
    j = np.where(j >= 0, position[j], -1)
    i = np.repeat(np.arange(len(chosen)), rows.shape[1] - 1)
    ok = j.ravel() >= 0
    graph = coo_matrix((np.ones(int(ok.sum()), dtype=np.int8), (i[ok], j.ravel()[ok])),
                       shape=(len(chosen), len(chosen)))
    _, component = connected_components(graph, directed=False)
    return chosen[component == np.bincount(component).argmax()]


def _compact(labels: np.ndarray, min_points: int) -> np.ndarray:
    """Drop labels with fewer than ``min_points`` points and renumber the rest 0..S-1 by size."""
    out = np.full(len(labels), -1, dtype=np.int64)
    valid = labels >= 0
    if not valid.any():
        return out
    values, inverse, counts = np.unique(labels[valid], return_inverse=True, return_counts=True)
    order = np.lexsort((values, -counts))  # largest first, ties by old label
    rank = np.empty(len(values), dtype=np.int64)
    rank[order] = np.arange(len(values))
    new = np.where(counts[inverse] >= min_points, rank[inverse], -1)
    keep = np.sort(np.unique(new[new >= 0]))
    remap = np.full(len(values) + 1, -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    out[valid] = remap[new]
    return out


@dataclass
class _Moments:
    """Count, centroid and centred covariance of a segment, combinable exactly."""

    n: int
    centroid: np.ndarray
    covariance: np.ndarray

    @staticmethod
    def of(points: np.ndarray) -> "_Moments":
        centroid = points.mean(axis=0)
        d = points - centroid
        return _Moments(len(points), centroid, d.T @ d / len(points))

    def plus(self, other: "_Moments") -> "_Moments":
        n = self.n + other.n
        centroid = (self.n * self.centroid + other.n * other.centroid) / n
        covariance = np.zeros((3, 3))
        for m in (self, other):
            delta = m.centroid - centroid
            covariance += m.n * (m.covariance + np.outer(delta, delta))
        return _Moments(n, centroid, covariance / n)

    @property
    def variance(self) -> float:
        """Mean squared orthogonal residual of the TLS plane [m²]."""
        return float(max(np.linalg.eigvalsh(self.covariance)[0], 0.0))


def _merge(points, neighbours, labels, params) -> np.ndarray:
    """Merge neighbouring segments whose joint plane fits about as well as their separate ones."""
    count = labels.max() + 1
    moments = [_Moments.of(points[labels == s]) for s in range(count)]
    a = np.repeat(labels, neighbours.shape[1] - 1)
    b = labels[neighbours[:, 1:].ravel()]
    touching = (a >= 0) & (b >= 0) & (a != b)
    pairs = np.unique(np.sort(np.column_stack([a[touching], b[touching]]), axis=1), axis=0)
    parent = list(range(count))

    def root(s: int) -> int:
        while parent[s] != s:
            parent[s] = parent[parent[s]]
            s = parent[s]
        return s

    floor = params.min_noise_m**2
    for s, t in pairs:
        rs, rt = root(int(s)), root(int(t))
        if rs == rt:
            continue
        ms, mt = moments[rs], moments[rt]
        joint = ms.plus(mt)
        pooled = (ms.n * ms.variance + mt.n * mt.variance) / joint.n
        if joint.variance <= params.merge_factor**2 * pooled + floor:
            parent[rt] = rs
            moments[rs] = joint
    roots = np.array([root(s) for s in range(count)])
    merged = np.where(labels >= 0, roots[np.maximum(labels, 0)], -1)
    return _compact(merged, params.min_points)


def _assign(points, neighbours, labels, noise, params) -> np.ndarray:
    """Give each point to the nearest plane among its own and its neighbours' segments, within
    ``distance_factor`` × the segment's residual RMS (at least × the object's noise)."""
    count = labels.max() + 1
    if count <= 0:
        return labels
    fits = {f.plane_id: f for f in fit_groups(points, labels)}
    normal = np.zeros((count + 1, 3))
    centroid = np.zeros((count + 1, 3))
    tolerance = np.full(count + 1, -1.0)
    for s, f in fits.items():
        normal[s], centroid[s] = f.normal, f.centroid
        tolerance[s] = params.distance_factor * max(f.rms_m, noise)
    candidates = labels[neighbours]  # (n, k); column 0 is the point itself
    slot = np.where(candidates >= 0, candidates, count)  # row `count` is a sentinel
    distance = np.abs(np.einsum("nkj,nkj->nk", points[:, None, :] - centroid[slot], normal[slot]))
    distance[(candidates < 0) | (distance > tolerance[slot])] = np.inf
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(points))
    return np.where(np.isfinite(distance[rows, best]), candidates[rows, best], -1)


def _beyond_edges(points, neighbours, labels, buffer) -> np.ndarray:
    """Points of a segment that are neither boundary points nor within ``buffer`` of one."""
    used = np.zeros(len(points), dtype=bool)
    fits = {f.plane_id: f for f in fit_groups(points, labels)}
    for s, f in fits.items():
        member = np.flatnonzero(labels == s)
        boundary = _boundary_points(points, neighbours[member], labels, s, f.normal)
        near = boundary.copy()
        if buffer > 0.0 and boundary.any():
            distance, _ = cKDTree(points[member[boundary]]).query(points[member], k=1,
                                                                  distance_upper_bound=buffer * (1.0 + 1e-9))
            near |= distance <= buffer
        used[member] = ~near
    return used


def _boundary_points(points, neighbours, labels, segment, normal) -> np.ndarray:
    """For the points with these neighbour rows (column 0: the point), whether the directions to
    their same-segment neighbours, projected on the plane, leave a gap wider than 90°."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    offset = points[neighbours[:, 1:]] - points[neighbours[:, :1]]
    angle = np.arctan2(offset @ v, offset @ u)
    angle[labels[neighbours[:, 1:]] != segment] = np.nan
    angle = np.sort(angle, axis=1)  # NaN last
    valid = np.isfinite(angle)
    count = valid.sum(axis=1)
    gaps = np.diff(angle, axis=1)
    gaps[~np.isfinite(gaps)] = 0.0
    widest = gaps.max(axis=1, initial=0.0)
    first = angle[:, 0]
    last = np.take_along_axis(angle, np.maximum(count - 1, 0)[:, None], axis=1)[:, 0]
    wrap = 2.0 * math.pi - (last - first)
    widest = np.maximum(widest, np.where(count > 0, wrap, 2.0 * math.pi))
    return (count < 2) | (widest > _MAX_GAP_RAD)
