"""Leaf area density grids from .npz, NetCDF and GeoTIFF stacks, and the errors of bad ones."""
from __future__ import annotations

import numpy as np
import pyproj
import pytest

from flightsim.core.errors import InputError
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import read_canopy, write_canopy_nc, write_canopy_npz

CRS = "EPSG:32648"
ORIGIN = np.array([409000.0, 3393000.0, 450.0])
LOWER_WORLD = np.array([408990.0, 3392980.0, 452.0])
CELL = np.array([2.0, 2.5, 0.5])


def _lad(shape=(4, 3, 5)):
    rng = np.random.default_rng(1)
    return rng.uniform(0.0, 1.5, shape).astype(np.float32)


def _canopy(**kwargs):
    return VoxelCanopy(_lad(), LOWER_WORLD - ORIGIN, CELL, **kwargs)


def _same(a: VoxelCanopy, b: VoxelCanopy):
    assert np.array_equal(a.lad, b.lad)
    assert np.allclose(a.lower, b.lower, rtol=0, atol=1e-9)
    assert np.allclose(a.cell, b.cell, rtol=0, atol=1e-12)
    assert (a.leaf_angles, a.leaf_reflectance, a.leaf_transmittance) == (
        b.leaf_angles, b.leaf_reflectance, b.leaf_transmittance)


def _centres(a: int, n: int) -> np.ndarray:
    return LOWER_WORLD[a] + (np.arange(n) + 0.5) * CELL[a]


@pytest.mark.parametrize("writer, suffix", [(write_canopy_npz, ".npz"), (write_canopy_nc, ".nc")])
def test_round_trip(tmp_path, writer, suffix):
    canopy = _canopy(leaf_angles="planophile", leaf_reflectance=0.45, leaf_transmittance=0.3)
    path = writer(tmp_path / f"c{suffix}", canopy, CRS, ORIGIN)
    assert path.is_file() and not list(tmp_path.glob(".*.part"))
    _same(read_canopy(path, CRS, ORIGIN), canopy)
    # another origin, the same world grid
    moved = read_canopy(path, pyproj.CRS(CRS), ORIGIN + [100.0, -50.0, 10.0])
    assert np.allclose(moved.lower, canopy.lower - [100.0, -50.0, 10.0], rtol=0, atol=1e-9)


def test_npz_without_crs_or_properties_is_in_the_scenes_crs(tmp_path):
    lad = _lad()
    np.savez(tmp_path / "c.npz", lad=lad, lower_world=LOWER_WORLD, cell=CELL)
    canopy = read_canopy(tmp_path / "c.npz", CRS, ORIGIN)
    _same(canopy, VoxelCanopy(lad, LOWER_WORLD - ORIGIN, CELL))


def test_netcdf_in_xyz_order_descending_north_with_a_rioxarray_grid_mapping(tmp_path):
    import xarray as xr

    lad = _lad()
    wkt = pyproj.CRS(CRS).to_wkt()
    ds = xr.Dataset(
        {"lad": (("x", "y", "z"), lad[:, ::-1, :], {"grid_mapping": "spatial_ref"}),
         "spatial_ref": ((), np.int32(0), {"crs_wkt": wkt, "spatial_ref": wkt})},
        coords={"x": _centres(0, 4), "y": _centres(1, 3)[::-1], "z": _centres(2, 5)},
    )
    ds.to_netcdf(tmp_path / "c.nc", engine="scipy")
    _same(read_canopy(tmp_path / "c.nc", CRS, ORIGIN), VoxelCanopy(lad, LOWER_WORLD - ORIGIN, CELL))


def test_netcdf4_hdf5_file_is_read(tmp_path):
    """A NetCDF-4 file (HDF5, as netCDF4 and h5netcdf write it), (z, y, x), with a float fill value."""
    import xarray as xr

    lad = _lad()
    coords = {name: (name, _centres(a, n), {"units": "m"}) for name, a, n in (("x", 0, 4), ("y", 1, 3), ("z", 2, 5))}
    ds = xr.Dataset({"lad": (("z", "y", "x"), np.ascontiguousarray(lad.transpose(2, 1, 0)))}, coords=coords,
                    attrs={"crs": pyproj.CRS(CRS).to_wkt(), "leaf_angles": "erectophile"})
    ds.to_netcdf(tmp_path / "c.nc", engine="h5netcdf", encoding={"lad": {"_FillValue": np.float32(-9999)}})
    with open(tmp_path / "c.nc", "rb") as fh:
        assert fh.read(4) == b"\x89HDF"
    canopy = read_canopy(tmp_path / "c.nc", CRS, ORIGIN)
    _same(canopy, VoxelCanopy(lad, LOWER_WORLD - ORIGIN, CELL, leaf_angles="erectophile"))


def _write_stack(path, lad, crs=CRS, tags=None, band_tags=None, nodata=None):
    import rasterio
    from affine import Affine

    nx, ny, nz = lad.shape
    north = LOWER_WORLD[1] + ny * CELL[1]
    with rasterio.open(path, "w", driver="GTiff", width=nx, height=ny, count=nz, dtype="float32", crs=crs,
                       transform=Affine(CELL[0], 0.0, LOWER_WORLD[0], 0.0, -CELL[1], north), nodata=nodata) as dst:
        for k in range(nz):
            dst.write(lad[:, ::-1, k].T, k + 1)  # row 0 is the north edge
            if band_tags:
                dst.update_tags(k + 1, **band_tags(k))
        if tags:
            dst.update_tags(**tags)


def test_geotiff_stack(tmp_path):
    lad = _lad()
    _write_stack(tmp_path / "c.tif", lad, tags=dict(layer_height_m=CELL[2], base_height_m=LOWER_WORLD[2],
                                                    leaf_reflectance="0.35"))
    _same(read_canopy(tmp_path / "c.tif", CRS, ORIGIN),
          VoxelCanopy(lad, LOWER_WORLD - ORIGIN, CELL, leaf_reflectance=0.35))
    # the vertical grid from band tags instead
    _write_stack(tmp_path / "b.tif", lad, band_tags=lambda k: dict(layer_height_m=CELL[2],
                                                                   base_height_m=LOWER_WORLD[2] + k * CELL[2]))
    _same(read_canopy(tmp_path / "b.tif", CRS, ORIGIN), VoxelCanopy(lad, LOWER_WORLD - ORIGIN, CELL))


# --- bad grids: each names scene.canopy (or its part) and the value --------------------------------------------


def _npz(path, **override):
    arrays = dict(lad=_lad(), lower_world=LOWER_WORLD, cell=CELL, crs=np.array(pyproj.CRS(CRS).to_wkt()))
    arrays.update(override)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def _raises(path, field, *fragments, crs=CRS):
    with pytest.raises(InputError) as error:
        read_canopy(path, crs, ORIGIN)
    message = str(error.value)
    assert error.value.field == field, message
    assert message.startswith(f"invalid {field} = ")
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_nan_and_negative_leaf_area_name_the_voxel(tmp_path):
    lad = _lad()
    lad[2, 1, 3] = np.nan
    _raises(_npz(tmp_path / "nan.npz", lad=lad), "scene.canopy", "nan at voxel (2, 1, 3)", "nan.npz")
    lad = _lad()
    lad[0, 2, 4] = -0.25
    _raises(_npz(tmp_path / "neg.npz", lad=lad), "scene.canopy", "-0.25 at voxel (0, 2, 4)")
    # a GeoTIFF's nodata is missing leaf area, refused too (band 2 = layer iz 1; row 0 = the northern iy = 2)
    lad = _lad()
    lad[3, 2, 1] = -9999.0
    _write_stack(tmp_path / "nodata.tif", lad, nodata=-9999.0,
                 tags=dict(layer_height_m=CELL[2], base_height_m=LOWER_WORLD[2]))
    _raises(tmp_path / "nodata.tif", "scene.canopy", "nan at voxel (3, 2, 1)")


def test_other_crs_is_refused(tmp_path):
    other = pyproj.CRS("EPSG:32649")
    message = _raises(_npz(tmp_path / "utm49.npz", crs=np.array(other.to_wkt())), "scene.canopy",
                      other.name, "the scene's CRS WGS 84 / UTM zone 48N", "reproject")
    assert "utm49.npz" in message
    _write_stack(tmp_path / "utm49.tif", _lad(), crs="EPSG:32649",
                 tags=dict(layer_height_m=CELL[2], base_height_m=LOWER_WORLD[2]))
    _raises(tmp_path / "utm49.tif", "scene.canopy", other.name, "reproject")
    canopy = _canopy()
    write_canopy_nc(tmp_path / "utm49.nc", canopy, "EPSG:32649", ORIGIN)
    _raises(tmp_path / "utm49.nc", "scene.canopy", other.name, "UTM zone 48N", "reproject")


def test_geographic_crs_is_refused(tmp_path):
    _raises(_npz(tmp_path / "geo.npz", crs=np.array("EPSG:4326")), "scene.canopy", "WGS 84", "geographic", "reproject")


def test_empty_grid(tmp_path):
    _raises(_npz(tmp_path / "empty.npz", lad=np.zeros((0, 3, 5), np.float32)), "scene.canopy", "empty",
            "(0, 3, 5)")
    import xarray as xr

    xr.Dataset({"lad": (("z", "y", "x"), np.zeros((0, 2, 2), np.float32))},
               coords={"x": [0.5, 1.5], "y": [0.5, 1.5], "z": np.zeros(0)}).to_netcdf(tmp_path / "empty.nc", engine="scipy")
    _raises(tmp_path / "empty.nc", "scene.canopy", "empty.nc: z of no voxel", "at least one voxel")


def test_missing_variables(tmp_path):
    _raises(_npz(tmp_path / "nocell.npz", cell=None), "scene.canopy", "nocell.npz: no array 'cell'")
    import xarray as xr

    xr.Dataset({"leaf": (("z", "y", "x"), np.zeros((2, 2, 2), np.float32))},
               coords={"x": [0.5, 1.5], "y": [0.5, 1.5], "z": [0.5, 1.5]}).to_netcdf(tmp_path / "nolad.nc", engine="scipy")
    _raises(tmp_path / "nolad.nc", "scene.canopy", "nolad.nc: no variable 'lad'")
    xr.Dataset({"lad": (("z", "y", "x"), np.zeros((2, 2, 2), np.float32))},
               coords={"x": [0.5, 1.5], "y": [0.5, 1.5]}).to_netcdf(tmp_path / "noz.nc", engine="scipy")
    _raises(tmp_path / "noz.nc", "scene.canopy", "noz.nc: no coordinate variable 'z'")
    _write_stack(tmp_path / "notag.tif", _lad(), tags=dict(layer_height_m=CELL[2]))
    _raises(tmp_path / "notag.tif", "scene.canopy", "notag.tif: no tag 'base_height_m'")


def test_bad_netcdf_axes(tmp_path):
    import xarray as xr

    lad = np.zeros((2, 2, 3), np.float32)
    xr.Dataset({"lad": (("z", "y", "x"), lad)}, coords={"x": [0.5, 1.5, 3.5], "y": [0.5, 1.5], "z": [0.5, 1.5]}
               ).to_netcdf(tmp_path / "uneven.nc", engine="scipy")
    _raises(tmp_path / "uneven.nc", "scene.canopy", "uneven.nc: x steps 1 to 2 m", "evenly spaced")
    ds = xr.Dataset({"lad": (("z", "y", "x"), lad)}, coords={"x": [0.5, 1.5, 2.5], "y": [0.5, 1.5], "z": [0.5, 1.5]})
    ds["x"].attrs["units"] = "degrees_east"
    ds.to_netcdf(tmp_path / "deg.nc", engine="scipy")
    _raises(tmp_path / "deg.nc", "scene.canopy", "deg.nc: x in 'degrees_east'", "metres")
    xr.Dataset({"lad": (("band", "y", "x"), lad)}, coords={"x": [0.5, 1.5, 2.5], "y": [0.5, 1.5], "band": [1, 2]}
               ).to_netcdf(tmp_path / "band.nc", engine="scipy")
    _raises(tmp_path / "band.nc", "scene.canopy", "('band', 'y', 'x')", "dimensions x, y, z")


def test_bad_paths_and_tags(tmp_path):
    _raises(tmp_path / "missing.npz", "scene.canopy", "missing.npz", "an existing .npz file")
    (tmp_path / "c.las").write_bytes(b"")
    _raises(tmp_path / "c.las", "scene.canopy", "c.las", ".npz, .nc (NetCDF) or .tif")
    (tmp_path / "junk.nc").write_bytes(b"not a netcdf file")
    _raises(tmp_path / "junk.nc", "scene.canopy", "junk.nc", "NetCDF file")
    _write_stack(tmp_path / "flat.tif", _lad(), tags=dict(layer_height_m=0.0, base_height_m=LOWER_WORLD[2]))
    _raises(tmp_path / "flat.tif", "scene.canopy.layer_height_m", "0.0", "thickness > 0")
    _raises(_npz(tmp_path / "cell.npz", cell=np.array([1.0, -1.0, 1.0])), "scene.canopy.cell", "-1.0", "cell.npz")
    _raises(_npz(tmp_path / "angles.npz", leaf_angles=np.array("conical")), "scene.canopy.leaf_angles", "conical")


def test_scene_canopy_lays_the_grid_over_any_scene(tmp_path, capsys):
    import flightsim
    from flightsim.cli import main
    from flightsim.scenes.build import build_scene

    grid = VoxelCanopy(_lad(), LOWER_WORLD - ORIGIN, CELL, leaf_reflectance=0.3)
    write_canopy_npz(tmp_path / "c.npz", grid, CRS, ORIGIN)
    cfg = flightsim.load_config(overrides={"scene.name": "plane", "scene.canopy": str(tmp_path / "c.npz")})
    scene = build_scene(cfg.scene, 50.0)
    _same(scene.canopy, grid)
    assert build_scene(flightsim.load_config().scene, 50.0).canopy is None
    assert main(["config", "--set", "scene.canopy=leaves.png"]) == 2
    assert "scene.canopy" in capsys.readouterr().err


def test_a_scene_that_brings_its_own_leaves_refuses_scene_canopy(tmp_path):
    import flightsim
    from flightsim.scenes.build import build_scene

    write_canopy_npz(tmp_path / "c.npz", VoxelCanopy(_lad(), LOWER_WORLD - ORIGIN, CELL), CRS, ORIGIN)
    cfg = flightsim.load_config(overrides={"scene.name": "forest", "scene.forest_size_m": 20.0,
                                           "scene.canopy": str(tmp_path / "c.npz")})
    with pytest.raises(InputError, match="scene.canopy.*forest scene: it brings its own leaves"):
        build_scene(cfg.scene, 50.0)
