"""A run's files as the in-memory objects users analyse: a georeferencing model's LAS tiles as one
``laspy.LasData``, ``waveforms.h5`` as an ``xarray.Dataset`` (dims shot × sample, GEDI L1B names), the photons as an
``xarray.Dataset`` (dim photon, ATL03 names), ``atl08.h5``'s land segments (dim segment, ATL08 names), ``l2a.h5``
(dim shot, GEDI L2A names) and ``chm.tif`` as an ``xarray.DataArray`` (y × x)."""
from __future__ import annotations

from pathlib import Path

import h5py
import laspy
import numpy as np
import pyproj
import xarray as xr

from flightsim.outputs.chm import MAX_CELLS
from flightsim.scenes.raster import read_raster
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
        attrs = _attrs(f)
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
    ``lat_ph``, ``lon_ph``, ``delta_time`` (ATL03's: since the SDP epoch), ``signal_conf_ph`` (its first surface
    type's column, land), ``dist_ph_along`` (from the photon's 20 m segment's start), ``x_atc``, ``ph_id_pulse``,
    ``truth_kind``, ``beam``); otherwise the same names from ``photons.h5`` (heights as the scene CRS's, latitude and
    longitude in its geodetic CRS, the signal confidence by the same ATL03-style signal finder over each line,
    ``dist_ph_along`` and ``x_atc`` both the distance from the line's first photon)."""
    atl03 = directory / "atl03.h5"
    return _from_atl03(atl03) if atl03.is_file() else _from_photons(directory / "photons.h5")


def _from_atl03(path: Path) -> xr.Dataset:
    parts = []
    with h5py.File(path) as f:
        for name in sorted(n for n in f if n.startswith("gt") and "heights" in f[n]):
            heights = f[f"{name}/heights"]
            columns = {k: ("photon", heights[k][:] if heights[k].ndim == 1 else heights[k][:, 0]) for k in heights}
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
                       "signal_conf_ph": ("photon", conf), "dist_ph_along": ("photon", along), "x_atc": ("photon", along),
                       "ph_id_pulse": ("photon", p["pulse"]), "truth_kind": ("photon", p["signal"].astype(np.int8)),
                       "beam": ("photon", p["pixel"]), "range_m": ("photon", p["range_m"])})


def atl08_dataset(path: Path) -> xr.Dataset:
    """The land segments of every ground track of ``atl08.h5`` (dim segment, tracks in name order, each in
    along-track order): ATL08's names without their groups (``h_te_mean``, ``h_canopy``, ``n_ca_photons``, …,
    :mod:`flightsim.outputs.atl08_h5`), their ``units``, and the coordinate ``beam`` (the track, "gt1", …). Heights
    that hold ATL08's ``_FillValue`` (too few photons: no canopy over bare ground) are NaN, as xarray decodes
    CF fill values; the file's attributes are the dataset's."""
    parts = []
    with h5py.File(path) as f:
        for track in sorted(f):
            columns = {}
            f[f"{track}/land_segments"].visititems(lambda name, item: columns.update(
                {name.split("/")[-1]: _decoded(item)} if isinstance(item, h5py.Dataset) else {}))
            n = len(next(iter(columns.values()))[1]) if columns else 0
            parts.append(xr.Dataset(columns, coords={"beam": ("segment", np.full(n, track))}))
        attrs = _attrs(f)
    return (xr.concat(parts, dim="segment") if parts else xr.Dataset()).assign_attrs(attrs)


def _decoded(dataset) -> tuple:
    """A 1-D dataset as an xarray variable on dim segment: its _FillValue as NaN, its units kept."""
    values, fill = dataset[:], dataset.attrs.get("_FillValue")
    if fill is not None:
        values = np.where(values == fill, np.nan, values).astype(values.dtype)
    return "segment", values, {"units": _text(dataset.attrs.get("units", ""))}


def l2a_dataset(path: Path) -> xr.Dataset:
    """Every shot of ``l2a.h5`` (dim shot, beams in number order): the GEDI L2A names of
    :mod:`flightsim.outputs.l2a_h5` with their ``units`` and ``description``, ``rh`` as shot × percentile
    (coordinate ``percentile`` 0 … 100 [%]), the simulator's truth as ``truth_elev_ground`` and ``truth_rh`` where
    the file has it, each beam's attributes (``pulse_sigma_s``, …) as per-shot variables; -9999 (no signal) kept as
    GEDI writes it; the file's attributes are the dataset's."""
    with h5py.File(path) as f:
        parts = [_l2a_beam(f[name]) for name in sorted(f) if name.startswith("BEAM")]
        attrs = _attrs(f)
    if not parts:
        return xr.Dataset(attrs=attrs)
    return xr.concat(parts, dim="shot").assign_coords(percentile=np.arange(101)).assign_attrs(attrs)


def _l2a_beam(group) -> xr.Dataset:
    def variable(dataset) -> tuple:
        dims = ("shot", "percentile") if dataset.ndim == 2 else ("shot",)
        return dims, dataset[:], {k: _text(dataset.attrs[k]) for k in ("units", "description") if k in dataset.attrs}

    columns = {name: variable(item) for name, item in group.items() if isinstance(item, h5py.Dataset)}
    if "truth" in group:
        columns.update({f"truth_{name}": variable(item) for name, item in group["truth"].items()})
    n = group["shot_number"].shape[0]
    columns.update({name: ("shot", np.full(n, value)) for name, value in group.attrs.items()})
    return xr.Dataset(columns)


def chm_array(path: Path) -> xr.DataArray:
    """``chm.tif`` as heights [m] (dims y × x, row 0 the northernmost), NaN where no data; coordinates ``x``, ``y``
    the cell centres in the raster's CRS [m], attributes ``crs`` (its WKT), ``units`` and ``cell_m``."""
    raster = read_raster(str(path), "chm", "a canopy height model GeoTIFF", MAX_CELLS)
    t, (rows, cols) = raster.transform, raster.values.shape
    heights = np.where(raster.valid, raster.values, np.nan)
    return xr.DataArray(heights, dims=("y", "x"), name="chm",
                        coords={"x": t.c + (np.arange(cols) + 0.5) * t.a, "y": t.f + (np.arange(rows) + 0.5) * t.e},
                        attrs={"crs": raster.crs.to_wkt(), "units": "m", "cell_m": float(t.a)})


def _attrs(f) -> dict:
    return {k: _text(v) for k, v in f.attrs.items()}


def _text(value):
    return value.decode() if isinstance(value, bytes) else value
