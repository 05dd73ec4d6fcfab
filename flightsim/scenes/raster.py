"""Band 1 of a GeoTIFF (rasterio) with its grid and CRS, checked for what a scene needs.

A raster must be readable, hold at least one pixel (at most ``max_pixels``), be north-up (no
rotation or shear; pixels may be non-square) and carry a projected CRS in metres. A raster in a
geographic CRS (degrees) is refused, not reprojected: the message names the UTM zone of its centre
and the ``gdalwarp`` command that reprojects it, so the resampling stays the user's choice.
Every problem raises ``InputError(field, path, ...)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.scenes.scene import parse_crs


@dataclass
class Raster:
    """Band 1 of a raster file.

    Attributes:
        values: (rows, cols) pixel values, as stored (row 0 is the northern edge).
        valid: (rows, cols) False at nodata pixels.
        transform: the affine pixel → world map (rasterio's ``Affine``; pixel corners).
        crs: the projected CRS of the world coordinates [m].
    """

    values: np.ndarray
    valid: np.ndarray
    transform: object
    crs: pyproj.CRS

    def pixel_of(self, east: np.ndarray, north: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of the pixel holding each world point [m]; row, col are 0 where not inside."""
        t = self.transform  # north-up: no rotation terms
        row, col = np.floor((north - t.f) / t.e).astype(np.int64), np.floor((east - t.c) / t.a).astype(np.int64)
        inside = (row >= 0) & (row < self.values.shape[0]) & (col >= 0) & (col < self.values.shape[1])
        return np.where(inside, row, 0), np.where(inside, col, 0), inside


def read_raster(path: str, field: str, what: str, max_pixels: int) -> Raster:
    """Band 1 of the GeoTIFF at ``path``; ``what`` ("a GeoTIFF height grid") words the errors of ``field``."""
    import rasterio
    from rasterio.errors import RasterioError

    if not Path(path).is_file():
        raise InputError(field, path, f"an existing file: {what}")
    try:
        with rasterio.open(path) as src:
            crs = _projected_crs(src, path, field, what)
            if src.count < 1 or not 1 <= src.width * src.height <= max_pixels:
                raise InputError(field, path, f"{what} of 1 to {max_pixels:,} pixels (this one: {src.count} band(s) "
                                              f"of {src.height} × {src.width})")
            t = src.transform
            if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
                raise InputError(field, path, f"{what}, north-up (no rotation or shear)")
            band = src.read(1, masked=True)
    except RasterioError as error:
        raise InputError(field, path, f"{what} that rasterio can read ({error})") from None
    return Raster(np.ma.getdata(band), ~np.ma.getmaskarray(band), t, crs)


def _projected_crs(src, path: str, field: str, what: str) -> pyproj.CRS:
    """The raster's CRS, if it is projected in metres."""
    if src.crs is None:
        raise InputError(field, path, f"{what} with a CRS (this one has none; set it, e.g. gdal_edit.py -a_srs "
                                      "EPSG:32648)")
    crs = pyproj.CRS.from_wkt(src.crs.to_wkt())
    if crs.is_geographic:
        t = src.transform
        lon = t.c + t.a * src.width / 2.0 + t.b * src.height / 2.0  # the raster's middle [deg]
        lat = t.f + t.d * src.width / 2.0 + t.e * src.height / 2.0
        utm = f"EPSG:{(32600 if lat >= 0 else 32700) + int(math.floor((lon + 180.0) / 6.0)) % 60 + 1}"
        raise InputError(field, path, f"{what} in a projected CRS in metres (this one is geographic, {crs.name}; "
                                      f"reproject it first, e.g. gdalwarp -t_srs {utm} -r bilinear {path} out.tif)")
    try:
        return parse_crs(crs, field)
    except InputError as error:
        raise InputError(field, path, f"{what} in {error.allowed}") from None
