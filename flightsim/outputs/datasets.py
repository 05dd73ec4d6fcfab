"""A run's files as the in-memory objects users analyse: a georeferencing model's LAS tiles as one
``laspy.LasData``, ``waveforms.h5`` as an ``xarray.Dataset`` (dims shot × sample, GEDI L1B names) and the photons as an
``xarray.Dataset`` (dim photon, ATL03 names)."""
from __future__ import annotations

from pathlib import Path

import h5py
import laspy
import numpy as np
import pyproj
import xarray as xr

from flightsim.scoring.signal_finder import SignalFinder

GEOLOCATION = {"x_bin0": "x_bin0", "y_bin0": "y_bin0", "z_bin0": "elevation_bin0", "x_lastbin": "x_lastbin",
               "y_lastbin": "y_lastbin", "z_lastbin": "elevation_lastbin", "latitude_bin0": "latitude_bin0",
               "longitude_bin0": "longitude_bin0", "latitude_lastbin": "latitude_lastbin",
               "longitude_lastbin": "longitude_lastbin"}  # waveforms.h5 geolocation/ name -> GEDI L1B name


def las_points(paths: list[Path]) -> laspy.LasData:
    """The points of LAS/LAZ tiles (one tile set: same point format, extra bytes and CRS) as one LasData, its
    offsets at the tiles' least corner; every dimension kept, coordinates as the tiles store them (1 mm grid)."""
    tiles = [laspy.read(p) for p in paths]
    if not tiles:
        return laspy.LasData(laspy.LasHeader(point_format=6, version="1.4"))
    header = laspy.LasHeader(point_format=tiles[0].header.point_format, version=tiles[0].header.version)
    header.scales = tiles[0].header.scales
    header.offsets = np.min([t.header.offsets for t in tiles], axis=0)
    header.vlrs.extend(v for v in tiles[0].header.vlrs if v.record_id != 4)  # the CRS (the extra bytes come back)
    header.global_encoding = tiles[0].header.global_encoding
    las = laspy.LasData(header)
    las.points = laspy.ScaleAwarePointRecord.zeros(sum(len(t.points) for t in tiles), header=header)
    for name in tiles[0].point_format.dimension_names:
        if name not in ("X", "Y", "Z"):
            las[name] = np.concatenate([np.asarray(t[name]) for t in tiles])
    las.x, las.y, las.z = (np.concatenate([np.asarray(getattr(t, a)) for t in tiles]) for a in "xyz")
    return las


def waveform_dataset(path: Path) -> xr.Dataset:
    """Every waveform of ``waveforms.h5`` (all beams, in file order): ``rxwaveform`` and ``txwaveform`` (shot ×
    sample [W]), ``shot_number``, ``beam``, ``delta_time``, the geolocation of the first and last sample, the
    ranging and the truth of each shot; ``sample_interval_s`` and the config as attributes."""
    with h5py.File(path) as f:
        beams = sorted(name for name in f if name.startswith("BEAM"))
        parts = [_beam_dataset(f[name], int(name[4:])) for name in beams]
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    if not parts:
        return xr.Dataset(attrs=attrs)
    return xr.concat(parts, dim="shot").assign_attrs(attrs)


def _beam_dataset(group, beam: int) -> xr.Dataset:
    n = group["shot_number"].shape[0]
    rx_count = int(group["rx_sample_count"][0]) if n else 0
    tx_count = int(group["tx_sample_count"][0]) if n else 0
    shot = {name: ("shot", group[name][:]) for name in ("shot_number", "delta_time", "rx_window_start_s",
                                                        "tx_window_start_s", "line_id", "pulse")}
    shot["beam"] = ("shot", np.full(n, beam, dtype=np.int32))
    shot.update({GEOLOCATION[k]: ("shot", group[f"geolocation/{k}"][:]) for k in GEOLOCATION
                 if f"geolocation/{k}" in group})
    for section in ("ranging", "truth"):
        for name, data in group[section].items():
            shot[f"{name}"] = (("shot", "component") if data.ndim == 2 else "shot", data[:])
    shot["rxwaveform"] = (("shot", "sample"), group["rxwaveform"][:].reshape(n, rx_count))
    shot["txwaveform"] = (("shot", "tx_sample"), group["txwaveform"][:].reshape(n, tx_count))
    return xr.Dataset(shot)


def photon_dataset(directory: Path) -> xr.Dataset:
    """Every photon of a photon run (dim photon): from orbit ``atl03.h5``'s heights of all beams (``h_ph``,
    ``lat_ph``, ``lon_ph``, ``delta_time``, ``signal_conf_ph``, ``dist_ph_along``, ``ph_id_pulse``, ``truth_kind``,
    ``beam``); otherwise the same names from ``photons.h5`` (heights as the scene CRS's, latitude and longitude in
    its geodetic CRS, the signal confidence by the same ATL03-style signal finder over each line)."""
    atl03 = directory / "atl03.h5"
    return _from_atl03(atl03) if atl03.is_file() else _from_photons(directory / "photons.h5")


def _from_atl03(path: Path) -> xr.Dataset:
    parts = []
    with h5py.File(path) as f:
        for name in sorted(f):
            heights = f[f"{name}/heights"]
            columns = {k: ("photon", heights[k][:]) for k in heights}
            columns["beam"] = ("photon", np.full(heights["h_ph"].shape[0], name))
            parts.append(xr.Dataset(columns))
    return xr.concat(parts, dim="photon") if parts else xr.Dataset()


def _from_photons(path: Path) -> xr.Dataset:
    with h5py.File(path) as f:
        p = {k: f[f"photons/{k}"][:] for k in f["photons"]}
        crs = pyproj.CRS.from_wkt(f.attrs["crs_wkt"])
    lon, lat = pyproj.Transformer.from_crs(crs, crs.geodetic_crs, always_xy=True).transform(p["x"], p["y"])
    along = np.zeros(len(p["x"]))
    conf = np.zeros(len(p["x"]), dtype=np.int8)
    for line in np.unique(p["line_id"]):
        rows = np.flatnonzero(p["line_id"] == line)
        along[rows] = np.hypot(p["x"][rows] - p["x"][rows[0]], p["y"][rows] - p["y"][rows[0]])
        conf[rows] = SignalFinder().classify(along[rows], p["z"][rows], p["pulse"][rows])
    return xr.Dataset({"h_ph": ("photon", p["z"]), "lat_ph": ("photon", np.asarray(lat)),
                       "lon_ph": ("photon", np.asarray(lon)), "delta_time": ("photon", p["delta_time"]),
                       "signal_conf_ph": ("photon", conf), "dist_ph_along": ("photon", along),
                       "ph_id_pulse": ("photon", p["pulse"]), "truth_kind": ("photon", p["signal"].astype(np.int8)),
                       "beam": ("photon", p["pixel"]), "range_m": ("photon", p["range_m"])})
