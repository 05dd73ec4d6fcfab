"""The hover platform (``flight.platform = "hover"``): a lander or tripod over the scene centre, descending or
still, over a small body that may spin beneath it (:mod:`flightsim.platforms.rotating_body`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import setting
from flightsim.platforms import rotating_body
from flightsim.platforms.flight import MIN_CLEARANCE_M, AttitudeSettings, check_clearance, scene_centre
from flightsim.scenes.scene import Scene
from trajectories import Trajectory

MIN_ROTATION_PERIOD_S, MAX_ROTATION_PERIOD_S = 60.0, 1.0e7  # a spinning body's period: 1 min to 116 days [s]
ROTATION_PERIOD_UNIT = f"s; 0 = not rotating, else at least {MIN_ROTATION_PERIOD_S:g} s"


@dataclass
class HoverSettings(AttitudeSettings):
    """A lander or tripod over the scene centre."""

    descent_mps: float = setting(0.0, "vertical speed (positive: descending)", "m/s", range=(-100.0, 100.0))
    body_rotation_period_s: float = setting(0.0, "rotation period of the body beneath, spinning about its local y "
                                            "axis through the local origin", ROTATION_PERIOD_UNIT,
                                            range=(0.0, MAX_ROTATION_PERIOD_S))

    def check(self, context) -> None:
        period = self.body_rotation_period_s
        if 0.0 < period < MIN_ROTATION_PERIOD_S:
            raise InputError("flight.body_rotation_period_s", period,
                             f"a finite number in [0, {MAX_ROTATION_PERIOD_S:g}] {ROTATION_PERIOD_UNIT}")


@register("platform", "hover")
class HoverPlatform:
    """A hover of the ``[flight]`` section (common and hover settings)."""

    settings = HoverSettings

    def __init__(self, flight):
        self.f = flight

    @property
    def rotating(self) -> bool:
        """Whether the scene spins beneath the hover (no height grid, clearance from the spin axis)."""
        return self.f.body_rotation_period_s > 0.0

    def spans(self) -> tuple[float, float, float]:
        return 0.0, 0.0, self.f.heading_deg

    def tilt_deg(self) -> float:
        return abs(self.f.roll_deg) + abs(self.f.pitch_deg)

    def trajectories(self, scene: Scene) -> list[Trajectory]:
        """flight.altitude_m above the scene centre's ground at the start, sinking at descent_mps, level, the
        sensor axis (body z) down; over a spinning body, the same hover held in inertial space, seen from the
        body."""
        f = self.f
        centre = scene_centre(scene)
        times = f.start_gps_time + np.array([0.0, f.duration_s])
        heights = centre[2] + f.altitude_m - f.descent_mps * (times - f.start_gps_time)
        position = np.column_stack([np.full(2, centre[0]), np.full(2, centre[1]), heights])
        attitude = np.tile(np.radians([f.roll_deg, f.pitch_deg, f.heading_deg % 360.0]), (2, 1))
        hover = Trajectory(times, position, attitude, 1)
        if not self.rotating:
            check_clearance(hover, scene, f.altitude_m)
            return [hover]
        spun = rotating_body.spun_hover(hover, scene, f.body_rotation_period_s)
        rotating_body.check_clearance(spun, scene, f.altitude_m, MIN_CLEARANCE_M)
        return [spun]
