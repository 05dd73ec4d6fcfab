"""The flight-line platform (``flight.platform = "lines"``): straight parallel lines over the scene centre, with
terrain following if asked, or a trajectory file flown instead."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightsim.core.registry import register
from flightsim.core.settings import setting
from flightsim.platforms.flight import AttitudeSettings, check_clearance, scene_centre
from flightsim.scenes.scene import Scene
from trajectories import Trajectory, climb_limited, plan_parallel_lines

MAX_CLIMB_MPS = 5.0  # terrain following: the fastest climb or descent of a planned line [m/s]


@dataclass
class LinesSettings(AttitudeSettings):
    """Parallel flight lines (or a trajectory file)."""

    speed_kmh: float = setting(200.0, "ground speed", "km/h", range=(0.0, 30000.0), lo_open=True)
    lines: int = setting(1, "parallel flight lines", "lines", range=(1, 65535))
    line_spacing_m: float = setting(200.0, "distance between neighbouring lines", "m", range=(0.0, 1.0e5),
                                    lo_open=True)
    trajectory: str = setting("", "a CSV trajectory file flown instead of the planned lines; \"\" = plan lines")
    terrain_following: bool = setting(False, "keep altitude_m above the ground under the aircraft, climbing and "
                                      f"descending at most {MAX_CLIMB_MPS:g} m/s (else above the scene's ground)")


@register("platform", "lines")
class LinesPlatform:
    """Flight lines of the ``[flight]`` section (common and lines settings)."""

    settings = LinesSettings

    def __init__(self, flight):
        self.f = flight

    @property
    def line_length_m(self) -> float:
        """Length of each planned flight line [m]."""
        return self.f.speed_kmh / 3.6 * self.f.duration_s

    def spans(self) -> tuple[float, float, float]:
        """(half length along the lines, half width across them [m], heading [deg]) of the planned lines."""
        f = self.f
        return self.line_length_m / 2.0, (f.lines - 1) / 2.0 * f.line_spacing_m, f.heading_deg

    def tilt_deg(self) -> float:
        """The largest lean of the sensor axis from nadir the attitude gives, to first order [deg]."""
        return abs(self.f.roll_deg) + abs(self.f.pitch_deg)

    def trajectories(self, scene: Scene) -> list[Trajectory]:
        """The trajectory file if one is given, else the planned lines; each clear of the terrain."""
        f = self.f
        trajectories = [Trajectory.read_csv(f.trajectory)] if f.trajectory else self._planned(scene)
        for trajectory in trajectories:
            check_clearance(trajectory, scene, f.altitude_m, f.trajectory)
        return trajectories

    def _planned(self, scene: Scene) -> list[Trajectory]:
        f = self.f
        centre = scene_centre(scene)
        lines = plan_parallel_lines(
            centre[0], centre[1], f.heading_deg, self.line_length_m, f.altitude_m, f.lines, f.line_spacing_m,
            speed_mps=f.speed_kmh / 3.6, roll_deg=f.roll_deg, pitch_deg=f.pitch_deg, start_gps_time=f.start_gps_time,
        )
        trajectories = [line.trajectory(ground_height_m=centre[2]) for line in lines]
        if not f.terrain_following:
            return trajectories
        return [follow_terrain(t, scene, f.altitude_m, MAX_CLIMB_MPS / (f.speed_kmh / 3.6)) for t in trajectories]


def follow_terrain(trajectory: Trajectory, scene: Scene, altitude_m: float, max_grade: float) -> Trajectory:
    """``trajectory`` at ``altitude_m`` [m] above the ground under each sample (the highest surface
    there, from :attr:`Scene.height_grid`; where there is none, the nearest samples' ground, else the
    scene's ground height), raised where needed so that it climbs and descends at most ``max_grade``
    (rise/run) and never comes lower than that: the least such profile. The attitude is kept."""
    local = scene.world_to_local(trajectory.position)
    ground = scene.height_grid.ground_height(local[:, 0], local[:, 1])
    known = np.isfinite(ground)
    along = np.r_[0.0, np.cumsum(np.hypot(*np.diff(local[:, :2], axis=0).T))]
    if not known.any():
        ground = np.full(len(local), scene.ground_z)
    elif not known.all():
        ground = np.interp(along, along[known], ground[known])
    height = climb_limited(along, ground + altitude_m, max_grade) + scene.origin[2]
    position = np.column_stack([trajectory.position[:, :2], height])
    return Trajectory(trajectory.gps_time, position, trajectory.attitude, trajectory.line_id)
