"""GEDI L2A-like metrics as HDF5 (h5py): ``l2a.h5``, per beam a group ``BEAMbbbb`` with one row per shot, the
names and types of the GEDI L2A data dictionary (``flightsim.outputs.l2a`` computes the metrics):

BEAMbbbb/shot_number                  uint64   as in waveforms.h5 (line_id · 2³² + pulse)
BEAMbbbb/beam                         uint16   the beam number
BEAMbbbb/delta_time                   float64  time of the shot [s]
BEAMbbbb/rh                           float32  (shots, 101) relative heights rh0 … rh100 above the lowest mode [m]
BEAMbbbb/elev_lowestmode, elev_highestreturn                          float64  [m]
BEAMbbbb/lat_lowestmode, lon_lowestmode, lat_highestreturn, lon_highestreturn  float64  [deg]
BEAMbbbb/num_detectedmodes            uint8
BEAMbbbb/sensitivity                  float32  maximum canopy cover the waveform's SNR can penetrate
BEAMbbbb/quality_flag                 uint8    1: a signal and sensitivity ≥ its threshold
BEAMbbbb/energy_total                 float32  energy above the noise mean [rx units · s]
BEAMbbbb/truth/elev_ground            float64  the simulator's true ground elevation [m]
BEAMbbbb/truth/rh                     float32  (shots, 101) rh of the noise-free energy profile above it [m]

-9999 in elevations, positions and rh: no signal. Beam attributes ``pulse_sigma_s``, ``footprint_sigma_m``,
``rho_ground``, ``rho_canopy`` when given; file attributes as given, and ``flightsim``. Written under a
temporary name and renamed when complete; bad input raises InputError before anything is written.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.outputs.h5_product import H5Product

COLUMNS = {  # name: (dtype, units, description)
    "shot_number": (np.uint64, "", "unique shot identifier"),
    "delta_time": (np.float64, "s", "time of the shot"),
    "rh": (np.float32, "m", "relative height metrics at 1 % intervals above the lowest mode"),
    "elev_lowestmode": (np.float64, "m", "elevation of the centre of the lowest mode"),
    "elev_highestreturn": (np.float64, "m", "elevation of the highest detected return"),
    "lat_lowestmode": (np.float64, "degrees", "latitude of the centre of the lowest mode"),
    "lon_lowestmode": (np.float64, "degrees", "longitude of the centre of the lowest mode"),
    "lat_highestreturn": (np.float64, "degrees", "latitude of the highest detected return"),
    "lon_highestreturn": (np.float64, "degrees", "longitude of the highest detected return"),
    "num_detectedmodes": (np.uint8, "", "number of detected modes"),
    "sensitivity": (np.float32, "", "maximum canopy cover that can be penetrated"),
    "quality_flag": (np.uint8, "", "1: a signal was found and sensitivity clears its threshold"),
    "energy_total": (np.float32, "", "integrated return energy above the mean noise"),
}
TRUTH = {
    "elev_ground": (np.float64, "m", "true ground elevation (simulator)"),
    "rh": (np.float32, "m", "rh of the noise-free energy profile above the true ground"),
}
BEAM_ATTRS = ("pulse_sigma_s", "footprint_sigma_m", "rho_ground", "rho_canopy")
_INTEGER_RANGE = {np.uint64: (0, np.iinfo(np.uint64).max), np.uint8: (0, 255)}


def write_l2a(path: str | os.PathLike, beams: dict[int, dict], truth: dict[int, dict] | None = None,
              attrs: dict | None = None) -> Path:
    """Write ``l2a.h5``; returns its path.

    Args:
        beams: beam number (0 … 9999) → its columns: every name of :data:`COLUMNS` ((shots,) arrays, ``rh``
            (shots, 101)), as :func:`flightsim.outputs.l2a.l2a_metrics` returns them plus ``shot_number`` and
            ``delta_time``; and optionally the scalars of :data:`BEAM_ATTRS` (written as the group's attributes).
        truth: beam number → ``elev_ground`` (shots,) and ``rh`` (shots, 101), or None.
        attrs: file attributes (e.g. ``config_toml``, ``crs_wkt``).
    """
    truth = truth or {}
    if not beams:
        raise InputError("beams", "{}", "at least one beam")
    unknown = sorted(set(truth) - set(beams))
    if unknown:
        raise InputError("truth", f"beam {unknown[0]}", "truth only for beams in beams")
    checked = {b: _beam(b, beams[b], truth.get(b)) for b in beams}
    product = H5Product(Path(path), **(attrs or {}))
    try:
        for b, (columns, truth_columns, beam_attrs) in checked.items():
            _write_group(product, f"BEAM{b:04d}", columns, COLUMNS)
            if truth_columns:
                _write_group(product, f"BEAM{b:04d}/truth", truth_columns, TRUTH)
            product.file[f"BEAM{b:04d}"].attrs.update(beam_attrs)
    except BaseException:
        product.abort()
        raise
    product.close()
    return Path(path)


def _beam(b, values: dict, truth: dict | None) -> tuple[dict, dict, dict]:
    """One beam's columns, truth columns and attributes, checked and cast to their dtypes."""
    if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 0 <= b <= 9999:
        raise InputError("beams", b, "beam numbers: integers in [0, 9999]")
    extra = sorted(set(values) - set(COLUMNS) - set(BEAM_ATTRS))
    if extra:
        raise InputError(f"beams[{b}]", extra[0], f"one of {sorted(COLUMNS)} or {list(BEAM_ATTRS)}")
    shots = (np.shape(values.get("shot_number"))[:1] or (0,))[0]
    columns = _columns(f"beams[{b}]", values, COLUMNS, shots)
    truth_columns = {}
    if truth is not None:
        extra = sorted(set(truth) - set(TRUTH))
        if extra:
            raise InputError(f"truth[{b}]", extra[0], f"one of {sorted(TRUTH)}")
        truth_columns = _columns(f"truth[{b}]", truth, TRUTH, shots)
    beam_attrs = {}
    for name in BEAM_ATTRS:
        if name in values:
            value = np.asarray(values[name], dtype=np.float64)
            if value.shape != () or not np.isfinite(value):
                raise InputError(f"beams[{b}].{name}", values[name], "one finite number")
            beam_attrs[name] = float(value)
    columns["beam"] = np.full(shots, b, np.uint16)
    return columns, truth_columns, beam_attrs


def _columns(where: str, values: dict, table: dict, shots: int) -> dict[str, np.ndarray]:
    """Every column of the table from ``values``: (shots,), or (shots, 101) for rh, finite, in their dtype's
    range, cast to it."""
    out = {}
    for name, (dtype, _, _) in table.items():
        if name not in values:
            raise InputError(f"{where}.{name}", "missing", "every column of the product")
        column = np.asarray(values[name])
        shape = (shots, 101) if name == "rh" else (shots,)
        if column.shape != shape or column.dtype.kind not in "biuf":
            raise InputError(f"{where}.{name}", f"shape {column.shape}", f"{shape} numbers, one row per shot")
        if not np.isfinite(column.astype(np.float64)).all():
            raise InputError(f"{where}.{name}", "a non-finite value", "finite values")
        if dtype in _INTEGER_RANGE:
            lo, hi = _INTEGER_RANGE[dtype]
            if column.dtype.kind == "f" or (len(column) and (column.min() < lo or column.max() > hi)):
                raise InputError(f"{where}.{name}", f"dtype {column.dtype}", f"integers in [{lo}, {hi}]")
        out[name] = column.astype(dtype)
    return out


def _write_group(product: H5Product, group: str, columns: dict, table: dict) -> None:
    """Append the columns (rh gzip-compressed) and label each dataset with its units and description."""
    product.append(group, columns, compress=True)
    for name in columns:
        dtype, units, description = table.get(name, (None, "", "beam number"))
        product.file[f"{group}/{name}"].attrs.update(units=units, description=description)
