"""Height grids as scenes: GeoTIFF (rasterio) and .npy grids meshed two triangles per cell, against the
grid's own numbers; and the waveform altimeter over a DEM slope against the closed-form echo width."""
from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from flightsim.core.errors import InputError
from flightsim.scenes.dem import dem_scene
from flightsim.engine.readouts.waveforms import Waveforms


def _write_tif(path, heights, west, north, cell, crs="EPSG:32648", nodata=None):
    with rasterio.open(path, "w", driver="GTiff", width=heights.shape[1], height=heights.shape[0], count=1,
                       dtype="float32", crs=crs, transform=from_origin(west, north, cell, cell), nodata=nodata) as dst:
        dst.write(heights.astype(np.float32), 1)


def test_geotiff_nodes_sit_at_pixel_centres_with_their_heights(tmp_path):
    rows, cols, cell, west, north = 5, 7, 2.0, 409000.0, 3393100.0
    i, j = np.mgrid[0:rows, 0:cols]
    east, northing = west + (j + 0.5) * cell, north - (i + 0.5) * cell
    heights = 100.0 + 0.01 * (east - west) - 0.02 * (north - northing)
    _write_tif(tmp_path / "dem.tif", heights, west, north, cell)
    scene = dem_scene(str(tmp_path / "dem.tif"), "EPSG:4326", (0, 0, 0), 1.0)
    world = scene.local_to_world(scene.vertices)
    expected = np.column_stack([east.ravel(), northing.ravel(), heights.ravel()])
    assert np.abs(world - expected).max() < 1e-4  # float32 heights in the file
    assert scene.crs.to_epsg() == 32648
    assert len(scene.triangles) == 2 * (rows - 1) * (cols - 1)
    normals = np.cross(*(scene.vertices[scene.triangles[:, k]] - scene.vertices[scene.triangles[:, 0]] for k in (1, 2)))
    assert (normals[:, 2] > 0).all()  # counter-clockwise seen from above


def test_nodata_cells_leave_holes_and_npy_grids_use_the_cell(tmp_path):
    heights = np.zeros((4, 4))
    heights[1, 1] = -9999.0
    _write_tif(tmp_path / "hole.tif", heights, 0.0, 100.0, 1.0, nodata=-9999.0)
    scene = dem_scene(str(tmp_path / "hole.tif"), None, (0, 0, 0), 1.0)
    assert len(scene.triangles) == 2 * 9 - 6  # the six triangles (of four cells) that meet the nodata node are gone
    np.save(tmp_path / "g.npy", np.arange(12.0).reshape(3, 4))
    grid = dem_scene(str(tmp_path / "g.npy"), "EPSG:32648", (1000.0, 2000.0, 50.0), 2.5)
    world = grid.local_to_world(grid.vertices)
    assert world[:, 0].min() == pytest.approx(1000.0 - 3.75) and world[:, 1].max() == pytest.approx(2000.0 + 2.5)
    assert world[0, 2] == pytest.approx(0.0) and grid.vertices[0, 2] == pytest.approx(-50.0)  # world H, local z = H − 50
    with pytest.raises(InputError, match="scene.cell_m"):
        dem_scene(str(tmp_path / "g.npy"), "EPSG:32648", (0, 0, 0), 0.0)


def test_waveform_over_a_dem_slope_has_the_closed_form_width(tmp_path):
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories
    from flightsim.studies.waveform import waveform_config

    s, cell, n = 0.1, 2.0, 161
    i, j = np.mgrid[0:n, 0:n]
    np.save(tmp_path / "slope.npy", s * cell * (j - n // 2))  # rises to the east
    cfg = waveform_config(str(tmp_path / "slope.npy"), **{"scene.cell_m": cell, "waveform.n_rings": 24,
                                                          "waveform.n_sectors": 48, "waveform.sample_interval_s": 5e-11,
                                                          "waveform.samples": 8192})
    scene = build_scene(cfg)
    parts = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Waveforms(), parts.append)
    power = parts[0].power_w[0].astype(np.float64)
    t = np.arange(power.size) * 5e-11
    mean = np.sum(t * power) / power.sum()
    rms = math.sqrt(np.sum((t - mean) ** 2 * power) / power.sum())
    e2, radius = math.exp(-2), 200e3 * 3e-4
    sigma_x = math.sqrt(radius ** 2 / 4 * (1 - 3 * e2) / (1 - e2))
    sigma_p = 7e-9 / (2 * math.sqrt(2 * math.log(2)))
    assert rms == pytest.approx(math.hypot(sigma_p, 2 * s * sigma_x / 299_792_458.0), rel=0.01)
