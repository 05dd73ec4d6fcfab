"""Vegetation as a turbid medium: leaf area density in voxels over a scene, in its local frame.

A :class:`VoxelCanopy` is a regular grid of leaf area density u [m²/m³] (nx, ny, nz voxels, indexed
[ix, iy, iz] = local east, north, up) from ``lower`` in steps of ``cell``, with one leaf angle distribution
(:mod:`flightsim.scenes.leaf_angles`) and the leaves' Lambertian reflectance and transmittance. A ray
loses G(μ) u of its flux per metre through it (:mod:`kernels.canopy`). Grids are read from files by
:mod:`flightsim.scenes.canopy_io` and estimated from ALS points by :mod:`flightsim.scenes.macarthur_horn`.

:meth:`VoxelCanopy.to_device` gives the :class:`kernels.canopy.Canopy` struct the kernels take;
:func:`no_canopy` an empty one (``present = 0``), so that a kernel always gets a valid struct.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes import leaf_angles

MAX_VOXELS = 1 << 31
"""Most voxels a grid may hold (device indices are 32-bit)."""

G_TABLE_SIZE = 257
"""Entries of the G(μ) table handed to the device."""


LEAF_CLASSES = (3, 4, 5)
"""ASPRS classes of leaf returns: low, medium, high vegetation (by height above the surface under them,
:mod:`kernels.canopy_returns`)."""

@dataclass
class VoxelCanopy:
    """Leaf area density in voxels, local frame.

    Attributes:
        lad: (nx, ny, nz) float32 leaf area density [m²/m³], ≥ 0 and finite; [ix, iy, iz] = local east,
            north, up.
        lower: (3,) float64 local coordinates [m] of the grid's lower corner (west, south, bottom).
        cell: (3,) float64 voxel edge lengths [m] (east, north, up), each > 0.
        leaf_angles: the de Wit leaf inclination distribution (:data:`leaf_angles.DISTRIBUTIONS`).
        leaf_reflectance: Lambertian reflectance of a leaf, in [0, 1].
        leaf_transmittance: Lambertian transmittance of a leaf, in [0, 1]; reflectance + transmittance ≤ 1.
    """

    lad: np.ndarray
    lower: np.ndarray
    cell: np.ndarray
    leaf_angles: str = "spherical"
    leaf_reflectance: float = 0.4
    leaf_transmittance: float = 0.4
    _device: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.lad = _leaf_area_density(self.lad)
        self.lower = _vector3(self.lower, "scene.canopy.lower", "three finite local coordinates (E, N, H) [m]",
                              positive=False)
        self.cell = _vector3(self.cell, "scene.canopy.cell", "three finite voxel edge lengths > 0 m (E, N, H)",
                             positive=True)
        self.leaf_angles = leaf_angles.check_distribution(self.leaf_angles)
        self.leaf_reflectance = _fraction(self.leaf_reflectance, "scene.canopy.leaf_reflectance")
        self.leaf_transmittance = _fraction(self.leaf_transmittance, "scene.canopy.leaf_transmittance")
        if self.leaf_reflectance + self.leaf_transmittance > 1.0:
            raise InputError("scene.canopy.leaf_transmittance", self.leaf_transmittance,
                             f"at most 1 − leaf_reflectance = {1.0 - self.leaf_reflectance:g} (a leaf cannot "
                             "scatter more than it receives)")

    @property
    def dims(self) -> tuple[int, int, int]:
        """Voxels per axis (nx, ny, nz)."""
        return tuple(int(n) for n in self.lad.shape)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners (3,) of the grid's box, local [m]."""
        return self.lower.copy(), self.lower + np.asarray(self.dims, dtype=np.float64) * self.cell

    def leaf_area_index(self) -> np.ndarray:
        """(nx, ny) float64 leaf area index of each column: Σ_z lad · cell_z [m²/m²]."""
        return self.lad.sum(axis=2, dtype=np.float64) * self.cell[2]

    def g_table(self, n: int = G_TABLE_SIZE) -> np.ndarray:
        """(n,) float64 G(μ) of the leaf angle distribution at μ = i / (n − 1) (:func:`leaf_angles.g_table`)."""
        return leaf_angles.g_table(self.leaf_angles, n)

    def to_device(self, device: str):
        """The :class:`kernels.canopy.Canopy` struct of this grid on the Warp ``device``; built once per device
        (the struct and its arrays are kept on this object). Change ``lad`` in place afterwards and the
        device copy goes stale: make a new :class:`VoxelCanopy` instead."""
        import warp as wp

        from flightsim.core.warp_runtime import init_warp
        from kernels import canopy as kc

        init_warp()
        key = str(wp.get_device(device))
        if key not in self._device:
            c = kc.Canopy()
            c.lad = wp.array(self.lad, dtype=wp.float32, device=device)
            c.lad_flat = c.lad.flatten()
            c.lower = wp.vec3d(*(float(v) for v in self.lower))
            c.cell = wp.vec3d(*(float(v) for v in self.cell))
            c.dims = wp.vec3i(*self.dims)
            c.g_table = wp.array(self.g_table(), dtype=wp.float64, device=device)
            c.present = 1
            c.leaf_layers = wp.array(leaf_layers(self.lad, LEAF_TILE), dtype=wp.int32, device=device)
            c.tile = LEAF_TILE
            self._device[key] = c
        return self._device[key]


def no_canopy(device: str):
    """A :class:`kernels.canopy.Canopy` with ``present = 0`` (a 1×1×1 zero grid, G = ½): every canopy function
    returns at once for it (no depth, no voxel), so kernels always take a valid struct. One per device."""
    import warp as wp

    from flightsim.core.warp_runtime import init_warp
    from kernels import canopy as kc

    init_warp()
    key = str(wp.get_device(device))
    if key not in _NO_CANOPY:
        c = kc.Canopy()
        c.lad = wp.zeros((1, 1, 1), dtype=wp.float32, device=device)
        c.lad_flat = c.lad.flatten()
        c.lower = wp.vec3d(0.0, 0.0, 0.0)
        c.cell = wp.vec3d(1.0, 1.0, 1.0)
        c.dims = wp.vec3i(1, 1, 1)
        c.g_table = wp.array(np.array([0.5, 0.5]), dtype=wp.float64, device=device)
        c.present = 0
        c.leaf_layers = wp.zeros((1, 1, 2), dtype=wp.int32, device=device)
        c.tile = 1
        _NO_CANOPY[key] = c
    return _NO_CANOPY[key]


_NO_CANOPY: dict = {}

LEAF_TILE = 4
"""Voxel columns per side of the tiles whose leafy layers bound a beam's walk (kernels.canopy.leaf_span)."""


def leaf_layers(lad: np.ndarray, tile: int) -> np.ndarray:
    """(⌈nx / tile⌉, ⌈ny / tile⌉, 2) int32: per tile of tile × tile voxel columns of ``lad`` (nx, ny, nz), the lowest
    voxel layer holding leaves and one past the highest (nz and 0 where none does)."""
    leafy = np.asarray(lad) > 0.0
    nx, ny, nz = leafy.shape
    some = leafy.any(axis=2)
    lowest = np.where(some, leafy.argmax(axis=2), nz)
    highest = np.where(some, nz - leafy[:, :, ::-1].argmax(axis=2), 0)
    tx, ty = -(-nx // tile), -(-ny // tile)

    def tiles(columns: np.ndarray, fill: int) -> np.ndarray:
        padded = np.pad(columns, ((0, tx * tile - nx), (0, ty * tile - ny)), constant_values=fill)
        return padded.reshape(tx, tile, ty, tile)

    return np.stack([tiles(lowest, nz).min(axis=(1, 3)), tiles(highest, 0).max(axis=(1, 3))], axis=-1).astype(np.int32)


def _leaf_area_density(value) -> np.ndarray:
    """``value`` as a C-contiguous (nx, ny, nz) float32 grid of finite values ≥ 0, else InputError naming
    ``scene.canopy`` and the first bad voxel."""
    allowed = "a 3-D grid (nx, ny, nz) of finite leaf area densities ≥ 0 m²/m³"
    try:
        given = np.asarray(value)
        if given.dtype.kind not in "biuf":
            raise TypeError
    except (TypeError, ValueError):
        raise InputError("scene.canopy", f"leaf area density {type(value).__name__}", allowed) from None
    if given.ndim != 3:
        raise InputError("scene.canopy", f"a leaf area grid of shape {given.shape}", allowed)
    if given.size == 0:
        raise InputError("scene.canopy", f"an empty leaf area grid of shape {given.shape}",
                         "a grid of at least one voxel")
    if given.size > MAX_VOXELS:
        raise InputError("scene.canopy", f"a leaf area grid of {given.size:,} voxels {given.shape}",
                         f"at most {MAX_VOXELS:,} voxels")
    with np.errstate(over="ignore", invalid="ignore"):
        lad = np.ascontiguousarray(given, dtype=np.float32)
    ok = np.isfinite(lad) & (lad >= 0.0)  # a float64 beyond float32's range becomes inf: refused too
    if not ok.all():
        ix, iy, iz = np.unravel_index(int(np.argmin(ok.reshape(-1))), lad.shape)
        raise InputError("scene.canopy", f"leaf area density {float(given[ix, iy, iz])!r} at voxel "
                                         f"({ix}, {iy}, {iz})", allowed)
    return lad


def _vector3(value, field_name: str, allowed: str, positive: bool) -> np.ndarray:
    try:
        vec = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(field_name, value, allowed) from None
    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or (positive and not np.all(vec > 0.0)):
        raise InputError(field_name, value if vec.shape != (3,) else tuple(float(v) for v in vec), allowed)
    return vec.copy()


def _fraction(value, field_name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(field_name, value, "a number in [0, 1]") from None
    if not (math.isfinite(x) and 0.0 <= x <= 1.0):
        raise InputError(field_name, value, "a number in [0, 1]")
    return x
