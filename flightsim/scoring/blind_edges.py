"""Edge buffer of blind plane extraction (:mod:`flightsim.scoring.blind`, step 7): the distance [m] of each
point from the boundary of its segment, from the points alone (intersection lines with touching segments,
and the edge of the segment's closed footprint), by Euclidean distance transforms of a raster."""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt

from flightsim.scoring.blind_neighbours import Neighbourhoods, group_indices, touching_pairs
from flightsim.scoring.planes import PlaneFit, fit_groups

_MAX_CELLS = 4_000_000  # largest raster of one segment's footprint


def auto_edge_buffer_m(spacing_m: float) -> float:
    """Automatic edge buffer [m] when none is given: half the typical point spacing."""
    return 0.5 * spacing_m if math.isfinite(spacing_m) else 0.0


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
    members_of = group_indices(labels)
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
    pairs, count = touching_pairs(labels, neighbours)
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
