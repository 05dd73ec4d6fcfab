"""Leaf area density in voxels from ALS points: the MacArthur–Horn (1969) inversion, column by column.

For near-vertical pulses through a turbid canopy, the probability that a pulse reaches height z without
interacting (the gap probability) is P(z) = exp(−G ∫_z^top u dz' / μ) (Beer–Lambert), so over a layer
[z, z + dz] of leaf area density u

    u = −ln(P(z) / P(z + dz)) / (G dz)                  (μ = 1, vertical view)

MacArthur & Horn (1969); the discrete form used by Hosoi & Omasa (2006) and by ``lidR::LAD`` (Bouvier et al.
2015: −ln(N(<z) / N(<z + dz)) / (k dz), k = 0.5). P(z) is estimated per voxel column by the fraction of
pulses whose first return lies below z, so the ratio of a layer is

    P(z_k) / P(z_{k+1}) = B_k / B_{k+1},   B_k = number of points of the column below z_k,

the fraction of the pulses that reached the layer's top and went through it (each pulse counted once). Pass
**first returns** (or single returns: one point per pulse); with ``return_number`` given, only the points
of return number 1 are used. Counting every return, as ``lidR::LAD`` does on a whole cloud, counts a pulse
at several heights and biases P(z) up (u down) under dense canopy.

Rules:

* a ground point (``is_ground``), or one less than ``min_height_m`` above the ground, reached the ground:
  it lies below every layer (low returns are understorey or noise, ``z0`` in ``lidR::LAD``); a point
  below the grid's bottom likewise; a point above the grid's top is above every layer;
* a layer no pulse reached (B_{k+1} = 0: occluded, or a column without points) has u = ``unknown_lad``
  (0 by default: no evidence of leaves);
* a layer that stopped every pulse that reached it (B_k = 0 < B_{k+1}: P = 0, u = ∞ by the formula) takes
  half a pulse through it, B_k = ½: u = ln(2 B_{k+1}) / (G dz), the most the layer's B_{k+1} pulses can
  resolve; then at most ``max_lad`` where given;
* a layer with points but no change (B_k = B_{k+1}) has u = 0.

Sampling error: given the n = B_{k+1} pulses reaching a layer of true density u, B_k is binomial (n, p),
p = exp(−G u dz), and to first order (delta method)

    σ(û) = sqrt((1 − p) / (n p)) / (G dz),

with a bias of order σ²·G·dz / 2 (from E[ln]); :func:`sampling_sigma` gives it.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes import leaf_angles as _leaf_angles
from flightsim.scenes.canopy import MAX_VOXELS, VoxelCanopy


def lad_from_points(
    xyz_local,
    is_ground,
    ground_height: Callable | float | np.ndarray,
    lower,
    cell,
    dims=None,
    *,
    g: float | None = None,
    min_height_m: float = 0.5,
    return_number=None,
    unknown_lad: float = 0.0,
    max_lad: float | None = None,
    leaf_angles: str = "spherical",
    leaf_reflectance: float = 0.4,
    leaf_transmittance: float = 0.4,
) -> VoxelCanopy:
    """The :class:`VoxelCanopy` of leaf area density estimated from first-return points (module docstring).

    Args:
        xyz_local: (N, 3) float64 local coordinates [m] of the points (one per pulse: first returns).
        is_ground: (N,) bool, True for ground returns.
        ground_height: the local ground height [m]: a callable ``f(x, y) -> z`` on arrays, a number, an
            (nx, ny) grid of each voxel column's ground height, or an (N,) array of each point's.
        lower: (3,) local corner [m] of the voxel grid.
        cell: (3,) voxel edge lengths [m].
        dims: (nx, ny, nz) voxels per axis; None: from ``lower`` to the voxel of the farthest point on each axis.
        g: the leaf projection G of a vertical view; None: G(μ = 1) of ``leaf_angles`` (½ for spherical).
        min_height_m: points less than this above the ground count as ground (≥ 0) [m].
        return_number: (N,) return numbers; if given, only points of return number 1 are used.
        unknown_lad: u of a layer no pulse reached [m²/m³].
        max_lad: the most u of any voxel [m²/m³]; None: only the half-pulse rule bounds it.
        leaf_angles, leaf_reflectance, leaf_transmittance: passed on to the :class:`VoxelCanopy`.
    """
    xyz, ground, used = _points(xyz_local, is_ground, return_number)
    if np.ndim(ground_height) == 1:  # each point's: those of the points used
        ground_height = _per_point(ground_height, len(used))[used]
    lower, cell, (nx, ny, nz) = _grid(lower, cell, dims, xyz)
    if not (math.isfinite(min_height_m) and min_height_m >= 0.0):
        raise InputError("min_height_m", min_height_m, "a finite height ≥ 0 m")
    if g is None:
        g = float(_leaf_angles.g_function(leaf_angles, np.array([1.0]))[0])
    if not (math.isfinite(g) and g > 0.0):
        raise InputError("g", g, "a leaf projection G > 0")

    # The column of each point; points outside the grid's x–y extent are not used.
    col = np.floor((xyz[:, :2] - lower[:2]) / cell[:2])
    inside = (col[:, 0] >= 0) & (col[:, 0] < nx) & (col[:, 1] >= 0) & (col[:, 1] < ny)
    xyz, ground, col = xyz[inside], ground[inside], col[inside].astype(np.int64)
    floor_z = _ground_heights(ground_height[inside] if np.ndim(ground_height) == 1 else ground_height, xyz, col,
                              (nx, ny))
    reached_ground = ground | (xyz[:, 2] < floor_z + min_height_m)
    # Layer of each point: −1 below every layer (ground, or under the grid), nz above every layer.
    layer = np.clip(np.floor((xyz[:, 2] - lower[2]) / cell[2]), -1, nz).astype(np.int64)
    layer[reached_ground] = -1
    counts = np.zeros((nx * ny, nz + 2), dtype=np.int64)  # [column, layer + 1]
    np.add.at(counts, (col[:, 0] * ny + col[:, 1], layer + 1), 1)
    lad = _invert(counts, g * cell[2], unknown_lad, max_lad)
    return VoxelCanopy(lad.reshape(nx, ny, nz).astype(np.float32), lower, cell, leaf_angles=leaf_angles,
                       leaf_reflectance=leaf_reflectance, leaf_transmittance=leaf_transmittance)


def _invert(counts: np.ndarray, g_dz: float, unknown_lad: float, max_lad: float | None) -> np.ndarray:
    """(columns, nz) u of each layer from the (columns, nz + 2) point counts [below the grid, layers, above]."""
    nz = counts.shape[1] - 2
    below = np.cumsum(counts[:, :nz + 1], axis=1).astype(np.float64)  # B_k = points below z_k, k = 0 … nz
    entered, through = below[:, 1:], below[:, :-1]  # B_{k+1}, B_k of layer k
    with np.errstate(divide="ignore", invalid="ignore"):
        lad = np.log(entered / np.maximum(through, 0.5)) / g_dz
    lad[entered == 0] = unknown_lad
    if max_lad is not None:
        lad = np.minimum(lad, max_lad)
    return lad


def _points(xyz_local, is_ground, return_number) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The checked (N, 3) coordinates and (N,) ground flags, first returns only where return numbers are given,
    and which of the given points they are (bool mask)."""
    xyz = np.asarray(xyz_local, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError("xyz_local", f"an array of shape {xyz.shape}", "(N, 3) local point coordinates [m]")
    if not np.all(np.isfinite(xyz)):
        raise InputError("xyz_local", "non-finite coordinates", "finite local coordinates [m]")
    ground = np.asarray(is_ground, dtype=bool)
    if ground.shape != (len(xyz),):
        raise InputError("is_ground", f"an array of shape {ground.shape}", f"({len(xyz)},) flags, one per point")
    used = np.ones(len(xyz), dtype=bool)
    if return_number is not None:
        numbers = np.asarray(return_number)
        if numbers.shape != (len(xyz),):
            raise InputError("return_number", f"an array of shape {numbers.shape}", f"({len(xyz)},) return numbers")
        used = numbers == 1
        xyz, ground = xyz[used], ground[used]
    return xyz, ground, used


def _per_point(heights, n: int) -> np.ndarray:
    """Checked (n,) float64 ground heights of the points [m]."""
    heights = np.asarray(heights, dtype=np.float64)
    if heights.shape != (n,):
        raise InputError("ground_height", f"an array of shape {heights.shape}", f"({n},) heights, one per point")
    return heights


def _grid(lower, cell, dims, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """The checked lower corner, cell and voxel counts (by default up to the voxel of the farthest point)."""
    lower = np.asarray(lower, dtype=np.float64)
    cell = np.asarray(cell, dtype=np.float64)
    if lower.shape != (3,) or not np.all(np.isfinite(lower)):
        raise InputError("scene.canopy.lower", lower, "three finite local coordinates [m]")
    if cell.shape != (3,) or not np.all(np.isfinite(cell) & (cell > 0.0)):
        raise InputError("scene.canopy.cell", cell, "three finite voxel edge lengths > 0 m")
    if dims is None:
        far = xyz.max(axis=0) if len(xyz) else lower + cell
        dims = np.maximum(np.floor((far - lower) / cell).astype(np.int64) + 1, 1)
    dims = tuple(int(n) for n in dims)
    if len(dims) != 3 or min(dims) < 1 or math.prod(dims) > MAX_VOXELS:
        raise InputError("dims", dims, f"three voxel counts ≥ 1, at most {MAX_VOXELS:,} voxels in all")
    return lower, cell, dims


def sampling_sigma(lad, pulses, g: float, dz: float) -> np.ndarray:
    """First-order standard error [m²/m³] of the MacArthur–Horn estimate of a layer of true density ``lad``
    reached by ``pulses`` pulses (module docstring)."""
    p = np.exp(-g * np.asarray(lad, dtype=np.float64) * dz)
    return np.sqrt((1.0 - p) / (np.asarray(pulses, dtype=np.float64) * p)) / (g * dz)


def _ground_heights(ground_height, xyz: np.ndarray, col: np.ndarray, columns: tuple[int, int]) -> np.ndarray:
    """The ground height [m] under each point, from a callable, a number, an (nx, ny) grid of columns or each
    point's own."""
    if callable(ground_height):
        z = np.asarray(ground_height(xyz[:, 0], xyz[:, 1]), dtype=np.float64)
        z = np.broadcast_to(z, (len(xyz),))
    else:
        grid = np.asarray(ground_height, dtype=np.float64)
        if grid.ndim == 0:
            z = np.full(len(xyz), float(grid))
        elif grid.shape == (len(xyz),):  # each point's (of the points used)
            z = grid
        elif grid.shape == columns:
            z = grid[col[:, 0], col[:, 1]]
        else:
            raise InputError("ground_height", f"an array of shape {grid.shape}",
                             f"a callable f(x, y), a number, an {columns} grid of column ground heights or one "
                             "per point [m]")
    if not np.all(np.isfinite(z)):
        raise InputError("ground_height", "non-finite heights", "finite ground heights [m] under every point")
    return z

