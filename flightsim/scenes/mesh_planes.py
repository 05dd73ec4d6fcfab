"""Mesh geometry for :func:`flightsim.scenes.meshio.load_mesh`: polygons fanned into triangles,
zero-area triangles found, faces grouped into planes, and each plane's :class:`PlaneInfo`.

Grouping (:func:`coplanar_planes`): faces are joined by edge connectivity and coplanarity (normal
angle ≤ COPLANAR_ANGLE_DEG, offset ≤ COPLANAR_OFFSET_M, every face against its plane's area-weighted
fit) without crossing a group (an OBJ group, or a PLY classification); a group's coplanar parts that
do not touch may be merged again.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from flightsim.scenes.mesh_format import kind_from_class
from flightsim.scenes.scene import CLASS_BUILDING, CLASS_GROUND, CLASS_ROAD, PlaneInfo, pitch_azimuth_deg, plane_info

COPLANAR_ANGLE_DEG = 1.0
"""Largest angle [deg] between the normals of two faces of one plane."""

COPLANAR_OFFSET_M = 0.05
"""Largest distance [m] of a face's corners from the plane it joins."""

DEGENERATE_SINE = 1e-9
"""A triangle is dropped when 2·area < DEGENERATE_SINE · (longest edge)²."""


def triangulate(corners: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons: face f has corners[offset_f : offset_f + sizes[f]] (sizes ≥ 3).

    Returns (T, 3) vertex indices, the triangles of each face together in face order, and the
    source face of each triangle.
    """
    fan = sizes - 2
    source = np.repeat(np.arange(len(sizes)), fan)
    first = np.r_[0, np.cumsum(sizes)[:-1]][source]
    j = np.arange(len(source)) - np.r_[0, np.cumsum(fan)[:-1]][source] + 1
    triangles = np.column_stack([corners[first], corners[first + j], corners[first + j + 1]])
    return triangles.astype(np.int64), source


def degenerate(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Mask of zero-area triangles (2·area < DEGENERATE_SINE · longest edge², or repeated corners)."""
    p0, p1, p2 = (vertices[triangles[:, k]] for k in range(3))
    e0, e1, e2 = p1 - p0, p2 - p1, p0 - p2
    longest = np.maximum(np.maximum(_norm_sq(e0), _norm_sq(e1)), _norm_sq(e2))
    twice_area_sq = _norm_sq(np.cross(e0, e2))
    return (twice_area_sq <= DEGENERATE_SINE**2 * longest * longest) | (longest == 0.0)


def _norm_sq(v: np.ndarray) -> np.ndarray:
    """Squared length of each row of (n, 3) ``v``."""
    return np.einsum("ij,ij->i", v, v)


def renumber(labels: np.ndarray) -> np.ndarray:
    """Labels → 0..P-1, in increasing label order."""
    _, index = np.unique(labels, return_inverse=True)
    return index.astype(np.int32)


def _triangle_geometry(vertices: np.ndarray, triangles: np.ndarray):
    p = vertices[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    twice_area = np.linalg.norm(cross, axis=1)
    return cross / twice_area[:, None], 0.5 * twice_area, p


def coplanar_planes(vertices: np.ndarray, triangles: np.ndarray, group: np.ndarray, merge_apart: bool) -> np.ndarray:
    """Plane id per triangle, in O(T log T) array operations.

    Vertices at the same position are welded first, so a triangle soup groups like a mesh. Two
    triangles of one group that share an edge are compatible when their normals are within
    COPLANAR_ANGLE_DEG and each one's corners lie within COPLANAR_OFFSET_M of the other's plane;
    the connected parts of compatible triangles are the first regions. A region is a plane when
    every triangle's normal is within COPLANAR_ANGLE_DEG of the region's area-weighted normal and
    every corner within COPLANAR_OFFSET_M of its plane through the area-weighted centroid; a region
    that is not (a curved surface) is cut in quarters at the mean of its triangles' centroids along
    its two axes of largest spread, and each quarter into its connected parts, until every region
    is a plane (every round handles only the regions that failed, so a mesh of T triangles takes
    about log₄ T rounds of O(T log T) work at most). With
    ``merge_apart``, planes of one group that do not touch (a ground split by roads) are merged
    when their normals and centroid offsets agree and their union is a plane.
    """
    normals, areas, corners = _triangle_geometry(vertices, triangles)
    _, weld = np.unique(np.round(vertices, 6), axis=0, return_inverse=True)
    a, b = _edge_pairs(weld.reshape(-1)[triangles])
    centroids = corners.mean(axis=1)
    keep = (group[a] == group[b]) & _same_plane(normals[a], centroids[a], normals[b], centroids[b], corners[a], corners[b])
    plane = _planar_regions(a[keep], b[keep], normals, areas, corners, centroids)
    if merge_apart:
        plane = _merge_coplanar(plane, group, normals, areas, corners, centroids)
    return _first_appearance_order(plane)


def _same_plane(n1, c1, n2, c2, corners1=None, corners2=None) -> np.ndarray:
    """Whether planes (unit normal n, point c) (m, 3) agree: normals within COPLANAR_ANGLE_DEG and each
    one's points (``corners`` (m, k, 3), else c) within COPLANAR_OFFSET_M of the other plane."""
    p1 = c1[:, None] if corners1 is None else corners1
    p2 = c2[:, None] if corners2 is None else corners2
    offset1 = np.abs(np.einsum("mkj,mj->mk", p1 - c2[:, None], n2)).max(axis=1)
    offset2 = np.abs(np.einsum("mkj,mj->mk", p2 - c1[:, None], n1)).max(axis=1)
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    return (np.einsum("mj,mj->m", n1, n2) >= cos_limit) & (offset1 <= COPLANAR_OFFSET_M) & (offset2 <= COPLANAR_OFFSET_M)


def _edge_pairs(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b), a < b, of triangles that share an (undirected) edge (every pair of a non-manifold edge)."""
    n_vertices = int(triangles.max()) + 1
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * n_vertices + edges[:, 1]
    order = np.argsort(key, kind="stable")
    owner = np.tile(np.arange(len(triangles)), 3)[order]
    starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    pairs = []
    for size in np.unique(sizes[sizes > 1]):  # 2 on a manifold mesh; more where several faces share an edge
        block = owner[starts[sizes == size][:, None] + np.arange(size)]
        i, j = np.triu_indices(size, 1)
        pairs.append(np.stack([block[:, i].reshape(-1), block[:, j].reshape(-1)]))
    a, b = np.concatenate(pairs, axis=1) if pairs else np.zeros((2, 0), dtype=np.int64)
    distinct = a != b
    return np.minimum(a, b)[distinct], np.maximum(a, b)[distinct]


def _connected(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Component label (0..C-1) of each of ``n`` nodes linked by edges (a, b)."""
    from scipy.sparse import coo_matrix  # here: a run whose scene needs no plane labelling does not load SciPy
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _area_weighted_planes(label, n_labels, normals, areas, centroids) -> tuple[np.ndarray, np.ndarray]:
    """Unit area-weighted normal (L, 3) and area-weighted centroid (L, 3) [m] of each label's
    triangles (zeros for a label without triangles)."""
    total = np.bincount(label, weights=areas, minlength=n_labels)
    normal = np.column_stack([np.bincount(label, weights=areas * normals[:, k], minlength=n_labels) for k in range(3)])
    centre = np.column_stack([np.bincount(label, weights=areas * centroids[:, k], minlength=n_labels) for k in range(3)])
    length = np.linalg.norm(normal, axis=1)
    return normal / np.where(length > 0.0, length, 1.0)[:, None], centre / np.where(total > 0.0, total, 1.0)[:, None]


def _planar(label, n_labels, normals, areas, corners, centroids) -> np.ndarray:
    """Per label: whether its triangles make a plane (module docstring's tolerances, against the
    label's area-weighted plane)."""
    normal, centre = _area_weighted_planes(label, n_labels, normals, areas, centroids)
    n = normal[label]
    height = np.einsum("tkj,tj->tk", corners, n) - np.einsum("lj,lj->l", normal, centre)[label][:, None]
    offset = np.maximum(np.maximum(np.abs(height[:, 0]), np.abs(height[:, 1])), np.abs(height[:, 2]))
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    fits = (np.einsum("tj,tj->t", normals, n) >= cos_limit) & (offset <= COPLANAR_OFFSET_M)
    return np.bincount(label, weights=~fits, minlength=n_labels) == 0


def _planar_regions(a, b, normals, areas, corners, centroids) -> np.ndarray:
    """Region label (0..R-1) per triangle: connected parts over edges (a, b), cut in quarters until
    planar (see :func:`coplanar_planes`)."""
    label = _connected(len(normals), a, b)
    todo, local, n_local = np.arange(len(normals)), label.copy(), int(label.max()) + 1
    while True:
        planar = _planar(local, n_local, normals[todo], areas[todo], corners[todo], centroids[todo])
        failed = np.flatnonzero(~planar[local])
        if not len(failed):
            return np.unique(label, return_inverse=True)[1].reshape(-1)
        position = np.full(len(todo), -1)
        position[failed] = np.arange(len(failed))
        a, b = position[a], position[b]  # edges as positions in the failed triangles
        a, b = a[(a >= 0) & (b >= 0)], b[(a >= 0) & (b >= 0)]
        todo, local = todo[failed], local[failed]
        part = _quarters(local, n_local, centroids[todo])
        a, b = a[part[a] == part[b]], b[part[a] == part[b]]
        local = _connected(len(todo), a, b)
        n_local = int(local.max()) + 1
        label[todo] = label.max() + 1 + local


def _quarters(label: np.ndarray, n_labels: int, points: np.ndarray) -> np.ndarray:
    """Part 4·label + 0…3 of each point (m, 3): below or above its label's mean along the label's
    two axes of largest spread, so that every label of two or more points is cut into two to four
    non-empty parts (by position parity where the first cut would leave one side empty)."""
    count = np.maximum(np.bincount(label, minlength=n_labels), 1)
    mean = np.column_stack([np.bincount(label, weights=points[:, k], minlength=n_labels) for k in range(3)]) / count[:, None]
    spread = np.column_stack([np.bincount(label, weights=(points[:, k] - mean[label, k]) ** 2, minlength=n_labels)
                              for k in range(3)])
    axes = np.argsort(spread, axis=1)[label]
    part = 4 * label
    for rank, weight in ((-1, 2), (-2, 1)):
        axis = axes[:, rank]
        side = (points[np.arange(len(points)), axis] > mean[label, axis]).astype(np.int64)
        one_sided = np.bincount(label, weights=side, minlength=n_labels) % count == 0
        fallback = np.arange(len(points)) % 2 if rank == -1 else 0
        part += weight * np.where(one_sided[label], fallback, side)
    return part


def _merge_coplanar(plane, group, normals, areas, corners, centroids) -> np.ndarray:
    """Merge planes of one group that agree (:func:`_same_plane` on their area-weighted planes) and
    whose union is a plane; candidates are the first plane of each neighbouring cell of a grid over
    (normal, offset) with cells of the tolerances' size."""
    n_regions = int(plane.max()) + 1
    normal, centre = _area_weighted_planes(plane, n_regions, normals, areas, centroids)
    region_group = np.zeros(n_regions, dtype=np.int64)
    region_group[plane] = group
    group_rank = np.unique(region_group, return_inverse=True)[1].reshape(-1)
    offset = np.einsum("rj,rj->r", normal, centre)
    chord = 2.0 * math.sin(math.radians(COPLANAR_ANGLE_DEG) / 2.0)
    d_cell = max(COPLANAR_OFFSET_M, float(np.ptp(offset)) * (4.0 / chord) ** 3 * (group_rank.max() + 1) / 2.0**58)
    cell = np.floor(np.column_stack([normal / chord, offset / d_cell])).astype(np.int64)
    cell -= cell.min(axis=0) - 1  # ≥ 1, so that every neighbour cell has a non-negative index
    stride = np.cumprod(np.r_[1, cell.max(axis=0)[::-1][:-1] + 2])[::-1]
    code = group_rank * int(np.prod(cell.max(axis=0) + 2)) + cell @ stride
    order = np.argsort(code, kind="stable")
    sorted_code = code[order]
    pairs = []
    for step in itertools.product((-1, 0, 1), repeat=4):
        target = code + np.asarray(step) @ stride
        at = np.minimum(np.searchsorted(sorted_code, target), n_regions - 1)
        found = np.flatnonzero(sorted_code[at] == target)
        pairs.append(np.stack([found, order[at[found]]]))
    a, b = np.concatenate(pairs, axis=1)
    link = (a != b) & _same_plane(normal[a], centre[a], normal[b], centre[b])
    merged = _connected(n_regions, a[link], b[link])
    n_merged = int(merged.max()) + 1
    accepted = _planar(merged[plane], n_merged, normals, areas, corners, centroids)
    return np.where(accepted[merged[plane]], merged[plane], n_merged + plane)


def _first_appearance_order(plane: np.ndarray) -> np.ndarray:
    """Renumber plane labels 0..P-1 in the order of their first triangle (file order)."""
    _, first, inverse = np.unique(plane, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int32)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first), dtype=np.int32)
    return rank[inverse.reshape(-1)]


def plane_infos(vertices, triangles, plane_of, classes) -> tuple[list[PlaneInfo], np.ndarray]:
    """PlaneInfo per plane (area-weighted normal and centroid, class covering most area)."""
    normals, areas, corners = _triangle_geometry(vertices, triangles)
    n_planes = int(plane_of.max()) + 1
    normal_sum = np.zeros((n_planes, 3))
    centroid_sum = np.zeros((n_planes, 3))
    np.add.at(normal_sum, plane_of, normals * areas[:, None])
    np.add.at(centroid_sum, plane_of, corners.mean(axis=1) * areas[:, None])
    area_sum = np.bincount(plane_of, weights=areas, minlength=n_planes)
    plane_classes = _majority(plane_of, classes.astype(np.int64), areas, n_planes).astype(np.uint8)
    largest = _majority(plane_of, np.arange(len(areas)), areas, n_planes)
    planes = []
    for k in range(n_planes):
        normal = normal_sum[k]
        if np.linalg.norm(normal) < 1e-9 * area_sum[k]:  # faces of opposite winding cancel
            normal = normals[largest[k]]
        if plane_classes[k] in (CLASS_GROUND, CLASS_ROAD) and normal[2] < 0.0:
            normal = -normal
        unit = normal / np.linalg.norm(normal)
        kind = _kind(int(plane_classes[k]), unit)
        planes.append(plane_info(k, kind, plane_classes[k], unit, centroid_sum[k] / area_sum[k]))
    return planes, plane_classes


def _majority(plane_of: np.ndarray, labels: np.ndarray, weights: np.ndarray, n_planes: int) -> np.ndarray:
    """Per plane, the label (≥ 0) with the largest summed weight (ties: the smallest label)."""
    span = int(labels.max()) + 1
    keys, inverse = np.unique(plane_of.astype(np.int64) * span + labels, return_inverse=True)
    totals = np.bincount(inverse.reshape(-1), weights=weights)
    plane, label = keys // span, keys % span
    order = np.lexsort((label, -totals, plane))
    first = np.r_[True, plane[order[1:]] != plane[order[:-1]]]
    best = np.empty(n_planes, dtype=np.int64)
    best[plane[order[first]]] = label[order[first]]
    return best


def _kind(classification: int, normal: np.ndarray) -> str:
    """Plane kind from its class and orientation: building faces steeper than 80° are walls."""
    if classification != CLASS_BUILDING:
        return kind_from_class(classification)
    pitch, _ = pitch_azimuth_deg(normal)
    if pitch >= 80.0:
        return "wall"
    return "roof" if normal[2] > 0.0 else "surface"
