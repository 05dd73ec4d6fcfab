"""The LAS 1.4 format of flightsim's point files (SPEC §8): header, CRS record, extra bytes, and the 1 mm
coordinate grid, shared by the point tiles (:mod:`.las_tiles`) and the grid products' LAS file.

Format of every tile:

- LAS 1.4, point data record format 6, scale 0.001 m on x, y, z; offsets at the tile's
  lower-left corner (x, y) and 0 (z).
- Global encoding: adjusted standard GPS time (bit 0) and WKT CRS (bit 4).
- CRS: one ``LASF_Projection``/2112 VLR holding OGC WKT1 (``WKT1_GDAL``). LAS 1.4 R15 defines
  that record as the coordinate-system WKT of OGC 01-009 (Coordinate Transformation Services,
  section 7), i.e. WKT1; only the LAS 1.5 draft admits any OGC WKT version. laspy's
  ``LasHeader.add_crs`` writes ``crs.to_wkt()``, which pyproj makes WKT2_2019
  (``PROJCRS[..., ENSEMBLE[...]]``): readers built on older GDAL/PROJ, LAStools or ESRI cannot
  parse it and open the tile without a CRS. WKT1 with its ``AUTHORITY["EPSG", ...]`` nodes is
  what PDAL and GDAL write for LAS 1.4, and round-trips to the same EPSG CRS.
- Extra bytes (``LASF_Spec``/4): ``beam_row`` u1, ``beam_col`` u1, ``prism_angle`` f4 [deg],
  ``range`` f4 [m] (one-way), ``plane_id`` i4 (-1: none), and ``position_error`` f4 [m] when asked;
  no min/max statistics are claimed (option bits 0).
- Identity fields are fixed (system identifier ``flightsim``, zero GUID, file source id 0,
  creation date given by the caller), so identical input gives byte-identical files.
"""
from __future__ import annotations

import datetime
import math

from typing import TYPE_CHECKING

import numpy as np
import pyproj
from pyproj.enums import WktVersion

from flightsim.core.errors import InputError

if TYPE_CHECKING:
    import laspy

SCALE_M = 0.001
"""Coordinate resolution of every tile [m]."""
SCAN_ANGLE_UNIT_DEG = 0.006
"""Unit of the LAS 1.4 scan-angle field [deg]."""
SYSTEM_IDENTIFIER = "flightsim"
GPS_EPOCH = datetime.date(1980, 1, 6)
ADJUSTED_GPS_OFFSET_S = 1.0e9
"""Adjusted standard GPS time = standard GPS time − this [s]."""
MAX_TILE_SIZE_M = 1_000_000
_MM_PER_M = 1000

# (LAS extra-bytes name, PointBatch field, dtype, description with units; at most 32 bytes)
_EXTRA_DIMS = (
    ("beam_row", "beam_row", np.uint8, "DOE sub-beam row i [index]"),
    ("beam_col", "beam_col", np.uint8, "DOE sub-beam column j [index]"),
    ("prism_angle", "prism_angle_deg", np.float32, "wedge prism angle phi [deg]"),
    ("range", "range_m", np.float32, "one-way range exit->hit [m]"),
    ("plane_id", "plane_id", np.int32, "scene plane id, -1 = none [id]"),
)
# fields written only when a run asks for them, by LAS extra-bytes name
OPTIONAL_DIMS = {
    "position_error": ("position_error", "position_error_m", np.float32, "true 3-D position error [m]"),
    "edge_distance": ("edge_distance", "edge_distance_m", np.float32, "true hit to plane edge [m]"),
}


def gps_week_date(gps_time_adjusted: float) -> datetime.date:
    """Calendar date of an adjusted standard GPS time [s] (standard GPS seconds − 1e9).

    The date is that of the GPS time scale, counted from the GPS epoch 1980-01-06 00:00:00;
    no leap seconds are applied, so within 18 s after midnight it is one day ahead of UTC.
    """
    seconds = float(gps_time_adjusted) + ADJUSTED_GPS_OFFSET_S
    if not math.isfinite(seconds) or seconds < 0.0:
        raise InputError(
            "gps_time_adjusted", gps_time_adjusted, "a finite adjusted standard GPS time >= -1e9 s"
        )
    return GPS_EPOCH + datetime.timedelta(days=math.floor(seconds / 86400.0))


def _tile_size_mm(tile_size_m: float) -> int:
    allowed = f"a whole number of metres in [1, {MAX_TILE_SIZE_M}]"
    try:
        size = float(tile_size_m)
    except (TypeError, ValueError):
        raise InputError("tile_size_m", tile_size_m, allowed) from None
    if not (math.isfinite(size) and size.is_integer() and 1 <= size <= MAX_TILE_SIZE_M):
        raise InputError("tile_size_m", tile_size_m, allowed)
    return int(size) * _MM_PER_M


def _validated_crs(crs) -> pyproj.CRS:
    """``crs`` as a pyproj CRS that is projected, in metres, and has a WKT1 form."""
    allowed = "a projected CRS in metres that has an OGC WKT1 form (e.g. EPSG:32648)"
    try:
        crs = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError:
        raise InputError("crs", crs, allowed) from None
    horizontal_units = {axis.unit_name for axis in crs.axis_info[:2]}
    if not crs.is_projected or not horizontal_units <= {"metre", "meter"}:
        raise InputError("crs", crs.name, allowed)
    if wkt1(crs) is None:
        raise InputError("crs", crs.name, allowed)
    return crs


def wkt1(crs: pyproj.CRS) -> str | None:
    """The OGC WKT1 (GDAL flavour) of ``crs``, or None where PROJ has none (pyproj may raise instead)."""
    try:
        return crs.to_wkt(WktVersion.WKT1_GDAL)
    except pyproj.exceptions.CRSError:
        return None


def _check_header_fields(creation_date: datetime.date, software: str) -> None:
    """Raise :class:`InputError` unless the tiles' creation date and generating software can be written."""
    if not isinstance(creation_date, datetime.date):
        raise InputError("creation_date", creation_date, "a datetime.date")
    if not (isinstance(software, str) and software.isascii() and len(software) <= 32):
        raise InputError("software", software, "an ASCII string of at most 32 characters")


def _tile_header_template(
    crs: pyproj.CRS, creation_date: datetime.date, software: str, dims: tuple[tuple, ...]
) -> laspy.LasHeader:
    """Header shared by every tile (all but the offsets). laspy is imported here, where a run first needs it."""
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    _check_header_fields(creation_date, software)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.system_identifier = SYSTEM_IDENTIFIER
    header.generating_software = software
    header.creation_date = creation_date
    header.file_source_id = 0  # a tile mixes flight lines; point_source_id carries the line
    header.scales = np.array([SCALE_M, SCALE_M, SCALE_M])
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.global_encoding.wkt = True
    header.vlrs.append(WktCoordinateSystemVlr(wkt1(crs)))
    header.add_extra_dims(
        [laspy.ExtraBytesParams(name, dtype, description) for name, _, dtype, description in dims]
    )
    # laspy 2.7 flags min/max as valid but tracks them wrongly for 1-D fields (the first value of
    # each write; laspy issue #346): claim no statistics rather than wrong ones.
    for vlr in header.vlrs.get("ExtraBytesVlr"):  # none when ``dims`` is empty
        for descriptor in vlr.extra_bytes_structs:
            descriptor.options = 0
    return header


def _quantized_mm(values: np.ndarray, name: str) -> np.ndarray:
    """``values`` [m] rounded to the 1 mm grid, as int64 [mm]."""
    scaled = np.rint(values / SCALE_M)
    if not np.all(np.abs(scaled) < 2.0**62):
        raise ValueError(f"{name} must be finite world coordinates [m]")
    return scaled.astype(np.int64)
