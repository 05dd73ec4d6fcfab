"""Products of gridded photon points (flightsim.outputs.grid_products): range image, PNG, GeoTIFF, LAS.

Expected values are built by hand (pixel positions, cell means, percentiles of known values) or
come from the readers (rasterio's transform and index, laspy, pyproj, matplotlib), never from the
code under test.
"""
from __future__ import annotations

import laspy
import matplotlib.image
import numpy as np
import pyproj
import pytest
import rasterio
from PIL import Image

from flightsim.core.errors import InputError
from flightsim.outputs.grid_products import height_raster, range_image, write_geotiff, write_png, write_points_las
from flightsim.scoring.photon_grid import GridPoints

UTM48N = pyproj.CRS.from_epsg(32648)
NAN = np.nan


def _grid(cells_cr: list[tuple[int, int]]) -> GridPoints:
    m = len(cells_cr)
    return GridPoints(np.zeros((m, 3)), np.array(cells_cr, dtype=np.int64).reshape(m, 2),
                      np.ones(m, np.int64), np.ones(m, np.int64), m)


# --- range image ---------------------------------------------------------------------------------

def test_range_image_is_north_up_with_nan_where_no_point():
    # (column, row): rows count northwards, so grid row 3 is image row 0 (the top)
    grid = _grid([(0, 0), (3, 0), (1, 3)])
    image = range_image(grid, 4, np.array([1.0, 2.0, 3.0]))
    expected = np.array([
        [NAN, 3.0, NAN, NAN],
        [NAN, NAN, NAN, NAN],
        [NAN, NAN, NAN, NAN],
        [1.0, NAN, NAN, 2.0],
    ])
    assert image.shape == (4, 4) and image.dtype == np.float64
    np.testing.assert_array_equal(image, expected)


@pytest.mark.parametrize("cells, values, grid, field", [
    (4, np.ones(2), _grid([(0, 0), (1, 1), (2, 2)]), "values"),
    (4, np.ones(1), _grid([(4, 0)]), "grid.cell"),
    (4, np.ones(1), _grid([(0, -1)]), "grid.cell"),
    (4, np.ones(2), _grid([(1, 2), (1, 2)]), "grid.cell"),
    (0, np.ones(1), _grid([(0, 0)]), "cells"),
])
def test_range_image_rejects_bad_input(cells, values, grid, field):
    with pytest.raises(InputError, match=f"invalid {field}"):
        range_image(grid, cells, values)


# --- PNG -----------------------------------------------------------------------------------------

def _ramp_with_nan_column() -> np.ndarray:
    """10 × 11: values 0..99 row-major in columns 0-9, NaN in column 10."""
    image = np.full((10, 11), NAN)
    image[:, :10] = np.arange(100.0).reshape(10, 10)
    return image


def test_png_colours_nan_and_spans_robust_percentiles(tmp_path):
    path = tmp_path / "range.png"
    write_png(path, _ramp_with_nan_column(), "range", "m")
    rgba = matplotlib.image.imread(path)
    assert rgba.shape == (10, 11, 4)
    np.testing.assert_array_equal(rgba[:, 10], 0.0)  # NaN: transparent
    assert np.all(rgba[:, :10, 3] == 1.0)
    # percentiles of 0..99 by linear interpolation: 2 % → 1.98, 98 % → 97.02
    text = Image.open(path).text
    assert float(text["vmin"]) == pytest.approx(1.98) and float(text["vmax"]) == pytest.approx(97.02)
    assert text["units"] == "m" and text["Title"] == "range"
    low = np.round(np.array(matplotlib.colormaps["viridis"](0.0)) * 255) / 255
    np.testing.assert_allclose(rgba[0, 0], low, atol=1e-6)  # 0 and 1 lie below vmin: the low end
    np.testing.assert_array_equal(rgba[0, 0], rgba[0, 1])
    assert not np.array_equal(rgba[0, 0], rgba[5, 0])  # 0 and 50 differ
    assert not np.array_equal(rgba[5, 0], rgba[9, 0])  # 50 and 90 differ
    assert [p.name for p in tmp_path.iterdir()] == ["range.png"]


def test_png_nan_colour_can_be_opaque_black(tmp_path):
    path = tmp_path / "h.png"
    write_png(path, _ramp_with_nan_column(), "height", "m", nan_rgba=(0, 0, 0, 1))
    np.testing.assert_array_equal(matplotlib.image.imread(path)[:, 10], [[0.0, 0.0, 0.0, 1.0]] * 10)


def test_png_of_no_finite_pixel_is_refused(tmp_path):
    with pytest.raises(InputError, match="invalid image"):
        write_png(tmp_path / "x.png", np.full((3, 3), NAN), "range", "m")
    assert list(tmp_path.iterdir()) == []


# --- GeoTIFF -------------------------------------------------------------------------------------

# cells of 2 m: A1, A2 share [409000, 409002) × [3392002, 3392004) (A1 at its centre); B alone at the
# centre of [409004, 409006) × [3392000, 3392002); so the raster is 3 columns × 2 rows from (409000, 3392004)
A1, A2, B = (409001.0, 3392003.0, 10.0), (409001.5, 3392002.5, 12.0), (409005.0, 3392001.0, 20.0)


def test_height_raster_means_per_cell_north_up():
    heights, west, north = height_raster(np.array([A1, A2, B]), 2.0)
    assert (west, north) == (409000.0, 3392004.0)
    np.testing.assert_array_equal(heights, [[11.0, NAN, NAN], [NAN, NAN, 20.0]])


def test_geotiff_reads_back_georeferenced(tmp_path):
    path = tmp_path / "dem.tif"
    heights, west, north = height_raster(np.array([A1, A2, B]), 2.0)
    write_geotiff(path, heights, (west, north), 2.0, UTM48N, nodata=-9999.0)
    assert [p.name for p in tmp_path.iterdir()] == ["dem.tif"]
    with rasterio.open(path) as src:
        assert pyproj.CRS.from_wkt(src.crs.to_wkt()) == UTM48N and src.crs.to_epsg() == 32648
        assert (src.count, src.width, src.height, src.dtypes[0]) == (1, 3, 2, "float32")
        assert src.nodata == -9999.0
        assert src.profile["compress"] == "lzw" and src.profile["tiled"]
        band = src.read(1, masked=True)
        transform = src.transform
        index = [src.index(x, y) for x, y, _ in (A1, B)]
    # pixel centres are the cell centres, where A1 and B were put
    xs, ys = rasterio.transform.xy(transform, [0, 1], [0, 2])
    np.testing.assert_array_equal(np.column_stack([xs, ys]), [A1[:2], B[:2]])
    assert index == [(0, 0), (1, 2)]
    assert band[0, 0] == (A1[2] + A2[2]) / 2 and band[1, 2] == B[2]
    assert band.mask.sum() == 4 and not band.mask[0, 0] and not band.mask[1, 2]


@pytest.mark.parametrize("cell_m", [0.0, -1.0, NAN])
def test_height_raster_rejects_bad_cell(cell_m):
    with pytest.raises(InputError, match="invalid cell_m"):
        height_raster(np.array([A1]), cell_m)


def test_height_raster_rejects_nan_and_bad_shapes():
    with pytest.raises(InputError, match="invalid points_world"):
        height_raster(np.array([A1, (NAN, 3392000.0, 1.0)]), 1.0)
    with pytest.raises(InputError, match="invalid points_world"):
        height_raster(np.zeros((3, 2)), 1.0)


def test_geotiff_rejects_nodata_among_heights(tmp_path):
    with pytest.raises(InputError, match="invalid nodata"):
        write_geotiff(tmp_path / "d.tif", np.array([[1.0, -9999.0]]), (409000.0, 3392004.0), 1.0, UTM48N)
    with pytest.raises(InputError, match="invalid cell_m"):
        write_geotiff(tmp_path / "d.tif", np.array([[1.0]]), (409000.0, 3392004.0), 0.0, UTM48N)
    assert list(tmp_path.iterdir()) == []


# --- LAS -----------------------------------------------------------------------------------------

def _points(n=500, seed=3):
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(409000, 409800, n), rng.uniform(3392000, 3392900, n),
                           rng.uniform(-40, 300, n)])
    return xyz, rng.integers(0, 65536, n), 3.0e8 + np.sort(rng.uniform(0, 5, n))


def test_las_round_trips_points_crs_and_photons(tmp_path):
    xyz, photons, gps_time = _points()
    path = tmp_path / "grid.las"
    write_points_las(path, xyz, UTM48N, photons=photons, gps_time=gps_time)
    assert [p.name for p in tmp_path.iterdir()] == ["grid.las"]
    las = laspy.read(path)
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    assert las.header.point_count == len(xyz)
    np.testing.assert_array_equal(las.header.scales, [0.001] * 3)
    assert np.all(las.header.offsets <= xyz.min(axis=0))
    for axis, k in zip("xyz", range(3)):
        assert np.abs(np.asarray(las[axis]) - xyz[:, k]).max() <= 0.0005
    assert las.header.parse_crs() == UTM48N
    wkt = las.header.vlrs.get("WktCoordinateSystemVlr")[0].string
    assert wkt.startswith("PROJCS[") and las.header.global_encoding.wkt
    np.testing.assert_array_equal(las["photons"], photons)
    assert las["photons"].dtype == np.uint16
    np.testing.assert_array_equal(las["gps_time"], gps_time)
    np.testing.assert_array_equal(las.classification, 2)


def test_las_without_photons_has_no_extra_bytes(tmp_path):
    xyz, _, _ = _points(20)
    write_points_las(tmp_path / "p.las", xyz, UTM48N)
    las = laspy.read(tmp_path / "p.las")
    assert list(las.point_format.extra_dimension_names) == [] and len(las.points) == 20


def test_las_with_a_nan_point_is_refused_and_leaves_no_file(tmp_path):
    xyz, photons, _ = _points(10)
    xyz[4, 2] = NAN
    with pytest.raises(InputError, match="invalid points_world"):
        write_points_las(tmp_path / "p.las", xyz, UTM48N, photons=photons)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kwargs, field", [
    ({"points_world": np.zeros((0, 3))}, "points_world"),
    ({"photons": np.full(10, 70000)}, "photons"),
    ({"photons": np.ones(9, np.int64)}, "photons"),
    ({"photons": np.ones(10)}, "photons"),
    ({"gps_time": np.full(10, NAN)}, "gps_time"),
    ({"crs": "EPSG:4326"}, "crs"),
])
def test_las_rejects_bad_input(tmp_path, kwargs, field):
    xyz, _, _ = _points(10)
    args = {"points_world": xyz, "crs": UTM48N, **kwargs}
    with pytest.raises(InputError, match=f"invalid {field}"):
        write_points_las(tmp_path / "p.las", **args)
    assert list(tmp_path.iterdir()) == []


def test_a_failed_write_leaves_neither_file_nor_temporary(tmp_path, monkeypatch):
    def fail(self, points):
        raise OSError("disk full")

    monkeypatch.setattr(laspy.LasWriter, "write_points", fail)
    with pytest.raises(OSError, match="disk full"):
        write_points_las(tmp_path / "p.las", _points(10)[0], UTM48N)
    assert list(tmp_path.iterdir()) == []
