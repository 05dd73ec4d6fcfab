"""Scene meshes: triangles labelled by plane id and ASPRS class, in a local frame.

A :class:`Scene` holds a triangle mesh in *local* coordinates [m] (world − origin, SPEC §2),
so that the kernels can use float32 without losing precision. Every triangle belongs to one
:class:`PlaneInfo` (a planar face: ground, road, roof, wall) and carries its ASPRS class, and may carry
its own Lambertian reflectance.

Scene builders:

- :func:`plane_scene`: one square plane, horizontal or sloped (the seed paper's altitude study).
- :func:`calibration_scene`: the calibration field of the seed paper (§4.2): flat ground, two
  perpendicular roads and 24 closed gable-roof houses of every ridge orientation, several
  eave heights and roof pitches.

Real meshes are read by :mod:`flightsim.scenes.meshio`.
"""
from __future__ import annotations

import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import pyproj
from pyproj.enums import WktVersion

from flightsim.core.errors import InputError
from flightsim.scenes.height_grid import HeightGrid

DEFAULT_ORIGIN: tuple[float, float, float] = (409000.0, 3393000.0, 450.0)
DEFAULT_CRS = "EPSG:32648"

CLASS_UNCLASSIFIED = 1
CLASS_GROUND = 2
CLASS_BUILDING = 6
CLASS_ROAD = 11

PLANE_KINDS = ("ground", "road", "roof", "wall", "surface")

ROAD_WIDTH_M = 10.0
"""Width of each calibration-field road [m]."""

BLOCK_MARGIN_M = 10.0
"""Ground kept between the calibration block's outermost wall and the scene edge [m]."""


@dataclass(frozen=True)
class PlaneInfo:
    """One planar face of a scene.

    Attributes:
        id: index of this plane in ``Scene.planes``.
        kind: "ground", "road", "roof", "wall" or "surface" (any other face: a building floor,
            a plane of a loaded mesh that is not known to be ground, road, roof or wall).
        classification: ASPRS class (2 ground, 6 building, 11 road surface, 1 unclassified).
        normal: (3,) unit normal, local ENU, pointing up for ground, roads and roofs and out of
            the solid for walls and floors.
        point: (3,) a point on the plane, local [m].
        pitch_deg: angle between the plane and the horizontal, in [0, 90] [deg].
        azimuth_deg: azimuth of the horizontal part of the normal (the down-slope direction of
            a roof or slope, the facing direction of a wall), clockwise from grid north, in
            [0, 360) [deg]; NaN for a horizontal plane.
        building: index of the building the plane belongs to, -1 if none.
    """

    id: int
    kind: str
    classification: int
    normal: np.ndarray
    point: np.ndarray
    pitch_deg: float
    azimuth_deg: float
    building: int = -1


def plane_info(
    plane_id: int, kind: str, classification: int, normal, point, building: int = -1
) -> PlaneInfo:
    """Build a :class:`PlaneInfo`, deriving unit normal, pitch and azimuth from ``normal``."""
    if kind not in PLANE_KINDS:
        raise InputError("scene.plane.kind", kind, f"one of {', '.join(PLANE_KINDS)}")
    n = np.asarray(normal, dtype=np.float64)
    length = np.linalg.norm(n)
    if n.shape != (3,) or not (np.isfinite(length) and length > 0.0):
        raise InputError("scene.plane.normal", normal, "a finite non-zero 3-vector")
    n = n / length
    pitch, azimuth = pitch_azimuth_deg(n)
    return PlaneInfo(
        id=int(plane_id),
        kind=kind,
        classification=int(classification),
        normal=n,
        point=np.asarray(point, dtype=np.float64).copy(),
        pitch_deg=pitch,
        azimuth_deg=azimuth,
        building=int(building),
    )


def pitch_azimuth_deg(normal: np.ndarray, horizontal_tol: float = 1e-12) -> tuple[float, float]:
    """Pitch [deg] in [0, 90] and azimuth [deg] in [0, 360) of a plane's unit normal.

    The azimuth is that of the horizontal part of the normal, clockwise from grid north: the
    down-slope direction of a plane whose normal points up, the facing direction of a wall.
    NaN when the plane is horizontal (horizontal part below ``horizontal_tol``).
    """
    nx, ny, nz = (float(c) for c in normal)
    horizontal = math.hypot(nx, ny)
    pitch = math.degrees(math.atan2(horizontal, abs(nz)))
    if horizontal < horizontal_tol:
        return pitch, float("nan")
    return pitch, math.degrees(math.atan2(nx, ny)) % 360.0


@dataclass
class Scene:
    """A labelled triangle mesh in local coordinates.

    Attributes:
        name: short name ("calibration", "plane", a file stem).
        crs: the projected CRS of the world coordinates (metres).
        origin: (3,) float64 world E, N, H [m] of the local origin; local = world − origin.
        vertices: (V, 3) float64 local coordinates [m].
        triangles: (T, 3) int32 vertex indices, wound counter-clockwise seen from the side the
            normal points to (outwards).
        plane_id: (T,) int32 index into ``planes`` of each triangle.
        classification: (T,) uint8 ASPRS class of each triangle.
        planes: one :class:`PlaneInfo` per plane id, ``planes[i].id == i``.
        ground_z: local height [m] that flight altitudes are measured from.
        dropped_degenerate: zero-area triangles dropped when the mesh was read (0 if built).
        planar: whether each plane id labels a planar face (False: the ids only label parts of a
            curved surface, e.g. a terrain read with ``scene.planes = "none"``, and a plane fit
            through a part's points measures its curvature, not the points' error).
        reflectance: (T,) float32 Lambertian albedo ρ of each triangle, in (0, 1] (a land-cover raster's,
            :mod:`flightsim.scenes.landcover`), read by the photon and waveform detectors; None: every
            face has the run's configured value (``photon.reflectance``, ``waveform.reflectance``).
    """

    name: str
    crs: pyproj.CRS
    origin: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    plane_id: np.ndarray
    classification: np.ndarray
    planes: list[PlaneInfo]
    ground_z: float
    dropped_degenerate: int = field(default=0)
    planar: bool = field(default=True)
    reflectance: np.ndarray | None = field(default=None, repr=False)
    _height_grid: HeightGrid | None = field(default=None, init=False, repr=False, compare=False)
    _bounds: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)
    _boundaries: Future | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.origin = _finite_vector3(self.origin, "scene.origin")
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        triangles = np.asarray(self.triangles)
        if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.shape[0] < 1:
            raise InputError("scene", f"triangles of shape {triangles.shape}", "a mesh with at least one triangle")
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError("scene", f"vertices of shape {self.vertices.shape}", "(V, 3) vertex coordinates")
        if not np.all(np.isfinite(self.vertices)):
            raise InputError("scene", "non-finite vertex coordinates", "finite vertex coordinates [m]")
        if triangles.min() < 0 or triangles.max() >= len(self.vertices):
            raise InputError(
                "scene", f"vertex indices {triangles.min()}..{triangles.max()}",
                f"indices in [0, {len(self.vertices) - 1}]",
            )
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.plane_id = np.ascontiguousarray(self.plane_id, dtype=np.int32)
        self.classification = np.ascontiguousarray(self.classification, dtype=np.uint8)
        n_tri = len(self.triangles)
        if self.plane_id.shape != (n_tri,) or self.classification.shape != (n_tri,):
            raise InputError("scene", "per-triangle labels of the wrong length", f"{n_tri} plane ids and classes")
        if any(p.id != i for i, p in enumerate(self.planes)):
            raise InputError("scene", "plane list", "planes[i].id == i for every plane")
        if self.plane_id.min() < 0 or self.plane_id.max() >= len(self.planes):
            raise InputError(
                "scene", f"plane ids {self.plane_id.min()}..{self.plane_id.max()}",
                f"plane ids in [0, {len(self.planes) - 1}]",
            )
        if self.reflectance is not None:
            self.reflectance = _albedos(self.reflectance, n_tri)
        if not isinstance(self.crs, pyproj.CRS):
            self.crs = parse_crs(self.crs)
        self.ground_z = float(self.ground_z)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners (3,) of the local bounding box [m] (found once, column by column: a
        reduction along axis 0 of an (N, 3) array runs ~9× slower, 0.24 s for 5e6 vertices)."""
        if self._bounds is None:
            columns = self.vertices.T
            self._bounds = (np.array([c.min() for c in columns]), np.array([c.max() for c in columns]))
        return self._bounds[0].copy(), self._bounds[1].copy()

    def boundary_segments(self) -> np.ndarray:
        """(S, 2, 3) local end points [m] of the edges that bound a plane
        (:func:`flightsim.scenes.edges.boundary_segments`), found once (or taken from
        :meth:`prefetch_boundary_segments`'s thread, waiting for it if need be)."""
        if self._boundaries is None:
            from flightsim.scenes.edges import boundary_segments  # edges imports this module

            self._boundaries = Future()
            self._boundaries.set_result(boundary_segments(self))
        return self._boundaries.result()

    def prefetch_boundary_segments(self) -> None:
        """Start finding :meth:`boundary_segments` in a background thread: its NumPy sorts and passes release
        the GIL, so the run's planning and BVH builds go on meanwhile (an 8e6-triangle DEM's boundaries take
        seconds)."""
        if self._boundaries is None:
            from flightsim.scenes.edges import boundary_segments

            pool = ThreadPoolExecutor(1, thread_name_prefix="boundaries")
            self._boundaries = pool.submit(boundary_segments, self)
            pool.shutdown(wait=False)  # the thread ends with its one task

    def terrain_top(self, xmin: float, ymin: float, xmax: float, ymax: float) -> float:
        """Highest local z [m] of the scene's surface over a closed local rectangle; −inf if none.

        Exact for planar triangles: the highest point of a triangle over the rectangle is a corner of
        their intersection (a triangle vertex inside the rectangle, a triangle edge crossing a rectangle
        side, or a rectangle corner inside the triangle), so a large sloped triangle counts only as high
        as it rises over the rectangle, not its whole height.
        """
        return float(self.terrain_tops([[xmin, ymin, xmax, ymax]])[0])

    def terrain_tops(self, rectangles) -> np.ndarray:
        """:meth:`terrain_top` of each row (xmin, ymin, xmax, ymax) of ``rectangles`` (R, 4) [m], from the
        triangles of the few cells of :attr:`height_grid` that can reach the top."""
        return self.height_grid.tops(rectangles)

    @property
    def height_grid(self) -> HeightGrid:
        """The scene's :class:`~flightsim.scenes.height_grid.HeightGrid`, built on first use (with NumPy,
        unless :meth:`build_height_grid` built it on a device first)."""
        if self._height_grid is None:
            self._height_grid = HeightGrid.build(self.vertices, self.triangles)
        return self._height_grid

    def build_height_grid(self, device: str) -> HeightGrid:
        """:attr:`height_grid`, built on the Warp ``device`` ("cpu", "cuda", "cuda:N") if not built yet."""
        if self._height_grid is None:
            self._height_grid = HeightGrid.build(self.vertices, self.triangles, device)
        return self._height_grid

    def adopt_height_grid(self, arrays) -> None:
        """Use the stored grid ``arrays`` (:meth:`HeightGrid.arrays` of this mesh) as :attr:`height_grid`;
        ValueError when they cannot be this mesh's grid."""
        self._height_grid = HeightGrid.from_arrays(arrays, self.vertices, self.triangles)

    def world_to_local(self, xyz) -> np.ndarray:
        """World coordinates (..., 3) [m] → local float64 (..., 3) [m]."""
        return np.asarray(xyz, dtype=np.float64) - self.origin

    def local_to_world(self, xyz) -> np.ndarray:
        """Local coordinates (..., 3) [m] → world float64 (..., 3) [m]."""
        return np.asarray(xyz, dtype=np.float64) + self.origin


def parse_crs(value, field: str = "scene.crs") -> pyproj.CRS:
    """A projected CRS in metres from anything pyproj accepts ("EPSG:32648", WKT, a CRS)."""
    allowed = "a projected CRS known to pyproj with axes in metres, e.g. 'EPSG:32648'"
    if value is None or (isinstance(value, str) and not value.strip()):
        raise InputError(field, value, allowed)
    try:
        crs = pyproj.CRS.from_user_input(value)
    except (pyproj.exceptions.CRSError, TypeError, ValueError):
        raise InputError(field, value, allowed) from None
    if not crs.is_projected:
        raise InputError(field, value, allowed + " (this one is not projected)")
    horizontal = crs.axis_info[:2]
    if len(horizontal) < 2 or any(ax.unit_name not in ("metre", "meter") for ax in horizontal):
        raise InputError(field, value, allowed + " (this one is not in metres)")
    try:
        has_wkt1 = crs.to_wkt(WktVersion.WKT1_GDAL) is not None
    except pyproj.exceptions.CRSError:
        has_wkt1 = False
    if not has_wkt1:
        raise InputError(field, value, allowed + " (this one has no OGC WKT1 form, which LAS 1.4 tiles need)")
    return crs


def required_half_extent(
    altitude_m: float, cone_half_angle_rad: float, along_track_half_m: float, margin_m: float = 50.0
) -> float:
    """Half side [m] of a square, centred on the line's midpoint, that holds the whole scan.

    The scan circle has radius ``altitude_m·tan(θ)``; its centre moves ±``along_track_half_m``
    along the line, whatever the heading, so the swept area fits in a square of half side
    along_track_half + radius (+ ``margin_m``).
    """
    if not (math.isfinite(altitude_m) and altitude_m > 0.0):
        raise InputError("altitude_m", altitude_m, "a finite altitude > 0 m")
    if not (math.isfinite(cone_half_angle_rad) and 0.0 <= cone_half_angle_rad < math.pi / 2):
        raise InputError("cone_half_angle_rad", cone_half_angle_rad, "an angle in [0, π/2) rad")
    if not (math.isfinite(along_track_half_m) and along_track_half_m >= 0.0):
        raise InputError("along_track_half_m", along_track_half_m, "a finite length ≥ 0 m")
    if not (math.isfinite(margin_m) and margin_m >= 0.0):
        raise InputError("margin_m", margin_m, "a finite length ≥ 0 m")
    return along_track_half_m + altitude_m * math.tan(cone_half_angle_rad) + margin_m


def plane_scene(
    half_extent_m: float,
    origin=DEFAULT_ORIGIN,
    crs=DEFAULT_CRS,
    slope: float = 0.0,
    slope_azimuth_deg: float = 0.0,
) -> Scene:
    """One square plane of half side ``half_extent_m`` [m] centred on local (0, 0, 0).

    ``slope`` is rise/run; the plane descends towards ``slope_azimuth_deg`` (clockwise from grid
    north), or rises towards it when negative: z = −slope·(x·sin a + y·cos a). Plane id 0,
    class 2 (ground); ground_z = 0 (the height at the centre).
    """
    _check_half_extent(half_extent_m, 0.0)
    if not (math.isfinite(slope) and abs(slope) <= 10.0):
        raise InputError("scene.slope", slope, "a rise/run in [-10, 10]")
    if not math.isfinite(slope_azimuth_deg):
        raise InputError("scene.slope_azimuth_deg", slope_azimuth_deg, "a finite azimuth [deg]")
    h = float(half_extent_m)
    az = math.radians(slope_azimuth_deg)
    down = np.array([math.sin(az), math.cos(az)])
    xy = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    z = -slope * (xy @ down)
    vertices = np.column_stack([xy, z])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    normal = np.array([slope * down[0], slope * down[1], 1.0])
    plane = plane_info(0, "ground", CLASS_GROUND, normal, (0.0, 0.0, 0.0))
    return Scene(
        name="plane",
        crs=parse_crs(crs),
        origin=origin,
        vertices=vertices,
        triangles=triangles,
        plane_id=np.zeros(2, dtype=np.int32),
        classification=np.full(2, CLASS_GROUND, dtype=np.uint8),
        planes=[plane],
        ground_z=0.0,
    )


# --------------------------------------------------------------------------------------------
# Calibration field
# --------------------------------------------------------------------------------------------

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
    h = _check_half_extent(half_extent_m, calibration_min_half_extent())
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


def _check_half_extent(half_extent_m: float, minimum: float) -> float:
    """``half_extent_m`` as a float, if it is finite and above ``minimum`` [m]."""
    allowed = f"a finite half side > {minimum:g} m"
    try:
        value = float(half_extent_m)
    except (TypeError, ValueError):
        raise InputError("scene.half_extent_m", half_extent_m, allowed) from None
    if not (math.isfinite(value) and value > minimum):
        raise InputError("scene.half_extent_m", half_extent_m, allowed)
    return value


def _albedos(value, n_tri: int) -> np.ndarray:
    """``value`` as (T,) float32 Lambertian albedos, each in (0, 1], else InputError naming scene.reflectance."""
    allowed = f"{n_tri} Lambertian albedos in (0, 1], one per triangle"
    try:
        given = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("scene.reflectance", value, allowed) from None
    if given.shape != (n_tri,):
        raise InputError("scene.reflectance", f"an array of shape {given.shape}", allowed)
    rho = np.ascontiguousarray(given, dtype=np.float32)
    bad = np.flatnonzero(~((rho > 0.0) & (rho <= 1.0)))  # NaN fails both
    if len(bad):
        raise InputError("scene.reflectance", f"{given[bad[0]]:g} at triangle {bad[0]}", allowed)
    return rho


def _finite_vector3(value, field: str) -> np.ndarray:
    try:
        vec = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(field, value, "three finite numbers (E, N, H) [m]") from None
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise InputError(field, value, "three finite numbers (E, N, H) [m]")
    return vec


# --------------------------------------------------------------------------------------------
# Polygon triangulation (ear clipping with holes bridged to the outer boundary)
# --------------------------------------------------------------------------------------------

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


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _segments_cross(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether closed segments pq and ab share a point other than a common endpoint."""
    shared = [x for x in (a, b) if np.array_equal(x, p) or np.array_equal(x, q)]
    if shared:
        return False
    d1 = _cross(q - p, a - p)
    d2 = _cross(q - p, b - p)
    d3 = _cross(b - a, p - a)
    d4 = _cross(b - a, q - a)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 != 0 and d2 != 0 and d3 != 0 and d4 != 0:
        return True
    return any(
        d == 0 and _on_segment(x, s0, s1)
        for d, x, s0, s1 in ((d1, a, p, q), (d2, b, p, q), (d3, p, a, b), (d4, q, a, b))
    )


def _on_segment(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    return bool(min(a[0], b[0]) <= x[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= x[1] <= max(a[1], b[1]))


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
    candidates = sorted(
        (float(np.sum((points[polygon[k]] - points[m]) ** 2)), j, k)
        for j, m in enumerate(hole) for k in range(len(polygon))
    )
    for _, j, k in candidates:
        m, v = points[hole[j]], points[polygon[k]]
        if not _in_sector(points, polygon, k, m):
            continue
        if any(_segments_cross(m, v, points[e0], points[e1]) for e0, e1 in edges):
            continue
        ring = hole[j:] + hole[:j]
        return polygon[:k + 1] + ring + [hole[j], polygon[k]] + polygon[k + 1:]
    raise RuntimeError("no visible vertex to bridge a hole; holes must lie strictly inside and apart")


def _clip_ears(points: np.ndarray, polygon: list[int]) -> list[tuple[int, int, int]]:
    """Ear clipping of a counter-clockwise (weakly) simple polygon; picks the fattest ear first."""
    polygon = list(polygon)
    triangles = []
    while len(polygon) > 3:
        best, best_quality = -1, -1.0
        for i in range(len(polygon)):
            quality = _ear_quality(points, polygon, i)
            if quality > best_quality:
                best, best_quality = i, quality
        if best < 0:
            raise RuntimeError("ear clipping found no ear; the polygon is not simple")
        n = len(polygon)
        triangles.append((polygon[best - 1], polygon[best], polygon[(best + 1) % n]))
        del polygon[best]
    triangles.append(tuple(polygon))
    return triangles


def _ear_quality(points: np.ndarray, polygon: list[int], i: int) -> float:
    """Smallest angle [rad] of the ear at polygon vertex i, or −1 if it is not an ear."""
    n = len(polygon)
    ia, ib, ic = polygon[i - 1], polygon[i], polygon[(i + 1) % n]
    a, b, c = points[ia], points[ib], points[ic]
    if _cross(b - a, c - b) <= 0.0:
        return -1.0
    corners = (a, b, c)
    for k in polygon:
        x = points[k]
        if any(np.array_equal(x, y) for y in corners):
            continue
        if _cross(b - a, x - a) >= 0.0 and _cross(c - b, x - b) >= 0.0 and _cross(a - c, x - c) >= 0.0:
            return -1.0
    return min(_angle(a, b, c), _angle(b, c, a), _angle(c, a, b))


def _angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Angle [rad] at vertex a of triangle abc."""
    u, w = b - a, c - a
    return math.atan2(abs(_cross(u, w)), float(np.dot(u, w)))
