"""Built-in small-body (asteroid) scenes for a mapping lidar.

- :func:`sandbox_scene`: the "small-body sandbox" of a field test, a square rough-terrain patch
  (side ``size_m``, default 12 m) centred on local (0, 0), as a heightfield mesh with the lunar
  landing zone's crater, boulder and roughness shapes (:mod:`flightsim.scenes.lunar`) at sandbox
  scale. Populations (per square metre, cumulative, D in metres), drawn from ``seed``:

  - craters N(>D) = SANDBOX_CRATER_K·D⁻² for 0.3 m ≤ D ≤ 3 m, simple bowls (lunar ``_crater``);
  - boulders N(>D) = SANDBOX_BOULDER_K·(D / 0.1 m)^-2.5 for 0.1 m ≤ D ≤ 0.8 m, half-buried
    spheres (lunar ``_boulder``);
  - roughness: fractional Brownian surface (Hurst 0.8) of SANDBOX_ROUGHNESS_RMS_M RMS.

  The surface reflectance of the sandbox is not part of the mesh: :data:`SANDBOX_REFLECTANCE`.

- :func:`ellipsoid_scene`: a closed triaxial ellipsoid body (semi-axes a, b, c along local x, y,
  z) centred on local (0, 0, 0), an icosahedron subdivided ``subdivisions`` times and mapped onto
  the ellipsoid, with a smooth random radial perturbation of RMS ``roughness_m``. Altitudes are
  measured from the north pole (ground_z = c).

Both are one face label ("surface", class 2 ground).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings
from flightsim.scenes import lunar
from flightsim.scenes.lunar import (MAX_NODES, _grid_triangles, _power_law, _roughness, stamp_terrain,
                                    surface_scene)
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, Scene
from flightsim.scenes.settings import ScenePart

SANDBOX_REFLECTANCE = 0.2
"""Lambertian reflectance of the sandbox surface (the paper's sandbox reflectance, 0.2); the
mesh carries none, so a caller that models reflectance reads it from here."""

SANDBOX_CRATER_K = 0.01  # N(>D) = K·D⁻² craters per m² (D in m): ~16 craters on 12 m × 12 m
SANDBOX_CRATER_MIN_M, SANDBOX_CRATER_MAX_M = 0.3, 3.0
SANDBOX_BOULDER_K = 0.3  # boulders per m² wider than SANDBOX_BOULDER_MIN_M: ~43 on 12 m × 12 m
SANDBOX_BOULDER_MIN_M, SANDBOX_BOULDER_MAX_M, SANDBOX_BOULDER_SLOPE = 0.1, 0.8, 2.5
SANDBOX_ROUGHNESS_RMS_M = 0.01  # RMS of the fBm roughness [m]

ELLIPSOID_AXES_M = (250.0, 120.2, 120.2)  # the paper's small body: semi-axes a, b, c [m]
NOISE_TERMS = 48  # random-phase cosines in the ellipsoid's radial perturbation
NOISE_MAX_ORDER = 12.0  # highest angular frequency of a cosine [cycles per radian of direction]
MAX_SUBDIVISIONS = 8  # 655 362 vertices, 1.3 M triangles


def sandbox_scene(origin=DEFAULT_ORIGIN, crs=DEFAULT_CRS, seed: int = 0, size_m: float = 12.0,
                  cell_m: float = 0.02) -> Scene:
    """The sandbox: a square of side ``size_m`` [m] centred on local (0, 0), grid ``cell_m`` [m].

    The grid holds an odd number of nodes per side (so a node sits at the centre), at most
    MAX_NODES; the cell shrinks slightly to fit the side exactly, or grows when the side would
    need more nodes. ground_z is the height [m] of the centre node.
    """
    size = _number("scene.size_m", size_m, 0.0, 1000.0, "a finite side in (0, 1000] m", low_open=True)
    cell = _number("scene.cell_m", cell_m, 0.001, 1.0, "a grid cell in [0.001, 1] m")
    half = size / 2.0
    nodes = min(int(math.ceil(size / cell)) + 1, MAX_NODES)
    nodes += 1 - nodes % 2  # odd, so that node nodes // 2 is at 0 (MAX_NODES is odd)
    axis = np.linspace(-half, half, nodes)
    x, y = np.meshgrid(axis, axis, indexing="xy")
    step = size / (nodes - 1)
    rng = np.random.default_rng([int(seed), 0x5A4D])
    z = _roughness(rng, nodes, step) * (SANDBOX_ROUGHNESS_RMS_M / lunar.ROUGHNESS_RMS_M)
    stamp_terrain(x, y, z, _sandbox_craters(rng, half), _sandbox_boulders(rng, half), half)
    ground_z = float(z[nodes // 2, nodes // 2])
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return surface_scene("sandbox", crs, origin, vertices, _grid_triangles(nodes), ground_z)


def _sandbox_craters(rng: np.random.Generator, half: float) -> list[tuple[float, float, float]]:
    """(x, y, D) [m] of every sandbox crater, larger first; N(>D) = K·D⁻² on [0.3, 3] m."""
    low, high = SANDBOX_CRATER_MIN_M, SANDBOX_CRATER_MAX_M
    count = rng.poisson(SANDBOX_CRATER_K * (2.0 * half) ** 2 * (low ** -2 - high ** -2))
    diameters = np.sort(_power_law(rng, count, low, high, 2.0))[::-1]
    centres = rng.uniform(-half, half, (count, 2))
    return [(float(cx), float(cy), float(d)) for (cx, cy), d in zip(centres, diameters)]


def _sandbox_boulders(rng: np.random.Generator, half: float) -> list[tuple[float, float, float]]:
    """(x, y, D) [m] of every sandbox boulder; N(>D) = K·(D / 0.1 m)^-2.5 on [0.1, 0.8] m."""
    low, high, slope = SANDBOX_BOULDER_MIN_M, SANDBOX_BOULDER_MAX_M, SANDBOX_BOULDER_SLOPE
    count = rng.poisson(SANDBOX_BOULDER_K * (2.0 * half) ** 2 * (1.0 - (high / low) ** -slope))
    diameters = _power_law(rng, count, low, high, slope)
    centres = rng.uniform(-half, half, (count, 2))
    return [(float(cx), float(cy), float(d)) for (cx, cy), d in zip(centres, diameters)]


def ellipsoid_scene(origin=DEFAULT_ORIGIN, crs=DEFAULT_CRS, seed: int = 0, a_m: float = ELLIPSOID_AXES_M[0],
                    b_m: float = ELLIPSOID_AXES_M[1], c_m: float = ELLIPSOID_AXES_M[2], subdivisions: int = 6,
                    roughness_m: float = 0.5) -> Scene:
    """A closed ellipsoid body, semi-axes ``a_m``, ``b_m``, ``c_m`` [m] along local x, y, z.

    The vertices of an icosahedron subdivided ``subdivisions`` times (10·4ⁿ + 2 vertices,
    20·4ⁿ triangles) are mapped from the unit sphere onto the ellipsoid by scaling the axes, then
    moved along their direction from the centre by a smooth random field of RMS ``roughness_m``
    [m] (so the body stays star-shaped: no overhangs). Triangles are counter-clockwise seen from
    outside; ground_z = ``c_m`` [m] (the unperturbed north pole).
    """
    axes = np.array([_number(f"scene.{name}", value, 0.0, 1.0e6, "a finite semi-axis in (0, 1e6] m", low_open=True)
                     for name, value in (("a_m", a_m), ("b_m", b_m), ("c_m", c_m))])
    level = _subdivisions(subdivisions)
    limit = 0.05 * axes.min()
    rough = _number("scene.roughness_m", roughness_m, 0.0, limit,
                    f"a finite RMS in [0, {limit:g}] m (5 % of the shortest axis)")
    unit, triangles = icosphere(level)
    points = unit * axes
    if rough > 0.0:
        rng = np.random.default_rng([int(seed), 0xE111])
        radius = np.linalg.norm(points, axis=1, keepdims=True)
        points = points * (1.0 + _radial_noise(rng, points / radius, rough)[:, None] / radius)
    return surface_scene("ellipsoid", crs, origin, points, triangles, float(axes[2]))


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere vertices (V, 3) and outward counter-clockwise triangles (T, 3) int32 of an
    icosahedron whose faces are each split into 4 ``subdivisions`` times (midpoints pushed out)."""
    vertices, triangles = _icosahedron()
    for _ in range(subdivisions):
        vertices, triangles = _subdivide(vertices, triangles)
    return vertices, triangles.astype(np.int32)


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """The 12 unit vertices and 20 triangles of a regular icosahedron, wound outwards."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = v[f]
    inward = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p.sum(axis=1)) < 0.0
    f[inward] = f[inward][:, ::-1]  # (convex about the origin: outward means positive det)
    return v, f


def _subdivide(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into 4 through its edge midpoints (shared between neighbours), keeping
    the winding; new vertices are projected onto the unit sphere."""
    a, b, c = triangles.T
    edges = np.sort(np.concatenate([np.column_stack([a, b]), np.column_stack([b, c]), np.column_stack([c, a])]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = vertices[unique[:, 0]] + vertices[unique[:, 1]]
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    ab, bc, ca = (len(vertices) + inverse.reshape(3, -1))
    new = np.concatenate([np.column_stack(t) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return np.concatenate([vertices, mid]), new


def _radial_noise(rng: np.random.Generator, direction: np.ndarray, rms: float) -> np.ndarray:
    """A smooth zero-mean field [m] on unit ``direction`` (V, 3): NOISE_TERMS cosines
    cos(ω k·u + φ) of random axis k, order ω in [1, NOISE_MAX_ORDER] (amplitude 1/ω) and phase φ,
    scaled to RMS ``rms`` [m] over the vertices."""
    k = rng.standard_normal((NOISE_TERMS, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    omega = rng.uniform(1.0, NOISE_MAX_ORDER, NOISE_TERMS)
    phase = rng.uniform(0.0, 2.0 * math.pi, NOISE_TERMS)
    field = np.cos((direction @ k.T) * omega + phase) @ (1.0 / omega)
    field -= field.mean()
    return field * (rms / math.sqrt(np.mean(field * field)))


def _number(field: str, value, low: float, high: float, allowed: str, low_open: bool = False) -> float:
    """``value`` as a float if it is finite and in [low, high] ((low, high] if ``low_open``)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(field, value, allowed) from None
    if isinstance(value, bool) or not (math.isfinite(number) and number <= high
                                       and (number > low if low_open else number >= low)):
        raise InputError(field, value, allowed)
    return number


def _subdivisions(value) -> int:
    """``value`` as an int in [0, MAX_SUBDIVISIONS]."""
    allowed = f"an integer in [0, {MAX_SUBDIVISIONS}]"
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value <= MAX_SUBDIVISIONS:
        raise InputError("scene.subdivisions", value, allowed)
    return int(value)


@dataclass
class SmallBodySettings(Settings):
    """A fixed-size small-body scene (no settings of its own: its relief comes from the run's seed)."""


@register("scene", "sandbox")
class SandboxScene(ScenePart):
    """The small-body sandbox of ``[scene]`` (12 m square)."""

    settings = SmallBodySettings

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return sandbox_scene(self.s.origin, self.s.crs, seed=seed)


@register("scene", "ellipsoid")
class EllipsoidScene(SandboxScene):
    """The paper's ellipsoidal small body of ``[scene]``."""

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return ellipsoid_scene(self.s.origin, self.s.crs, seed=seed)
