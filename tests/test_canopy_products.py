"""The canopy products of runs and their readers in the Python API: atl08.h5 of an orbit photon pass over a forest
(h_canopy against the forest's true canopy height model under the footprints), over bare ground (terrain, canopy
fill values) and turned off; chm.tif of a discrete run over a forest against the true CHM and against the discrete
detector's trigger depth in the stand's leaf voxels (both computed here in float64); ``output.chm_m = 0``; and
``Result.l2a`` on a hand-written l2a.h5."""
from __future__ import annotations

import math

import h5py
import numpy as np
import pyproj
import pytest

import flightsim
from flightsim.api import Result
from flightsim.core.errors import InputError
from flightsim.engine.products.las import write_chm
from flightsim.instrument.pairs import SINGLE_BEAM
from flightsim.outputs.l2a_h5 import write_l2a
from flightsim.scenes.forest_scene import stand
from flightsim.scenes.forest_voxels import stand_voxels
from flightsim.studies.forest_truth import canopy_height_model

WGS84_A, WGS84_F = 6378137.0, 1.0 / 298.257223563


def _ecef(lat, lon, h) -> np.ndarray:
    """Earth-centred coordinates [m] of geodetic latitude, longitude [deg] and ellipsoidal height [m]."""
    phi, lam = np.radians(lat), np.radians(lon)
    e2 = WGS84_F * (2.0 - WGS84_F)
    n = WGS84_A / np.sqrt(1.0 - e2 * np.sin(phi) ** 2)
    return np.stack([(n + h) * np.cos(phi) * np.cos(lam), (n + h) * np.cos(phi) * np.sin(lam),
                     (n * (1.0 - e2) + h) * np.sin(phi)], axis=-1)


def _local_en(cfg, lat, lon, h) -> tuple[np.ndarray, np.ndarray]:
    """East, north [m] in the tangent plane at the scene origin (the orbit platform's local frame)."""
    lon0, lat0 = pyproj.Transformer.from_crs(cfg.scene.crs, "EPSG:4326", always_xy=True).transform(
        *cfg.scene.origin[:2])
    d = _ecef(lat, lon, h) - _ecef(lat0, lon0, cfg.scene.origin[2])
    phi, lam = math.radians(lat0), math.radians(lon0)
    east = np.array([-math.sin(lam), math.cos(lam), 0.0])
    north = np.array([-math.sin(phi) * math.cos(lam), -math.sin(phi) * math.sin(lam), math.cos(phi)])
    return d @ east, d @ north


def _file_segments(path) -> dict[str, np.ndarray]:
    """Every land-segment dataset of every track, concatenated in track order, fill values as NaN."""
    columns: dict[str, list] = {}
    with h5py.File(path) as f:
        for track in sorted(f):
            def add(name, item, track=track):
                if isinstance(item, h5py.Dataset):
                    values = item[:].astype(np.float64)
                    if "_FillValue" in item.attrs:
                        values[item[:] == item.attrs["_FillValue"]] = np.nan
                    columns.setdefault(name.split("/")[-1], []).append(values)
                    if name == "n_seg_ph":
                        columns.setdefault("beam", []).append(np.full(len(values), track))
            f[f"{track}/land_segments"].visititems(add)
    return {k: np.concatenate(v) for k, v in columns.items()}


def test_atl08_of_an_orbit_pass_over_a_forest_measures_the_canopy(tmp_path):
    """A 190 m stand (trees 20 ± 2 m) under a 0.0565 s pass (400 m of track, the scene origin at mid-pass): the
    100 m segments 1 and 2 lie over the stand. Truth per segment: the 98th percentile of the true CHM (0.25 m cells)
    at points of the Gaussian footprint (σ = 3 m: the fan's 0.024 mrad e⁻² full angle from 500 km) around each
    shot's footprint centre. ATL08's h_canopy is the 98th percentile of the leaf photons' heights above its ground,
    and leaf photons come from a Beer–Lambert depth below the crown surface (mean 1/(G·LAD) ≈ 5 m here), so it
    lies below the truth: by 0.3–2.7 m over seeds 0–7 (the 98th percentile of a Monte Carlo of that depth in the
    stand's voxels agreed with h_canopy to ±1 m). Bound: −3.0 m ≤ h_canopy − truth ≤ +0.5 m (+0.5: the ranging
    noise, σ 0.22 m); the ground under the stand within 0.5 m."""
    cfg = flightsim.load_config(instrument="atlas", overrides={
        **SINGLE_BEAM, "scene.name": "forest", "scene.forest_size_m": 190.0, "scene.forest_height_sd_m": 2.0,
        "photon.reflectance": 0.5, "flight.duration_s": 0.0565, "photon.gate_m": [499900.0, 500100.0]})
    result = flightsim.simulate(cfg)
    assert "atl08.h5" in result.stats["files"]
    with h5py.File(result.directory / "atl03.h5") as f:
        geo = {k: f[f"gt1/footprint/{k}"][:] for k in ("lat", "lon", "h")}
    east, north = _local_en(cfg, geo["lat"], geo["lon"], geo["h"])
    along = np.hypot(east - east[0], north - north[0])  # the first photon is over the first footprint (nadir)
    trees = stand(cfg.scene, cfg.run.seed)
    cell = 0.25
    chm, west, top = canopy_height_model(trees, cell)
    file = _file_segments(result.directory / "atl08.h5")
    segment = (file["segment_id_beg"] - 1) // 5  # 100 m segments of 20 m ATL03 segments
    rng = np.random.default_rng(0)
    checked = 0
    for k in (1, 2):
        shots = (along >= 100.0 * k) & (along < 100.0 * (k + 1))
        assert np.abs(north[shots]).max() < 100.0 and np.abs(east[shots]).max() < 20.0  # over the stand (±95 m)
        spots = rng.normal(0.0, 3.0, (shots.sum(), 400, 2))
        col = np.floor((east[shots, None] + spots[..., 0] - west) / cell).astype(np.int64)
        row = np.floor((top - north[shots, None] - spots[..., 1]) / cell).astype(np.int64)
        inside = (col >= 0) & (col < chm.shape[1]) & (row >= 0) & (row < chm.shape[0])
        truth = np.percentile(np.where(inside, chm[np.clip(row, 0, chm.shape[0] - 1),
                                                   np.clip(col, 0, chm.shape[1] - 1)], 0.0), 98)
        (j,) = np.flatnonzero(segment == k)
        assert -3.0 <= file["h_canopy"][j] - truth <= 0.5, (k, file["h_canopy"][j], truth)
        assert abs(file["h_te_mean"][j] - cfg.scene.origin[2]) < 0.5
        checked += 1
    assert checked == 2
    ds = result.atl08
    assert set(ds.data_vars) == set(file) - {"beam"} and list(ds.beam.values) == list(file["beam"])
    for name, values in file.items():
        np.testing.assert_array_equal(ds[name].values.astype(values.dtype), values, err_msg=name)
    assert ds.h_canopy.attrs["units"] == "meters" and "config_toml" in ds.attrs


def test_atl08_over_bare_ground_has_terrain_and_fill_values_and_can_be_turned_off(tmp_path):
    """The atlas pass over its plane (at the scene origin's height): terrain heights within 0.15 m (the dead
    time's pile-up biases ATL03's ground photons upwards by a few cm) and no canopy: fill values, NaN in the
    API. With ``output.atl08 = false`` no atl08.h5."""
    overrides = {**SINGLE_BEAM, "flight.duration_s": 0.03, "photon.gate_m": [499900.0, 500100.0]}
    result = flightsim.simulate(flightsim.load_config(instrument="atlas", overrides=overrides))
    ds = result.atl08
    assert result.stats["files"] == ["photons.h5", "photons", "atl03.h5", "atl08.h5"]
    assert ds.sizes["segment"] >= 2 and set(ds.beam.values) == {"gt1"}
    assert np.abs(ds.h_te_mean.values - result.cfg.scene.origin[2]).max() < 0.15
    assert np.isnan(ds.h_canopy.values).all() and np.isnan(ds.canopy_openness.values).all()
    with h5py.File(result.directory / "atl08.h5") as f:
        stored = f["gt1/land_segments/canopy/h_canopy"]
        assert (stored[:] == stored.attrs["_FillValue"]).all()
    off = flightsim.simulate(flightsim.load_config(instrument="atlas", overrides={**overrides,
                                                                                 "flight.duration_s": 0.005,
                                                                                 "output.atl08": False}))
    assert off.stats["files"] == ["photons.h5", "photons", "atl03.h5"]
    assert not (off.directory / "atl08.h5").exists() and off.atl08 is None


def _voxel_first_returns(cfg, trees) -> tuple[np.ndarray, np.ndarray]:
    """Height above the ground [m] where the discrete detector triggers in each vertical column of the stand's leaf
    voxels, (nx, ny) east, north, 0 where the column's leaves never reach the threshold; and the voxels' lower
    corner. Closed form of kernels/canopy_returns.py: the leaves send back ρ_l(1 − exp(−τ)) of a beam after an
    optical depth τ = G·∫LAD ds (G = 0.5, spherical), so the first return is at τ* = −ln(1 − threshold/ρ_l) along a
    beam of 15° off nadir (the Risley cone): ds = dz / cos 15°."""
    lad, lower, cell = stand_voxels(trees, cfg.scene.forest_voxel_m)
    tau_star = -math.log(1.0 - cfg.discrete.threshold / cfg.scene.forest_leaf_reflectance)
    tau = 0.5 * lad[:, :, ::-1].astype(np.float64) * cell[2] / math.cos(math.radians(15.0))  # top down
    depth = np.cumsum(tau, axis=2)
    k = np.argmax(depth >= tau_star, axis=2)
    i, j = np.indices(k.shape)
    before = np.where(k > 0, depth[i, j, np.maximum(k - 1, 0)], 0.0)
    fraction = (tau_star - before) / np.maximum(tau[i, j, k], 1e-300)
    heights = lower[2] + cell[2] * (lad.shape[2] - k - fraction)
    return np.where(depth[..., -1] >= tau_star, heights, 0.0), lower


def test_chm_of_a_discrete_run_over_a_forest(tmp_path):
    """The default Risley instrument 150 m over a 60 m stand for 2 s (exact model only). In the cells of 1 m with
    at least 10 first returns over a crown (true CHM > 2 m), chm.tif is the true CHM (highest crown top over the
    cell) minus the trigger depth: in a crown's full leaf density (LAD ≈ 0.38 m²/m³) τ* = 0.118 takes 0.6 m, but
    the top voxels hold only the part of the crown inside them, so in the voxel columns the first return lies
    ≈ 1.4 m below the crown top (computed here from the voxels). Bounds: bias vs the truth in [−2.0, −0.6] m and
    within 0.4 m of the voxels' prediction; RMSE < 1.8 m (the scan's beams cross neighbouring columns: 15° off
    nadir); the median difference from the voxels' prediction within 0.25 m. Open cells (true CHM 0) are 0."""
    cfg = flightsim.load_config(overrides={"scene.name": "forest", "scene.forest_size_m": 60.0,
                                           "flight.duration_s": 2.0, "flight.altitude_m": 150.0,
                                           "output.models": ["exact"]})
    result = flightsim.simulate(cfg)
    assert result.stats["chm"]["file"] == "chm.tif" and result.stats["chm"]["cell_m"] == 1.0
    chm = result.chm
    assert pyproj.CRS.from_wkt(chm.attrs["crs"]) == pyproj.CRS(cfg.scene.crs)
    origin = np.asarray(cfg.scene.origin)
    x, y = np.meshgrid(chm.x.values - origin[0], chm.y.values - origin[1])  # local cell centres
    np.testing.assert_allclose(np.diff(chm.x.values), 1.0)
    assert np.allclose((x - 0.5) % 1.0, 0.0) and np.allclose((y - 0.5) % 1.0, 0.0)
    trees = stand(cfg.scene, cfg.run.seed)
    truth, west, north = canopy_height_model(trees, 1.0)
    col, row = np.floor(x - west).astype(np.int64), np.floor(north - y).astype(np.int64)
    inside = (col >= 0) & (col < truth.shape[1]) & (row >= 0) & (row < truth.shape[0])
    true_chm = np.where(inside, truth[np.clip(row, 0, truth.shape[0] - 1), np.clip(col, 0, truth.shape[1] - 1)], -1)
    voxel, lower = _voxel_first_returns(cfg, trees)
    vi, vj = np.floor(x - lower[0]).astype(np.int64), np.floor(y - lower[1]).astype(np.int64)
    in_grid = (vi >= 0) & (vi < voxel.shape[0]) & (vj >= 0) & (vj < voxel.shape[1])
    predicted = np.where(in_grid, voxel[np.clip(vi, 0, voxel.shape[0] - 1), np.clip(vj, 0, voxel.shape[1] - 1)], 0.0)
    las = result.points["exact"]
    first = np.asarray(las.return_number) == 1
    counts = np.zeros(chm.shape, np.int64)
    np.add.at(counts, (np.floor(chm.y.values[0] + 0.5 - np.asarray(las.y)[first]).astype(np.int64),
                       np.floor(np.asarray(las.x)[first] - chm.x.values[0] + 0.5).astype(np.int64)), 1)
    crowns = (counts >= 10) & (true_chm > 2.0)
    assert crowns.sum() > 500
    error = chm.values[crowns] - true_chm[crowns]
    expected = (predicted - true_chm)[crowns].mean()
    assert -2.0 <= error.mean() <= -0.6 and abs(error.mean() - expected) <= 0.4, (error.mean(), expected)
    assert math.sqrt((error ** 2).mean()) < 1.8
    assert abs(np.median(chm.values[crowns] - predicted[crowns])) <= 0.25
    open_cells = (counts >= 5) & (true_chm == 0.0)
    assert open_cells.sum() > 10 and np.abs(chm.values[open_cells]).max() < 0.5


def test_chm_m_zero_writes_no_chm_no_points_none_and_bad_values_are_refused(tmp_path):
    cfg = flightsim.load_config(overrides={"scene.name": "forest", "scene.forest_size_m": 60.0,
                                           "flight.duration_s": 0.2, "flight.altitude_m": 150.0,
                                           "output.models": ["exact"], "output.chm_m": 0})
    result = flightsim.simulate(cfg)
    assert result.stats["leaf_returns"] > 0 and "chm" not in result.stats
    assert not (result.directory / "chm.tif").exists() and result.chm is None
    assert write_chm(tmp_path, "exact", {}, 1.0, None) == {"file": None, "reason": "no points", "model": "exact",
                                                          "cell_m": 1.0, "points": 0}
    with pytest.raises(InputError, match="output.chm_m"):
        flightsim.load_config(overrides={"output.chm_m": -1.0})


def test_l2a_dataset_reads_every_beam_of_l2a_h5(tmp_path):
    """Two beams written by write_l2a (truth and beam attributes for beam 5 only): one shot dim, rh as shot ×
    percentile, each value as written."""
    rng = np.random.default_rng(1)

    def beam(n, first):
        columns = {"shot_number": np.arange(first, first + n, dtype=np.uint64), "delta_time": rng.uniform(0, 1, n),
                   "rh": np.sort(rng.uniform(-2, 30, (n, 101)), axis=1), "num_detectedmodes": np.full(n, 2, np.uint8),
                   "quality_flag": np.ones(n, np.uint8)}
        columns.update({k: rng.uniform(0, 1, n) for k in (
            "elev_lowestmode", "elev_highestreturn", "lat_lowestmode", "lon_lowestmode", "lat_highestreturn",
            "lon_highestreturn", "sensitivity", "energy_total")})
        return columns

    beams = {5: {**beam(3, 100), "pulse_sigma_s": 2.5e-9}, 2: beam(4, 10)}
    truth = {5: {"elev_ground": rng.uniform(0, 1, 3), "rh": rng.uniform(0, 20, (3, 101))}}
    (tmp_path / "run").mkdir()
    write_l2a(tmp_path / "run" / "l2a.h5", beams, truth, {"crs_wkt": "EPSG:32648"})
    ds = Result(tmp_path / "run", {}, None).l2a
    assert ds.sizes == {"shot": 7, "percentile": 101} and list(ds.percentile.values) == list(range(101))
    assert list(ds.beam.values) == [2] * 4 + [5] * 3  # beams in number order
    for name in ("shot_number", "delta_time", "rh", "elev_lowestmode", "sensitivity", "quality_flag"):
        expected = np.concatenate([beams[2][name], beams[5][name]]).astype(ds[name].dtype)
        np.testing.assert_array_equal(ds[name].values, expected, err_msg=name)
    assert ds.rh.dims == ("shot", "percentile") and ds.rh.attrs["units"] == "m"
    np.testing.assert_array_equal(ds.truth_rh.values[4:], truth[5]["rh"].astype(np.float32))
    assert np.isnan(ds.truth_elev_ground.values[:4]).all() and np.isnan(ds.pulse_sigma_s.values[:4]).all()
    assert (ds.pulse_sigma_s.values[4:] == 2.5e-9).all() and ds.attrs["crs_wkt"] == "EPSG:32648"
    assert Result(tmp_path, {}, None).l2a is None
