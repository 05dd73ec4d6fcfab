"""The large-footprint waveform patent's ground (seed: large-footprint-echo-waveform-patent.txt, Figs. 3–5):
flat and sloping footprints are the ``plane`` scene (``scene.slope``); :func:`bump_scene` is flat ground
with a raised-cosine hill in the middle,
    z = (h/2)(1 + cos(πρ/a)) for ρ = √(x² + y²) < a, else 0     (h = BUMP_HEIGHT_M, a = BUMP_RADIUS_M),
the shape of the float64 reference model's ``BumpSurface`` (the patent gives no size). The mesh is a
grid of BUMP_CELL_M cells; its facets stand off the hill by at most cell²/8 × the largest curvature
h π²/(2a²): 1.9 mm at the defaults.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings
from flightsim.scenes.lunar import MAX_NODES, _grid_triangles, surface_scene
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, Scene
from flightsim.scenes.settings import ScenePart

BUMP_HEIGHT_M = 5.0
BUMP_RADIUS_M = 20.0
BUMP_CELL_M = 0.5


def bump_height(x: np.ndarray, y: np.ndarray, height_m: float = BUMP_HEIGHT_M, radius_m: float = BUMP_RADIUS_M):
    """The hill's height z(x, y) [m]."""
    rho = np.hypot(x, y)
    return np.where(rho < radius_m, 0.5 * height_m * (1.0 + np.cos(np.pi * rho / radius_m)), 0.0)


def bump_scene(half_extent_m: float, origin=DEFAULT_ORIGIN, crs=DEFAULT_CRS) -> Scene:
    """Flat ground of half side ``half_extent_m`` [m] with the hill at local (0, 0); ground_z = 0 (the
    flat ground's height, not the hilltop's)."""
    if not (math.isfinite(half_extent_m) and 0.0 < half_extent_m <= 0.5 * BUMP_CELL_M * (MAX_NODES - 1)):
        raise InputError("scene half extent", half_extent_m,
                         f"(0, {0.5 * BUMP_CELL_M * (MAX_NODES - 1):g}] m for the bump's {BUMP_CELL_M:g} m grid")
    nodes = 2 * math.ceil(half_extent_m / BUMP_CELL_M) + 1
    axis = BUMP_CELL_M * (np.arange(nodes) - nodes // 2)
    x, y = np.meshgrid(axis, axis, indexing="xy")
    vertices = np.column_stack([x.ravel(), y.ravel(), bump_height(x, y).ravel()])
    return surface_scene("bump", crs, origin, vertices, _grid_triangles(nodes), 0.0)


@dataclass
class BumpSettings(Settings):
    """Flat ground with the waveform patent's hill (no settings of its own)."""


@register("scene", "bump")
class BumpScene(ScenePart):
    """The bump of ``[scene]``, sized to the flight."""

    settings = BumpSettings
    sized = True

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return bump_scene(half_extent_m, self.s.origin, self.s.crs)
