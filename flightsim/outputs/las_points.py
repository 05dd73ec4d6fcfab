"""Points as flightsim writes and reads them: :class:`PointBatch`, equal-length arrays with one entry per
returned point, and :func:`read_points`, the points of LAS/LAZ files (1.2–1.4, ours or anyone's)."""
from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.outputs.las_format import SCAN_ANGLE_UNIT_DEG

if TYPE_CHECKING:
    import laspy


@dataclasses.dataclass
class PointBatch:
    """Equal-length 1-D arrays, one entry per returned point.

    Arrays are converted to the dtypes below on construction: an integer field takes integers
    that fit its dtype (floats are an error, never truncated), a float field takes any numbers.
    The ``None``-able fields are ``None`` for points read from LAS files without our extra bytes.
    """

    x: np.ndarray  #: world easting [m], float64
    y: np.ndarray  #: world northing [m], float64
    z: np.ndarray  #: world height [m], float64
    gps_time: np.ndarray  #: adjusted standard GPS time [s], float64 (NaN: not in the file)
    point_source_id: np.ndarray  #: flight line, uint16
    classification: np.ndarray  #: ASPRS class, uint8
    scan_angle_deg: np.ndarray  #: signed off-nadir angle [deg], float32
    intensity: np.ndarray  #: uint16
    beam_row: np.ndarray | None  #: DOE row i, uint8
    beam_col: np.ndarray | None  #: DOE column j, uint8
    prism_angle_deg: np.ndarray | None  #: prism angle φ [deg], float32
    range_m: np.ndarray | None  #: one-way range [m], float32
    plane_id: np.ndarray  #: scene plane id, int32 (-1: none / unknown)
    position_error_m: np.ndarray | None = None  #: true 3-D position error [m], float32
    edge_distance_m: np.ndarray | None = None  #: true hit to its plane's boundary, capped [m], float32

    def __post_init__(self) -> None:
        n = None
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if value is None:
                if field.name not in _OPTIONAL_FIELDS:
                    raise ValueError(f"PointBatch.{field.name} must be an array, not None")
                continue
            array = _converted(field.name, np.asarray(value))
            if array.ndim != 1:
                raise ValueError(f"PointBatch.{field.name} must be 1-D, got shape {array.shape}")
            if n is None:
                n = len(array)
            elif len(array) != n:
                raise ValueError(f"PointBatch.{field.name} has {len(array)} entries, x has {n}")
            setattr(self, field.name, array)

    def __len__(self) -> int:
        return len(self.x)

    def select(self, mask: np.ndarray) -> PointBatch:
        """The points picked by a boolean mask or an index array."""
        return PointBatch(
            **{
                name: None if value is None else value[mask]
                for name, value in self._arrays().items()
            }
        )

    @staticmethod
    def concatenate(batches: Sequence[PointBatch]) -> PointBatch:
        """All points of ``batches`` in order; an optional field is None if any batch lacks it."""
        if not batches:
            raise ValueError("PointBatch.concatenate needs at least one batch")
        columns = {}
        for name in _FIELD_DTYPES:
            parts = [getattr(batch, name) for batch in batches]
            columns[name] = None if any(p is None for p in parts) else np.concatenate(parts)
        return PointBatch(**columns)

    def _arrays(self) -> dict[str, np.ndarray | None]:
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}


_FIELD_DTYPES = {
    "x": np.float64,
    "y": np.float64,
    "z": np.float64,
    "gps_time": np.float64,
    "point_source_id": np.uint16,
    "classification": np.uint8,
    "scan_angle_deg": np.float32,
    "intensity": np.uint16,
    "beam_row": np.uint8,
    "beam_col": np.uint8,
    "prism_angle_deg": np.float32,
    "range_m": np.float32,
    "plane_id": np.int32,
    "position_error_m": np.float32,
    "edge_distance_m": np.float32,
}
_OPTIONAL_FIELDS = frozenset(
    {"beam_row", "beam_col", "prism_angle_deg", "range_m", "position_error_m", "edge_distance_m"}
)


def _converted(name: str, array: np.ndarray) -> np.ndarray:
    """``array`` as the dtype of field ``name``: integers must fit, floats never become ints."""
    dtype = np.dtype(_FIELD_DTYPES[name])
    if dtype.kind in "iu":
        if array.dtype.kind not in "biu":
            raise ValueError(f"PointBatch.{name} must hold integers, got {array.dtype}")
        info = np.iinfo(dtype)
        if array.size and (array.min() < info.min or array.max() > info.max):
            raise ValueError(f"PointBatch.{name} has values outside the {dtype} range")
    elif array.dtype.kind not in "biuf":
        raise ValueError(f"PointBatch.{name} must hold numbers, got {array.dtype}")
    return array.astype(dtype, copy=False)


def read_points(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
) -> tuple[PointBatch, pyproj.CRS | None]:
    """All points of one or more LAS/LAZ files (1.2–1.4), and their CRS.

    Fields absent from a file are filled in: ``gps_time`` NaN, ``plane_id`` -1, and
    ``beam_row``/``beam_col``/``prism_angle_deg``/``range_m``/``position_error_m``/``edge_distance_m`` None (None
    for all files if any file lacks the field). The CRS is the one the files declare (None if
    none does; an unparsable CRS record is ignored with a warning); files declaring different
    CRSs are refused.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = list(paths)
    if not paths:
        raise InputError("paths", paths, "at least one LAS/LAZ file")
    import laspy  # here: a run that only writes points does not load laspy before its first ray

    batches = []
    crs = None
    for path in paths:
        try:
            las = laspy.read(path)
        except (OSError, laspy.LaspyException) as err:
            raise InputError("path", str(path), f"a readable LAS/LAZ file ({err})") from err
        batches.append(_batch_from_las(las))
        file_crs = _file_crs(las.header, path)
        if file_crs is not None:
            if crs is not None and file_crs != crs:
                allowed = f"a file in the same CRS as the others ({crs.name})"
                raise InputError("path", str(path), allowed)
            crs = file_crs
    return PointBatch.concatenate(batches), crs


def _batch_from_las(las: laspy.LasData) -> PointBatch:
    names = set(las.point_format.dimension_names)
    n = len(las.points)

    def extra(las_name: str) -> np.ndarray | None:
        return np.asarray(las[las_name]) if las_name in names else None

    if "scan_angle" in names:  # point formats 6-10: int16 in 0.006 deg
        scan_angle = np.asarray(las["scan_angle"], dtype=np.float64) * SCAN_ANGLE_UNIT_DEG
    else:  # point formats 0-5: int8 in whole degrees
        scan_angle = np.asarray(las["scan_angle_rank"], dtype=np.float64)
    plane_id = extra("plane_id")
    return PointBatch(
        x=np.asarray(las.x, dtype=np.float64),
        y=np.asarray(las.y, dtype=np.float64),
        z=np.asarray(las.z, dtype=np.float64),
        gps_time=np.asarray(las["gps_time"]) if "gps_time" in names else np.full(n, np.nan),
        point_source_id=np.asarray(las["point_source_id"]),
        classification=np.asarray(las["classification"]),
        scan_angle_deg=scan_angle.astype(np.float32),
        intensity=np.asarray(las["intensity"]),
        beam_row=extra("beam_row"),
        beam_col=extra("beam_col"),
        prism_angle_deg=extra("prism_angle"),
        range_m=extra("range"),
        plane_id=np.full(n, -1, dtype=np.int32) if plane_id is None else plane_id,
        position_error_m=extra("position_error"),
        edge_distance_m=extra("edge_distance"),
    )


def _file_crs(header: laspy.LasHeader, path) -> pyproj.CRS | None:
    try:
        return header.parse_crs()
    except pyproj.exceptions.CRSError as err:
        warnings.warn(f"{path}: ignoring a CRS record pyproj cannot parse ({err})", stacklevel=3)
        return None
