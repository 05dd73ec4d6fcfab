"""Blind plane extraction: planar segments found from the points alone (SPEC §9).

This is what a user with real data does, using nothing the simulator knows (no plane ids, no
true edge distances). Per ASPRS class:

1. **Objects.** Vegetation and noise classes are skipped. Ground, water and road points
   (classes 2, 9, 11) are one surface each; points of any other class (buildings, class 6, and
   unclassified data) are split into objects by horizontal connectivity (touching cells of an
   (x, y) grid of the link distance), so that each building is processed on its own. Objects
   of fewer than 2k points are skipped: their neighbourhoods would span the whole object.
2. **Local planes.** Each point's normal and planarity residual come from a PCA of its k
   nearest neighbours in its object.
3. **Region growing**, as the connected components of a graph: two neighbouring points are
   linked when both neighbourhoods are planar (residual within a few times the object's noise
   scale, the median residual), their normals agree and each lies near the other's tangent
   plane. The thresholds follow the point scatter, which grows with altitude and with the
   georeferencing model's distortion.
4. **Split** by sequential RANSAC of any grown segment whose plane fits much worse than its
   points' own neighbourhoods (growing leaked across a ridge).
5. **Merge** of neighbouring segments whose joint plane fits about as well as their separate
   ones, or within the object's noise scale.
6. **Assignment.** Every point of the object, including the non-planar ones along ridges and
   eaves, goes to the nearest plane among its neighbours' segments if within a few times that
   segment's RMS (repeated, so points of another surface are shed); a ridge therefore splits
   where the two roof planes are equidistant. Points still unassigned are searched once more
   for planes by RANSAC alone (sparse data, where every neighbourhood straddles an edge).
7. **Edge buffer.** Points within the buffer of their segment's boundary are left out: of the
   intersection line with a touching segment (a ridge, an eave above a wall), or of the edge of
   the segment's footprint where its points end (:func:`boundary_distance_m`).
8. **Final fit**: two-pass total least squares of the remaining points.

Vectorised with numpy and scipy (cKDTree, sparse connected components, Euclidean distance
transforms); the only sampling (RANSAC) is seeded, so results are deterministic.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt, label
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from flightsim.scoring.planes import PlaneFit, fit_groups, fit_points, group_moments

SKIPPED_CLASSES = frozenset({3, 4, 5, 7, 18})
"""ASPRS classes never searched for planes: low/medium/high vegetation, low and high noise."""

SURFACE_CLASSES = frozenset({2, 9, 11})
"""ASPRS classes taken as one continuous surface (ground, water, road), not split into objects."""

_CHUNK = 100_000  # points per block of the batched neighbourhood PCA
_MAX_CELLS = 4_000_000  # largest raster of one segment's footprint


@dataclass(frozen=True)
class BlindParams:
    """Tuning of the blind extractor; factors are in units of the estimated noise scale."""

    k: int = 24  #: neighbours for local normals, footprints and object links
    k_grow: int = 12  #: neighbours linked when growing and offered when assigning
    k_noise: int = 12  #: neighbours of the planarity residual, the local noise scale
    max_angle_deg: float = 12.0  #: largest angle between the normals of two linked neighbours [deg]
    smooth_factor: float = 2.5  #: a point grows only if its planarity residual ≤ this × noise
    distance_factor: float = 4.0  #: tangent-plane, RANSAC and assignment tolerance, × noise or RMS
    planar_factor: float = 2.0  #: a grown segment is planar if its RMS ≤ this × its median residual
    merge_factor: float = 1.25  #: merge touching segments if joint RMS ≤ this × max(pooled RMS, noise)
    ransac_angle_deg: float = 20.0  #: largest angle between a point's normal and a RANSAC plane [deg]
    ransac_hypotheses: int = 256  #: candidate planes per RANSAC round
    ransac_rounds: int = 32  #: most planes taken out of one leaked segment
    ransac_max_points: int = 50_000  #: RANSAC only in segments (and objects) up to this size
    assign_passes: int = 3  #: passes of nearest-plane assignment
    min_points: int = 30  #: smallest segment kept
    min_noise_m: float = 5e-4  #: floor of the noise scale (mm-quantised LAS coordinates) [m]
    link_factor: float = 3.0  #: object link radius, × the median distance to the k-th neighbour
    closing_factor: float = 2.0  #: footprint closing radius, × the median distance to the k-th neighbour
    seed: int = 0  #: seed of the RANSAC sampling


@dataclass
class Segment:
    """One extracted plane."""

    id: int  #: index in ``BlindResult.segments``
    classification: int  #: ASPRS class of its points
    members: np.ndarray  #: indices of every point assigned to it
    indices: np.ndarray  #: indices of the points fitted: members beyond the edge buffer
    fit: PlaneFit  #: TLS fit of ``indices``, in the input frame; ``fit.plane_id`` is ``id``


@dataclass
class BlindResult:
    """Segments, and per point its segment (-1: none) and whether it was fitted."""

    segments: list[Segment]
    labels: np.ndarray  #: (n,) segment id of each point, -1 if unassigned
    used: np.ndarray  #: (n,) bool, the point is in some segment's fit
    edge_buffer_m: float  #: edge buffer applied [m]
    spacing_m: float  #: median nearest-neighbour distance of the points searched [m]
    timings_s: dict = field(default_factory=dict)  #: wall time of each stage [s]


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


def auto_edge_buffer_m(spacing_m: float) -> float:
    """Automatic edge buffer [m] when none is given: half the typical point spacing."""
    return 0.5 * spacing_m if math.isfinite(spacing_m) else 0.0


def extract_planes(xyz: np.ndarray, classification: np.ndarray | None = None, edge_buffer_m: float | None = None,
                   params: BlindParams = BlindParams()) -> BlindResult:
    """Blind planar segments of a point cloud.

    Args:
        xyz: (n, 3) world or local coordinates [m].
        classification: (n,) ASPRS classes; None takes all points as one unclassified set.
        edge_buffer_m: points within this distance of their segment's boundary are left out of
            its fit [m]; None: :func:`auto_edge_buffer_m` of the point spacing.
        params: tuning, see :class:`BlindParams`.
    """
    clock = _Clock()
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    origin = points.mean(axis=0) if n else np.zeros(3)
    points = points - origin  # centred: float64 keeps sub-mm detail of world coordinates
    classes = np.ones(n, dtype=np.int64) if classification is None else np.asarray(classification, dtype=np.int64)
    work = []
    for cls in np.unique(classes):
        index = np.flatnonzero(classes == cls)
        if int(cls) not in SKIPPED_CLASSES and len(index) >= max(params.min_points, 3):
            work.append((int(cls), index, neighbourhoods(points[index], params.k)))
    clock("neighbours")
    spacing = float(np.median(np.concatenate([w[2].nearest_m for w in work]))) if work else float("nan")
    buffer = auto_edge_buffer_m(spacing) if edge_buffer_m is None else float(edge_buffer_m)
    labels = np.full(n, -1, dtype=np.int64)
    used = np.zeros(n, dtype=bool)
    segments: list[Segment] = []
    for cls, index, near in work:
        objects = [np.arange(len(index))] if cls in SURFACE_CLASSES else _objects(points[index], near, params)
        clock("objects")
        for obj in objects:
            if len(obj) < max(params.min_points, 2 * params.k):
                continue  # neighbourhoods would span the whole object: no local noise scale to go by
            local_labels, local_used = _segment_object(points[index[obj]], _restrict(near, obj), buffer, params,
                                                       clock)
            members_of = _group_indices(local_labels)
            for members in members_of:
                kept = members[local_used[members]]
                if len(kept) < 3:
                    continue
                seg_id = len(segments)
                fit = fit_points(points[index[obj[kept]]], seg_id)
                fit.centroid = fit.centroid + origin
                segments.append(Segment(seg_id, cls, index[obj[members]], index[obj[kept]], fit))
                labels[index[obj[members]]] = seg_id
                used[index[obj[kept]]] = True
    clock("fit")
    return BlindResult(segments, labels, used, buffer, spacing, clock.stages)


class _Clock:
    """Accumulates wall time per named stage."""

    def __init__(self) -> None:
        self.stages: dict[str, float] = {}
        self.last = time.perf_counter()

    def __call__(self, stage: str) -> None:
        now = time.perf_counter()
        self.stages[stage] = self.stages.get(stage, 0.0) + now - self.last
        self.last = now


def _group_indices(labels: np.ndarray) -> list[np.ndarray]:
    """Indices of each label 0..max (label order), by one stable sort."""
    if len(labels) == 0 or labels.max() < 0:
        return []
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(labels.max() + 2))
    return [order[bounds[g]:bounds[g + 1]] for g in range(labels.max() + 1)]


def _objects(points: np.ndarray, near: Neighbourhoods, params: BlindParams) -> list[np.ndarray]:
    """Split points into objects by horizontal connectivity; return each object's indices.

    The (x, y) plane is cut into square cells of the link distance; occupied cells that touch
    (8-connectivity) form one object, so points closer than the link distance always share an
    object and objects are at least that far apart.
    """
    link = max(params.link_factor * float(np.median(near.reach_m)), 1e-6)
    cell = np.floor((points[:, :2] - points[:, :2].min(axis=0)) / link).astype(np.int64)
    occupied = np.zeros(tuple(cell.max(axis=0) + 1), dtype=bool)
    occupied[cell[:, 0], cell[:, 1]] = True
    grid, _ = label(occupied, structure=np.ones((3, 3), dtype=bool))
    return _group_indices(grid[cell[:, 0], cell[:, 1]] - 1)


def _restrict(near: Neighbourhoods, subset: np.ndarray) -> Neighbourhoods:
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


def _segment_object(points: np.ndarray, near: Neighbourhoods, buffer: float, params: BlindParams,
                    clock: _Clock) -> tuple[np.ndarray, np.ndarray]:
    """Segment one object; return per-point labels (-1 none, 0..S-1) and the fitted-point mask."""
    normals, residual = local_planes(points, near.index, params.k_noise)
    noise = max(float(np.median(residual)), params.min_noise_m)
    growing = near.index[:, :params.k_grow + 1]
    gap = params.link_factor * float(np.median(near.reach_m))  # widest gap of the scan pattern [m]
    clock("normals")
    labels = _grow(points, growing, normals, residual, noise, params)
    clock("grow")
    labels = _split_non_planar(points, growing, normals, residual, labels, params)
    clock("split")
    for _ in range(2):  # merge the grown cores, then again once every point is assigned
        labels = _merge_and_assign(points, near.index, growing, labels, noise, gap, params, clock)
    if _leftover_planes(points, growing, normals, labels, noise, params):
        labels = _merge_and_assign(points, near.index, growing, labels, noise, gap, params, clock)
    clock("split")
    if labels.max() < 0:
        return labels, np.zeros(len(points), dtype=bool)
    closing = params.closing_factor * float(np.median(near.reach_m))
    distance = boundary_distance_m(points, labels, near, params.max_angle_deg, closing_m=closing)
    clock("edges")
    return labels, (labels >= 0) & (distance > buffer)


def _leftover_planes(points, neighbours, normals, labels, noise, params) -> bool:
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
    pieces = _compact(pieces, params.min_points)
    labels[leftover[pieces >= 0]] = pieces[pieces >= 0] + labels.max() + 1
    return bool(pieces.max(initial=-1) >= 0)


def _merge_and_assign(points, neighbours, growing, labels, noise, gap, params, clock) -> np.ndarray:
    """Merge coplanar neighbours, then assign every point to its nearest plane (repeatedly)."""
    if labels.max() < 0:
        return labels
    labels = _merge(points, neighbours, labels, noise, gap, params)
    clock("merge")
    for _ in range(params.assign_passes):
        labels = _assign(points, growing, labels, params)
    labels = _compact(labels, params.min_points)
    clock("assign")
    return labels


def _grow(points, neighbours, normals, residual, noise, params) -> np.ndarray:
    """Region growing as connected components of the graph of compatible neighbour pairs."""
    n, k = neighbours.shape
    smooth = residual <= params.smooth_factor * noise
    i = np.repeat(np.arange(n), k - 1)
    j = neighbours[:, 1:].ravel()
    ok = smooth[i] & smooth[j] & (i != j)
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
    """Re-segment by RANSAC each grown segment whose plane fits much worse than its points'
    own neighbourhoods (growing leaked across a ridge or a step)."""
    out = labels.copy()
    next_label = labels.max() + 1
    fits = fit_groups(points, labels)
    members_of = _group_indices(labels)
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
    return _compact(out, params.min_points)


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


def _compact(labels: np.ndarray, min_points: int) -> np.ndarray:
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


def _touching_pairs(labels: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct label pairs (a, b), a < b, of neighbouring points, and how many neighbour links
    join each pair."""
    a = np.repeat(labels, neighbours.shape[1] - 1)
    b = labels[neighbours[:, 1:].ravel()]
    touching = (a >= 0) & (b >= 0) & (a != b)
    pairs = np.sort(np.column_stack([a[touching], b[touching]]), axis=1)
    if len(pairs) == 0:
        return pairs.reshape(0, 2), np.zeros(0, dtype=np.int64)
    return np.unique(pairs, axis=0, return_counts=True)


def _merge(points, neighbours, labels, noise, gap, params) -> np.ndarray:
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
    touching, _ = _touching_pairs(labels, neighbours)
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
    return _compact(np.where(labels >= 0, roots[np.maximum(labels, 0)], -1), params.min_points)


def _close_pairs(points: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """Label pairs (a, b), a < b, whose bounding boxes are less than ``gap`` [m] apart."""
    members_of = _group_indices(labels)
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


def _assign(points, neighbours, labels, params) -> np.ndarray:
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


def boundary_distance_m(points: np.ndarray, labels: np.ndarray, near: Neighbourhoods,
                        min_angle_deg: float = 12.0, min_contacts: int = 3,
                        closing_m: float | None = None) -> np.ndarray:
    """Distance [m] of each labelled point from the boundary of its group (label ≥ 0), estimated
    from the points alone; NaN for unlabelled points.

    Two kinds of boundary:

    - **shared edges**: where a group touches another (at least ``min_contacts`` neighbour links)
      whose plane meets it at ``min_angle_deg`` or more, the edge is the intersection line of
      the two planes (a ridge, an eave above a wall);
    - **free edges**, where the group's points end: the points of the group and of its
      shared-edge partners are projected on the group's plane and rasterised, the occupied cells
      closed (dilated, then eroded) by a disc of the group's median distance to its k-th
      neighbour, which fills the gaps of the scan pattern but not the outside; the outermost
      points lie on the edge of that footprint.

    The boundary distance is the smaller of the two.
    """
    distance = np.full(len(points), np.nan)
    fits = {f.plane_id: f for f in fit_groups(points, labels)}
    partners = _partners(labels, near.index, fits, min_angle_deg, min_contacts)
    members_of = _group_indices(labels)
    for g, fit in fits.items():
        member = members_of[g]
        u, v = _plane_axes(fit.normal)
        footprint = np.concatenate([member, *(members_of[h] for h in partners.get(g, ()))])
        d = points[footprint] - fit.centroid
        uv = np.column_stack([d @ u, d @ v])
        closing = float(np.median(near.reach_m[member])) if closing_m is None else closing_m
        edge = _footprint_distance(uv, closing)[:len(member)]
        for h in partners.get(g, ()):
            edge = np.minimum(edge, _line_distance(points[member], fit, fits[h]))
        distance[member] = edge
    return distance


def _partners(labels, neighbours, fits, min_angle_deg, min_contacts) -> dict[int, list[int]]:
    """For each group, the groups it shares an edge with (see :func:`boundary_distance_m`)."""
    pairs, count = _touching_pairs(labels, neighbours)
    sin_min = math.sin(math.radians(min_angle_deg))
    partners: dict[int, list[int]] = {}
    for (g, h), c in zip(pairs.tolist(), count.tolist()):
        if c >= min_contacts and g in fits and h in fits:
            if np.linalg.norm(np.cross(fits[g].normal, fits[h].normal)) >= sin_min:
                partners.setdefault(g, []).append(h)
                partners.setdefault(h, []).append(g)
    return partners


def _line_distance(points: np.ndarray, a: PlaneFit, b: PlaneFit) -> np.ndarray:
    """Distance [m] of points (m, 3) from the intersection line of two non-parallel planes."""
    direction = np.cross(a.normal, b.normal)
    direction /= np.linalg.norm(direction)
    matrix = np.array([a.normal, b.normal, direction])
    origin = np.linalg.solve(matrix, [a.normal @ a.centroid, b.normal @ b.centroid, direction @ a.centroid])
    return np.linalg.norm(np.cross(points - origin, direction), axis=1)


def _footprint_distance(uv: np.ndarray, radius: float) -> np.ndarray:
    """Distance [m] of 2-D points (m, 2) [m] from the edge of their footprint closed by ``radius``
    (less half a raster cell, so that the outermost points are at about 0)."""
    radius = max(radius, 1e-6)
    extent = uv.max(axis=0) - uv.min(axis=0) + 2.0 * radius
    cell = max(radius / 8.0, math.sqrt(extent[0] * extent[1] / _MAX_CELLS))
    pad = int(math.ceil(radius / cell)) + 2
    index = np.floor((uv - uv.min(axis=0)) / cell).astype(np.int64) + pad
    occupied = np.zeros(tuple(index.max(axis=0) + pad + 1), dtype=bool)
    occupied[index[:, 0], index[:, 1]] = True
    dilated = distance_transform_edt(~occupied, sampling=cell) <= radius
    closed = (distance_transform_edt(dilated, sampling=cell) > radius) | occupied
    inside = distance_transform_edt(closed, sampling=cell)
    return inside[index[:, 0], index[:, 1]] - 0.5 * cell


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal vectors spanning the plane of this unit normal."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)
