"""The calibration field (``scene.name = "calibration"``, the default) of the seed paper (§4.2): flat ground, two
perpendicular roads and 24 closed gable-roof houses of every ridge orientation, several eave heights and roof
pitches."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyproj

from flightsim.core.registry import register
from flightsim.core.settings import Settings
from flightsim.scenes.scene import (CLASS_BUILDING, CLASS_GROUND, CLASS_ROAD, DEFAULT_CRS, DEFAULT_ORIGIN, PlaneInfo,
                                    Scene, check_half_extent, parse_crs, plane_info)
from flightsim.scenes.settings import ScenePart
from flightsim.scenes.triangulate import triangulate_polygon_with_holes

ROAD_WIDTH_M = 10.0
"""Width of each calibration-field road [m]."""

BLOCK_MARGIN_M = 10.0
"""Ground kept between the calibration block's outermost wall and the scene edge [m]."""


@dataclass
class CalibrationSettings(Settings):
    """The calibration field (no settings of its own: its ground grows with the flight)."""


@register("scene", "calibration")
class CalibrationScene(ScenePart):
    """The calibration field of ``[scene]``, its ground sized to the flight (at least the houses' block)."""

    settings = CalibrationSettings
    sized = True

    def build(self, half_extent_m: float, seed: int) -> Scene:
        half = max(half_extent_m, calibration_min_half_extent() + self.s.margin_m)
        return calibration_scene(half, self.s.origin, self.s.crs)


@dataclass(frozen=True)
class GableHouse:
    """A closed gable-roof house: rectangular footprint, two equal roof faces meeting at a ridge.

    Attributes:
        center: (x, y) local centre of the footprint [m].
        ridge_azimuth_deg: azimuth of the ridge line, clockwise from grid north, in [0, 180) [deg].
        length_m: footprint side along the ridge [m].
        width_m: footprint side across the ridge [m].
        eave_m: height of the wall tops (eaves) above the ground [m].
        pitch_deg: roof pitch [deg].
    """

    center: tuple[float, float]
    ridge_azimuth_deg: float
    length_m: float
    width_m: float
    eave_m: float
    pitch_deg: float

    @property
    def ridge_m(self) -> float:
        """Ridge height above the ground [m]."""
        return self.eave_m + 0.5 * self.width_m * math.tan(math.radians(self.pitch_deg))

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal unit vectors (E, N) along the ridge (u) and 90° clockwise from it (v)."""
        a = math.radians(self.ridge_azimuth_deg)
        return np.array([math.sin(a), math.cos(a)]), np.array([math.cos(a), -math.sin(a)])

    def footprint(self) -> np.ndarray:
        """(4, 2) footprint corners, clockwise seen from above [m]."""
        u, v = self.axes()
        c = np.asarray(self.center, dtype=np.float64)
        hl, hw = 0.5 * self.length_m, 0.5 * self.width_m
        return np.array([c - hl * u - hw * v, c + hl * u - hw * v, c + hl * u + hw * v, c - hl * u + hw * v])


_BLOCK_COLUMNS_M = (30.0, 78.0, 126.0)
_BLOCK_ROWS_M = (42.0, 114.0)
_QUADRANT_SIGNS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))
_PITCHES_DEG = (15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0)
_EAVES_M = (6.0, 8.5, 11.0, 14.0, 17.0, 20.0, 22.5, 25.0)
_LENGTHS_M = (20.0, 25.0, 30.0, 35.0, 40.0)
_WIDTHS_M = (10.0, 12.0, 14.0, 16.0, 18.0)


def calibration_houses() -> list[GableHouse]:
    """The 24 houses of the calibration field, 6 per quadrant between the roads.

    Ridge azimuths run through 0°, 15°, …, 165° twice (house i has (7·i mod 12)·15°), so the
    roof faces slope towards every multiple of 15°; pitches cycle through 15°…45°, eave heights
    through 6…25 m, footprints through 20…40 m × 10…18 m, with cycle lengths that are pairwise
    coprime with 12 so that orientations, pitches and heights mix.
    """
    houses = []
    for i in range(24):
        sx, sy = _QUADRANT_SIGNS[i // 6]
        cell = i % 6
        houses.append(GableHouse(
            center=(sx * _BLOCK_COLUMNS_M[cell % 3], sy * _BLOCK_ROWS_M[cell // 3]),
            ridge_azimuth_deg=15.0 * ((7 * i) % 12),
            length_m=_LENGTHS_M[i % 5],
            width_m=_WIDTHS_M[(2 * i + 1 + i // 5) % 5],
            eave_m=_EAVES_M[(3 * i) % 8],
            pitch_deg=_PITCHES_DEG[i % 7],
        ))
    return houses


def calibration_min_half_extent() -> float:
    """Smallest half side [m] of the calibration field: the house block plus a margin."""
    reach = max(np.abs(h.footprint()).max() for h in calibration_houses())
    return math.ceil(reach) + BLOCK_MARGIN_M


class _MeshBuilder:
    """Accumulates labelled polygons into vertex/triangle arrays."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.n_vertices = 0
        self.triangles: list[np.ndarray] = []
        self.plane_id: list[int] = []
        self.planes: list[PlaneInfo] = []

    def add_vertices(self, points: np.ndarray) -> np.ndarray:
        """Append (n, 3) points; return their indices."""
        points = np.asarray(points, dtype=np.float64)
        self.vertices.append(points)
        index = np.arange(self.n_vertices, self.n_vertices + len(points))
        self.n_vertices += len(points)
        return index

    def add_plane(self, kind: str, classification: int, normal, point, building: int = -1) -> int:
        """Register a plane; return its id."""
        plane_id = len(self.planes)
        self.planes.append(plane_info(plane_id, kind, classification, normal, point, building))
        return plane_id

    def add_triangles(self, triangles, plane_id: int) -> None:
        """Append triangles (global vertex indices) of one plane."""
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.triangles.append(triangles)
        self.plane_id.extend([plane_id] * len(triangles))

    def scene(self, name: str, crs: pyproj.CRS, origin, ground_z: float) -> Scene:
        plane_id = np.asarray(self.plane_id, dtype=np.int32)
        classes = np.array([p.classification for p in self.planes], dtype=np.uint8)
        return Scene(
            name=name, crs=crs, origin=origin,
            vertices=np.concatenate(self.vertices),
            triangles=np.concatenate(self.triangles),
            plane_id=plane_id,
            classification=classes[plane_id],
            planes=self.planes,
            ground_z=ground_z,
        )


def _add_house(mesh: _MeshBuilder, house: GableHouse, building: int) -> None:
    """A closed house: 2 roof faces, 2 eave walls, 2 pentagonal gable ends, 1 floor.

    The 10 corners are shared by all faces, so every edge belongs to exactly two triangles;
    every face is wound so that its normal points out of the (convex) solid.
    """
    u, _ = house.axes()
    foot = house.footprint()
    c = np.asarray(house.center, dtype=np.float64)
    ridge = np.array([c - 0.5 * house.length_m * u, c + 0.5 * house.length_m * u])
    corners = np.vstack([
        np.column_stack([foot, np.zeros(4)]),                   # 0-3: floor corners
        np.column_stack([foot, np.full(4, house.eave_m)]),      # 4-7: eave corners above them
        np.column_stack([ridge, np.full(2, house.ridge_m)]),    # 8-9: ridge ends
    ])
    first = mesh.add_vertices(corners)[0]
    inside = np.array([c[0], c[1], 0.5 * house.eave_m])
    faces = (
        ("roof", (4, 5, 9, 8)),
        ("roof", (7, 6, 9, 8)),
        ("wall", (0, 1, 5, 4)),
        ("wall", (3, 2, 6, 7)),
        ("wall", (0, 3, 7, 8, 4)),  # gable ends: pentagons up to the ridge
        ("wall", (1, 2, 6, 9, 5)),
        ("surface", (0, 1, 2, 3)),  # floor
    )
    for kind, polygon in faces:
        pts = corners[list(polygon)]
        normal = np.cross(pts[1] - pts[0], pts[2] - pts[0])
        if np.dot(normal, pts.mean(axis=0) - inside) < 0.0:
            polygon, normal = polygon[::-1], -normal
        plane = mesh.add_plane(kind, CLASS_BUILDING, normal, pts[0], building)
        fan = [(polygon[0], polygon[k], polygon[k + 1]) for k in range(1, len(polygon) - 1)]
        mesh.add_triangles(first + np.asarray(fan), plane)


def calibration_scene(half_extent_m: float, origin=DEFAULT_ORIGIN, crs=DEFAULT_CRS) -> Scene:
    """The calibration field of the seed paper (§4.2), centred on local (0, 0).

    Flat ground at z = 0 (plane 0, class 2) with a square half side ``half_extent_m`` [m]; an
    E–W road (plane 1) and a N–S road (plane 2), 10 m wide, class 11, flush with the ground and
    crossing at (0, 0) (the crossing belongs to the E–W road); 24 closed gable-roof houses
    (:func:`calibration_houses`) in the four ~145 m quadrants of the central 300 m × 300 m block.
    Each house contributes 7 planes (class 6): two "roof" faces, four "wall" faces (two
    rectangular eave walls, two pentagonal gable ends) and its floor ("surface", facing down).
    Ground, roads and floors tile the square exactly: the ground is triangulated around the
    roads and the house footprints, sharing their corners, so no triangles overlap.
    """
    h = check_half_extent(half_extent_m, calibration_min_half_extent())
    houses = calibration_houses()
    mesh = _MeshBuilder()
    up = (0.0, 0.0, 1.0)
    ground = mesh.add_plane("ground", CLASS_GROUND, up, (0.0, 0.0, 0.0))
    road_ew = mesh.add_plane("road", CLASS_ROAD, up, (0.0, 0.0, 0.0))
    road_ns = mesh.add_plane("road", CLASS_ROAD, up, (0.0, 0.0, 0.0))
    w = 0.5 * ROAD_WIDTH_M
    for x0, x1 in ((-h, -w), (-w, w), (w, h)):
        _add_rectangle(mesh, x0, -w, x1, w, road_ew)
    _add_rectangle(mesh, -w, w, w, h, road_ns)
    _add_rectangle(mesh, -w, -h, w, -w, road_ns)
    for sx, sy in _QUADRANT_SIGNS:
        xs = sorted((sx * w, sx * h))
        ys = sorted((sy * w, sy * h))
        outer = np.array([[xs[0], ys[0]], [xs[1], ys[0]], [xs[1], ys[1]], [xs[0], ys[1]]])
        holes = [
            house.footprint() for house in houses
            if np.sign(house.center[0]) == sx and np.sign(house.center[1]) == sy
        ]
        points, triangles = triangulate_polygon_with_holes(outer, holes)
        index = mesh.add_vertices(np.column_stack([points, np.zeros(len(points))]))
        mesh.add_triangles(index[triangles], ground)
    for building, house in enumerate(houses):
        _add_house(mesh, house, building)
    return mesh.scene("calibration", parse_crs(crs), origin, ground_z=0.0)


def _add_rectangle(mesh: _MeshBuilder, x0: float, y0: float, x1: float, y1: float, plane: int) -> None:
    """An axis-aligned rectangle at z = 0, facing up, as two triangles."""
    index = mesh.add_vertices([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    mesh.add_triangles([index[[0, 1, 2]], index[[0, 2, 3]]], plane)
