"""Polygon triangulation: ear clipping with holes bridged to the outer boundary (the calibration field's ground
around its roads and houses)."""
from __future__ import annotations

import math

import numpy as np


def triangulate_polygon_with_holes(
    outer: np.ndarray, holes: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a simple polygon with disjoint polygonal holes, adding no vertices.

    Args:
        outer: (n, 2) boundary, either winding.
        holes: (m, 2) boundaries, either winding, strictly inside ``outer`` and apart from each other.

    Returns:
        points (P, 2) = outer then holes, each ring re-ordered counter-clockwise (outer) or
        clockwise (holes); triangles (T, 3) indices into points, counter-clockwise. Every
        polygon edge is an edge of exactly one triangle.
    """
    rings = [_wound(outer, counter_clockwise=True)] + [_wound(h, counter_clockwise=False) for h in holes]
    points = np.concatenate(rings)
    polygon = list(range(len(outer)))
    starts = np.cumsum([len(outer)] + [len(h) for h in holes])
    pending = [list(range(starts[k], starts[k + 1])) for k in range(len(holes))]
    pending.sort(key=lambda ring: -points[ring, 0].max())
    while pending:
        hole = pending.pop(0)
        polygon = _bridge_hole(points, polygon, hole, pending)
    return points, np.array(_clip_ears(points, polygon), dtype=np.int64).reshape(-1, 3)


def _wound(ring, counter_clockwise: bool) -> np.ndarray:
    """A polygon ring (n, 2) in the asked winding (shoelace sign)."""
    ring = np.asarray(ring, dtype=np.float64)
    x, y = ring[:, 0], ring[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return ring if (area > 0.0) == counter_clockwise else ring[::-1].copy()


def _cross(a: np.ndarray, b: np.ndarray):
    """z of the cross product of 2-vectors a and b (or of their (k, 2) rows, broadcast)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _crosses_any(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the closed segment pq shares a point with any closed segment a[i] b[i] ((k, 2) each) other than a
    common endpoint; a segment with an endpoint at p or q is not counted."""
    shared = (a == p).all(axis=1) | (a == q).all(axis=1) | (b == p).all(axis=1) | (b == q).all(axis=1)
    d1 = _cross(q - p, a - p)
    d2 = _cross(q - p, b - p)
    d3 = _cross(b - a, p - a)
    d4 = _cross(b - a, q - a)
    proper = ((d1 > 0) != (d2 > 0)) & ((d3 > 0) != (d4 > 0)) & (d1 != 0) & (d2 != 0) & (d3 != 0) & (d4 != 0)
    touching = ((d1 == 0) & _on_segment(a, p, q)) | ((d2 == 0) & _on_segment(b, p, q)) \
        | ((d3 == 0) & _on_segment(p, a, b)) | ((d4 == 0) & _on_segment(q, a, b))
    return bool((~shared & (proper | touching)).any())


def _on_segment(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether x lies in the bounding box of segment ab (any of them broadcast over (k, 2) rows)."""
    x, a, b = np.broadcast_arrays(x, a, b)
    return ((np.minimum(a[..., 0], b[..., 0]) <= x[..., 0]) & (x[..., 0] <= np.maximum(a[..., 0], b[..., 0]))
            & (np.minimum(a[..., 1], b[..., 1]) <= x[..., 1]) & (x[..., 1] <= np.maximum(a[..., 1], b[..., 1])))


def _in_sector(points: np.ndarray, polygon: list[int], k: int, target: np.ndarray) -> bool:
    """Whether the direction from polygon vertex k to ``target`` enters the polygon's interior."""
    cur = points[polygon[k]]
    a = points[polygon[(k + 1) % len(polygon)]] - cur
    b = points[polygon[k - 1]] - cur
    d = target - cur
    if _cross(a, b) > 0.0:
        return _cross(a, d) > 0.0 and _cross(d, b) > 0.0
    return _cross(a, d) > 0.0 or _cross(d, b) > 0.0


def _bridge_hole(points: np.ndarray, polygon: list[int], hole: list[int], others: list[list[int]]) -> list[int]:
    """Splice ``hole`` into ``polygon`` through the shortest segment that crosses no edge."""
    edges = [(polygon[i], polygon[(i + 1) % len(polygon)]) for i in range(len(polygon))]
    for ring in [hole] + others:
        edges += [(ring[i], ring[(i + 1) % len(ring)]) for i in range(len(ring))]
    ends = points[np.array(edges)]  # (edges, 2 ends, 2)
    candidates = sorted(
        (float(np.sum((points[polygon[k]] - points[m]) ** 2)), j, k)
        for j, m in enumerate(hole) for k in range(len(polygon))
    )
    for _, j, k in candidates:
        m, v = points[hole[j]], points[polygon[k]]
        if not _in_sector(points, polygon, k, m):
            continue
        if _crosses_any(m, v, ends[:, 0], ends[:, 1]):
            continue
        ring = hole[j:] + hole[:j]
        return polygon[:k + 1] + ring + [hole[j], polygon[k]] + polygon[k + 1:]
    raise RuntimeError("no visible vertex to bridge a hole; holes must lie strictly inside and apart")


def _clip_ears(points: np.ndarray, polygon: list[int]) -> list[tuple[int, int, int]]:
    """Ear clipping of a counter-clockwise (weakly) simple polygon; picks the fattest ear first (the first of equals
    in the polygon's order). An ear's quality is kept between clips unless its triangle changed (the clipped
    vertex's neighbours) or it was no ear for a vertex inside while being convex (the clipped vertex may have been
    that one): a clip only removes a vertex, so an ear stays an ear with the same quality and a reflex vertex with
    the same neighbours stays reflex."""
    polygon = list(polygon)
    triangles = []
    ring = points[polygon]
    quality = [_ear_quality(ring, i) for i in range(len(polygon))]
    while len(polygon) > 3:
        best = int(np.argmax(quality))
        if quality[best] < 0.0:
            raise RuntimeError("ear clipping found no ear; the polygon is not simple")
        n = len(polygon)
        triangles.append((polygon[best - 1], polygon[best], polygon[(best + 1) % n]))
        del polygon[best], quality[best]
        ring = points[polygon]
        n -= 1
        for i in range(n):
            neighbour = i == (best - 1) % n or i == best % n
            if neighbour or (quality[i] < 0.0 and _convex(ring, i)):
                quality[i] = _ear_quality(ring, i)
    triangles.append(tuple(polygon))
    return triangles


def _convex(ring: np.ndarray, i: int) -> bool:
    """Whether the polygon ``ring`` (n, 2) turns left (strictly) at vertex i."""
    a, b, c = ring[i - 1], ring[i], ring[(i + 1) % len(ring)]
    return _cross(b - a, c - b) > 0.0


def _ear_quality(ring: np.ndarray, i: int) -> float:
    """Smallest angle [rad] of the ear at vertex i of the polygon ``ring`` (n, 2), or −1 if it is not an ear:
    convex there, and no other vertex (one at a corner's position aside) in the closed triangle."""
    if not _convex(ring, i):
        return -1.0
    a, b, c = ring[i - 1], ring[i], ring[(i + 1) % len(ring)]
    at_corner = (ring == a).all(axis=1) | (ring == b).all(axis=1) | (ring == c).all(axis=1)
    inside = ~at_corner
    for p, q in ((a, b), (b, c), (c, a)):
        edge = q - p
        inside &= edge[0] * (ring[:, 1] - p[1]) - edge[1] * (ring[:, 0] - p[0]) >= 0.0
    if inside.any():
        return -1.0
    return min(_angle(a, b, c), _angle(b, c, a), _angle(c, a, b))


def _angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Angle [rad] at vertex a of triangle abc."""
    u, w = b - a, c - a
    return math.atan2(abs(_cross(u, w)), float(np.dot(u, w)))
