"""ALS point clouds: reading LAS/LAZ (CRS from the file, refused when geographic or missing, noise dropped,
ground classified or the lowest per cell, empty clouds refused), the ground surface against the synthetic
truth it was sampled from, a DEM beside the cloud, and the ``cloud`` scene kind through the config.

``tests/data/cloud_plot.laz`` (LAS 1.4, point format 6, EPSG:32648: 7,350 ground and 6,125 canopy returns over
35 m × 35 m and 40 noise points, 82 kB) was written by ``_write_cloud(path, *_forest_plot())`` below."""
from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
from rasterio.transform import from_origin

from flightsim.core.errors import InputError
from flightsim.scenes.cloud_ground import ground_scene
from flightsim.scenes.pointcloud import read_point_cloud

DATA = Path(__file__).parent / "data"
E0, N0 = 409_000.0, 3_393_000.0  # a corner in UTM 48N


def _write_cloud(path, xyz, classes, crs="EPSG:32648", version="1.4", returns=None) -> None:
    header = laspy.LasHeader(point_format=6 if version == "1.4" else 1, version=version)
    header.scales, header.offsets = [0.001] * 3, np.floor(xyz.min(axis=0))
    if crs is not None:
        header.add_crs(pyproj.CRS(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = np.asarray(classes, dtype=np.uint8)
    if returns is not None:
        las.return_number, las.number_of_returns = returns
    las.write(str(path))


def _surface(e, n):
    """The synthetic ground: world height [m] at world E, N [m]."""
    return 300.0 + 0.08 * (e - E0) - 0.05 * (n - N0) + 0.6 * np.sin((e - E0) / 13.0) * np.cos((n - N0) / 17.0)


def _forest_plot(seed=5, side=35.0, hole=None):
    """(world xyz, classes, returns) of ground returns at 6/m² on the synthetic ground (none within the square
    ``hole`` = (e0, n0, e1, n1)), canopy returns 5–25 m above it at 5/m², and 20 low and 20 high noise points."""
    rng = np.random.default_rng(seed)
    ground = rng.uniform(0.0, side, (int(6 * side * side), 2)) + (E0, N0)
    if hole is not None:
        e0, n0, e1, n1 = hole
        ground = ground[~((ground[:, 0] > e0) & (ground[:, 0] < e1) & (ground[:, 1] > n0) & (ground[:, 1] < n1))]
    canopy = rng.uniform(0.0, side, (int(5 * side * side), 2)) + (E0, N0)
    noise = rng.uniform(0.0, side, (40, 2)) + (E0, N0)
    xyz = np.concatenate([np.column_stack([ground, _surface(*ground.T)]),
                          np.column_stack([canopy, _surface(*canopy.T) + rng.uniform(5.0, 25.0, len(canopy))]),
                          np.column_stack([noise, _surface(*noise.T) + np.repeat([-30.0, 80.0], 20)])])
    classes = np.concatenate([np.full(len(ground), 2), np.full(len(canopy), 5), np.repeat([7, 18], 20)])
    number = np.concatenate([np.full(len(ground), 2), np.ones(len(canopy) + 40)]).astype(np.uint8)
    return xyz, classes, "EPSG:32648", "1.4", (number, np.full(len(xyz), 2, dtype=np.uint8))


def test_crs_origin_noise_and_returns_from_the_file(tmp_path):
    xyz, classes, *_ = _forest_plot()
    _write_cloud(tmp_path / "plot.las", xyz, classes, crs="EPSG:32633", version="1.2")  # GeoTIFF keys
    cloud = read_point_cloud(tmp_path / "plot.las", chunk_points=1000)
    assert cloud.crs.to_epsg() == 32633
    kept = ~np.isin(classes, (7, 18))
    world = np.round(xyz[kept], 3)  # the file's 1 mm quantisation
    expected_origin = [(world[:, 0].min() + world[:, 0].max()) / 2, (world[:, 1].min() + world[:, 1].max()) / 2,
                       world[classes[kept] == 2, 2].min()]
    assert np.allclose(cloud.origin, expected_origin, atol=1e-9)
    assert np.abs(cloud.xyz + cloud.origin - world).max() < 1e-6
    assert np.array_equal(cloud.classification, classes[kept])
    assert (cloud.return_number == 1).all() and (cloud.number_of_returns == 1).all()  # format 1 left them at 0
    given = read_point_cloud(tmp_path / "plot.las", crs="EPSG:4326", origin=(E0, N0, 0.0))  # the file's CRS wins
    assert given.crs.to_epsg() == 32633 and np.array_equal(given.origin, [E0, N0, 0.0])
    for read in (cloud, given):  # the bounds found as the chunks are read: the kept points' own extremes
        lo, hi = read.bounds()
        assert np.array_equal(lo, read.xyz.min(axis=0)) and np.array_equal(hi, read.xyz.max(axis=0))
    noise_z = xyz[~kept, 2]
    assert noise_z.min() < world[:, 2].min() and noise_z.max() > world[:, 2].max()  # noise beyond both ends


def test_a_geographic_or_missing_crs_is_refused_with_the_command_that_fixes_it(tmp_path):
    lonlat = np.column_stack([np.linspace(105.01, 105.02, 50), np.linspace(30.61, 30.62, 50), np.zeros(50)])
    _write_cloud(tmp_path / "deg.laz", lonlat, np.full(50, 2), crs="EPSG:4326")
    with pytest.raises(InputError, match=r"geographic.*pdal translate .*out_srs=EPSG:32648"):
        read_point_cloud(tmp_path / "deg.laz")
    feet = np.column_stack([np.full(5, 2e6), np.full(5, 5e5), np.zeros(5)])
    _write_cloud(tmp_path / "feet.las", feet, np.full(5, 2), crs="EPSG:2227")  # California zone 3, US survey feet
    with pytest.raises(InputError, match="metres.*reproject"):
        read_point_cloud(tmp_path / "feet.las")
    xyz, classes, *_ = _forest_plot()
    _write_cloud(tmp_path / "bare.las", xyz, classes, crs=None)
    with pytest.raises(InputError, match=r"scene\.crs.*a_srs"):
        read_point_cloud(tmp_path / "bare.las")
    assert read_point_cloud(tmp_path / "bare.las", crs="EPSG:32648").crs.to_epsg() == 32648


def test_unclassified_clouds_need_a_classifier_or_the_lowest_point_per_cell(tmp_path):
    rng = np.random.default_rng(2)
    xyz = np.column_stack([rng.uniform(0, 10, 3000) + E0, rng.uniform(0, 10, 3000) + N0, rng.uniform(0, 20, 3000)])
    _write_cloud(tmp_path / "raw.laz", xyz, np.ones(3000))
    with pytest.raises(InputError, match=r"filters\.smrf.*lasground"):
        read_point_cloud(tmp_path / "raw.laz")
    cloud = read_point_cloud(tmp_path / "raw.laz", ground="lowest", cell_m=2.0)
    world = cloud.xyz + cloud.origin
    cells = np.floor((world[:, :2] - world[:, :2].min(axis=0)) / 2.0)  # 2 m cells from the lower-left corner
    lowest = []
    for cell in np.unique(cells, axis=0):  # the lowest point of each cell, found the slow way
        inside = np.flatnonzero((cells == cell).all(axis=1))
        lowest.append(inside[np.argmin(world[inside, 2])])
    assert np.array_equal(np.sort(np.flatnonzero(cloud.ground)), np.sort(lowest))
    assert cloud.origin[2] == pytest.approx(world[lowest, 2].min())  # the lowest ground


def test_empty_and_broken_clouds_are_refused(tmp_path):
    noise = np.column_stack([np.full(4, E0), np.full(4, N0), np.arange(4.0)])
    _write_cloud(tmp_path / "noise.las", noise, [7, 18, 7, 18])
    with pytest.raises(InputError, match="at least one point that is not noise"):
        read_point_cloud(tmp_path / "noise.las")
    laspy.LasData(laspy.LasHeader(point_format=6, version="1.4")).write(str(tmp_path / "none.las"))
    with pytest.raises(InputError, match="at least one point"):
        read_point_cloud(tmp_path / "none.las")
    (tmp_path / "junk.laz").write_bytes(b"not a point cloud")
    (tmp_path / "cut.laz").write_bytes((DATA / "cloud_plot.laz").read_bytes()[:50_000])  # its points cut short
    for name in ("junk.laz", "cut.laz"):
        with pytest.raises(InputError, match="laspy can read"):
            read_point_cloud(tmp_path / name)
    with pytest.raises(InputError, match=r"\.las or \.laz"):
        read_point_cloud(tmp_path / "plot.xyz")


def test_ground_surface_follows_the_synthetic_truth_and_fills_a_hole(tmp_path):
    hole = (E0 + 12.0, N0 + 14.0, E0 + 22.0, N0 + 24.0)  # 10 m × 10 m without ground returns (a building)
    xyz, classes, *_ = _forest_plot(seed=9, hole=hole)
    _write_cloud(tmp_path / "plot.laz", xyz, classes)
    cloud = read_point_cloud(tmp_path / "plot.laz")
    scene = ground_scene(cloud, "plot", 1.0)
    world = scene.local_to_world(scene.vertices)
    truth = _surface(world[:, 0], world[:, 1])
    # a cell's mean sits off its centre by up to half its diagonal (one point in a corner) on slopes of up to 0.13
    assert np.abs(world[:, 2] - truth).max() < 0.1 and np.sqrt(np.mean((world[:, 2] - truth) ** 2)) < 0.02
    inside = (world[:, 0] > hole[0] + 1) & (world[:, 0] < hole[2] - 1) & (world[:, 1] > hole[1] + 1) & (
        world[:, 1] < hole[3] - 1)
    assert inside.sum() > 50 and np.abs(world[inside, 2] - truth[inside]).max() < 0.06  # linear across the hole
    assert scene.cloud is cloud and np.array_equal(scene.origin, cloud.origin) and not scene.planar
    assert (scene.classification == 2).all()
    lo, hi = cloud.bounds()
    assert (scene.vertices[:, :2].min(axis=0) <= lo[:2] + 0.5 + 1e-9).all()
    assert (scene.vertices[:, :2].max(axis=0) >= hi[:2] - 0.5 - 1e-9).all()


def test_ground_cells_in_pieces_on_threads_are_the_whole_clouds_means(monkeypatch):
    """The ground grid's cells worked out in pieces of 997 points on four threads: every cell's mean the one the
    ground points' heights give when summed in the cloud's order over all of them at once (the same bits)."""
    from flightsim.core import process_map
    from flightsim.scenes.cloud_ground import ground_grid

    xyz, classes, *_ = _forest_plot(seed=4)
    order = np.random.default_rng(5).permutation(len(xyz))  # ground and canopy points mixed in every piece
    cloud = _cloud_of(xyz[order, :2] - (E0, N0))
    heights = np.random.default_rng(6).normal(0.0, 100.0, len(xyz)) / 3.0  # sums whose rounding shows the order
    cloud.xyz[:, 2], cloud.classification = heights, classes[order].astype(np.uint8)
    monkeypatch.setattr(process_map, "ROWS_PER_PIECE", 997)
    monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    heights, _ = ground_grid(cloud, 1.5)
    lo, hi = cloud.bounds()
    cols, rows = (int(np.ceil((hi[a] - lo[a]) / 1.5)) for a in (0, 1))
    ground = cloud.xyz[cloud.classification == 2]
    column = np.minimum(((ground[:, 0] - lo[0]) / 1.5).astype(np.int64), cols - 1)
    row = rows - 1 - np.minimum(((ground[:, 1] - lo[1]) / 1.5).astype(np.int64), rows - 1)
    sums, counts = np.zeros((rows, cols)), np.zeros((rows, cols), dtype=np.int64)
    for r, c, z in zip(row.tolist(), column.tolist(), ground[:, 2].tolist()):  # in the cloud's order, one by one
        sums[r, c] += z
        counts[r, c] += 1
    filled = counts > 0
    assert filled.mean() > 0.9 and np.array_equal(heights[filled], sums[filled] / counts[filled])


def test_a_dem_beside_the_cloud_is_its_ground(tmp_path):
    xyz, classes, *_ = _forest_plot()
    _write_cloud(tmp_path / "plot.laz", xyz, classes)
    cloud = read_point_cloud(tmp_path / "plot.laz")
    i, j = np.mgrid[0:40, 0:40]
    east, north = E0 - 2.0 + (j + 0.5), N0 + 38.0 - (i + 0.5)
    for name, crs in (("dem.tif", "EPSG:32648"), ("other.tif", "EPSG:32647")):
        with rasterio.open(tmp_path / name, "w", driver="GTiff", width=40, height=40, count=1, dtype="float64",
                           crs=crs, transform=from_origin(E0 - 2.0, N0 + 38.0, 1.0, 1.0)) as dst:
            dst.write(_surface(east, north), 1)
    scene = ground_scene(cloud, "plot", 1.0, str(tmp_path / "dem.tif"))
    world = scene.local_to_world(scene.vertices)
    assert np.array_equal(scene.origin, cloud.origin) and len(world) == 1600
    assert np.abs(world[:, 2] - _surface(world[:, 0], world[:, 1])).max() < 1e-6
    with pytest.raises(InputError, match="cloud_dem.*cloud's CRS"):
        ground_scene(cloud, "plot", 1.0, str(tmp_path / "other.tif"))


def test_the_cloud_scene_kind_reads_its_settings_from_the_config():
    import flightsim
    from flightsim.scenes.build import scene_part

    path = str(DATA / "cloud_plot.laz")
    cfg = flightsim.load_config(overrides={"scene.name": path, "scene.cloud_cell_m": 2.0})
    assert (cfg.scene.rho_ground, cfg.scene.rho_canopy, cfg.scene.cloud_normalise) == (0.4, 0.57, False)
    scene = scene_part(cfg.scene).build(0.0, 0)
    assert scene.crs.to_epsg() == 32648 and len(scene.cloud) == 13_475
    assert not np.isin(scene.cloud.classification, (7, 18)).any()
    assert np.allclose(np.diff(np.unique(scene.vertices[:, 0])), 2.0)
    for key, value in (("scene.rho_ground", 0.0), ("scene.cloud_ground", "highest"),
                       ("scene.cloud_dem", "dem.png")):
        with pytest.raises(InputError, match=key.replace(".", r"\.")):
            flightsim.load_config(overrides={"scene.name": path, key: value})


def test_a_cloud_scene_keeps_its_points_however_often_it_is_built(tmp_path, monkeypatch):
    import flightsim
    from flightsim.scenes.build import build_scene

    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "cache"))
    cfg = flightsim.load_config(overrides={"scene.name": str(DATA / "cloud_plot.laz")})
    first, second = (build_scene(cfg.scene, 0.0, use_cache=True) for _ in range(2))
    assert len(first.cloud) == len(second.cloud) == 13_475


def test_a_cloud_scene_carries_the_leaf_area_its_first_returns_imply():
    import flightsim
    from flightsim.scenes.build import build_scene

    cfg = flightsim.load_config(overrides={"scene.name": str(DATA / "cloud_plot.laz"), "scene.cloud_voxel_m": [4.0, 1.0]})
    scene = build_scene(cfg.scene, 0.0)
    canopy, cloud = scene.canopy, scene.cloud
    assert np.array_equal(canopy.cell, [4.0, 4.0, 1.0]) and canopy.leaf_reflectance == cfg.scene.rho_canopy
    # every vegetation point lies inside the grid, and the grid holds leaves only in columns with vegetation
    vegetation = cloud.xyz[np.isin(cloud.classification, (3, 4, 5))]
    index = np.floor((vegetation - canopy.lower) / canopy.cell).astype(int)
    assert (index >= 0).all() and (index < np.array(canopy.lad.shape)).all()
    leafy = canopy.lad.sum(axis=2) > 0
    occupied = np.zeros(leafy.shape, bool)
    occupied[index[:, 0], index[:, 1]] = True
    assert leafy.any() and not (leafy & ~occupied).any()


def _cloud_of(xy):
    from flightsim.scenes.pointcloud import PointCloud

    n = len(xy)
    ones = np.ones(n, dtype=np.uint8)
    return PointCloud(np.column_stack([xy, np.zeros(n)]), np.full(n, 2), ones, ones, pyproj.CRS("EPSG:32648"),
                      np.zeros(3))


@pytest.mark.parametrize("grid_cells", [None, 16])  # 16: the occupancy grid too large, the tree of every point
@pytest.mark.parametrize("piece", [None, 1000])  # 1000: the cells' keys worked out in pieces on threads
def test_centres_beyond_reach_are_those_whose_nearest_point_is_at_least_reach_away(monkeypatch, grid_cells, piece):
    from flightsim.core import process_map
    from flightsim.scenes import pointcloud

    if grid_cells is not None:
        monkeypatch.setattr(pointcloud, "GRID_CELLS", grid_cells)
    if piece is not None:
        monkeypatch.setattr(process_map, "ROWS_PER_PIECE", piece)
        monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    rng = np.random.default_rng(11)
    xy = rng.uniform(0.0, 200.0, (20_000, 2))
    xy = xy[np.hypot(xy[:, 0] - 120.0, xy[:, 1] - 70.0) > 40.0]  # a hole of radius 40 m
    reach = 16.5
    centres = np.concatenate([rng.uniform(-30.0, 230.0, (3000, 2)),  # inside, in the hole, beyond the edges
                              [[120.0, 70.0], [-10.0, 50.0], [500.0, 500.0]]])
    # centres on the reach itself: a point exactly reach away (east of it) and one a hair closer
    ring = xy[:50] + np.array([[-reach, 0.0]] * 25 + [[-reach + 1e-9, 0.0]] * 25)
    alone = ring[np.array([np.hypot(*(xy - c).T).min() for c in ring]) >= reach - 1e-9]
    centres = np.concatenate([centres, alone])
    nearest = np.array([np.hypot(*(xy - c).T).min() for c in centres])  # float64 brute force
    expected = np.flatnonzero(nearest >= reach)
    found = pointcloud.centres_beyond(_cloud_of(xy), centres, reach)
    assert np.array_equal(found, expected)
    assert 50 < len(expected) < len(centres) - 1000  # both kinds plenty
    assert {3000, 3002} <= set(expected) and 3001 not in expected  # the hole's middle and far away; 10 m west is near


def test_a_clouds_bounds_are_its_points_extremes_and_follow_new_points():
    rng = np.random.default_rng(2)
    cloud = _cloud_of(rng.uniform(-50.0, 80.0, (1000, 2)))
    lo, hi = cloud.bounds()
    assert np.array_equal(lo, cloud.xyz.min(axis=0)) and np.array_equal(hi, cloud.xyz.max(axis=0))
    lo[:] = 1e9  # a caller's copy: the cloud's bounds stay
    assert np.array_equal(cloud.bounds()[0], cloud.xyz.min(axis=0))
    cloud.xyz = cloud.xyz[:10] + 1000.0  # points replaced: bounds of the new ones
    assert np.array_equal(cloud.bounds()[1], cloud.xyz.max(axis=0))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("version", ["1.2", "1.4"])
def test_a_file_read_on_threads_is_what_laspy_reads_whole(tmp_path, monkeypatch, version, suffix):
    """A file's chunks (an uncompressed one's mapped from the file, a compressed one's decompressed in turn) read on
    four threads, noise among them so that chunks move down after it: every kept point's coordinates, class and
    return numbers as ``laspy.read`` of the whole file gives them, in file order (formats 1 and 6 pack the class and
    returns differently)."""
    import flightsim.scenes.pointcloud as pointcloud

    xyz, classes, _, _, returns = _forest_plot(seed=8)
    order = np.random.default_rng(3).permutation(len(xyz))  # noise points spread over the chunks
    returns = tuple(r[order] for r in returns) if version == "1.4" else None
    _write_cloud(tmp_path / f"plot{suffix}", xyz[order], classes[order], crs="EPSG:32633", version=version,
                 returns=returns)
    monkeypatch.setattr(pointcloud, "thread_count", lambda pieces: 4)
    monkeypatch.setattr(pointcloud, "READ_PART", 1)
    cloud = read_point_cloud(tmp_path / f"plot{suffix}", chunk_points=997, origin=(E0, N0, 0.0))
    las = laspy.read(str(tmp_path / f"plot{suffix}"))
    kept = ~np.isin(np.asarray(las.classification), (7, 18))
    assert np.count_nonzero(~kept) == 40 and len(np.unique(np.flatnonzero(~kept) // 997)) > 5  # in many chunks
    world = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])[kept]
    assert np.array_equal(cloud.xyz, world - np.array([E0, N0, 0.0]))
    assert np.array_equal(cloud.classification, np.asarray(las.classification)[kept])
    for mine, theirs in ((cloud.return_number, las.return_number), (cloud.number_of_returns, las.number_of_returns)):
        assert np.array_equal(mine, np.maximum(np.asarray(theirs)[kept], 1))
    lo, hi = cloud.bounds()
    assert np.array_equal(lo, cloud.xyz.min(axis=0)) and np.array_equal(hi, cloud.xyz.max(axis=0))
    from flightsim.core import process_map

    monkeypatch.setattr(process_map, "ROWS_PER_PIECE", 997)  # the lowest ground found in pieces on threads
    monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    own = read_point_cloud(tmp_path / f"plot{suffix}", chunk_points=997)
    assert own.origin[2] == world[np.asarray(las.classification)[kept] == 2, 2].min()


def test_an_uncompressed_file_cut_short_is_refused(tmp_path):
    xyz, classes, *_ = _forest_plot()
    _write_cloud(tmp_path / "plot.las", xyz, classes)
    data = (tmp_path / "plot.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[:len(data) // 2])
    with pytest.raises(InputError, match="laspy can read"):
        read_point_cloud(tmp_path / "cut.las")
