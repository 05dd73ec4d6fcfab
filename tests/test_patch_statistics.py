"""Per-patch fit statistics of LAS runs over curved ground (flightsim.outputs.consumers.PatchStatistics).

A plane fit through a whole curved surface measures its curvature, not the points' error, so a LAS run
over a curved scene scores square patches instead. The patch moments summed on the device must equal
numpy's two-pass fits of the same points grouped by patch, and the patch raster must put each patch where
the LAS points of that patch lie.
"""
import math

import laspy
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.core.errors import InputError
from flightsim.engine.products.las import PATCH_RASTER
from flightsim.engine.run import simulate_to_directory
from flightsim.engine.tracer import Tracer
from flightsim.outputs.consumers import AUTO_PATCH_M, MAX_PATCHES, MIN_PATCH_POINTS, PatchStatistics, patch_grid
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.scoring.planes import fit_groups
from flightsim.engine.readouts.points import Points

E0, N0, H0 = 409000.0, 3393000.0, 450.0  # the default scene origin
RADIUS_M = 600.0  # curvature radius of the test surface along east


def _curved_dem(path, cell=4.0, half=400.0):
    """A GeoTIFF of the cylinder-like surface H = H0 + (E − E0)² / (2 R), nodes centred on (E0, N0)."""
    n = round(2 * half / cell) + 1
    east = E0 + (np.arange(n) - (n - 1) / 2) * cell
    heights = np.broadcast_to(H0 + (east[None, :] - E0) ** 2 / (2 * RADIUS_M), (n, n)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs="EPSG:32648",
                       transform=from_origin(east[0] - cell / 2, N0 + half + cell / 2, cell, cell)) as dst:
        dst.write(heights, 1)


def _config(dem, device="cpu", **settings) -> RunConfig:
    cfg = RunConfig()
    base = {"scene.name": str(dem), "flight.duration_s": 0.3, "flight.lines": 2, "flight.line_spacing_m": 120.0,
            "instrument.errors": ["ranging"], "ranging.noise_m": 0.02, "run.device": device, "run.chunk_pulses": 131}
    for key, value in {**base, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


@pytest.fixture(scope="module")
def dem(tmp_path_factory):
    path = tmp_path_factory.mktemp("curved") / "dem.tif"
    _curved_dem(path)
    return path


def _patch_of(xy: np.ndarray, grid) -> np.ndarray:
    """Row-major patch of local (x, y) points, computed as the kernel's definition states (float64)."""
    i = np.clip(np.floor((xy[:, 0].astype(np.float64) - grid.low[0]) / grid.patch_m), 0, grid.nx - 1)
    j = np.clip(np.floor((xy[:, 1].astype(np.float64) - grid.low[1]) / grid.patch_m), 0, grid.ny - 1)
    return (j * grid.nx + i).astype(np.int64)


def test_device_patch_fits_equal_numpys_two_pass_fits(dem, device):
    cfg = _config(dem, device)
    scene = build_scene(cfg)
    assert not scene.planar
    grid = patch_grid(scene, cfg.scoring.patch_m)
    assert grid.patch_m == AUTO_PATCH_M
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    fits = PatchStatistics(simulator, grid)
    simulator.run(Points(on_device=True), fits)
    rms, count = fits.rms_grids()
    chunks = []
    simulator.run(Points(), chunks.append)
    points = {m: np.concatenate([c.points[m] for c in chunks]) for m in ("exact", "nominal")}
    label = _patch_of(points["exact"], grid)
    assert np.array_equal(np.bincount(label, minlength=grid.nx * grid.ny), count.ravel())
    fitted = np.flatnonzero(count.ravel() >= MIN_PATCH_POINTS)
    assert len(fitted) > 40
    for model in ("exact", "nominal"):
        expected = np.full(grid.nx * grid.ny, np.nan)
        for f in fit_groups(points[model], label, min_points=MIN_PATCH_POINTS):
            expected[f.plane_id] = f.rms_m
        assert np.array_equal(np.isfinite(expected), np.isfinite(rms[model].ravel()))
        np.testing.assert_allclose(rms[model].ravel()[fitted], expected[fitted], rtol=1e-6)


def _tilted_dem(path, slope, cell=4.0, half=400.0):
    """A GeoTIFF of the plane H = H0 + slope·(E − E0), nodes centred on (E0, N0)."""
    n = round(2 * half / cell) + 1
    east = E0 + (np.arange(n) - (n - 1) / 2) * cell
    heights = np.broadcast_to(H0 + slope * (east[None, :] - E0), (n, n)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs="EPSG:32648",
                       transform=from_origin(east[0] - cell / 2, N0 + half + cell / 2, cell, cell)) as dst:
        dst.write(heights, 1)


def test_patch_rms_on_flat_ground_is_the_ranging_noise_across_the_ground(tmp_path):
    """On a tilted plane the patch fits leave the ranging noise's component along the ground's normal n:
    each return's (measured − true)·n, from the run's truth. With n_p returns in patch p its fit removes 3
    degrees of freedom, so pooled² = Σ_p Σ_{i∈p} ((m − t)·n)² (n_p − 3)/n_p / Σ n_p, within sampling error."""
    slope = 0.2
    _tilted_dem(tmp_path / "tilted.tif", slope)
    cfg = _config(tmp_path / "tilted.tif", **{"output.models": ["exact"], "instrument.errors": ["ranging"],
                                                          "ranging.noise_m": 0.05})
    from flightsim import api

    run = api.simulate(cfg, with_truth=True)
    normal = np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    across = (run.returns.points["exact"] - run.returns.true_points) @ normal
    summary = simulate_to_directory(cfg, tmp_path / "run")
    assert summary["points"]["exact"] == len(across)
    scene = build_scene(cfg)
    grid = patch_grid(scene, 0.0)
    label = _patch_of(run.returns.points["exact"] - scene.origin, grid)
    n_p = np.bincount(label)
    kept = n_p[label] >= MIN_PATCH_POINTS
    expected = math.sqrt(np.sum(across[kept] ** 2 * (1 - 3 / n_p[label[kept]])) / kept.sum())
    assert 0.03 < expected < 0.05  # the noise is 5 cm along beams up to ~20° off the normal
    assert summary["patches"]["rms_m"]["exact"] == pytest.approx(expected, rel=0.01)


def test_a_curved_scene_reports_patches_and_a_raster_where_the_points_lie(dem, tmp_path):
    summary = simulate_to_directory(_config(dem), tmp_path / "run")
    assert summary["rms_m"] == {"exact": None, "nominal": None}  # no whole-surface plane fit
    patches = summary["patches"]
    assert patches["patch_m"] == AUTO_PATCH_M and patches["raster"] == PATCH_RASTER
    assert patches["patches"] > 40
    # 2 cm of ranging noise, and the curvature: over a patch of side L of z = x²/(2R), points spread evenly
    # in x leave u²/(2R) (u from the patch centre) after the plane fit, an RMS of L²/(2R·√180) (3.9 cm)
    curvature = AUTO_PATCH_M**2 / (2 * RADIUS_M * math.sqrt(180.0))
    for value in (patches["rms_m"]["exact"], patches["median_rms_m"]["exact"]):
        assert 0.019 < value < math.hypot(0.02, curvature)
    assert patches["rms_m"]["nominal"] > patches["rms_m"]["exact"]
    points = np.concatenate([np.column_stack([las.x, las.y]) for las in
                             (laspy.read(p) for p in sorted((tmp_path / "run" / "exact").glob("*.las")))])
    assert len(points) == summary["points"]["exact"]
    with rasterio.open(tmp_path / "run" / PATCH_RASTER) as src:
        assert src.crs.to_epsg() == 32648 and src.count == 3
        assert src.descriptions == ("exact plane-fit RMS [m]", "nominal plane-fit RMS [m]", "returns")
        exact, returns = src.read(1), src.read(3)
        rows, cols = rasterio.transform.rowcol(src.transform, points[:, 0], points[:, 1])
        size = (src.height, src.width)
    assert returns.sum() == len(points)
    at_points = np.bincount(np.ravel_multi_index((rows, cols), size), minlength=size[0] * size[1]).reshape(size)
    # LAS coordinates are rounded to the mm: a point within a mm of a patch side may land in its neighbour
    edge = patches["patch_m"]
    near_side = np.sum(np.min(np.abs((points - [E0 - 400.0, N0 - 400.0]) / edge - np.round((points - [E0 - 400.0,
                                                                                           N0 - 400.0]) / edge)),
                              axis=1) * edge < 1e-3)
    assert np.abs(at_points - returns).sum() <= 2 * near_side
    assert np.array_equal(np.isfinite(exact), returns >= MIN_PATCH_POINTS)


def test_planar_scenes_score_planes_and_patches_only_when_asked(tmp_path):
    cfg = RunConfig()
    for key, value in {"flight.duration_s": 0.1, "run.device": "cpu"}.items():
        set_value(cfg, key, value)
    summary = simulate_to_directory(validate(cfg), tmp_path / "planes")
    assert "patches" not in summary and not (tmp_path / "planes" / PATCH_RASTER).exists()
    assert all(v is not None for v in summary["rms_m"].values())
    set_value(cfg, "scoring.patch_m", 40.0)
    summary = simulate_to_directory(validate(cfg), tmp_path / "patches")
    assert summary["patches"]["patch_m"] == 40.0 and (tmp_path / "patches" / PATCH_RASTER).is_file()


def test_too_many_patches_are_refused_before_anything_is_written(dem, tmp_path):
    with pytest.raises(InputError) as err:
        simulate_to_directory(_config(dem, **{"scoring.patch_m": 0.1}), tmp_path / "out")
    assert err.value.field == "scoring.patch_m" and "≥ 1" in str(err.value)
    assert not (tmp_path / "out").exists()
    scene = build_scene(_config(dem))
    low, high = scene.bounds()
    auto = patch_grid(scene, 0.0)
    assert auto.nx * auto.ny <= MAX_PATCHES
    assert auto.nx == math.ceil((high[0] - low[0]) / AUTO_PATCH_M)


def test_buildings_on_a_dem_keep_it_curved(tmp_path):
    from flightsim.scenes import testdem
    from flightsim.scenes.dem import dem_scene

    paths = testdem.write(tmp_path, size_m=400.0, cell_m=4.0)
    bare = dem_scene(str(paths["dem"]), "EPSG:32648", (E0, N0, H0), 0.0)
    built = dem_scene(str(paths["dem"]), "EPSG:32648", (E0, N0, H0), 0.0, buildings=str(paths["buildings"]))
    assert len(built.triangles) > len(bare.triangles) and not built.planar and not bare.planar
    assert patch_grid(built, 0.0) is not None
