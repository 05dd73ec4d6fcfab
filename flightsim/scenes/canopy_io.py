"""Leaf area density grids read from and written to files, in the scene's CRS (:class:`VoxelCanopy`).

Three formats, by suffix; all give leaf area density [m²/m³] on a regular grid in world metres of a
projected CRS, turned into the scene's local frame (world − origin):

``.npz``
    arrays ``lad`` (nx, ny, nz) [ix, iy, iz] = east, north, up; ``lower_world`` (3,) world E, N, H [m] of
    the grid's lower corner; ``cell`` (3,) voxel edge lengths [m]; optional ``crs`` (a WKT or "EPSG:…"
    string), ``leaf_angles`` (a string), ``leaf_reflectance`` and ``leaf_transmittance`` (numbers).
``.nc`` (NetCDF, read with xarray)
    variable ``lad`` of dimensions (z, y, x) or (x, y, z) (or any order; also named east/easting,
    north/northing, height/elevation), with 1-D coordinate variables of the voxel centres in world metres,
    evenly spaced, ascending or descending (a single centre needs a ``cell_m`` attribute); the CRS from a
    ``crs`` attribute (WKT) of ``lad`` or of the file, or the ``crs_wkt``/``spatial_ref`` attribute of the
    grid-mapping variable (``lad``'s ``grid_mapping``, or one named ``spatial_ref`` or ``crs``, as rioxarray
    and GDAL write it); leaf properties from attributes ``leaf_angles``, ``leaf_reflectance``,
    ``leaf_transmittance`` of the file. NetCDF-3 files are read by xarray's scipy engine, NetCDF-4 (HDF5)
    files by its h5netcdf engine.
``.tif``/``.tiff`` (a GeoTIFF stack, read with rasterio)
    one band per layer, the bottom layer first, north-up; the vertical grid from the tags
    ``layer_height_m`` (the layer thickness) and ``base_height_m`` (world H of the bottom of layer 1) of the
    dataset, or else of band 1 (a band's own ``base_height_m`` must then be band 1's plus the layers below).

A grid whose file names no CRS is taken to be in the scene's; one in another CRS is refused (reproject it
first: the resampling of leaf area is the user's choice), one in a geographic CRS too. Missing values
(NaN, a NetCDF fill value, a GeoTIFF's nodata) are refused like negative ones, naming the voxel: set
voxels without leaves to 0. Every problem is an ``InputError`` of ``scene.canopy``.

:func:`write_canopy_npz` and :func:`write_canopy_nc` write a :class:`VoxelCanopy` (the NetCDF as NetCDF-3
with xarray's scipy engine, which every NetCDF reader reads); both files appear complete or not at all.
"""
from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from flightsim.core.atomic import replaced_atomically
from flightsim.core.errors import InputError
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.scene import parse_crs

FIELD = "scene.canopy"
SUFFIXES = (".npz", ".nc", ".tif", ".tiff")
LEAF_PROPERTIES = ("leaf_angles", "leaf_reflectance", "leaf_transmittance")
AXIS_NAMES = {
    0: ("x", "east", "easting", "e"),
    1: ("y", "north", "northing", "n"),
    2: ("z", "height", "elevation", "h", "up"),
}
METRE_UNITS = ("m", "metre", "meter", "metres", "meters")


@dataclass
class _Grid:
    """A grid as read, world frame."""

    lad: np.ndarray  # (nx, ny, nz)
    lower_world: np.ndarray  # (3,) world E, N, H [m]
    cell: np.ndarray  # (3,) [m]
    crs: str | None  # WKT or any pyproj input; None: not given
    properties: dict = field(default_factory=dict)  # leaf_angles, leaf_reflectance, leaf_transmittance


def read_canopy(path, crs, origin) -> VoxelCanopy:
    """The :class:`VoxelCanopy` of the grid file at ``path`` (.npz, .nc, .tif), in the local frame of a scene
    of CRS ``crs`` and local origin ``origin`` (world E, N, H [m])."""
    path = Path(path)
    scene_crs = crs if isinstance(crs, pyproj.CRS) else parse_crs(crs)
    origin = np.asarray(origin, dtype=np.float64)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(FIELD, str(path), "a leaf area density grid file: .npz, .nc (NetCDF) or .tif (GeoTIFF stack)")
    if not path.is_file():
        raise InputError(FIELD, str(path), f"an existing {suffix} file of leaf area density")
    if suffix == ".npz":
        grid = _read_npz(path)
    elif suffix == ".nc":
        grid = _read_netcdf(path)
    else:
        grid = _read_geotiff(path)
    _check_crs(grid.crs, scene_crs, path)
    try:
        return VoxelCanopy(grid.lad, grid.lower_world - origin, grid.cell, **grid.properties)
    except InputError as error:
        raise InputError(error.field, error.value, f"{error.allowed} (in {path})") from None


def write_canopy_npz(path, canopy: VoxelCanopy, crs, origin) -> Path:
    """Write ``canopy`` (local frame of a scene of CRS ``crs``, origin ``origin``) as an .npz grid in world
    coordinates, atomically (the same grid gives the same bytes); returns the path."""
    path = Path(path)
    scene_crs = crs if isinstance(crs, pyproj.CRS) else parse_crs(crs)
    arrays = dict(lad=canopy.lad, lower_world=canopy.lower + np.asarray(origin, dtype=np.float64),
                  cell=canopy.cell, crs=np.array(scene_crs.to_wkt()), leaf_angles=np.array(canopy.leaf_angles),
                  leaf_reflectance=np.float64(canopy.leaf_reflectance),
                  leaf_transmittance=np.float64(canopy.leaf_transmittance))
    with replaced_atomically(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():  # np.savez's layout, with fixed member dates: the bytes are the grid's
            member = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            member.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(member, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)
    return path


def write_canopy_nc(path, canopy: VoxelCanopy, crs, origin) -> Path:
    """Write ``canopy`` as a NetCDF-3 grid (``lad`` (z, y, x), voxel-centre coordinates in world metres, the
    CRS as a ``spatial_ref`` grid mapping with ``crs_wkt``, as rioxarray writes it), atomically; returns the path."""
    import xarray as xr

    path = Path(path)
    scene_crs = crs if isinstance(crs, pyproj.CRS) else parse_crs(crs)
    lower = canopy.lower + np.asarray(origin, dtype=np.float64)
    centres = [lower[a] + (np.arange(n, dtype=np.float64) + 0.5) * canopy.cell[a] for a, n in enumerate(canopy.dims)]
    wkt = scene_crs.to_wkt()
    coords = {name: (name, centres[a], {"units": "m", "cell_m": float(canopy.cell[a]),
                                        "long_name": f"voxel centre, world {long}"})
              for a, (name, long) in enumerate((("x", "easting"), ("y", "northing"), ("z", "height")))}
    ds = xr.Dataset(
        {"lad": (("z", "y", "x"), np.ascontiguousarray(canopy.lad.transpose(2, 1, 0)),
                 {"units": "m2 m-3", "long_name": "leaf area density", "grid_mapping": "spatial_ref"}),
         "spatial_ref": ((), np.int32(0), {"crs_wkt": wkt, "spatial_ref": wkt})},
        coords=coords,
        attrs={"leaf_angles": canopy.leaf_angles, "leaf_reflectance": float(canopy.leaf_reflectance),
               "leaf_transmittance": float(canopy.leaf_transmittance), "crs": wkt},
    )
    with replaced_atomically(path) as tmp:
        ds.to_netcdf(tmp, engine="scipy")
    return path


def _check_crs(text, scene_crs: pyproj.CRS, path: Path) -> None:
    """Refuse a grid whose CRS is geographic or not the scene's."""
    if text is None or (isinstance(text, str) and not text.strip()):
        return
    try:
        file_crs = pyproj.CRS.from_user_input(text)
    except (pyproj.exceptions.CRSError, TypeError, ValueError):
        raise InputError(FIELD, str(text), f"a CRS pyproj can read (the CRS of {path})") from None
    if file_crs.is_geographic:
        raise InputError(FIELD, file_crs.name, f"a grid in the scene's CRS {scene_crs.name}, in metres ({path} is "
                                               "in a geographic CRS, in degrees); reproject it first")
    if not file_crs.equals(scene_crs, ignore_axis_order=True):
        raise InputError(FIELD, file_crs.name, f"a grid in the scene's CRS {scene_crs.name}; reproject {path} first")


def _properties(attrs) -> dict:
    """The leaf properties among a file's attributes or arrays."""
    found = {}
    for name in LEAF_PROPERTIES:
        if name in attrs:
            value = np.asarray(attrs[name])
            value = value.reshape(-1)[0] if value.size == 1 else value
            if isinstance(value, bytes | np.bytes_):
                value = value.decode()
            found[name] = str(value) if name == "leaf_angles" else value
    return found


def _read_npz(path: Path) -> _Grid:
    allowed = ("an .npz of arrays lad (nx, ny, nz), lower_world (3,) world E, N, H [m] and cell (3,) [m], "
               "optionally crs")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise InputError(FIELD, str(path), f"{allowed} that NumPy can read ({error})") from None
    for name in ("lad", "lower_world", "cell"):
        if name not in arrays:
            raise InputError(FIELD, f"{path.name}: no array '{name}'", allowed)
    crs = str(arrays["crs"]) if "crs" in arrays else None
    for name in ("lower_world", "cell"):
        if np.asarray(arrays[name]).shape != (3,):
            raise InputError(f"{FIELD}.{name}", f"an array of shape {np.asarray(arrays[name]).shape}",
                             f"(3,) values (E, N, H) [m] (in {path})")
    return _Grid(arrays["lad"], np.asarray(arrays["lower_world"], dtype=np.float64),
                 np.asarray(arrays["cell"], dtype=np.float64), crs, _properties(arrays))


def _read_netcdf(path: Path) -> _Grid:
    ds = _open_netcdf(path)
    allowed = "a NetCDF variable lad (z, y, x) of leaf area density [m²/m³] with voxel-centre coordinates x, y, z [m]"
    if "lad" not in ds.variables:
        raise InputError(FIELD, f"{path.name}: no variable 'lad'", allowed)
    var = ds["lad"]
    if var.ndim != 3:
        raise InputError(FIELD, f"{path.name}: lad of dimensions {var.dims}", allowed)
    axis_of = {}
    for dim in var.dims:
        axis = next((a for a, names in AXIS_NAMES.items() if str(dim).lower() in names), None)
        if axis is None or axis in axis_of.values():
            raise InputError(FIELD, f"{path.name}: lad of dimensions {var.dims}",
                             "dimensions x, y, z (east, north, up) in any order")
        axis_of[dim] = axis
    dim_of = {a: d for d, a in axis_of.items()}
    lad = np.asarray(var.transpose(dim_of[0], dim_of[1], dim_of[2]).values)
    lower, cell = np.zeros(3), np.zeros(3)
    for a in range(3):
        dim = dim_of[a]
        if dim not in ds.variables or ds[dim].ndim != 1:
            raise InputError(FIELD, f"{path.name}: no coordinate variable '{dim}'",
                             "1-D voxel-centre coordinates [m] for each dimension of lad")
        coord = ds[dim]
        units = str(coord.attrs.get("units", "m")).strip().lower()
        if units not in METRE_UNITS:
            raise InputError(FIELD, f"{path.name}: {dim} in '{units}'", f"coordinates {dim} in metres")
        centres = np.asarray(coord.values, dtype=np.float64)
        lower[a], cell[a], flip = _regular_axis(centres, coord.attrs.get("cell_m"), f"{path.name}: {dim}")
        if flip:
            lad = np.flip(lad, axis=a)
    return _Grid(lad, lower, cell, _netcdf_crs(ds, var), _properties(ds.attrs))


def _regular_axis(centres: np.ndarray, cell_attr, what: str) -> tuple[float, float, bool]:
    """(lower edge, cell, descending) of evenly spaced voxel centres [m]."""
    if len(centres) == 0:
        raise InputError(FIELD, f"{what} of no voxel", "a grid of at least one voxel along each axis")
    if not np.all(np.isfinite(centres)):
        raise InputError(FIELD, what, "finite voxel-centre coordinates [m]")
    if len(centres) == 1:
        try:
            cell = float(np.asarray(cell_attr).reshape(-1)[0]) if cell_attr is not None else float("nan")
        except (TypeError, ValueError):
            cell = float("nan")
        if not (np.isfinite(cell) and cell > 0.0):
            raise InputError(FIELD, f"{what} of one voxel centre", "two or more centres, or a cell_m attribute > 0 [m]")
        return float(centres[0]) - 0.5 * cell, cell, False
    steps = np.diff(centres)
    step = (centres[-1] - centres[0]) / (len(centres) - 1)
    if step == 0.0 or not np.all(np.abs(steps - step) <= 1e-6 * abs(step)):
        raise InputError(FIELD, f"{what} steps {steps.min():g} to {steps.max():g} m",
                         "evenly spaced voxel centres (a regular grid)")
    first = centres[0] if step > 0 else centres[-1]
    return float(first) - 0.5 * abs(step), abs(float(step)), bool(step < 0)


def _netcdf_crs(ds, var) -> str | None:
    """The CRS WKT a NetCDF file gives for ``lad``, or None."""
    for attrs in (var.attrs, ds.attrs):
        for key in ("crs", "crs_wkt", "spatial_ref"):
            if isinstance(attrs.get(key), str) and attrs[key].strip():
                return attrs[key]
    names = [var.attrs.get("grid_mapping"), var.encoding.get("grid_mapping"), "spatial_ref", "crs"]
    for name in names:
        if isinstance(name, str) and name in ds.variables:
            attrs = ds[name].attrs
            for key in ("crs_wkt", "spatial_ref"):
                if isinstance(attrs.get(key), str) and attrs[key].strip():
                    return attrs[key]
    return None


def _open_netcdf(path: Path):
    """The file as an xarray Dataset, loaded (the file closed again)."""
    import xarray as xr

    try:
        with xr.open_dataset(path, decode_times=False) as ds:
            return ds.load()
    except (ValueError, OSError, TypeError, RuntimeError) as error:
        raise InputError(FIELD, str(path), f"a NetCDF file xarray can read ({error})") from None


def _read_geotiff(path: Path) -> _Grid:
    import rasterio
    from rasterio.errors import RasterioError

    allowed = ("a GeoTIFF stack of leaf area density, one band per layer from the bottom up, with tags "
               "layer_height_m and base_height_m")
    try:
        with rasterio.open(path) as src:
            t = src.transform
            if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
                raise InputError(FIELD, str(path), f"{allowed}, north-up (no rotation or shear)")
            tags, band_tags = src.tags(), [src.tags(b) for b in range(1, src.count + 1)]
            bands = src.read(masked=True)
            crs = src.crs.to_wkt() if src.crs is not None else None
            rows = src.height
    except RasterioError as error:
        raise InputError(FIELD, str(path), f"{allowed} that rasterio can read ({error})") from None
    dz = _tag(tags, band_tags, "layer_height_m", path, allowed)
    base = _tag(tags, band_tags, "base_height_m", path, allowed)
    if not (np.isfinite(dz) and dz > 0.0):
        raise InputError(f"{FIELD}.layer_height_m", dz, f"a layer thickness > 0 m (in {path})")
    for b, bt in enumerate(band_tags):
        if "base_height_m" in bt and "base_height_m" not in tags:
            own = float(bt["base_height_m"])
            if abs(own - (base + b * dz)) > 1e-6 * max(1.0, abs(own)):
                raise InputError(f"{FIELD}.base_height_m", f"{own:g} m in band {b + 1}",
                                 f"band 1's base plus the layers below: {base + b * dz:g} m (in {path})")
    values = np.ma.filled(bands.astype(np.float64), np.nan)  # nodata → NaN, refused by the canopy's check
    lad = np.ascontiguousarray(values.transpose(2, 1, 0)[:, ::-1, :])  # [band, row, col] → [x, y (north), z]
    lower = np.array([t.c, t.f + t.e * rows, base])
    return _Grid(lad, lower, np.array([t.a, -t.e, dz]), crs, _properties(tags))


def _tag(tags: dict, band_tags: list[dict], name: str, path: Path, allowed: str) -> float:
    """A number from the dataset's tags, or else band 1's."""
    for source in (tags, band_tags[0] if band_tags else {}):
        if name in source:
            try:
                return float(source[name])
            except ValueError:
                raise InputError(f"{FIELD}.{name}", source[name], f"a number [m] (in {path})") from None
    raise InputError(FIELD, f"{path.name}: no tag '{name}'", allowed)
