"""The plane scene (``scene.name = "plane"``): one square plane, horizontal or sloped, sized to the flight (the
seed paper's altitude study)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.scenes.scene import (CLASS_GROUND, DEFAULT_CRS, DEFAULT_ORIGIN, Scene, check_half_extent, parse_crs,
                                    plane_info)
from flightsim.scenes.settings import ScenePart


@dataclass
class PlaneSettings(Settings):
    """One square plane."""

    slope: float = setting(0.0, "rise/run of the plane, descending towards grid north", "rise/run", range=(-2.0, 2.0))


@register("scene", "plane")
class PlaneScene(ScenePart):
    """A plane of ``[scene]`` (common and plane settings), sized to the flight."""

    settings = PlaneSettings
    sized = True

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return plane_scene(half_extent_m, self.s.origin, self.s.crs, slope=self.s.slope)


def plane_scene(
    half_extent_m: float,
    origin=DEFAULT_ORIGIN,
    crs=DEFAULT_CRS,
    slope: float = 0.0,
    slope_azimuth_deg: float = 0.0,
) -> Scene:
    """One square plane of half side ``half_extent_m`` [m] centred on local (0, 0, 0).

    ``slope`` is rise/run; the plane descends towards ``slope_azimuth_deg`` (clockwise from grid
    north), or rises towards it when negative: z = −slope·(x·sin a + y·cos a). Plane id 0,
    class 2 (ground); ground_z = 0 (the height at the centre).
    """
    check_half_extent(half_extent_m, 0.0)
    if not (math.isfinite(slope) and abs(slope) <= 10.0):
        raise InputError("scene.slope", slope, "a rise/run in [-10, 10]")
    if not math.isfinite(slope_azimuth_deg):
        raise InputError("scene.slope_azimuth_deg", slope_azimuth_deg, "a finite azimuth [deg]")
    h = float(half_extent_m)
    az = math.radians(slope_azimuth_deg)
    down = np.array([math.sin(az), math.cos(az)])
    xy = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    z = -slope * (xy @ down)
    vertices = np.column_stack([xy, z])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    normal = np.array([slope * down[0], slope * down[1], 1.0])
    plane = plane_info(0, "ground", CLASS_GROUND, normal, (0.0, 0.0, 0.0))
    return Scene(
        name="plane",
        crs=parse_crs(crs),
        origin=origin,
        vertices=vertices,
        triangles=triangles,
        plane_id=np.zeros(2, dtype=np.int32),
        classification=np.full(2, CLASS_GROUND, dtype=np.uint8),
        planes=[plane],
        ground_z=0.0,
    )
