"""Canopy height model (flightsim.outputs.chm) from points sampled on analytic surfaces.

Ground is the plane g(x, y) = 100 + 0.1·x − 0.05·y; trees are cones of height H and radius R, h = H·(1 − r/R).
First returns lie on g + max(h, 0), with a second return on the ground under part of the canopy. Within a
cell of side L every point is at most d = L/√2 from the centre, so the highest first return differs from
(g + h)(centre) by at most (|∇g| + max H/R)·d, and the mean ground height of a cell (a plane: g at the mean
point), or a linear interpolation of such means, differs from g(centre) by at most |∇g|·d: the CHM differs
from h(centre) by at most (2|∇g| + max H/R)·d (clipping at 0 only brings it closer).
"""
from __future__ import annotations

import numpy as np
import pyproj
import pytest
import rasterio

from flightsim.core.errors import InputError
from flightsim.outputs.chm import chm_from_points, write_chm_tif

UTM48N = pyproj.CRS.from_epsg(32648)
SLOPE = np.array([0.1, -0.05])
CONES = [(20.0, 20.0, 15.0, 6.0), (42.0, 35.0, 10.0, 5.0), (15.0, 45.0, 20.0, 8.0)]  # x, y, H, R
E0, N0 = 500_000.0, 3_400_000.0  # a UTM corner: the grid must stay on whole cells of absolute coordinates
HOLE = (50.0, 56.0, 4.0, 10.0)  # a square [m] without any point


def _ground(x, y):
    return 100.0 + SLOPE[0] * x + SLOPE[1] * y


def _canopy(x, y):
    return np.max([np.clip(h * (1 - np.hypot(x - cx, y - cy) / r), 0.0, None) for cx, cy, h, r in CONES], axis=0)


def _points(density=20.0, seed=0):
    rng = np.random.default_rng(seed)
    n = int(60 * 60 * density)
    x, y = rng.uniform(0, 60, n), rng.uniform(0, 60, n)
    keep = ~((x >= HOLE[0]) & (x < HOLE[1]) & (y >= HOLE[2]) & (y < HOLE[3]))
    x, y = x[keep], y[keep]
    h = _canopy(x, y)
    tree = h > 0
    under = tree & (rng.uniform(size=len(x)) < 0.3) & (x < 30)  # no ground returns under the 2nd cone
    xs = np.concatenate([x, x[under]])
    ys = np.concatenate([y, y[under]])
    zs = np.concatenate([_ground(x, y) + h, _ground(x[under], y[under])])
    ret = np.concatenate([np.ones(len(x), np.uint8), np.full(under.sum(), 2, np.uint8)])
    cls = np.concatenate([np.where(tree, 5, 2), np.full(under.sum(), 2)]).astype(np.uint8)
    return xs + E0, ys + N0, zs, ret, cls


def test_chm_matches_the_cones_at_cell_centres():
    cell = 1.0
    model, transform = chm_from_points(*_points(), cell)
    rows, cols = model.chm.shape
    assert (rows, cols) == (60, 60) and (transform.c, transform.f, transform.a) == (E0, N0 + 60, cell)
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    xc, yc = c * cell, 60.0 - r * cell  # cell centres (local): row 0 is the north edge
    bound = (2 * np.hypot(*SLOPE) + max(h / rad for _, _, h, rad in CONES)) * cell / np.sqrt(2)
    hole = (xc > HOLE[0]) & (xc < HOLE[1]) & (yc > HOLE[2]) & (yc < HOLE[3])
    assert np.isnan(model.chm[hole]).all() and np.isnan(model.dsm[hole]).all()
    error = model.chm[~hole] - _canopy(xc, yc)[~hole]
    assert np.abs(error).max() <= bound
    assert np.abs(model.dtm - _ground(xc, yc)).max() <= np.hypot(*SLOPE) * cell / np.sqrt(2)  # holes too
    assert (model.chm[~hole] >= 0).all()


def test_a_flat_topped_canopy_gives_its_height_exactly():
    """Flat ground at 10 m, a 7 m high box canopy over x in [10, 20): covered cells read 7, open cells 0."""
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 30, 20000), rng.uniform(0, 10, 20000)
    box = (x >= 10) & (x < 20)
    z = np.where(box, 17.0, 10.0)
    x2 = np.concatenate([x, x[box][::5]])
    y2 = np.concatenate([y, y[box][::5]])
    z2 = np.concatenate([z, np.full(len(x[box][::5]), 10.0)])
    ret = np.concatenate([np.ones(len(x), int), np.full(len(x[box][::5]), 2)])
    cls = np.concatenate([np.where(box, 5, 2), np.full(len(x[box][::5]), 2)])
    model, _ = chm_from_points(x2, y2, z2, ret, cls, 2.0)
    np.testing.assert_array_equal(model.chm[:, 5:10], 7.0)
    np.testing.assert_array_equal(model.chm[:, :5], 0.0)
    np.testing.assert_array_equal(model.chm[:, 10:], 0.0)
    np.testing.assert_array_equal(model.dtm, 10.0)
    every, _ = chm_from_points(x2, y2, z2, ret, cls, 2.0, dsm_returns="all")
    np.testing.assert_array_equal(every.chm, model.chm)


def test_bounds_fix_the_grid():
    x, y, z, ret, cls = _points(density=2.0)
    model, transform = chm_from_points(x, y, z, ret, cls, 5.0, bounds=(E0 - 10, N0 + 1, E0 + 20.5, N0 + 30))
    assert model.chm.shape == (6, 7) and (transform.c, transform.f) == (E0 - 10, N0 + 30)
    assert np.isnan(model.chm[:, :2]).all()  # west of the points


def test_geotiff_holds_the_chm_in_the_crs(tmp_path):
    model, transform = chm_from_points(*_points(density=4.0), 2.0)
    path = write_chm_tif(tmp_path / "chm.tif", model.chm, transform, UTM48N)
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32648 and src.transform == transform and src.nodata == -9999.0
        band = src.read(1)
    np.testing.assert_array_equal(band == -9999.0, np.isnan(model.chm))
    np.testing.assert_array_equal(band[~np.isnan(model.chm)], model.chm[~np.isnan(model.chm)].astype(np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chm.tif"]


@pytest.mark.parametrize("change, field", [
    ({"z": [1.0, np.nan]}, "z"),
    ({"y": [0.0]}, "y"),
    ({"classification": [5, 5]}, "classification"),
    ({"classification": [2.0, 2.0]}, "classification"),
    ({"return_number": [0, 1]}, "return_number"),
    ({"cell_m": -1.0}, "cell_m"),
    ({"cell_m": 1e-6}, "cell_m"),
    ({"bounds": (1.0, 0.0, 0.0, 1.0)}, "bounds"),
    ({"dsm_returns": "last"}, "dsm_returns"),
])
def test_bad_input_is_refused_by_name(change, field):
    args = dict(x=[0.0, 1.0], y=[0.0, 1.0], z=[1.0, 2.0], return_number=[1, 1], classification=[2, 5], cell_m=1.0)
    args.update(change)
    with pytest.raises(InputError, match=f"invalid {field}"):
        chm_from_points(**args)


def test_write_refuses_a_rotated_transform(tmp_path):
    from affine import Affine

    with pytest.raises(InputError, match="invalid transform"):
        write_chm_tif(tmp_path / "chm.tif", np.zeros((2, 2)), Affine(1, 0.1, 0, 0, -1, 0), UTM48N)
    assert list(tmp_path.iterdir()) == []
