"""Scene meshes: triangles labelled by plane id and ASPRS class, in a local frame.

A :class:`Scene` holds a triangle mesh in *local* coordinates [m] (world − origin, SPEC §2),
so that the kernels can use float32 without losing precision. Every triangle belongs to one
:class:`PlaneInfo` (a planar face: ground, road, roof, wall) and carries its ASPRS class, and may carry
its own Lambertian reflectance.

Each kind of scene is a part in its own module (``scene.name`` chooses it): the built-in plane
(:mod:`~flightsim.scenes.plane`), calibration field (:mod:`~flightsim.scenes.calibration`), lunar landing
zone (:mod:`~flightsim.scenes.lunar`), small bodies (:mod:`~flightsim.scenes.smallbody`) and the waveform
patent's bump (:mod:`~flightsim.scenes.footprint`); meshes (:mod:`~flightsim.scenes.mesh`) and height
grids (:mod:`~flightsim.scenes.dem`) read from files.
"""
from __future__ import annotations

import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyproj
from pyproj.enums import WktVersion

from flightsim.core.errors import InputError
from flightsim.scenes import edges
from flightsim.scenes.canopy import LEAF_CLASSES
from flightsim.scenes.height_grid import HeightGrid

DEFAULT_ORIGIN: tuple[float, float, float] = (409000.0, 3393000.0, 450.0)
DEFAULT_CRS = "EPSG:32648"

CLASS_UNCLASSIFIED = 1
CLASS_GROUND = 2
CLASS_BUILDING = 6
CLASS_ROAD = 11

PLANE_KINDS = ("ground", "road", "roof", "wall", "surface")


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
        canopy: leaf area in voxels over the mesh (:class:`flightsim.scenes.canopy.VoxelCanopy`, local frame),
            crossed by every ray before the surface it hits; None: no vegetation.
        cloud: the ALS point cloud the scene was made from (:class:`flightsim.scenes.pointcloud.PointCloud`,
            local frame), which large-footprint waveforms may sum directly; None: none.
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
    canopy: Any = field(default=None, repr=False)
    cloud: Any = field(default=None, repr=False)
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
            self._boundaries = Future()
            self._boundaries.set_result(edges.boundary_segments(self))
        return self._boundaries.result()

    def prefetch_boundary_segments(self) -> None:
        """Start finding :meth:`boundary_segments` in a background thread: its NumPy sorts and passes release
        the GIL, so the run's planning and BVH builds go on meanwhile (an 8e6-triangle DEM's boundaries take
        seconds)."""
        if self._boundaries is None:
            pool = ThreadPoolExecutor(1, thread_name_prefix="boundaries")
            self._boundaries = pool.submit(edges.boundary_segments, self)
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

    @property
    def height_grid_built(self) -> bool:
        """Whether :attr:`height_grid` is built (or adopted from the scene cache) already."""
        return self._height_grid is not None

    def build_height_grid(self, device: str) -> HeightGrid:
        """:attr:`height_grid`, built on the Warp ``device`` ("cpu", "cuda", "cuda:N") if not built yet."""
        if self._height_grid is None:
            self._height_grid = HeightGrid.build(self.vertices, self.triangles, device)
        return self._height_grid

    def adopt_height_grid(self, arrays) -> None:
        """Use the stored grid ``arrays`` (:meth:`HeightGrid.arrays` of this mesh) as :attr:`height_grid`;
        ValueError when they cannot be this mesh's grid."""
        self._height_grid = HeightGrid.from_arrays(arrays, self.vertices, self.triangles)

    def face_labels(self, plane_ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ASPRS class, plane id) int32 of each face a return can come from: the triangles' (their plane ids
        ``plane_ids``, default :attr:`plane_id`), then, with a canopy, its leaf faces (:data:`LEAF_CLASSES`, plane
        −1; :func:`kernels.canopy_returns.leaf_face` numbers them after the triangles)."""
        classes = self.classification.astype(np.int32)
        ids = np.asarray(self.plane_id if plane_ids is None else plane_ids, dtype=np.int32)
        if self.canopy is not None:
            classes = np.concatenate([classes, np.asarray(LEAF_CLASSES, dtype=np.int32)])
            ids = np.concatenate([ids, np.full(len(LEAF_CLASSES), -1, dtype=np.int32)])
        return classes, ids

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


def check_half_extent(half_extent_m: float, minimum: float) -> float:
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
