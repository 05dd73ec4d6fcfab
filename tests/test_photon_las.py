"""LAS tiles of a photon run from orbit in the CRS the user picks: every photon, noise as class 7, the
ground photons of the mid-run shots on the scene origin re-projected by pyproj here."""
from __future__ import annotations

import laspy
import numpy as np
import pyproj
import pytest

from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.run import simulate_to_directory
from flightsim.instrument.pairs import SINGLE_BEAM


@pytest.mark.parametrize("crs", ["", "EPSG:32647"])
def test_photon_points_in_the_output_crs(tmp_path, crs):
    cfg = preset_config("atlas")
    for key, value in {**SINGLE_BEAM, "flight.duration_s": 0.02, "photon.gate_m": [499850.0, 500150.0],
                       "output.crs": crs}.items():
        set_value(cfg, key, value)
    cfg = validate(cfg)
    summary = simulate_to_directory(cfg, tmp_path / "a")
    assert summary["files"] == ["photons.h5", "photons", "atl03.h5", "atl08.h5"]
    tiles = sorted((tmp_path / "a" / "photons").glob("*.las"))
    assert sum(summary["photon_tiles"].values()) == summary["photons"] and len(tiles) == len(summary["photon_tiles"])
    las = [laspy.read(t) for t in tiles]
    assert las[0].header.parse_crs() == pyproj.CRS(crs or cfg.scene.crs)
    x, y, z, t, c = (np.concatenate([np.asarray(f[k], dtype=np.float64) for f in las])
                     for k in ("x", "y", "z", "gps_time", "classification"))
    assert (c == 7).sum() == summary["photons"] - summary["signal_photons"]
    # the pass is above the scene origin at mid-run: the ground photons of the shots around it are there
    origin = pyproj.Transformer.from_crs(cfg.scene.crs, crs or cfg.scene.crs, always_xy=True).transform(
        *cfg.scene.origin[:2])
    mid = (c == 1) & (np.abs(t - (cfg.flight.start_gps_time + 0.01)) < 2e-4)  # ±1.4 m of track
    assert mid.sum() >= 2
    assert np.hypot(x[mid] - origin[0], y[mid] - origin[1]).max() < 8.0  # within the 12 m footprint
    assert np.median(z[c == 1]) == pytest.approx(cfg.scene.origin[2], abs=0.15)  # WGS84 height of the plane


def test_the_tiles_of_a_run_off_orbit_are_the_same_made_on_threads(tmp_path, monkeypatch):
    """Off orbit the LAS records of a run's parts are made on LAS_THREADS threads side by side and written in order:
    every tile byte as on one thread (a SPAD run in parts of 2,000 photons)."""
    import threading

    import flightsim.engine.products.photons as product
    from flightsim.outputs.photon_las import PhotonLas

    cfg = preset_config("spad")
    set_value(cfg, "flight.duration_s", 0.002)
    set_value(cfg, "run.host_photons", 2000)
    cfg = validate(cfg)
    makers = []
    monkeypatch.setattr(PhotonLas, "prepare", lambda self, chunk, make=PhotonLas.prepare: (
        makers.append(threading.get_ident()), make(self, chunk))[1])
    monkeypatch.setattr(product, "thread_count", lambda most: most)
    threads = {}
    for name, count in (("one", 1), ("three", 3)):
        monkeypatch.setattr(product, "LAS_THREADS", count)
        makers.clear()
        writers = simulate_to_directory(cfg, tmp_path / name)["writers_s"]
        threads[name] = (len(makers), len(set(makers)))
        assert set(writers) == {"photons.h5", "photons/"} and writers["photons/"]["busy"] > 0
        assert (writers["photons/"]["prepare"] > 0) == (count > 1)  # the records made apart on several threads
    assert threads["one"][0] > 10 and threads["one"][1] == 1 and threads["three"][1] > 1  # the case: many parts
    tiles = sorted(p.name for p in (tmp_path / "one" / "photons").iterdir())
    assert tiles and tiles == sorted(p.name for p in (tmp_path / "three" / "photons").iterdir())
    for tile in tiles:
        one, three = (tmp_path / name / "photons" / tile for name in ("one", "three"))
        assert one.read_bytes() == three.read_bytes(), tile
