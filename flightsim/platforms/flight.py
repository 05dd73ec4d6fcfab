"""The flight: the settings every platform shares (``[flight]``: which platform, how high, how long, when), the
attitude settings of the platforms that hold one, and the check that a trajectory clears the terrain."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.core.settings import Settings, setting
from flightsim.scenes.scene import Scene
from trajectories import Trajectory

MIN_CLEARANCE_M = 1.0  # the sensor must stay at least this far above the terrain [m]
CLEARANCE_PIECES = 64  # a trajectory's clearance is checked over this many runs of samples


@dataclass
class FlightSettings(Settings):
    """What flies the instrument, how high, how long and from when; the platform's own settings join these."""

    table = "flight"

    platform: str = setting("lines", "what flies the instrument: lines (flight lines or a trajectory file), hover "
                            "(a lander or tripod over the scene centre), orbit (a spacecraft), shots (a pulse over "
                            "each footprint centre of a file), tripod (a terrestrial scanner's scan position)",
                            choices=lambda: tuple(sorted(registry.kinds("platform"))))
    altitude_m: float = setting(500.0, "height above the ground (the hover's at its start, the orbit's over the "
                                "scene origin)", "m", range=(0.0, 1.0e6), lo_open=True)
    duration_s: float = setting(10.0, "flight time per line", "s", range=(0.0, 36000.0), lo_open=True)
    start_gps_time: float = setting(450_000_000.0, "time of the first pulse, adjusted standard GPS time", "s",
                                    range=(-1.0e9, 2.0e9))


@dataclass
class AttitudeSettings(Settings):
    """The attitude a level platform holds (the lines and hover platforms)."""

    heading_deg: float = setting(0.0, "heading, clockwise from grid north", "deg", range=(-360.0, 360.0))
    roll_deg: float = setting(0.0, "roll (positive: right wing down)", "deg", range=(-30.0, 30.0))
    pitch_deg: float = setting(0.0, "pitch (positive: nose up)", "deg", range=(-30.0, 30.0))


def clearance(trajectory: Trajectory, scene: Scene, pieces: int = CLEARANCE_PIECES) -> tuple[float, float, float]:
    """(clearance, sensor height, terrain top) [m, local heights] where a trajectory comes closest
    to the terrain.

    The trajectory is cut into up to ``pieces`` runs of consecutive samples; over each run's
    bounding rectangle the terrain's highest point is compared with the run's lowest sample
    (positions are linear between samples, so the rectangle holds the whole run).
    """
    local = scene.world_to_local(trajectory.position)
    bounds = np.unique(np.linspace(0, len(local) - 1, min(pieces, len(local) - 1) + 1).round().astype(int))
    rects, lowest = [], []
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        run = local[i0:i1 + 1]
        rects.append([run[:, 0].min(), run[:, 1].min(), run[:, 0].max(), run[:, 1].max()])
        lowest.append(run[:, 2].min())
    tops = scene.terrain_tops(rects)
    margin = np.asarray(lowest) - tops
    k = int(np.argmin(margin))
    return float(margin[k]), float(lowest[k]), float(tops[k])


def _clear_at_a_glance(trajectory: Trajectory, scene: Scene) -> bool:
    """True when the lowest sample is clear of the height grid's bound of the terrain under the
    trajectory's rectangle (a cheap sufficient test; the exact one runs only when this fails)."""
    local = scene.world_to_local(trajectory.position)
    top = scene.height_grid.top_bound(local[:, 0].min(), local[:, 1].min(), local[:, 0].max(), local[:, 1].max())
    return local[:, 2].min() - top >= MIN_CLEARANCE_M


def check_clearance(trajectory: Trajectory, scene: Scene, altitude_m: float, trajectory_file: str = "") -> None:
    """Reject a flight whose sensor does not stay at least MIN_CLEARANCE_M above the terrain beneath it, naming
    the trajectory file when one was flown, else flight.altitude_m."""
    if _clear_at_a_glance(trajectory, scene):
        return
    margin, height, top = clearance(trajectory, scene)
    if margin >= MIN_CLEARANCE_M:
        return
    if trajectory_file:
        raise InputError("flight.trajectory", trajectory_file,
                         f"a trajectory at least {MIN_CLEARANCE_M:g} m above the terrain beneath it (it flies at "
                         f"{height + scene.origin[2]:.3f} m over terrain reaching {top + scene.origin[2]:.3f} m)")
    rise = top - scene.ground_z
    raise InputError("flight.altitude_m", altitude_m,
                     f"an altitude above {rise + MIN_CLEARANCE_M:.3f} m: the terrain beneath the flight rises "
                     f"{rise:.3f} m above the scene's ground (to {top + scene.origin[2]:.3f} m)")


def scene_centre(scene: Scene) -> np.ndarray:
    """World coordinates of the centre of the scene's bounds at its ground height [m]."""
    lo, hi = scene.bounds()
    return scene.local_to_world(np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, scene.ground_z]))
