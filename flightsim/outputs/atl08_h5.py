"""ATL08-like land and vegetation heights as HDF5 (h5py): ``atl08.h5``, per beam a group ``gtN`` (or ``gtNl``,
``gtNr``) with the groups, names and types of the ICESat-2 ATL08 data dictionary
(``flightsim.outputs.atl08`` computes them):

gtx/land_segments/latitude, longitude            float32  segment middle [deg]
gtx/land_segments/delta_time                     float64  segment middle [s]
gtx/land_segments/segment_id_beg, segment_id_end int32    first and last ATL03 20 m segment
gtx/land_segments/n_seg_ph                       int32    photons in the segment
gtx/land_segments/terrain/h_te_mean, h_te_median float32  ground photon heights [m]
gtx/land_segments/terrain/n_te_photons           int32
gtx/land_segments/canopy/h_canopy                float32  98th percentile of canopy heights above ground [m]
gtx/land_segments/canopy/h_mean_canopy, canopy_openness  float32  their mean and standard deviation [m]
gtx/land_segments/canopy/n_ca_photons, n_toc_photons     int32
gtx/signal_photons/classed_pc_flag               int8     0 noise, 1 ground, 2 canopy, 3 top of canopy
gtx/signal_photons/classed_pc_indx               int32    1-based index of the photon in atl03.h5's heights
gtx/signal_photons/ph_segment_id                 int32    its ATL03 20 m segment
gtx/signal_photons/ph_h                          float32  height above the interpolated ground [m]
gtx/signal_photons/d_flag                        int8     1: dense (the density filter's signal)
gtx/signal_photons/delta_time                    float64  [s]

Unlike ATL08, ``signal_photons`` holds every photon (noise too), in the order given, so it lines up with
atl03.h5 row for row. Float heights carry ``_FillValue`` = 3.4028235e38 (ATL08's) where a segment has too few
photons. File attributes as given and ``flightsim``. Written under a temporary name and renamed when
complete; bad input raises InputError before anything is written.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.outputs.atl08 import FILL, PHOTON_COLUMNS, SEGMENT_COLUMNS, atl08_segments
from flightsim.outputs.h5_product import H5Product

LAYOUT = {  # column: (group below gtx, dtype, units)
    "latitude": ("land_segments", np.float32, "degrees_north"),
    "longitude": ("land_segments", np.float32, "degrees_east"),
    "delta_time": ("land_segments", np.float64, "seconds"),
    "segment_id_beg": ("land_segments", np.int32, "1"),
    "segment_id_end": ("land_segments", np.int32, "1"),
    "n_seg_ph": ("land_segments", np.int32, "1"),
    "h_te_mean": ("land_segments/terrain", np.float32, "meters"),
    "h_te_median": ("land_segments/terrain", np.float32, "meters"),
    "n_te_photons": ("land_segments/terrain", np.int32, "1"),
    "h_canopy": ("land_segments/canopy", np.float32, "meters"),
    "h_mean_canopy": ("land_segments/canopy", np.float32, "meters"),
    "canopy_openness": ("land_segments/canopy", np.float32, "meters"),
    "n_ca_photons": ("land_segments/canopy", np.int32, "1"),
    "n_toc_photons": ("land_segments/canopy", np.int32, "1"),
}
PHOTON_LAYOUT = {
    "classed_pc_flag": (np.int8, "1"), "classed_pc_indx": (np.int32, "1"), "ph_segment_id": (np.int32, "1"),
    "ph_h": (np.float32, "meters"), "d_flag": (np.int8, "1"), "delta_time": (np.float64, "seconds"),
}
ATL03_INPUTS = {"along_track_m": "x_atc", "h_ph": "h_ph", "lat": "lat_ph", "lon": "lon_ph",
                "signal_conf_ph": "signal_conf_ph", "delta_time": "delta_time"}  # atl08_segments' argument: atl03 name
_FILLED = ("h_te_mean", "h_te_median", "h_canopy", "h_mean_canopy", "canopy_openness", "ph_h")
_BEAM = re.compile(r"gt[1-9][0-9]*[lr]?")


def write_atl08(path: str | os.PathLike, beams: dict, attrs: dict | None = None) -> Path:
    """Write ``atl08.h5``; returns its path.

    Args:
        beams: ground track → the dict :func:`flightsim.outputs.atl08.atl08_segments` returns for it
            (``land_segments`` and ``signal_photons``). A track is a group name (``gt1l``, ``gt2``, …) or a
            beam number b >= 0, written ``gt{b+1}`` as atl03.h5 names it.
        attrs: file attributes (e.g. ``config_toml``).
    """
    if not beams:
        raise InputError("beams", "{}", "at least one ground track")
    checked = {_track(name): _beam(name, value) for name, value in beams.items()}
    if len(checked) != len(beams):
        raise InputError("beams", sorted(map(str, beams)), "distinct ground tracks")
    product = H5Product(Path(path), **(attrs or {}))
    try:
        for track, (segments, photons) in checked.items():
            for name, values in segments.items():
                _append(product, f"{track}/{LAYOUT[name][0]}", name, values, LAYOUT[name][2])
            for name, values in photons.items():
                _append(product, f"{track}/signal_photons", name, values, PHOTON_LAYOUT[name][1])
    except BaseException:
        product.abort()
        raise
    product.close()
    return Path(path)


def atl08_of_track(atl03_path: str | os.PathLike, track: str, segment_m: float, threads: int = 1) -> dict:
    """:func:`flightsim.outputs.atl08.atl08_segments` (default settings, on ``threads``) of one ground track of a
    finished atl03.h5, its photons read here (only the columns ATL08 needs: along-track distance ``x_atc``, height,
    latitude, longitude, the land column of the signal confidence, time): a worker process reads its own track."""
    import h5py

    with h5py.File(atl03_path, "r") as f:
        heights = f[f"{track}/heights"]
        columns = {arg: heights[name][:] for arg, name in ATL03_INPUTS.items()}
    if columns["signal_conf_ph"].ndim == 2:  # ATL03's (n, 5): ATL08 reads the land surface type's column
        columns["signal_conf_ph"] = columns["signal_conf_ph"][:, 0]
    return atl08_segments(**columns, segment_m=segment_m, threads=threads)


def write_atl08_track(path: str | os.PathLike, atl03_path: str | os.PathLike, track: str, segment_m: float,
                      threads: int = 1) -> str:
    """:func:`atl08_of_track` of one ground track written to a file of its own at ``path`` (its group as atl08.h5
    holds it, compressed here: a worker process writes its own track); the path."""
    return str(write_atl08(path, {track: atl08_of_track(atl03_path, track, segment_m, threads)}))


def join_atl08(path: str | os.PathLike, tracks: dict, attrs: dict | None = None) -> Path:
    """Write ``atl08.h5`` from the tracks' own files (track → path of :func:`write_atl08_track`), each track's group
    copied whole, its chunks as they were compressed; the same file :func:`write_atl08` makes of them all at once.
    Returns its path."""
    import h5py

    product = H5Product(Path(path), **(attrs or {}))
    try:
        for track, part in tracks.items():
            with h5py.File(part, "r") as f:
                f.copy(f[track], product.file, name=track)
    except BaseException:
        product.abort()
        raise
    product.close()
    return Path(path)


def _track(name) -> str:
    if isinstance(name, (int, np.integer)) and not isinstance(name, bool) and name >= 0:
        return f"gt{int(name) + 1}"
    if isinstance(name, str) and _BEAM.fullmatch(name):
        return name
    raise InputError("beams", name, "ground tracks named gtN, gtNl or gtNr, or beam numbers >= 0")


def _beam(name, value) -> tuple[dict, dict]:
    """One track's segment and photon columns, checked (same lengths, finite) and cast to ATL08's types."""
    if not isinstance(value, dict) or set(value) != {"land_segments", "signal_photons"}:
        raise InputError(f"beams[{name}]", type(value).__name__, "atl08_segments' dict: land_segments, signal_photons")
    segments = _columns(f"beams[{name}].land_segments", value["land_segments"], SEGMENT_COLUMNS,
                        {k: v[1] for k, v in LAYOUT.items()})
    photons = _columns(f"beams[{name}].signal_photons", value["signal_photons"], PHOTON_COLUMNS,
                       {k: v[0] for k, v in PHOTON_LAYOUT.items()})
    return segments, photons


def _columns(where: str, values: dict, names: tuple, dtypes: dict) -> dict[str, np.ndarray]:
    if not isinstance(values, dict) or set(values) != set(names):
        raise InputError(where, sorted(values) if isinstance(values, dict) else values, f"the columns {list(names)}")
    rows = len(np.asarray(values[names[0]]))
    out = {}
    for name in names:
        column = np.asarray(values[name])
        if column.shape != (rows,) or column.dtype.kind not in "iuf":
            raise InputError(f"{where}.{name}", f"shape {column.shape}", f"({rows},) numbers, like {names[0]}")
        if not np.isfinite(column).all():
            raise InputError(f"{where}.{name}", "a non-finite value", f"finite values ({FILL:g} where none)")
        if np.dtype(dtypes[name]).kind == "i" and column.dtype.kind == "f":
            raise InputError(f"{where}.{name}", f"dtype {column.dtype}", "integers")
        out[name] = column.astype(dtypes[name])
    return out


def _append(product: H5Product, group: str, name: str, values: np.ndarray, units: str) -> None:
    product.append(group, {name: values}, compress=True)
    dataset = product.file[f"{group}/{name}"]
    dataset.attrs["units"] = units
    if name in _FILLED:
        dataset.attrs["_FillValue"] = np.float32(FILL)
