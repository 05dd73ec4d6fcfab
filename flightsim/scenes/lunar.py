"""A built-in lunar landing zone: a heightfield mesh with craters, boulders, a regional slope and
small-scale roughness, at the scale a lander's hazard-avoidance imager sees from 100 m.

Populations (per square metre, cumulative, D in metres), drawn from ``seed``:
- craters N(>D) = 0.03·D⁻² for 1 m ≤ D ≤ half the scene's half side (a mare-like equilibrium
  density), plus one crater of D = 0.4 × half side placed off-centre so every zone has a large one;
  a simple bowl: floor 0.2·D below the rim crest, rim 0.04·D above the surroundings, ejecta
  falling off as (R/r)³ outside, to 0 at 4 R;
- boulders N(>D) = 0.01·(D / 0.3 m)^-2.5 for 0.3 m ≤ D ≤ 2 m, half-buried spheres (height D/2);
- roughness: fractional Brownian surface (Hurst 0.8) of 3 cm RMS;
- slope: z descends towards grid north at ``slope`` (rise/run), as the plane scene's.
The mesh is a regular grid of ``cell_m`` (coarsened so that it holds at most MAX_NODES² vertices),
two triangles per cell, one face label ("surface", class 2 ground); ground_z is the height under
the centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.scenes.scene import (CLASS_GROUND, DEFAULT_CRS, DEFAULT_ORIGIN, Scene, check_half_extent,
                                    parse_crs, plane_info)
from flightsim.scenes.settings import ScenePart

MAX_NODES = 1025  # grid nodes per side at most (about 2.1 M triangles)
CRATER_K = 0.03  # N(>D) = K·D⁻² craters per m² (D in m)
CRATER_MIN_M = 1.0
BOULDER_K = 0.01  # boulders per m² wider than BOULDER_MIN_M
BOULDER_MIN_M, BOULDER_MAX_M, BOULDER_SLOPE = 0.3, 2.0, 2.5
ROUGHNESS_RMS_M, HURST = 0.03, 0.8
EJECTA_REACH = 4.0  # the ejecta blanket ends (continuously) at this many crater radii


def lunar_scene(half_extent_m: float = 60.0, origin=DEFAULT_ORIGIN, crs=DEFAULT_CRS, seed: int = 0,
                cell_m: float = 0.25, slope: float = 0.05) -> Scene:
    """The landing zone: a square of half side ``half_extent_m`` [m] centred on local (0, 0)."""
    half = check_half_extent(half_extent_m, 0.0)
    if not (math.isfinite(cell_m) and 0.01 <= cell_m <= 10.0):
        raise InputError("scene.cell_m", cell_m, "a grid cell in [0.01, 10] m")
    if not (math.isfinite(slope) and abs(slope) <= 2.0):
        raise InputError("scene.slope", slope, "a rise/run in [-2, 2]")
    nodes = min(int(math.ceil(2.0 * half / cell_m)) + 1, MAX_NODES)
    axis = np.linspace(-half, half, nodes)
    x, y = np.meshgrid(axis, axis, indexing="xy")
    rng = np.random.default_rng([int(seed), 0x10A4])
    z = -slope * y + _roughness(rng, nodes, 2.0 * half / (nodes - 1))
    stamp_terrain(x, y, z, _craters(rng, half), _boulders(rng, half), half)
    centre = nodes // 2
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return surface_scene("lunar", crs, origin, vertices, _grid_triangles(nodes), float(z[centre, centre]),
                         normal=(0.0, slope, 1.0))


def stamp_terrain(x: np.ndarray, y: np.ndarray, z: np.ndarray, craters, boulders, half: float) -> None:
    """Add each crater (x, y, D) [m] to the square grid of heights ``z`` (nodes × nodes over ±``half``),
    then rest each boulder (x, y, D) on it; each touches only the nodes within its reach."""
    nodes = len(z)
    step = 2.0 * half / (nodes - 1)
    for cx, cy, diameter in craters:
        window = _window(cx, cy, EJECTA_REACH * diameter / 2.0, half, step, nodes)
        z[window] += _crater(np.hypot(x[window] - cx, y[window] - cy), diameter)
    for cx, cy, diameter in boulders:
        window = _window(cx, cy, diameter / 2.0, half, step, nodes)
        z[window] = np.maximum(z[window], _boulder(x[window] - cx, y[window] - cy, diameter, z[window]))


def surface_scene(name: str, crs, origin, vertices: np.ndarray, triangles: np.ndarray, ground_z: float,
                  normal=(0.0, 0.0, 1.0)) -> Scene:
    """A Scene of one "surface" face label (class 2; its plane through (0, 0, ground_z) with ``normal``), not
    planar: a LAS run over it scores patches of the ground, not the whole surface as one plane."""
    plane = plane_info(0, "surface", CLASS_GROUND, normal, (0.0, 0.0, ground_z))
    return Scene(name=name, crs=parse_crs(crs), origin=origin, vertices=vertices, triangles=triangles,
                 plane_id=np.zeros(len(triangles), dtype=np.int32),
                 classification=np.full(len(triangles), CLASS_GROUND, dtype=np.uint8),
                 planes=[plane], ground_z=ground_z, planar=False)


def _power_law(rng: np.random.Generator, count: int, low: float, high: float, exponent: float) -> np.ndarray:
    """``count`` diameters with N(>D) ∝ D^-exponent on [low, high] (inverse-CDF sampling)."""
    u = rng.random(count)
    a, b = low ** -exponent, high ** -exponent
    return (a - u * (a - b)) ** (-1.0 / exponent)


def _craters(rng: np.random.Generator, half: float) -> list[tuple[float, float, float]]:
    """(x, y, D) of every crater [m]: the large one, then the population, larger first."""
    area = (2.0 * half) ** 2
    largest = max(CRATER_MIN_M, 0.5 * half)
    count = rng.poisson(CRATER_K * area * (CRATER_MIN_M ** -2 - largest ** -2))
    diameters = np.sort(_power_law(rng, count, CRATER_MIN_M, largest, 2.0))[::-1]
    centres = rng.uniform(-half, half, (count, 2))
    big = 0.4 * half
    return [(0.35 * half, -0.25 * half, big)] + [(float(cx), float(cy), float(d))
                                                for (cx, cy), d in zip(centres, diameters)]


def _crater(r: np.ndarray, diameter: float) -> np.ndarray:
    """Height change of a simple crater of ``diameter`` [m] at distances ``r`` from its centre [m]."""
    radius = diameter / 2.0
    rim, floor = 0.04 * diameter, 0.2 * diameter  # rim above the surroundings, floor below the rim
    inside = rim - floor * (1.0 - (r / radius) ** 2)
    fade = EJECTA_REACH ** -3
    outside = rim * np.maximum((radius / np.maximum(r, radius)) ** 3 - fade, 0.0) / (1.0 - fade)
    return np.where(r <= radius, inside, outside)


def _boulders(rng: np.random.Generator, half: float) -> list[tuple[float, float, float]]:
    count = rng.poisson(BOULDER_K * (2.0 * half) ** 2 * (1.0 - (BOULDER_MAX_M / BOULDER_MIN_M) ** -BOULDER_SLOPE))
    diameters = _power_law(rng, count, BOULDER_MIN_M, BOULDER_MAX_M, BOULDER_SLOPE)
    centres = rng.uniform(-half, half, (count, 2))
    return [(float(cx), float(cy), float(d)) for (cx, cy), d in zip(centres, diameters)]


def _boulder(dx: np.ndarray, dy: np.ndarray, diameter: float, ground: np.ndarray) -> np.ndarray:
    """Surface of a half-buried sphere of ``diameter`` [m] resting at its centre's ground height."""
    radius = diameter / 2.0
    d2 = dx * dx + dy * dy
    cap = np.sqrt(np.maximum(radius * radius - d2, 0.0))
    base = ground[np.unravel_index(np.argmin(d2), d2.shape)]
    return np.where(d2 < radius * radius, base + cap, -np.inf)


def _window(cx: float, cy: float, reach: float, half: float, step: float, nodes: int) -> tuple[slice, slice]:
    """(row, column) slices of the grid nodes within ``reach`` [m] of (cx, cy) in x and y."""
    lo = [max(int(math.floor((c - reach + half) / step)), 0) for c in (cy, cx)]
    hi = [min(int(math.ceil((c + reach + half) / step)) + 1, nodes) for c in (cy, cx)]
    return slice(lo[0], hi[0]), slice(lo[1], hi[1])


def _roughness(rng: np.random.Generator, nodes: int, cell: float) -> np.ndarray:
    """Fractional Brownian surface (power spectrum ∝ k^-(2H+2)) scaled to ROUGHNESS_RMS_M [m]."""
    k = np.fft.fftfreq(nodes, d=cell)
    kk = np.hypot(*np.meshgrid(k, k, indexing="xy"))
    kk[0, 0] = np.inf
    amplitude = kk ** -(HURST + 1.0)
    field = np.fft.ifft2(amplitude * np.fft.fft2(rng.standard_normal((nodes, nodes)))).real
    return field * (ROUGHNESS_RMS_M / field.std())


def _grid_triangles(nodes: int) -> np.ndarray:
    """Two counter-clockwise (seen from +z) triangles per cell of a ``nodes`` × ``nodes`` grid."""
    i, j = np.meshgrid(np.arange(nodes - 1), np.arange(nodes - 1), indexing="xy")
    a = (j * nodes + i).ravel()
    b, c, d = a + 1, a + nodes + 1, a + nodes
    return np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]).astype(np.int32)


@dataclass
class LunarSettings(Settings):
    """The landing zone's tilt (its craters, boulders and roughness come from the run's seed)."""

    slope: float = setting(0.0, "rise/run of the zone, descending towards grid north", "rise/run", range=(-2.0, 2.0))


@register("scene", "lunar")
class LunarScene(ScenePart):
    """The lunar landing zone of ``[scene]``, sized to the flight."""

    settings = LunarSettings
    sized = True

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return lunar_scene(half_extent_m, self.s.origin, self.s.crs, seed=seed, slope=self.s.slope)
