"""Products of gridded photon points (issue 12): a range image and its PNG, a height GeoTIFF, one LAS file.

Orientation of every raster here: north-up, as a viewer shows it. Image row 0 is the northernmost
(+y) row and column 0 the westernmost (−x) column; a :class:`GridPoints` cell (column c, row r), whose
rows count northwards from 0, is image pixel ``[cells − 1 − r, c]``.

Every file appears complete or not at all (written under a hidden temporary name beside it, fsync'ed,
then renamed); bad input raises one :class:`InputError` naming the argument before anything is written,
and no NaN point or height reaches a file.
"""
from __future__ import annotations

import datetime
import os
from pathlib import Path
from typing import TYPE_CHECKING

import laspy
import numpy as np
import pyproj

from flightsim.core.version import __version__
from flightsim.core.atomic import replaced_atomically
from flightsim.core.errors import InputError, positive
from flightsim.outputs.las_format import _quantized_mm, _tile_header_template, _validated_crs, gps_week_date, wkt1

if TYPE_CHECKING:
    from flightsim.scoring.photon_grid import GridPoints

PNG_PERCENTILES = (2.0, 98.0)
"""Percentiles of the finite pixels that span the PNG's colour map (robust to outliers)."""
GROUND_CLASS = 2
"""ASPRS class of every point of :func:`write_points_las` (ground)."""
_PHOTONS_DIM = (("photons", "photons", np.uint16, "photons averaged into point"),)
_INT32_MAX = np.iinfo(np.int32).max


def range_image(grid: GridPoints, cells: int, values: np.ndarray) -> np.ndarray:
    """(cells, cells) float64 image of one value per point of ``grid`` (e.g. range [m] or height [m]).

    Pixel ``[cells − 1 − r, c]`` holds the value of the point of cell (column c, row r): north-up, row 0
    at the top (see the module docstring); NaN where no point.

    Args:
        grid: gridded points, at most one per cell, cells in ``[0, cells)``.
        cells: columns and rows of the cell grid (the frame's ``cells``, not ``grid.cells``).
        values: (m,) one value per point of ``grid``, in its units.
    """
    if isinstance(cells, bool) or not isinstance(cells, (int, np.integer)) or cells < 1:
        raise InputError("cells", cells, "an integer >= 1")
    ij = np.asarray(grid.cell)
    m = len(grid.points)
    if ij.shape != (m, 2) or ij.dtype.kind not in "iu":
        raise InputError("grid.cell", f"shape {ij.shape}", f"({m}, 2) integer columns and rows")
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (m,):
        raise InputError("values", f"shape {values.shape}", f"({m},), one value per point of grid")
    if m and (ij.min() < 0 or ij.max() >= cells):
        raise InputError("grid.cell", f"range [{ij.min()}, {ij.max()}]", f"columns and rows in [0, {cells})")
    pixel_row, pixel_col = cells - 1 - ij[:, 1], ij[:, 0]
    if len(np.unique(pixel_row * cells + pixel_col)) != m:
        raise InputError("grid.cell", "a repeated cell", "at most one point per cell")
    image = np.full((cells, cells), np.nan)
    image[pixel_row, pixel_col] = values
    return image


def write_png(
    path: str | os.PathLike,
    image: np.ndarray,
    label: str,
    units: str,
    *,
    cmap: str = "viridis",
    nan_rgba: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> Path:
    """Write ``image`` (2-D, row 0 at the top) as an RGBA PNG, one pixel per element; returns the path.

    The colour map ``cmap`` spans the 2nd to 98th percentile of the finite pixels (values beyond take
    its end colours); NaN pixels are ``nan_rgba`` (transparent by default). The PNG's text metadata
    holds ``Title`` (``label``), ``units``, ``vmin``, ``vmax`` (in ``units``) and ``cmap``. Drawn by
    ``matplotlib.image.imsave``, which needs no GUI backend (imported here: the GeoTIFF and LAS writers beside
    this one do without it, and it costs a run ~0.3 s).
    """
    import matplotlib
    import matplotlib.colors
    import matplotlib.image

    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2 or image.size == 0:
        raise InputError("image", f"shape {image.shape}", "a non-empty 2-D array")
    finite = image[np.isfinite(image)]
    if finite.size == 0:
        raise InputError("image", "no finite pixel", "at least one finite value")
    if cmap not in matplotlib.colormaps:
        raise InputError("cmap", cmap, "the name of a matplotlib colour map")
    if not matplotlib.colors.is_color_like(nan_rgba):
        raise InputError("nan_rgba", nan_rgba, "a matplotlib colour, e.g. (0, 0, 0, 0)")
    colours = matplotlib.colormaps[cmap].with_extremes(bad=nan_rgba)
    vmin, vmax = (float(v) for v in np.percentile(finite, PNG_PERCENTILES))
    norm = matplotlib.colors.Normalize(vmin, vmax)
    rgba = colours(norm(np.ma.masked_invalid(image)), bytes=True)
    metadata = {"Title": label, "units": units, "vmin": repr(vmin), "vmax": repr(vmax), "cmap": cmap}
    with replaced_atomically(path) as tmp:
        matplotlib.image.imsave(tmp, rgba, format="png", metadata=metadata)
    return Path(path)


def height_raster(points_world: np.ndarray, cell_m: float) -> tuple[np.ndarray, float, float]:
    """Grid world points into a north-up raster of mean heights: ``(heights, west, north)``.

    Cells are ``[i·cell_m, (i+1)·cell_m)`` in x and y (so rasters of different frames align); the
    raster spans the cells holding points, ``heights[0, 0]`` is the cell at (``west``, ``north``), the
    raster's upper-left corner [m]. ``heights`` (rows, columns) float64 is the mean height [m] of the
    points in each cell, NaN where none.

    Args:
        points_world: (m, 3) world E, N, H [m], finite, m >= 1.
        cell_m: cell side [m], > 0.
    """
    xyz = _finite_points(points_world, "points_world")
    cell_m = positive("cell_m", cell_m, "m")
    i = np.floor(xyz[:, 0] / cell_m).astype(np.int64)
    j = np.floor(xyz[:, 1] / cell_m).astype(np.int64)
    columns, rows = int(i.max() - i.min()) + 1, int(j.max() - j.min()) + 1
    flat = (j.max() - j) * columns + (i - i.min())
    sums = np.bincount(flat, weights=xyz[:, 2], minlength=rows * columns)
    counts = np.bincount(flat, minlength=rows * columns)
    with np.errstate(invalid="ignore", divide="ignore"):
        heights = (sums / counts).reshape(rows, columns)
    return heights, float(i.min() * cell_m), float((j.max() + 1) * cell_m)


def write_geotiff(
    path: str | os.PathLike,
    heights: np.ndarray,
    origin_xy: tuple[float, float],
    cell_m: float,
    crs: pyproj.CRS,
    nodata: float = -9999.0,
) -> Path:
    """Write a north-up single-band float32 GeoTIFF of ``heights`` [m]; returns the path.

    Args:
        heights: (rows, columns) heights [m], row 0 the northernmost; NaN: no data.
        origin_xy: (west, north) world coordinates [m] of the raster's upper-left corner.
        cell_m: pixel side [m], > 0.
        crs: CRS of the world coordinates: projected, in metres, with a WKT1 form (written as WKT1).
        nodata: value stored for NaN; finite, and no height may equal it.

    The file is LZW-compressed (floating-point predictor), tiled 256 × 256, with ``nodata`` set.
    """
    heights = np.asarray(heights, dtype=np.float64)
    if heights.ndim != 2 or heights.size == 0:
        raise InputError("heights", f"shape {heights.shape}", "a non-empty 2-D array")
    with np.errstate(over="ignore"):
        band = heights.astype(np.float32)
    if np.isinf(band).any():
        raise InputError("heights", "an infinite value", "finite float32 heights [m] or NaN")
    west, north = _finite_pair("origin_xy", origin_xy)
    cell_m = positive("cell_m", cell_m, "m")
    crs = _validated_crs(crs)
    if not np.isfinite(nodata) or np.any(band == np.float32(nodata)):
        raise InputError("nodata", nodata, "a finite value that no height equals")
    band[np.isnan(band)] = nodata
    import rasterio  # here, not at the top: a run writing no raster (returns.las alone) skips its ~0.2 s import
    from rasterio.crs import CRS as RasterioCRS
    from rasterio.transform import from_origin

    profile = dict(
        driver="GTiff", width=band.shape[1], height=band.shape[0], count=1, dtype="float32",
        crs=RasterioCRS.from_wkt(wkt1(crs)), transform=from_origin(west, north, cell_m, cell_m),
        nodata=float(nodata), compress="lzw", predictor=3, tiled=True, blockxsize=256, blockysize=256,
    )
    with replaced_atomically(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        dst.write(band, 1)
    return Path(path)


def write_points_las(
    path: str | os.PathLike,
    points_world: np.ndarray,
    crs: pyproj.CRS,
    photons: np.ndarray | None = None,
    gps_time: np.ndarray | None = None,
    *,
    creation_date: datetime.date | None = None,
) -> Path:
    """Write the points as one LAS 1.4 file; returns the path.

    Point format 6, every point class 2 (ground), one return of one; scale 0.001 m, offsets the
    whole metres at or below the lowest x, y, z; the CRS as the OGC WKT1 VLR of the LAS tiles
    (:mod:`flightsim.outputs.las_tiles`), with the same header conventions.

    Args:
        points_world: (m, 3) world E, N, H [m], finite, m >= 1, within 2147 km of their minimum.
        crs: CRS of the world coordinates: projected, in metres, with a WKT1 form.
        photons: (m,) integers in [0, 65535]: written as the extra-bytes dimension ``photons`` (uint16).
        gps_time: (m,) finite adjusted standard GPS time [s]; 0 when not given.
        creation_date: header creation date; by default the GPS date of the earliest ``gps_time``.
    """
    xyz = _finite_points(points_world, "points_world")
    m = len(xyz)
    gps_time = np.zeros(m) if gps_time is None else _finite_column("gps_time", gps_time, m)
    dims = ()
    if photons is not None:
        photons = _uint16_column("photons", photons, m)
        dims = _PHOTONS_DIM
    if creation_date is None:
        creation_date = gps_week_date(gps_time.min())
    header = _tile_header_template(_validated_crs(crs), creation_date, f"flightsim {__version__}", dims)
    quantized = np.column_stack([_quantized_mm(xyz[:, k], "xyz"[k]) for k in range(3)])
    offset_mm = np.floor_divide(quantized.min(axis=0), 1000) * 1000
    if (quantized - offset_mm).max() > _INT32_MAX:
        raise InputError("points_world", "extent > 2147 km", "points within 2147 km of their minimum [m]")
    header.offsets = offset_mm / 1000  # whole metres, exact
    record = laspy.PackedPointRecord.zeros(m, header.point_format)
    for k, name in enumerate("XYZ"):
        record[name] = quantized[:, k] - offset_mm[k]
    record["return_number"] = np.ones(m, np.uint8)
    record["number_of_returns"] = np.ones(m, np.uint8)
    record["classification"] = np.full(m, GROUND_CLASS, np.uint8)
    record["gps_time"] = gps_time
    if photons is not None:
        record["photons"] = photons
    with replaced_atomically(path) as tmp, open(tmp, "wb") as fh:
        with laspy.LasWriter(fh, header, do_compress=False, closefd=False) as writer:
            writer.write_points(record)
    return Path(path)


def _finite_points(points, name: str) -> np.ndarray:
    """``points`` as (m, 3) float64, m >= 1, all finite."""
    xyz = np.asarray(points, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise InputError(name, f"shape {xyz.shape}", "(m, 3) E, N, H [m] with m >= 1")
    if not np.isfinite(xyz).all():
        raise InputError(name, f"{np.count_nonzero(~np.isfinite(xyz).all(axis=1))} non-finite points", "finite [m]")
    return xyz


def _finite_column(name: str, values, m: int) -> np.ndarray:
    """``values`` as (m,) finite float64."""
    column = np.asarray(values, dtype=np.float64)
    if column.shape != (m,) or not np.isfinite(column).all():
        raise InputError(name, f"shape {column.shape}", f"({m},) finite values, one per point")
    return column


def _uint16_column(name: str, values, m: int) -> np.ndarray:
    """``values`` as (m,) uint16; integers only, in range."""
    column = np.asarray(values)
    if column.shape != (m,) or column.dtype.kind not in "iu":
        raise InputError(name, f"shape {column.shape}, {column.dtype}", f"({m},) integers, one per point")
    if column.min() < 0 or column.max() > np.iinfo(np.uint16).max:
        raise InputError(name, f"range [{column.min()}, {column.max()}]", "integers in [0, 65535]")
    return column.astype(np.uint16)


def _finite_pair(name: str, value) -> tuple[float, float]:
    """``value`` as two finite floats."""
    allowed = "two finite world coordinates (west, north) [m]"
    try:
        pair = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(name, value, allowed) from None
    if pair.shape != (2,) or not np.isfinite(pair).all():
        raise InputError(name, value, allowed)
    return float(pair[0]), float(pair[1])
