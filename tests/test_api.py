"""The Python API returns every product: points as laspy.LasData, waveforms and photons as xarray Datasets with
GEDI L1B and ATL03 names, the summary, and write() giving exactly the files of `flightsim simulate --out`."""
from __future__ import annotations

import hashlib
import json

import h5py
import laspy
import numpy as np
import pytest
import xarray as xr

import flightsim
from flightsim.cli import main

VOLATILE = ("wall_s", "stages_s")


def _digests(directory) -> dict:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file() and p.suffix in (".las", ".laz", ".tif", ".toml")}


def _summary(directory) -> dict:
    return {k: v for k, v in json.loads((directory / "summary.json").read_text()).items() if k not in VOLATILE}


def test_points_are_the_tiles_and_write_gives_the_command_line_s_files(tmp_path):
    cfg = flightsim.load_config(overrides={"flight.duration_s": 0.2, "output.position_error": True})
    result = flightsim.simulate(cfg, with_truth=True)
    assert set(result.points) == {"exact", "nominal"}
    for model, las in result.points.items():
        assert isinstance(las, laspy.LasData) and len(las.points) == result.stats["points"][model]
        tiles = [laspy.read(p) for p in sorted((result.directory / model).glob("*.las"))]
        assert np.array_equal(np.sort(las.gps_time), np.sort(np.concatenate([t.gps_time for t in tiles])))
        assert np.array_equal(np.sort(las.X * 0.001 + las.header.offsets[0]),
                              np.sort(np.concatenate([t.x for t in tiles])))
        assert set(las.point_format.extra_dimension_names) >= {"beam_row", "range", "plane_id", "position_error"}
    # each LAS point is a return of result.returns, on the 1 mm grid
    exact, returns = result.points["exact"], result.returns
    order = np.lexsort((exact.beam_row.astype(int) * 256 + exact.beam_col, exact.gps_time))
    assert len(order) == len(returns.pulse)
    returned = np.lexsort((returns.beam, returns.line, returns.pulse))
    assert np.abs(exact.xyz[order] - returns.points["exact"][returned]).max() <= 0.0005 + 1e-9
    result.write(tmp_path / "api")
    assert main(["simulate", "--duration", "0.2", "--set", "output.position_error=true", "--out",
                 str(tmp_path / "cli")]) == 0
    assert _digests(tmp_path / "api") == _digests(tmp_path / "cli")
    assert _summary(tmp_path / "api") == _summary(tmp_path / "cli")


def test_waveforms_are_a_gedi_l1b_dataset_of_the_file():
    result = flightsim.simulate(flightsim.load_config(instrument="change1", overrides={
        "fixed.prf_hz": 4.0, "flight.duration_s": 0.6, "waveform.samples": 4096, "waveform.n_rings": 8,
        "waveform.n_sectors": 16}))
    ds = result.waveforms
    assert isinstance(ds, xr.Dataset) and ds.sizes["shot"] == result.stats["waveforms"] == 3
    for name in ("rxwaveform", "txwaveform", "shot_number", "delta_time", "latitude_bin0", "longitude_bin0",
                 "elevation_bin0", "range_halfpower_m", "nadir_range_m"):
        assert name in ds, name
    assert ds["rxwaveform"].dims == ("shot", "sample") and ds.sizes["sample"] == 4096
    with h5py.File(result.directory / "waveforms.h5") as f:
        g = f["BEAM0000"]
        starts, count = g["rx_sample_start_index"][:] - 1, int(g["rx_sample_count"][0])
        for shot, start in enumerate(starts):
            assert np.array_equal(ds["rxwaveform"][shot].values, g["rxwaveform"][start:start + count])
        assert np.array_equal(ds["shot_number"].values, g["shot_number"][:])
    assert result.points == {} and result.photons is None and result.returns is None
    # 3 shots of 4096 float32 samples and ~45 per-shot datasets: small chunks (a 64k-row chunk each made 23 MB)
    assert (result.directory / "waveforms.h5").stat().st_size < 1_000_000


def test_photons_from_orbit_are_the_atl03_heights():
    result = flightsim.simulate(flightsim.load_config(instrument="atlas", overrides={"flight.duration_s": 0.02}))
    ds = result.photons
    assert ds.sizes["photon"] == result.stats["photons"]
    with h5py.File(result.directory / "atl03.h5") as f:  # six ground tracks in name order
        tracks = ["gt1l", "gt1r", "gt2l", "gt2r", "gt3l", "gt3r"]
        assert np.array_equal(ds["h_ph"].values, np.concatenate([f[f"{t}/heights/h_ph"][:] for t in tracks]))
        assert np.array_equal(ds["signal_conf_ph"].values,
                              np.concatenate([f[f"{t}/heights/signal_conf_ph"][:, 0] for t in tracks]))
        assert list(np.unique(ds["beam"].values)) == tracks
    for name in ("lat_ph", "lon_ph", "delta_time", "dist_ph_along", "ph_id_pulse"):
        assert name in ds


def test_photons_of_a_hover_get_atl03_names_and_their_heights_from_photons_h5():
    result = flightsim.simulate(flightsim.load_config(instrument="spad", overrides={"flight.duration_s": 0.0004}))
    ds = result.photons
    with h5py.File(result.directory / "photons.h5") as f:
        assert np.array_equal(ds["h_ph"].values, f["photons/z"][:])
        assert np.array_equal(ds["truth_kind"].values, f["photons/signal"][:].astype(np.int8))
    assert set(np.unique(ds["signal_conf_ph"].values)) <= {0, 1, 2, 3, 4}
    signal = ds["truth_kind"].values > 0
    assert (ds["signal_conf_ph"].values[signal] == 4).mean() > 0.9  # the sandbox's echoes are found


def test_a_result_written_into_its_own_directory_or_over_a_run_needs_overwrite(tmp_path):
    result = flightsim.simulate(flightsim.load_config(overrides={"flight.duration_s": 0.1}), out=tmp_path / "run")
    assert result.write(tmp_path / "run") == tmp_path / "run"
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("mine")
    with pytest.raises(flightsim.core.errors.InputError, match="--out"):
        result.write(tmp_path / "other")


def test_returns_kept_from_many_chunks_keep_their_own_ranges():
    """Each chunk's host returns are the API's own copies: later chunks (here 20 of 50 pulses) must not overwrite
    the ranges of earlier ones. The LAS tiles, written chunk by chunk as they come, are the reference."""
    cfg = flightsim.load_config(overrides={"flight.duration_s": 0.2, "run.chunk_pulses": 50})
    result = flightsim.simulate(cfg)
    exact, returns = result.points["exact"], result.returns
    order = np.lexsort((exact.beam_row.astype(int) * 256 + exact.beam_col, exact.gps_time))
    returned = np.lexsort((returns.beam, returns.line, returns.pulse))
    assert len(np.unique(returns.pulse // 50)) >= 10  # many chunks
    assert np.abs(np.asarray(exact.range)[order] - returns.range_m[returned]).max() < 1e-3
