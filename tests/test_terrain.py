"""Real terrain: GeoTIFF DEMs flown as the equivalent built-in plane, nodata holes, refused rasters, land cover
in the LAS classification, buildings, the simplification's error bound, and the test-DEM generator — each
against numbers worked out here from the rasters' own definitions."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from scipy.ndimage import binary_dilation

from flightsim import api
from flightsim.core.errors import InputError
from flightsim.engine.run import simulate_to_directory
from flightsim.scenes import testdem
from flightsim.scenes.dem import dem_scene
from flightsim.scenes.gridmesh import grid_triangles
from flightsim.scenes.landcover import REFLECTANCE, triangle_reflectance
from flightsim.scenes.meshio import load_mesh

ROOT = Path(__file__).resolve().parents[1]
E0, N0, H0 = 409000.0, 3393000.0, 450.0  # the default scene origin
SHORT = {"flight.duration_s": 0.1, "run.device": "cpu", "output.models": ["exact"]}


def _write_tif(path, values, west, north, cell_e, cell_n, crs="EPSG:32648", nodata=None, dtype="float32"):
    with rasterio.open(path, "w", driver="GTiff", width=values.shape[1], height=values.shape[0], count=1,
                       dtype=dtype, crs=crs, transform=from_origin(west, north, cell_e, cell_n), nodata=nodata) as dst:
        dst.write(values.astype(dtype), 1)


def _tilted_dem(path, slope, cell_e=2.0, cell_n=3.0, half_e=400.0, half_n=402.0, hole=None):
    """A GeoTIFF of the plane H = H0 − slope·(N − N0) with nodes (pixel centres) centred on (E0, N0); ``hole``
    (west, south, east, north) world [m] sets the nodes inside it to nodata. Returns the node coordinates."""
    cols, rows = round(2 * half_e / cell_e) + 1, round(2 * half_n / cell_n) + 1
    east = E0 + (np.arange(cols) - (cols - 1) / 2) * cell_e
    north = N0 - (np.arange(rows) - (rows - 1) / 2) * cell_n
    heights = np.broadcast_to(H0 - slope * (north[:, None] - N0), (rows, cols)).copy()
    if hole is not None:
        w, s, e, n = hole
        heights[np.ix_((north >= s) & (north <= n), (east >= w) & (east <= e))] = -9999.0
    _write_tif(path, heights, east[0] - cell_e / 2, north[0] + cell_n / 2, cell_e, cell_n, nodata=-9999.0)
    return east, north


@pytest.mark.parametrize("slope", [0.0, 0.1])
def test_flat_and_tilted_geotiffs_give_the_points_of_the_builtin_plane(tmp_path, slope):
    _tilted_dem(tmp_path / "dem.tif", slope)  # non-square 2 m × 3 m pixels
    plane = api.simulate(api.load_config(overrides={**SHORT, "scene.name": "plane", "scene.slope": slope}))
    dem = api.simulate(api.load_config(overrides={**SHORT, "scene.name": str(tmp_path / "dem.tif")}))
    a, b = plane.returns.points["exact"], dem.returns.points["exact"]
    assert len(a) == len(b) > 1000
    assert np.abs(a - b).max() < 2e-3  # float32 local coordinates, hundreds of metres from the origin
    assert np.abs(b[:, 2] - (H0 - slope * (b[:, 1] - N0))).max() < 2e-3  # on the plane the raster describes


def test_nodata_holes_are_holes_no_returns_from_them(tmp_path):
    hole = (E0 + 100.0, N0 - 40.0, E0 + 170.0, N0 + 40.0)  # across the scan circle (radius 134 m)
    _tilted_dem(tmp_path / "full.tif", 0.05)
    east, north = _tilted_dem(tmp_path / "hole.tif", 0.05, hole=hole)
    # the mesh's hole: every cell with a nodata corner, i.e. out to the nearest valid nodes around the hole
    w, e = east[east < hole[0]].max(), east[east > hole[2]].min()
    s, n = north[north < hole[1]].max(), north[north > hole[3]].min()
    runs = {}
    for name in ("full", "hole"):
        cfg = api.load_config(overrides={**SHORT, "scene.name": str(tmp_path / f"{name}.tif")})
        runs[name] = api.simulate(cfg, with_truth=True).returns
    inside = {k: ((r.true_points[:, 0] > w) & (r.true_points[:, 0] < e) & (r.true_points[:, 1] > s)
                  & (r.true_points[:, 1] < n)) for k, r in runs.items()}
    assert inside["full"].sum() > 300  # the scan crosses the hole
    assert inside["hole"].sum() == 0  # rays through the hole miss: no zero-height wall or floor under it
    assert len(runs["hole"].true_points) == (~inside["full"]).sum()
    key = lambda r: r.pulse * 1000 + r.beam  # noqa: E731 - the same pulse and beam in both runs
    kept = np.isin(key(runs["full"]), key(runs["hole"]))
    assert np.abs(runs["full"].true_points[kept] - runs["hole"].true_points).max() < 1e-6


def test_unreadable_empty_geographic_and_crs_less_geotiffs_are_refused(tmp_path):
    heights = np.full((5, 5), 100.0)
    _write_tif(tmp_path / "wgs84.tif", heights, 105.0, 30.7, 1e-4, 1e-4, crs="EPSG:4326")
    _write_tif(tmp_path / "nocrs.tif", heights, 0.0, 100.0, 1.0, 1.0, crs=None)
    _write_tif(tmp_path / "allnodata.tif", np.full((5, 5), -9999.0), 0.0, 100.0, 1.0, 1.0, nodata=-9999.0)
    (tmp_path / "junk.tif").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "empty.tif").write_bytes(b"")
    cases = {"wgs84.tif": "gdalwarp -t_srs EPSG:32648",  # 105° E: UTM zone 48 north
             "nocrs.tif": "with a CRS", "allnodata.tif": "three valid heights", "junk.tif": "rasterio can read",
             "empty.tif": "rasterio can read", "missing.tif": "an existing file"}
    for name, words in cases.items():
        with pytest.raises(InputError, match="scene.name") as error:
            dem_scene(str(tmp_path / name), None, (0.0, 0.0, 0.0), 1.0)
        assert words in str(error.value), str(error.value)


def _class_dem(tmp_path):
    """A flat DEM (2 m nodes) with a land-cover raster of 10 m pixels whose edges run along node lines,
    covering only the DEM's northern part, with nodata pixels on the scan circle (radius 134 m), and one
    flat-roofed box building 20 m high, 30 m × 20 m, centred 130 m south of the middle (under the scan)."""
    _tilted_dem(tmp_path / "dem.tif", 0.0, cell_e=2.0, cell_n=2.0)
    west, north = E0 - 200.0, N0 + 200.0  # node lines: E0 ± 2k, N0 ± 2k
    codes = np.array([2, 3, 5, 6, 9, 11], dtype=np.uint8)[np.add.outer(np.arange(30), 2 * np.arange(40)) % 6]
    codes[18:22, 33] = 0  # nodata, 134 m east of the middle
    _write_tif(tmp_path / "cover.tif", codes, west, north, 10.0, 10.0, nodata=0, dtype="uint8")
    box = np.array([[E0 + x, N0 - 130.0 + y, H0 + z] for z in (-1.0, 20.0)
                    for x, y in ((-15, -10), (15, -10), (15, 10), (-15, 10))])
    faces = "g roof\nf 5 6 7 8\ng wall\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\ng floor\nf 1 4 3 2\n"
    (tmp_path / "house.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in box) + faces)
    return codes, west, north


def test_land_cover_and_buildings_reach_the_las_classification(tmp_path):
    codes, west, north = _class_dem(tmp_path)
    cfg = api.load_config(overrides={**SHORT, "flight.duration_s": 0.3, "scene.name": str(tmp_path / "dem.tif"),
                                     "scene.landcover": str(tmp_path / "cover.tif"),
                                     "scene.buildings": str(tmp_path / "house.obj")})
    simulate_to_directory(cfg, tmp_path / "out")
    las = [laspy.read(p) for p in sorted((tmp_path / "out" / "exact").glob("*.las"))]
    x, y, z = (np.concatenate([np.asarray(f[k]) for f in las]) for k in ("x", "y", "z"))
    got = np.concatenate([np.asarray(f.classification) for f in las])
    on_roof = (np.abs(x - E0) < 15.0) & (np.abs(y - N0 + 130.0) < 10.0) & (z > H0 + 1.0)
    by_house = (np.abs(x - E0) < 16.0) & (np.abs(y - N0 + 130.0) < 11.0)
    assert on_roof.sum() > 20 and np.all(got[on_roof] == 6) and np.abs(z[on_roof] - (H0 + 20.0)).max() < 2e-3
    col, row = np.floor((x - west) / 10.0).astype(int), np.floor((north - y) / 10.0).astype(int)
    off_edge = (np.abs((x - west) / 10.0 - np.round((x - west) / 10.0)) > 1e-3) & (
        np.abs((north - y) / 10.0 - np.round((north - y) / 10.0)) > 1e-3)
    covered = (row >= 0) & (row < codes.shape[0]) & (col >= 0) & (col < codes.shape[1])
    expected = np.full(len(x), 2)
    expected[covered] = codes[row[covered], col[covered]]
    nodata = covered & (expected == 0)
    expected[nodata] = 2  # a nodata pixel keeps the ground
    ground = ~by_house & off_edge & (np.abs(z - H0) < 1e-2)
    assert ground.sum() > 3000 and len(np.unique(expected[ground])) == 6
    assert (~covered[ground]).sum() > 100 and nodata[ground].sum() > 10
    assert np.array_equal(got[ground], expected[ground])


def test_land_cover_classes_carry_their_reflectance_and_buildings_their_planes(tmp_path):
    _class_dem(tmp_path)
    scene = dem_scene(str(tmp_path / "dem.tif"), None, (0.0, 0.0, H0), 1.0, 0.0, str(tmp_path / "cover.tif"),
                      str(tmp_path / "house.obj"))
    reflectance = triangle_reflectance(scene)
    for code, rho in REFLECTANCE.items():
        assert np.all(reflectance[scene.classification == code] == np.float32(rho))
    assert {9: 0.05, 2: 0.25, 6: 0.35}.items() <= REFLECTANCE.items()
    kinds = sorted((p.kind, p.classification, p.building) for p in scene.planes[1:])
    assert kinds == [("roof", 6, 0), ("surface", 6, 0)] + [("wall", 6, 0)] * 4
    roof = next(p for p in scene.planes if p.kind == "roof")
    assert roof.point[2] + scene.origin[2] == pytest.approx(H0 + 20.0) and roof.normal[2] == pytest.approx(1.0)


def test_buildings_outside_the_dem_and_land_cover_in_another_crs_are_refused(tmp_path):
    _class_dem(tmp_path)
    (tmp_path / "far.obj").write_text(f"v {E0 + 390} {N0} {H0}\nv {E0 + 410} {N0} {H0}\nv {E0 + 400} {N0 + 10} {H0}\n"
                                      "f 1 2 3\n")
    with pytest.raises(InputError, match="scene.buildings") as error:
        dem_scene(str(tmp_path / "dem.tif"), None, (0.0, 0.0, H0), 1.0, buildings=str(tmp_path / "far.obj"))
    assert "inside the DEM's extent" in str(error.value) and "E 409410.00" in str(error.value)
    _write_tif(tmp_path / "utm47.tif", np.full((3, 3), 2), E0 - 10, N0 + 10, 10.0, 10.0, crs="EPSG:32647",
               dtype="uint8")
    with pytest.raises(InputError, match="scene.landcover"):
        dem_scene(str(tmp_path / "dem.tif"), None, (0.0, 0.0, H0), 1.0, landcover=str(tmp_path / "utm47.tif"))
    _write_tif(tmp_path / "codes.tif", np.full((3, 3), 42), E0 - 10, N0 + 10, 10.0, 10.0, dtype="uint8")
    with pytest.raises(InputError, match="scene.landcover"):
        dem_scene(str(tmp_path / "dem.tif"), None, (0.0, 0.0, H0), 1.0, landcover=str(tmp_path / "codes.tif"))
    with pytest.raises(InputError, match="scene.buildings"):
        api.load_config(overrides={"scene.name": "plane", "scene.buildings": str(tmp_path / "house.obj")})


def _full_surface(heights, x, y):
    """Height of the two-triangles-per-cell surface (diagonal SW–NE) at (x, y) in node units (x east from
    column 0, y south from row 0), by barycentric interpolation inside its cell."""
    j = np.minimum(np.floor(x).astype(int), heights.shape[1] - 2)
    i = np.minimum(np.floor(y).astype(int), heights.shape[0] - 2)
    fx, fy = x - j, (i + 1) - y  # east of the west side, north of the south side
    sw, se, ne, nw = heights[i + 1, j], heights[i + 1, j + 1], heights[i, j + 1], heights[i, j]
    return np.where(fx >= fy, sw + fx * (se - sw) + fy * (ne - se), sw + fy * (nw - sw) + fx * (ne - nw))


def _mesh_height(points2, triangles, x, y):
    """Height of the mesh (nodes at points2 (V, 3)) at each (x, y): the triangle holding it, brute force."""
    a, b, c = (points2[triangles[:, k]] for k in range(3))
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    out = np.full(len(x), np.nan)
    for k in range(len(x)):
        px, py = x[k] - a[:, 0], y[k] - a[:, 1]
        u = (px * (c[:, 1] - a[:, 1]) - py * (c[:, 0] - a[:, 0])) / det
        v = ((b[:, 0] - a[:, 0]) * py - (b[:, 1] - a[:, 1]) * px) / det
        hit = np.flatnonzero((u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9))
        if len(hit):
            t = hit[0]
            out[k] = a[t, 2] + u[t] * (b[t, 2] - a[t, 2]) + v[t] * (c[t, 2] - a[t, 2])
    return out


@pytest.mark.parametrize("tolerance", [0.1, 0.5])
def test_simplification_stays_within_its_vertical_tolerance_and_has_no_cracks(tolerance):
    rows, cols = 121, 133
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    heights = 0.05 * jj + 8.0 * np.exp(-((jj - 80.0) ** 2 + (ii - 50.0) ** 2) / 900.0)  # a sloping plain, a hill
    heights[80:, :40] += np.random.default_rng(1).normal(0.0, 0.3, (rows - 80, 40))  # a rough corner
    heights[40:46, 50:53] = np.nan  # a nodata hole
    full, simple = grid_triangles(heights), grid_triangles(heights, tolerance)
    assert len(simple) < 0.5 * len(full)
    nodes = np.column_stack([jj.ravel(), -ii.ravel(), heights.ravel()])  # x east, y north [node units]

    def area(t):
        p = nodes[t]
        (x0, y0), (x1, y1), (x2, y2) = (p[:, k, :2].T for k in range(3))
        return 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))

    assert area(simple).min() > 0 and area(simple).sum() == pytest.approx(area(full).sum())  # same cover, no overlap
    edges = np.sort(np.concatenate([simple[:, [0, 1]], simple[:, [1, 2]], simple[:, [2, 0]]]), axis=1)
    edge, uses = np.unique(edges, axis=0, return_counts=True)
    assert uses.max() == 2
    row, col = edge[uses == 1] // cols, edge[uses == 1] % cols  # (E, 2 ends) of the edges of one triangle only
    on_border = np.all((row == 0) | (row == rows - 1), axis=1) | np.all((col == 0) | (col == cols - 1), axis=1)
    by_hole = binary_dilation(np.isnan(heights), np.ones((3, 3), bool))[row, col].all(axis=1)
    assert np.all(on_border | by_hole)  # the grid's border or the hole's: no T-junction anywhere
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, cols - 1, 3000), rng.uniform(0, rows - 1, 3000)
    x, y = np.r_[x, jj[1:, 1:].ravel() - 0.5], np.r_[y, ii[1:, 1:].ravel() - 0.5]  # and every cell's middle
    reference = _full_surface(np.nan_to_num(heights, nan=-1e9), x, y)
    keep = reference > -1e8
    got = _mesh_height(nodes * [1, -1, 1], simple, x[keep], y[keep])  # y down in the helper's units
    assert not np.isnan(got).any()
    error = np.abs(got - reference[keep])
    assert error.max() <= tolerance + 1e-9
    assert error.max() > 0.25 * tolerance  # the simplification used its budget


def test_generator_is_deterministic_and_its_files_open_with_their_crs(tmp_path):
    args = ["--size-m", "400", "--cell-m", "4", "--seed", "7"]
    for name in ("a", "b"):
        done = subprocess.run([sys.executable, "-m", "flightsim.scenes.testdem", "--out", str(tmp_path / name), *args],
                              capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 0, done.stderr
    testdem.write(tmp_path / "c", 400.0, 4.0, seed=8)
    read = {}
    for name in ("a", "b", "c"):
        with rasterio.open(tmp_path / name / "dem.tif") as dem, \
                rasterio.open(tmp_path / name / "landcover.tif") as cover:
            assert dem.crs.to_epsg() == cover.crs.to_epsg() == 32648 and dem.shape == cover.shape == (101, 101)
            assert dem.res == (4.0, 4.0) and dem.transform.c == pytest.approx(E0 - 202.0)
            read[name] = (dem.read(1), cover.read(1), (tmp_path / name / "buildings.obj").read_text())
    assert all(np.array_equal(u, v) for u, v in zip(read["a"][:2], read["b"][:2])) and read["a"][2] == read["b"][2]
    assert not np.array_equal(read["a"][0], read["c"][0])
    heights, codes, _ = read["a"]
    assert set(np.unique(codes)) <= set(REFLECTANCE) and {2, 9, 6} <= set(np.unique(codes))
    assert heights[codes == 9].max() < heights[codes != 9].mean() - 30.0  # the river runs in the valley
    town = load_mesh(tmp_path / "a" / "buildings.obj", "EPSG:32648")
    world = town.local_to_world(town.vertices)
    assert np.all(np.abs(world[:, :2] - [E0, N0]) < 200.0) and set(town.classification) == {6}
    scene = dem_scene(str(tmp_path / "a" / "dem.tif"), None, (0.0, 0.0, H0), 1.0, 0.0,
                      str(tmp_path / "a" / "landcover.tif"), str(tmp_path / "a" / "buildings.obj"))
    assert len(scene.planes) > 1 + 6 * 3
    bad = subprocess.run([sys.executable, "-m", "flightsim.scenes.testdem", "--out", str(tmp_path / "d"), "--cell-m",
                          "0"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and bad.stderr.strip().startswith("flightsim: error: invalid --cell-m = 0.0")


@pytest.mark.parametrize("triangles", [10_000, 300_000])
def test_terrain_has_about_the_asked_triangle_count(triangles):
    scene = testdem.terrain(triangles, seed=1)
    assert abs(len(scene.triangles) - triangles) < 0.02 * triangles
    assert scene.vertices[:, 2].max() - scene.vertices[:, 2].min() > 60.0  # hills and a valley
    assert scene.crs.to_epsg() == 32648
