"""Buildings on a terrain scene: an OBJ or PLY mesh (``scene.buildings``) in the DEM's CRS world
coordinates, merged into the DEM's mesh.

The mesh is read by :func:`flightsim.scenes.meshio.load_mesh` (its faces grouped into planes); every one
of its triangles becomes class 6 (building), each plane a "roof" (facing up, up to 80° steep), a
"wall" (steeper) or a "surface" (facing down: a floor); each connected part of the mesh is one building.
The scene stays curved (``planar`` False, as the DEM): a LAS run scores patches of the ground, and a
patch holding a building holds its roof and wall returns too. When the DEM carries per-triangle reflectance (a
land-cover raster), the building triangles get class 6's (:data:`flightsim.scenes.landcover.REFLECTANCE`);
without it they, like the ground, take the run's value. Every vertex must lie inside the DEM's horizontal
extent, else ``InputError("scene.buildings", ...)``.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from flightsim.core.errors import InputError
from flightsim.scenes.landcover import REFLECTANCE
from flightsim.scenes.meshio import load_mesh
from flightsim.scenes.scene import CLASS_BUILDING, Scene, plane_info

WALL_PITCH_DEG = 80.0  # building planes steeper than this are walls [deg]


def add_buildings(scene: Scene, path: str) -> Scene:
    """``scene`` with the building mesh at ``path`` added (planes after the scene's own)."""
    try:
        mesh = load_mesh(path, scene.crs, name=scene.name)
    except InputError as error:
        raise InputError("scene.buildings", path, error.allowed) from None
    vertices = mesh.local_to_world(mesh.vertices) - scene.origin
    _check_inside(scene, vertices, path)
    building = _parts(mesh.triangles, len(vertices))
    first = np.unique(mesh.plane_id, return_index=True)[1]
    offset = len(scene.planes)
    planes = [plane_info(offset + p.id, _kind(p.pitch_deg, p.normal), CLASS_BUILDING, p.normal,
                         p.point + mesh.origin - scene.origin, int(building[first[p.id]])) for p in mesh.planes]
    return Scene(name=scene.name, crs=scene.crs, origin=scene.origin,
                 vertices=np.concatenate([scene.vertices, vertices]),
                 triangles=np.concatenate([scene.triangles, mesh.triangles + len(scene.vertices)]),
                 plane_id=np.concatenate([scene.plane_id, mesh.plane_id + offset]),
                 classification=np.concatenate([scene.classification,
                                                np.full(len(mesh.triangles), CLASS_BUILDING, dtype=np.uint8)]),
                 planes=scene.planes + planes, ground_z=scene.ground_z, planar=scene.planar,
                 dropped_degenerate=scene.dropped_degenerate + mesh.dropped_degenerate,
                 reflectance=_reflectance(scene, len(mesh.triangles)))


def _reflectance(scene: Scene, n_building: int) -> np.ndarray | None:
    """The scene's per-triangle reflectance followed by class 6's for ``n_building`` triangles; None if it has none."""
    if scene.reflectance is None:
        return None
    return np.concatenate([scene.reflectance, np.full(n_building, REFLECTANCE[CLASS_BUILDING], dtype=np.float32)])


def _check_inside(scene: Scene, vertices: np.ndarray, path: str) -> None:
    """Refuse buildings with a vertex (local [m]) outside the scene's horizontal extent."""
    lo, hi = scene.bounds()
    outside = np.any((vertices[:, :2] < lo[:2] - 1e-6) | (vertices[:, :2] > hi[:2] + 1e-6), axis=1)
    if np.any(outside):
        east, north = vertices[np.argmax(outside), :2] + scene.origin[:2]
        (w, s), (e, n) = lo[:2] + scene.origin[:2], hi[:2] + scene.origin[:2]
        raise InputError("scene.buildings", path,
                         f"buildings inside the DEM's extent E {w:.2f}…{e:.2f}, N {s:.2f}…{n:.2f} m "
                         f"(a vertex lies at E {east:.2f}, N {north:.2f})")


def _parts(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(T,) index of the connected part (vertices shared through triangles) of each triangle."""
    a, b = triangles.ravel(), np.roll(triangles, 1, axis=1).ravel()
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1][triangles[:, 0]]


def _kind(pitch_deg: float, normal: np.ndarray) -> str:
    if pitch_deg > WALL_PITCH_DEG:
        return "wall"
    return "roof" if normal[2] > 0.0 else "surface"
