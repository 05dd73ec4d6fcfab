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
   the segment's footprint where its points end (:func:`.blind_edges.boundary_distance_m`).
8. **Final fit**: two-pass total least squares of the remaining points.

Vectorised with numpy and scipy (cKDTree, sparse connected components, Euclidean distance
transforms); the only sampling (RANSAC) is seeded, so results are deterministic. Steps 1–3 and the
whole are here; neighbourhoods and local planes in :mod:`.blind_neighbours`, RANSAC (4, and the
second search of 6) in :mod:`.blind_ransac`, merging and assignment (5, 6) in :mod:`.blind_merge`,
the edge buffer (7) in :mod:`.blind_edges`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import label
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from flightsim.scoring.blind_edges import auto_edge_buffer_m, boundary_distance_m
from flightsim.scoring.blind_merge import assign, merge
from flightsim.scoring.blind_neighbours import (Neighbourhoods, compact, group_indices, local_planes, neighbourhoods,
                                               restrict)
from flightsim.scoring.blind_ransac import leftover_planes, split_non_planar
from flightsim.scoring.planes import PlaneFit, fit_points

SKIPPED_CLASSES = frozenset({3, 4, 5, 7, 18})
"""ASPRS classes never searched for planes: low/medium/high vegetation, low and high noise."""

SURFACE_CLASSES = frozenset({2, 9, 11})
"""ASPRS classes taken as one continuous surface (ground, water, road), not split into objects."""


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


def extract_planes(xyz: np.ndarray, classification: np.ndarray | None = None, edge_buffer_m: float | None = None,
                   params: BlindParams = BlindParams()) -> BlindResult:
    """Blind planar segments of a point cloud.

    Args:
        xyz: (n, 3) world or local coordinates [m].
        classification: (n,) ASPRS classes; None takes all points as one unclassified set.
        edge_buffer_m: points within this distance of their segment's boundary are left out of
            its fit [m]; None: :func:`.blind_edges.auto_edge_buffer_m` of the point spacing.
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
            local_labels, local_used = _segment_object(points[index[obj]], restrict(near, obj), buffer, params,
                                                       clock)
            members_of = group_indices(local_labels)
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
    return group_indices(grid[cell[:, 0], cell[:, 1]] - 1)


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
    labels = split_non_planar(points, growing, normals, residual, labels, params)
    clock("split")
    for _ in range(2):  # merge the grown cores, then again once every point is assigned
        labels = _merge_and_assign(points, near.index, growing, labels, noise, gap, params, clock)
    if leftover_planes(points, growing, normals, labels, noise, params):
        labels = _merge_and_assign(points, near.index, growing, labels, noise, gap, params, clock)
    clock("split")
    if labels.max() < 0:
        return labels, np.zeros(len(points), dtype=bool)
    closing = params.closing_factor * float(np.median(near.reach_m))
    distance = boundary_distance_m(points, labels, near, params.max_angle_deg, closing_m=closing)
    clock("edges")
    return labels, (labels >= 0) & (distance > buffer)


def _merge_and_assign(points, neighbours, growing, labels, noise, gap, params, clock) -> np.ndarray:
    """Merge coplanar neighbours, then assign every point to its nearest plane (repeatedly)."""
    if labels.max() < 0:
        return labels
    labels = merge(points, neighbours, labels, noise, gap, params)
    clock("merge")
    for _ in range(params.assign_passes):
        labels = assign(points, growing, labels, params)
    labels = compact(labels, params.min_points)
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
    return compact(component, params.min_points)
