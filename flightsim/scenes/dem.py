"""Height grids as scenes: a GeoTIFF DEM (rasterio: its CRS, transform and nodata) or a ``.npy`` grid,
turned into a mesh of two triangles per cell (or an error-bounded simplification of it), with an
optional land-cover raster (:mod:`flightsim.scenes.landcover`) and buildings
(:mod:`flightsim.scenes.buildings`).

Node (row i, column j) of a GeoTIFF stands at the centre of its pixel, world (E, N) from the raster's
transform (any pixel size, square or not); a ``.npy`` grid (rows from north to south, as a raster) is
laid out at ``cell_m`` spacing centred on the scene's origin, in the scene's CRS. Heights are world H
[m]; the local origin is the grid's middle at the scene origin's H (local z = H − origin H), so a hover
over the scene centre looks at the grid's middle; ground_z is the local height of the middle node.
A triangle with a nodata (or non-finite) corner is left out: the mesh has a hole there, and a ray
through it misses. A GeoTIFF must carry a projected CRS in metres: one in a geographic CRS is refused
with the ``gdalwarp`` command that reprojects it (:mod:`flightsim.scenes.raster`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.scenes.gridmesh import grid_triangles
from flightsim.scenes.lunar import surface_scene
from flightsim.scenes.scene import Scene
from flightsim.scenes.settings import ScenePart

DEM_SUFFIXES = (".tif", ".tiff", ".npy")
MAX_DEM_NODES = 6001 * 6001  # about 72 M triangles


@dataclass
class DemSettings(Settings):
    """A height grid read from a file, its simplification, land cover and buildings."""

    cell_m: float = setting(1.0, "node spacing of a .npy height grid (a GeoTIFF has its own)", "m",
                            range=(0.0, 1.0e5), lo_open=True)
    simplify_m: float = setting(0.0, "largest vertical error of a simplified grid; 0 = two triangles per cell", "m",
                                range=(0.0, 1.0e4))
    landcover: str = setting("", "a GeoTIFF of ASPRS class codes in the grid's CRS (classes and reflectance of the "
                             "triangles); \"\" = none")
    buildings: str = setting("", "an .obj/.ply mesh of buildings in the grid's CRS world coordinates; \"\" = none")

    def check(self, context) -> None:
        for name, value, suffixes in (("scene.landcover", self.landcover, (".tif", ".tiff")),
                                      ("scene.buildings", self.buildings, (".obj", ".ply"))):
            if value and Path(value).suffix.lower() not in suffixes:
                raise InputError(name, value, f"\"\" or a {'/'.join(suffixes)} file path")


@register("scene", "dem")
class DemScene(ScenePart):
    """The height grid named by ``scene.name`` (a .tif/.tiff/.npy file), with ``[scene]``'s DEM settings."""

    settings = DemSettings
    suffixes = DEM_SUFFIXES

    def build(self, half_extent_m: float, seed: int) -> Scene:
        s = self.s
        return dem_scene(s.name, s.crs, s.origin, s.cell_m, s.simplify_m, s.landcover, s.buildings)


def dem_scene(path: str, crs, origin, cell_m: float, simplify_m: float = 0.0, landcover: str = "",
              buildings: str = "") -> Scene:
    """The scene of the height grid at ``path`` (.tif/.tiff: its own CRS and geometry; .npy: ``crs``,
    centred on ``origin``, ``cell_m`` [m] apart), simplified to within ``simplify_m`` [m] (0: every cell),
    classified by the ``landcover`` raster (which also sets each triangle's reflectance) and with the
    ``buildings`` mesh (paths; "" for none)."""
    if Path(path).suffix.lower() == ".npy":
        heights, centre, step = _npy(path, cell_m), np.asarray(origin, dtype=np.float64)[:2], (cell_m, cell_m)
    else:
        heights, centre, step, crs = _geotiff(path)
    scene = grid_scene(Path(path).stem, heights, centre, step, crs, float(np.asarray(origin, dtype=np.float64)[2]),
                       simplify_m)
    if landcover:
        from flightsim.scenes.landcover import landcover_classes, triangle_reflectance

        scene.classification = landcover_classes(scene, landcover)
        scene.reflectance = triangle_reflectance(scene)
    if buildings:
        from flightsim.scenes.buildings import add_buildings

        scene = add_buildings(scene, buildings)
    return scene


def grid_scene(name: str, heights: np.ndarray, centre_en: np.ndarray, step: tuple[float, float], crs,
               base_h: float = 0.0, simplify_m: float = 0.0) -> Scene:
    """Mesh of ``heights`` (rows north to south; NaN = nodata) with node spacing ``step`` = (east, north)
    [m], its centre node at world ``centre_en``; local z = height − ``base_h``; simplified to within
    ``simplify_m`` [m] vertically (0: two triangles per cell). Only nodes of some triangle are kept."""
    rows, cols = heights.shape
    if rows < 2 or cols < 2 or rows * cols > MAX_DEM_NODES:
        raise InputError("scene.name", f"a {rows} × {cols} grid", f"2 × 2 to {MAX_DEM_NODES:,} nodes")
    triangles = grid_triangles(heights, simplify_m)
    if len(triangles) == 0:
        raise InputError("scene.name", name, "a height grid with three valid heights around at least one triangle")
    node = np.arange(rows * cols)
    if simplify_m > 0.0 or not np.isfinite(heights).all():  # keep only the nodes of some triangle
        used = np.zeros(rows * cols, dtype=bool)
        used[triangles.ravel()] = True
        node = np.flatnonzero(used)
        triangles = (np.cumsum(used, dtype=np.int64) - 1).astype(np.int32)[triangles]
    vertices = np.empty((len(node), 3))
    vertices[:, 0] = (node % cols - (cols - 1) / 2) * step[0]
    vertices[:, 1] = ((rows - 1) / 2 - node // cols) * step[1]
    vertices[:, 2] = heights.ravel()[node] - base_h
    centre = heights[rows // 2, cols // 2] - base_h
    origin = (float(centre_en[0]), float(centre_en[1]), base_h)
    ground_z = float(centre) if np.isfinite(centre) else float(np.median(vertices[:, 2]))
    return surface_scene(name, crs, origin, vertices, triangles, ground_z)


def _npy(path: str, cell_m: float) -> np.ndarray:
    if not Path(path).is_file():
        raise InputError("scene.name", path, "an existing .tif/.tiff/.npy height grid")
    heights = np.load(path, allow_pickle=False)
    if heights.ndim != 2 or heights.dtype.kind not in "fiu":
        raise InputError("scene.name", path, "a 2-D numeric .npy height grid [m]")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise InputError("scene.cell_m", cell_m, "a grid spacing > 0 m")
    return heights.astype(np.float64)


def _geotiff(path: str) -> tuple[np.ndarray, np.ndarray, tuple[float, float], object]:
    """(heights with NaN at nodata, world E, N of the grid's middle, (east, north) step [m], CRS)."""
    from flightsim.scenes.raster import read_raster

    dem = read_raster(path, "scene.name", "a GeoTIFF height grid", MAX_DEM_NODES)
    heights = np.where(dem.valid, dem.values, np.nan).astype(np.float64)
    t = dem.transform
    rows, cols = heights.shape
    centre = np.array([t.c + cols / 2 * t.a, t.f + rows / 2 * t.e])  # the grid's middle (pixel centres)
    return heights, centre, (t.a, -t.e), dem.crs
