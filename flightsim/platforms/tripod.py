"""The tripod platform (``flight.platform = "tripod"``): a terrestrial laser scanner standing still at one scan
position, ``flight.altitude_m`` above the ground beneath it, levelled (or tilted on a tilt mount), turned to a
heading; the body frame is the hover's (x forward, y right, z down), so a level tripod's head axis is vertical."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.platforms.flight import check_clearance
from flightsim.scenes.scene import Scene
from trajectories import Trajectory

FOOT_M = 0.01  # half side of the patch of terrain under the tripod whose top is its ground [m]


@dataclass
class TripodSettings(Settings):
    """A static scan position: where the tripod stands, how it is turned and levelled."""

    position_m: tuple[float, float] = setting((0.0, 0.0), "east, north of the tripod from the centre of the "
                                              "scene's bounds", "m", length=2, items=(-1.0e5, 1.0e5))
    heading_deg: float = setting(0.0, "heading of the head's zero azimuth, clockwise from grid north", "deg",
                                 range=(-360.0, 360.0))
    roll_deg: float = setting(0.0, "levelling error or tilt-mount angle about the heading axis (positive: "
                              "right side down)", "deg", range=(-90.0, 90.0))
    pitch_deg: float = setting(0.0, "levelling error or tilt-mount angle about the right axis (positive: "
                               "front up)", "deg", range=(-90.0, 90.0))


def ground_under(scene: Scene, east: float, north: float) -> float:
    """Local height of the ground under a point [m]: the terrain's top there, or the scene's ground height off
    the scene's bounds."""
    lo, hi = scene.bounds()
    if lo[0] <= east <= hi[0] and lo[1] <= north <= hi[1]:
        rect = np.array([[east - FOOT_M, north - FOOT_M, east + FOOT_M, north + FOOT_M]])
        return float(scene.terrain_tops(rect)[0])
    return scene.ground_z


@register("platform", "tripod")
class TripodPlatform:
    """A tripod of the ``[flight]`` section (common and tripod settings): one scan position held for
    ``flight.duration_s``."""

    settings = TripodSettings

    def __init__(self, flight):
        self.f = flight

    def spans(self) -> tuple[float, float, float]:
        return 0.0, 0.0, self.f.heading_deg

    def tilt_deg(self) -> float:
        return abs(self.f.roll_deg) + abs(self.f.pitch_deg)

    def origin_local(self, scene: Scene) -> np.ndarray:
        """The scanner's origin in the scene's local frame [m]."""
        lo, hi = scene.bounds()
        east = (lo[0] + hi[0]) / 2.0 + self.f.position_m[0]
        north = (lo[1] + hi[1]) / 2.0 + self.f.position_m[1]
        return np.array([east, north, ground_under(scene, east, north) + self.f.altitude_m])

    def trajectories(self, scene: Scene) -> list[Trajectory]:
        """The scan position held still from start_gps_time for duration_s."""
        f = self.f
        times = f.start_gps_time + np.array([0.0, f.duration_s])
        position = np.tile(scene.local_to_world(self.origin_local(scene)), (2, 1))
        attitude = np.tile(np.radians([f.roll_deg, f.pitch_deg, f.heading_deg % 360.0]), (2, 1))
        tripod = Trajectory(times, position, attitude, 1)
        check_clearance(tripod, scene, f.altitude_m)
        return [tripod]
