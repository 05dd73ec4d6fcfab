"""Canopy height model from multi-return points (NumPy, SciPy, rasterio): a DTM, a DSM and their difference,
the CHM, on a north-up grid, and the CHM as a GeoTIFF.

- **Grid**: cells of side ``cell_m`` at whole multiples of ``cell_m`` in x and y (rasters of different runs
  align), spanning the points (or ``bounds``), north-up as :mod:`flightsim.outputs.grid_products` writes:
  row 0 the northernmost, column 0 the westernmost; the affine ``transform`` maps (column, row) to x, y.
- **DTM**: the mean height of the ground points (ASPRS class 2) in each cell; cells without one are filled by
  linear interpolation between the centres of the cells with one (``scipy.interpolate.griddata``), and
  beyond their convex hull by the nearest such cell.
- **DSM**: the highest first return (``return_number`` 1) in each cell, or the highest point with
  ``dsm_returns="all"``; NaN where the cell has none.
- **CHM** = DSM − DTM, clipped at 0; NaN (no data) where the DSM has none.

Bad input raises InputError naming the argument; the GeoTIFF is written under a temporary name and renamed
when complete (:func:`flightsim.outputs.grid_products.write_geotiff`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj
from affine import Affine
from scipy.interpolate import griddata
from scipy.spatial import QhullError

from flightsim.core.errors import InputError, positive
from flightsim.outputs.grid_products import write_geotiff

GROUND_CLASS = 2
DSM_RETURNS = ("first", "all")
MAX_CELLS = 1 << 27  # largest grid (rows × columns)


@dataclass(frozen=True)
class CanopyModel:
    """The three rasters [m], (rows, columns) float64, row 0 the northernmost."""

    chm: np.ndarray  # canopy height, DSM − DTM clipped at 0; NaN where no point
    dtm: np.ndarray  # ground elevation, every cell
    dsm: np.ndarray  # highest first return (or point); NaN where none


def chm_from_points(x, y, z, return_number, classification, cell_m: float, bounds=None,
                    dsm_returns: str = "first") -> tuple[CanopyModel, Affine]:
    """DTM, DSM and CHM of the points on a grid of ``cell_m``, and the grid's affine transform.

    Args:
        x, y, z: (n,) world E, N, H [m], finite, n >= 1.
        return_number: (n,) integers >= 1 (1: first return).
        classification: (n,) ASPRS classes (integers 0 … 255); class 2 (ground) makes the DTM.
        cell_m: cell side [m], > 0.
        bounds: (west, south, east, north) [m] of the grid, or None: the cells holding points. Points outside
            are left out; the grid's corners are the bounds rounded outwards to whole cells.
        dsm_returns: "first" (highest first return) or "all" (highest point).
    """
    xyz, ret, cls = _points(x, y, z, return_number, classification)
    cell = positive("cell_m", cell_m, "m")
    if dsm_returns not in DSM_RETURNS:
        raise InputError("dsm_returns", dsm_returns, f"one of {DSM_RETURNS}")
    west, north, cols, rows = _grid(xyz, cell, bounds)
    col = np.floor((xyz[:, 0] - west) / cell).astype(np.int64)
    row = np.floor((north - xyz[:, 1]) / cell).astype(np.int64)
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    flat = row * cols + col
    ground = inside & (cls == GROUND_CLASS)
    if not ground.any():
        raise InputError("classification", "no ground point in the grid", "at least one class 2 (ground) point")
    dtm = _fill(_cell_mean(flat[ground], xyz[ground, 2], rows * cols).reshape(rows, cols))
    top = inside & ((ret == 1) if dsm_returns == "first" else True)
    dsm = np.full(rows * cols, -np.inf)
    np.maximum.at(dsm, flat[top], xyz[top, 2])
    dsm = np.where(np.isfinite(dsm), dsm, np.nan).reshape(rows, cols)
    chm = np.where(np.isnan(dsm), np.nan, np.maximum(np.nan_to_num(dsm) - dtm, 0.0))
    return CanopyModel(chm, dtm, dsm), Affine(cell, 0.0, west, 0.0, -cell, north)


def write_chm_tif(path: str | os.PathLike, grid: np.ndarray, transform: Affine, crs: pyproj.CRS,
                  nodata: float = -9999.0) -> Path:
    """Write a raster of :func:`chm_from_points` (the CHM, or the DTM or DSM) as a north-up float32 GeoTIFF in
    ``crs`` (projected, metres), NaN as ``nodata``; returns the path.

    Args:
        grid: (rows, columns) heights [m], row 0 the northernmost.
        transform: the grid's affine transform: north-up, square cells.
        crs: the points' CRS.
    """
    if not isinstance(transform, Affine) or transform.b != 0 or transform.d != 0 or transform.a != -transform.e:
        raise InputError("transform", transform, "a north-up affine transform with square cells")
    return write_geotiff(path, grid, (transform.c, transform.f), transform.a, crs, nodata=nodata)


def _points(x, y, z, return_number, classification) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) float64 coordinates, return numbers and classes, checked."""
    columns = []
    for name, value in (("x", x), ("y", y), ("z", z)):
        column = np.asarray(value, dtype=np.float64)
        if column.ndim != 1 or len(column) == 0 or len(column) != np.shape(x)[0]:
            raise InputError(name, f"shape {column.shape}", "(n,) values, n >= 1, as many as x")
        if not np.isfinite(column).all():
            raise InputError(name, f"{np.count_nonzero(~np.isfinite(column))} non-finite values", "finite [m]")
        columns.append(column)
    n = len(columns[0])
    out = []
    for name, value, lo, hi in (("return_number", return_number, 1, 255), ("classification", classification, 0, 255)):
        column = np.asarray(value)
        if column.shape != (n,) or column.dtype.kind not in "iu" or column.min() < lo or column.max() > hi:
            raise InputError(name, f"shape {column.shape}, dtype {column.dtype}", f"({n},) integers in [{lo}, {hi}]")
        out.append(column.astype(np.int64))
    return np.column_stack(columns), out[0], out[1]


def _grid(xyz: np.ndarray, cell: float, bounds) -> tuple[float, float, int, int]:
    """West and north edges [m] and the columns and rows of the grid."""
    if bounds is None:
        west, south = np.floor(xyz[:, :2].min(axis=0) / cell) * cell
        east, north = (np.floor(xyz[:, :2].max(axis=0) / cell) + 1) * cell
    else:
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape != (4,) or not np.isfinite(b).all() or b[0] >= b[2] or b[1] >= b[3]:
            raise InputError("bounds", bounds, "(west, south, east, north) [m], finite, west < east, south < north")
        west, south = np.floor(b[:2] / cell) * cell
        east, north = np.ceil(b[2:] / cell) * cell
    cols, rows = int(round((east - west) / cell)), int(round((north - south) / cell))
    if cols * rows > MAX_CELLS:
        raise InputError("cell_m", cell, f"a cell giving at most {MAX_CELLS} cells over the points ({cols} × {rows})")
    return float(west), float(north), cols, rows


def _cell_mean(flat: np.ndarray, z: np.ndarray, cells: int) -> np.ndarray:
    """Mean of z per cell (NaN where none)."""
    count = np.bincount(flat, minlength=cells)
    total = np.bincount(flat, weights=z, minlength=cells)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _fill(grid: np.ndarray) -> np.ndarray:
    """NaN cells filled linearly from the cells with values (cell centres), beyond their hull by the nearest."""
    known = ~np.isnan(grid)
    if known.all():
        return grid
    rows, cols = np.indices(grid.shape)
    points, values = np.column_stack([rows[known], cols[known]]), grid[known]
    holes = np.column_stack([rows[~known], cols[~known]])
    try:
        filled = griddata(points, values, holes, method="linear")
    except QhullError:  # fewer than 3 cells, or all in a line: no triangles
        filled = np.full(len(holes), np.nan)
    outside = np.isnan(filled)
    filled[outside] = griddata(points, values, holes[outside], method="nearest")
    out = grid.copy()
    out[~known] = filled
    return out
