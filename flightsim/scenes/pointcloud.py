"""ALS point clouds as scenes: a LAS/LAZ file (COPC files are LAZ) read with laspy + lazrs into a
:class:`PointCloud` in the scene's local frame, and the ``cloud`` scene kind (``scene.name`` a .las/.laz path)
whose mesh is the ground surface under the points (:mod:`flightsim.scenes.cloud_ground`).

Reading (:func:`read_point_cloud`):
- The file is read in chunks of at most ``chunk_points``, so a file larger than the memory laspy would need for
  all its fields at once still reads; only x, y, z (float64, scaled as laspy scales them), the class and the
  return numbers are kept. The chunks are read on a thread per core: an uncompressed (.las) file's point records
  mapped from the file, a compressed one's decompressed by laspy's chunk iterator (lazrs on its own threads) while
  the threads read the chunks before.
- CRS: the file's (laspy's ``header.parse_crs()``: its WKT or GeoTIFF keys). It must be projected, in metres:
  a geographic CRS (degrees) is refused with the PDAL command that reprojects it to its UTM zone, a CRS in feet
  likewise. A file without a CRS uses ``crs`` only when the caller passes one (the scene kind passes
  ``scene.crs`` only when it was set away from its default), else it is refused with the command that
  assigns one.
- Classes (ASPRS): 2 ground, 3–5 vegetation, 6 building; 7 (low noise) and 18 (high noise) are dropped. A
  cloud without ground points (class 2) is refused, naming PDAL's ``filters.smrf`` and LAStools'
  ``lasground``, unless ``ground = "lowest"``: then the lowest point of each ``cell_m`` cell is the ground
  (every other point that the file calls ground becomes unclassified, 1). A cloud with no point left after
  dropping the noise is refused.
- Return numbers: a file whose ``return_number`` or ``number_of_returns`` is 0 (some writers leave them
  unset) gets 1 there: each such point is taken as the only return of its pulse.
- Origin: ``origin`` when given (world E, N, H [m]); else the middle of the cloud's horizontal bounding box at
  the height of its lowest ground point, so that local z is the height above the lowest ground and local x, y
  stay within half the cloud's extent (float32 in kernels keeps ≪ 1 mm over a 20 km tile).
"""
from __future__ import annotations

import math
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.core.process_map import by_pieces, thread_count
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, Scene, parse_crs
from flightsim.scenes.settings import ScenePart

CLOUD_SUFFIXES = (".las", ".laz")
CLASS_GROUND = 2
CLASS_UNCLASSIFIED = 1
NOISE_CLASSES = (7, 18)  # ASPRS low noise, high noise: dropped
CHUNK_POINTS = 2_000_000
READ_PART = 250_000  # the fewest points of a chunk the reading threads take
GRID_CELLS = 1 << 27  # the most cells of centres_beyond's occupancy grid (128 MiB of flags)
GROUND_MODES = ("classified", "lowest")
_CLASSIFY_HINT = ("a cloud with ground points (class 2): classify it first, e.g. PDAL's filters.smrf (pdal translate "
                  "in.laz out.laz smrf) or LAStools' lasground (lasground -i in.laz -o out.laz), or set "
                  "scene.cloud_ground = \"lowest\" to take the lowest point of each scene.cloud_cell_m cell as ground")


@dataclass
class PointCloud:
    """An ALS point cloud in a scene's local frame.

    Attributes:
        xyz: (N, 3) float64 local coordinates [m] (world − ``origin``).
        classification: (N,) uint8 ASPRS class (2 ground, 3–5 vegetation, 6 building, ...; no noise).
        return_number: (N,) uint8, 1 for the first return of a pulse.
        number_of_returns: (N,) uint8 returns of the point's pulse (≥ 1).
        crs: the projected CRS of the world coordinates (metres).
        origin: (3,) float64 world E, N, H [m] of the local origin.
    """

    xyz: np.ndarray
    classification: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    crs: pyproj.CRS
    origin: np.ndarray
    _bounds: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        self.origin = _finite3(self.origin)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3 or not np.isfinite(self.xyz).all():
            raise InputError("scene.cloud", f"points of shape {self.xyz.shape}", "(N, 3) finite local x, y, z [m]")
        for name in ("classification", "return_number", "number_of_returns"):
            values = np.ascontiguousarray(getattr(self, name), dtype=np.uint8)
            if values.shape != (len(self.xyz),):
                raise InputError("scene.cloud", f"{name} of shape {values.shape}", f"one per point ({len(self.xyz)})")
            setattr(self, name, values)

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def ground(self) -> np.ndarray:
        """(N,) bool: the ground points (class 2)."""
        return self.ground_of(slice(None))

    def ground_of(self, points: slice) -> np.ndarray:
        """bool of each of the points ``points``: whether it is ground (class 2)."""
        return self.classification[points] == CLASS_GROUND

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners (3,) of the local bounding box [m] (column by column, as Scene.bounds); worked out
        once for the points held (0.15 s a 1e7 points; the scene, the ground grid, the footprints' check and the
        device grid each ask), copies handed out."""
        if self._bounds is None or self._bounds[0] is not self.xyz:
            columns = self.xyz.T
            self._bounds = (self.xyz, np.array([c.min() for c in columns]), np.array([c.max() for c in columns]))
        return self._bounds[1].copy(), self._bounds[2].copy()


def centres_beyond(cloud: PointCloud, centres_xy: np.ndarray, reach_m: float) -> np.ndarray:
    """Indices (ascending) of the horizontal ``centres_xy`` (F, 2) local [m] with no point of ``cloud`` closer than
    ``reach_m`` [m] in x, y (a KD-tree's nearest distance ≥ reach, without building one over every point).

    A centre whose cell of a grid of side reach/2 holds a point has one within 0.71 reach; the others are looked up
    in a KD-tree of the points of the 3 × 3 cells of side 1.001 reach around them, which hold every point closer
    than reach (a grid too fine for memory, > GRID_CELLS cells, takes the tree of every point instead)."""
    centres = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    xy = cloud.xyz[:, :2]
    lo, hi = (corner[:2] for corner in cloud.bounds())
    fine = _cell_keys(xy, lo, reach_m / 2.0, np.floor((hi - lo) / (reach_m / 2.0)) + 1.0)
    if fine is None:
        return _beyond(xy, centres, reach_m)
    keys, shape = fine
    occupied = np.zeros(shape[0] * shape[1], dtype=bool)
    occupied[keys] = True
    own = _cell_keys(centres, lo, reach_m / 2.0, np.array(shape), outside=True)[0]
    unsure = np.flatnonzero((own < 0) | ~occupied[np.maximum(own, 0)])
    if unsure.size == 0:
        return unsure
    side = 1.001 * reach_m
    points, shape = _cell_keys(xy, lo, side, np.floor((hi - lo) / side) + 1.0)
    wanted = np.zeros(shape[0] * shape[1], dtype=bool)
    column, row = (np.floor((centres[unsure, a] - lo[a]) / side).astype(np.int64) for a in (0, 1))
    for dc in (-1, 0, 1):
        for dr in (-1, 0, 1):
            c, r = column + dc, row + dr
            inside = (c >= 0) & (c < shape[0]) & (r >= 0) & (r < shape[1])
            wanted[r[inside] * shape[0] + c[inside]] = True
    return unsure[_beyond(xy[wanted[points]], centres[unsure], reach_m)]


def _cell_keys(xy: np.ndarray, lo: np.ndarray, side: float, top: np.ndarray, outside: bool = False):
    """(keys, (columns, rows)): the row-major cell of each position in a grid of ``side`` [m] from ``lo`` with
    ``top`` (columns, rows) cells (−1 for a position outside it: tested only when ``outside`` may hold any); None
    when the grid would pass GRID_CELLS."""
    if top[0] * top[1] > GRID_CELLS:
        return None
    shape = (int(top[0]), int(top[1]))
    keys = np.empty(len(xy), dtype=np.int64)

    def piece(rows: slice) -> None:
        index = np.floor((xy[rows] - lo) / side)
        cell = index[:, 1] * shape[0] + index[:, 0]
        if outside:
            inside = (index[:, 0] >= 0) & (index[:, 0] < shape[0]) & (index[:, 1] >= 0) & (index[:, 1] < shape[1])
            cell = np.where(inside, cell, -1.0)
        keys[rows] = cell

    by_pieces(len(xy), piece)
    return keys, shape


def _beyond(xy: np.ndarray, centres: np.ndarray, reach_m: float) -> np.ndarray:
    """Indices of ``centres`` whose nearest point of ``xy`` is ≥ ``reach_m`` away (all of them when ``xy`` is
    empty)."""
    from scipy.spatial import cKDTree

    if len(xy) == 0:
        return np.arange(len(centres))
    # a tree split at midpoints builds in half the time of a balanced one (2.2 against 4.8 s for 1e7 points)
    distance, _ = cKDTree(xy, balanced_tree=False, compact_nodes=False).query(centres)
    return np.flatnonzero(distance >= reach_m)


def read_point_cloud(path, crs=None, origin=None, ground: str = "classified", cell_m: float = 1.0,
                     chunk_points: int = CHUNK_POINTS) -> PointCloud:
    """The point cloud of the LAS/LAZ file at ``path`` (see the module's notes).

    Args:
        path: a .las or .laz file (COPC included).
        crs: the CRS to use when the file has none (anything pyproj accepts); None: the file must carry one.
        origin: world E, N, H [m] of the local origin; None: the bounding box's middle at the lowest ground.
        ground: "classified" (class 2 is the ground) or "lowest" (the lowest point per ``cell_m`` cell).
        cell_m: the cell of ``ground = "lowest"`` [m].
        chunk_points: points read at a time.
    """
    import laspy

    path = str(path)
    _check_file(path)
    if ground not in GROUND_MODES:
        raise InputError("scene.cloud_ground", ground, "one of " + ", ".join(GROUND_MODES))
    try:
        with laspy.open(path) as reader:
            file_crs = _file_crs(reader.header, path)
            world, classes, returns, (lo, hi) = _read_points(reader, path, chunk_points)
    except InputError:
        raise
    except Exception as error:  # laspy's, lazrs's (RuntimeError) and laszip's errors of a broken file
        raise InputError("scene.name", path, f"a LAS/LAZ file laspy can read ({type(error).__name__}: "
                                             f"{' '.join(str(error).split())})") from None
    if len(world) == 0:
        raise InputError("scene.name", path, "a point cloud with at least one point that is not noise "
                                             f"(classes {' and '.join(map(str, NOISE_CLASSES))} are dropped)")
    cloud_crs = file_crs if file_crs is not None else _given_crs(crs, path)
    if ground == "lowest":
        from flightsim.scenes.cloud_ground import lowest_per_cell

        lowest = lowest_per_cell(world, cell_m)
        classes[classes == CLASS_GROUND] = CLASS_UNCLASSIFIED
        classes[lowest] = CLASS_GROUND
    elif not np.any(classes == CLASS_GROUND):
        raise InputError("scene.name", path, _CLASSIFY_HINT)
    local_origin = _origin(lo, hi, world, classes) if origin is None else _finite3(origin)
    world -= local_origin
    cloud = PointCloud(world, classes, returns[0], returns[1], cloud_crs, local_origin)
    # its bounds from the file's, each point's shift rounded alike (rounding is monotone: the same extremes)
    cloud._bounds = (cloud.xyz, lo - local_origin, hi - local_origin)
    return cloud


def _check_file(path: str) -> None:
    if Path(path).suffix.lower() not in CLOUD_SUFFIXES:
        raise InputError("scene.name", path, "a .las or .laz point cloud")
    if not Path(path).is_file():
        raise InputError("scene.name", path, "an existing .las/.laz point cloud")


def _read_points(reader, path: str, chunk_points: int) -> tuple:
    """(world xyz (N, 3) float64, classes, (return number, number of returns), (lowest, highest) world x, y, z) of
    every point of the file at ``path`` that is not noise. Each chunk's kept points are written where its first
    point stands in the file (the chunks on a thread per core, :func:`_chunks`), then moved together when any chunk
    held noise; the bounds found chunk by chunk, each column contiguous there."""
    total = int(reader.header.point_count)
    world = np.empty((total, 3))
    classes, number, count = (np.empty(total, dtype=np.uint8) for _ in range(3))
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)

    def store(at: int, chunk) -> tuple[int, int, np.ndarray, np.ndarray]:
        cls = np.asarray(chunk.classification, dtype=np.uint8)
        keep = ~np.isin(cls, NOISE_CLASSES)
        n = int(keep.sum())
        part = slice(at, at + n)
        rows = slice(None) if n == len(cls) else keep  # no noise point: every row, without gathering the rows first
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        for axis, values in enumerate((chunk.x, chunk.y, chunk.z)):
            column = np.asarray(values, dtype=np.float64)[rows]
            world[part, axis] = column
            if n:
                low[axis], high[axis] = column.min(), column.max()
        classes[part] = cls[rows]
        number[part] = np.asarray(chunk.return_number, dtype=np.uint8)[rows]
        count[part] = np.asarray(chunk.number_of_returns, dtype=np.uint8)[rows]
        return at, n, low, high

    kept = 0
    for at, n, low, high in _chunks(reader, path, max(int(chunk_points), 1), store):
        if at != kept:  # noise dropped before this chunk: its kept points move down to follow the others'
            for column in (world, classes, number, count):
                column[kept:kept + n] = column[at:at + n]
        kept += n
        lo, hi = np.minimum(lo, low), np.maximum(hi, high)
    number, count = number[:kept], count[:kept]
    number[number == 0] = 1
    count[count == 0] = 1
    return world[:kept], classes[:kept], (number, count), (lo, hi)


def _chunks(reader, path: str, chunk_points: int, store) -> list:
    """``store(first point's index in the file, chunk)`` of each chunk of the file at ``path``, in file order, on a
    thread per core: chunks of at most ``chunk_points`` and at least READ_PART points (enough for two a core), no
    more than a chunk a thread held at once."""
    total = int(reader.header.point_count)
    workers = thread_count(-(-total // READ_PART))
    size = min(chunk_points, max(READ_PART, -(-total // (2 * workers))))
    stored, pending, at = [], deque(), 0
    with ThreadPoolExecutor(workers, thread_name_prefix="cloud-read") as pool:
        for chunk in _records(reader, path, size):
            pending.append(pool.submit(store, at, chunk))
            at += len(chunk)
            while len(pending) > workers:
                stored.append(pending.popleft().result())
        return stored + [done.result() for done in pending]


def _records(reader, path: str, size: int):
    """The file's point records, ``size`` at a time: an uncompressed file's mapped from the file, a compressed one's
    decompressed by laspy (lazrs on its own threads) as the caller asks for them."""
    import laspy

    header = reader.header
    fmt = header.point_format
    if header.are_points_compressed or fmt.size != fmt.dtype().itemsize:
        yield from reader.chunk_iterator(size)
        return
    records = np.memmap(path, dtype=fmt.dtype(), mode="r", offset=header.offset_to_point_data,
                        shape=(int(header.point_count),))
    for at in range(0, len(records), size):
        yield laspy.ScaleAwarePointRecord(records[at:at + size], fmt, header.scales, header.offsets)


def _file_crs(header, path: str) -> pyproj.CRS | None:
    """The file's CRS if it has one (projected, in metres), else None."""
    try:
        crs = header.parse_crs()
    except Exception as error:  # laspy raises pyproj's and its own errors for a malformed CRS record
        raise InputError("scene.name", path, f"a LAS/LAZ file whose CRS record pyproj can read ({error})") from None
    if crs is None:
        return None
    if crs.is_geographic:
        command = _reproject_command(header, path)
        raise InputError("scene.name", path, "a point cloud in a projected CRS in metres (this one is geographic, "
                                             f"{crs.name}; reproject it first, e.g. {command})")
    try:
        return parse_crs(crs, "scene.name")
    except InputError as error:
        raise InputError("scene.name", path, f"a point cloud in {error.allowed}; reproject it first, e.g. "
                                             f"{_reproject_command(header, path)}") from None


def _reproject_command(header, path: str) -> str:
    """The PDAL command that reprojects the file to the UTM zone of its middle (its coordinates read as
    longitude, latitude when the CRS is geographic; else the zone is left for the user to choose)."""
    lon, lat = (float(header.mins[i] + header.maxs[i]) / 2.0 for i in (0, 1))
    if abs(lon) <= 180.0 and abs(lat) <= 90.0:
        target = f"EPSG:{(32600 if lat >= 0 else 32700) + int(math.floor((lon + 180.0) / 6.0)) % 60 + 1}"
    else:
        target = "EPSG:<a UTM zone in metres>"
    stem = Path(path).stem
    return (f"pdal translate {path} {stem}_utm.laz reprojection "
            f"--filters.reprojection.out_srs={target}")


def _given_crs(crs, path: str) -> pyproj.CRS:
    if crs is None or (isinstance(crs, str) and not crs.strip()):
        raise InputError("scene.crs", "(none: the file has no CRS)",
                         f"the CRS of {path}: set scene.crs (a projected CRS in metres, e.g. 'EPSG:32648'), or "
                         f"write it into the file, e.g. pdal translate {path} out.laz "
                         "--writers.las.a_srs=EPSG:32648")
    return parse_crs(crs, "scene.crs")


def _origin(lo: np.ndarray, hi: np.ndarray, world: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """The bounding box's (``lo``, ``hi``) middle (E, N) at the lowest ground point's height H [m]."""
    middle = (lo[:2] + hi[:2]) / 2.0
    lowest = by_pieces(len(world), lambda rows: world[rows, 2][classes[rows] == CLASS_GROUND].min(initial=np.inf))
    return np.array([middle[0], middle[1], float(min(lowest))])


def _finite3(value) -> np.ndarray:
    vec = np.asarray(value, dtype=np.float64)
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise InputError("scene.origin", value, "three finite numbers (E, N, H) [m]")
    return vec


@dataclass
class CloudSettings(Settings):
    """An ALS point cloud (.las/.laz), its ground surface and how large-footprint waveforms weigh its points."""

    cloud_cell_m: float = setting(1.0, "cell of the ground grid under the cloud (mean height of its ground points; "
                                  "also the cell of cloud_ground = \"lowest\")", "m", range=(0.05, 100.0))
    cloud_ground: str = setting("classified", "which points are ground: classified (ASPRS class 2) or lowest (the "
                                "lowest point of each cloud_cell_m cell)", choices=GROUND_MODES)
    cloud_dem: str = setting("", "a GeoTIFF DEM in the cloud's CRS to use as the ground instead of the ground "
                             "points; \"\" = none")
    rho_ground: float = setting(0.4, "reflectance of ground points (class 2) in cloud waveforms; 0.4 = the GEDI "
                                "simulator's rhoG (gediMetric, Hancock et al. 2019)", range=(0.0, 1.0), lo_open=True)
    rho_canopy: float = setting(0.57, "reflectance of every other point (vegetation, buildings, unclassified) in "
                                "cloud waveforms; 0.57 = the GEDI simulator's rhoC", range=(0.0, 1.0), lo_open=True)
    cloud_normalise: bool = setting(False, "divide each point's weight by the last returns in its 1.5 m cell, as "
                                    "gediRat's normCover does for uneven ALS density (moves rh50 by up to ~2 m on "
                                    "real plots)")
    cloud_voxel_m: tuple[float, float] = setting((5.0, 1.0), "horizontal and vertical voxel size of the leaf area "
                                                 "the rays of discrete, photon and cloud_method = rays waveform runs "
                                                 "cross (MacArthur-Horn from the first returns)", "m", length=2,
                                                 items=(0.1, 100.0))

    def check(self, context) -> None:
        if self.cloud_dem and Path(self.cloud_dem).suffix.lower() not in (".tif", ".tiff"):
            raise InputError("scene.cloud_dem", self.cloud_dem, "\"\" or a .tif/.tiff GeoTIFF DEM path")


@register("scene", "cloud")
class CloudScene(ScenePart):
    """The point cloud named by ``scene.name`` (a .las/.laz file): its ground as the mesh, the points as
    ``Scene.cloud``. ``scene.crs`` and ``scene.origin`` count as given when they differ from their defaults (the
    config does not record whether a shared setting was set)."""

    settings = CloudSettings
    suffixes = CLOUD_SUFFIXES
    cacheable = False  # the scene cache keeps meshes, not the points

    def build(self, half_extent_m: float, seed: int) -> Scene:
        from flightsim.scenes.cloud_ground import ground_scene

        s = self.s
        crs = s.crs if s.crs != DEFAULT_CRS else None
        origin = s.origin if tuple(s.origin) != tuple(DEFAULT_ORIGIN) else None
        cloud = read_point_cloud(s.name, crs, origin, s.cloud_ground, s.cloud_cell_m)
        scene = ground_scene(cloud, Path(s.name).stem, s.cloud_cell_m, s.cloud_dem)
        if self.cloud_leaves:
            scene.canopy = cloud_canopy(cloud, scene, s.cloud_voxel_m, s.rho_canopy)
        return scene


def cloud_canopy(cloud: PointCloud, ground: Scene, voxel_m, leaf_reflectance: float):
    """The leaf area the cloud's canopy points imply, for the rays that cross it: MacArthur–Horn
    (:mod:`flightsim.scenes.macarthur_horn`) from the first returns over ``ground``'s surface, in voxels of
    ``voxel_m`` = (horizontal, vertical) [m] spanning the cloud; None when the cloud has no point above the ground."""
    from flightsim.scenes.macarthur_horn import lad_from_points

    low, high = cloud.bounds()
    z = ground.height_grid.ground_height(cloud.xyz[:, 0], cloud.xyz[:, 1])  # under each point, NaN off the mesh
    top = float(high[2])
    floor = float(np.nanmin(z))
    if not top > floor:
        return None
    cell = np.array([voxel_m[0], voxel_m[0], voxel_m[1]], dtype=np.float64)
    lower = np.array([low[0], low[1], floor])
    dims = np.maximum(np.ceil((np.array([high[0], high[1], top]) - lower) / cell).astype(int), 1)
    ground_height = np.where(np.isnan(z), floor, z)
    return lad_from_points(cloud.xyz, cloud.ground, ground_height, lower, cell, tuple(dims),
                           return_number=cloud.return_number, leaf_reflectance=leaf_reflectance)
