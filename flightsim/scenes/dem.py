"""Height grids as scenes: a GeoTIFF DEM (rasterio: its CRS, transform and nodata) or a ``.npy`` grid,
turned into a mesh of two triangles per cell.

Node (row i, column j) of a GeoTIFF stands at the centre of its pixel, world (E, N) from the raster's
transform; a ``.npy`` grid (rows from north to south, as a raster) is laid out at ``cell_m`` spacing
centred on the scene's origin, in the scene's CRS. Heights are world H [m]; the local origin is the
grid's middle at the scene origin's H (local z = H − origin H), so a hover over the scene centre looks
at the grid's middle; ground_z is the local height of the middle node.
A triangle with a nodata (or non-finite) corner is left out: the mesh has a hole there.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.lunar import surface_scene
from flightsim.scenes.scene import Scene

DEM_SUFFIXES = (".tif", ".tiff", ".npy")
MAX_DEM_NODES = 4097 * 4097  # about 33 M triangles


def is_dem(name: str) -> bool:
    return Path(name).suffix.lower() in DEM_SUFFIXES


def dem_scene(path: str, crs, origin, cell_m: float) -> Scene:
    """The scene of the height grid at ``path`` (.tif/.tiff: its own CRS and geometry; .npy: ``crs``,
    centred on ``origin``, ``cell_m`` [m] apart)."""
    if not Path(path).is_file():
        raise InputError("scene.name", path, "an existing .tif/.tiff/.npy height grid")
    if Path(path).suffix.lower() == ".npy":
        heights, centre, step = _npy(path, cell_m), np.asarray(origin, dtype=np.float64)[:2], (cell_m, cell_m)
    else:
        heights, centre, step, crs = _geotiff(path)
    return grid_scene(Path(path).stem, heights, centre, step, crs, float(np.asarray(origin, dtype=np.float64)[2]))


def grid_scene(name: str, heights: np.ndarray, centre_en: np.ndarray, step: tuple[float, float], crs,
               base_h: float = 0.0) -> Scene:
    """Mesh of ``heights`` (rows north to south; NaN = nodata) with node spacing ``step`` = (east, north)
    [m], its centre node at world ``centre_en``; local z = height − ``base_h``."""
    rows, cols = heights.shape
    if rows < 2 or cols < 2 or rows * cols > MAX_DEM_NODES:
        raise InputError("scene.name", f"a {rows} × {cols} grid", f"2 × 2 to {MAX_DEM_NODES:,} nodes")
    x = (np.arange(cols) - (cols - 1) / 2) * step[0]
    y = ((rows - 1) / 2 - np.arange(rows)) * step[1]
    xx, yy = np.meshgrid(x, y, indexing="xy")
    z = heights - base_h
    vertices = np.column_stack([xx.ravel(), yy.ravel(), np.nan_to_num(z.ravel())])
    node = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = node[1:, :-1], node[1:, 1:], node[:-1, 1:], node[:-1, :-1]  # SW, SE, NE, NW of each cell
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    finite = np.isfinite(z.ravel())
    triangles = triangles[finite[triangles].all(axis=1)]
    if len(triangles) == 0:
        raise InputError("scene.name", name, "a height grid with at least one cell of four valid heights")
    centre = z[rows // 2, cols // 2]
    origin = (float(centre_en[0]), float(centre_en[1]), base_h)
    return surface_scene(name, crs, origin, vertices, triangles.astype(np.int32),
                         float(centre) if np.isfinite(centre) else float(np.nanmedian(z)))


def _npy(path: str, cell_m: float) -> np.ndarray:
    heights = np.load(path, allow_pickle=False)
    if heights.ndim != 2 or heights.dtype.kind not in "fiu":
        raise InputError("scene.name", path, "a 2-D numeric .npy height grid [m]")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise InputError("scene.cell_m", cell_m, "a grid spacing > 0 m")
    return heights.astype(np.float64)


def _geotiff(path: str) -> tuple[np.ndarray, np.ndarray, tuple[float, float], object]:
    """(heights with NaN at nodata, world E, N of the grid's middle, (east, north) step [m], CRS WKT)."""
    import rasterio

    with rasterio.open(path) as src:
        if src.crs is None or not src.crs.is_projected:
            raise InputError("scene.name", path, "a GeoTIFF in a projected CRS (metres)")
        t = src.transform
        if t.b != 0 or t.d != 0 or t.e >= 0:
            raise InputError("scene.name", path, "a north-up GeoTIFF (no rotation)")
        heights = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        rows, cols = heights.shape
        centre = np.array([t.c + cols / 2 * t.a, t.f + rows / 2 * t.e])  # the grid's middle (pixel centres)
        return heights, centre, (t.a, -t.e), src.crs.to_wkt()
