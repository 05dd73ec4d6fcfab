"""Flight paths for flightsim: flight-line plans, attitude, pulse timing, trajectory files.

Depends only on numpy, scipy and the standard library (never on flightsim or warp).
"""
from .attitude import euler_from_rotation, make_continuous, quaternion_from_matrix, rotation_body_to_enu
from .errors import TrajectoryError
from .lines import FlightLine, climb_limited, plan_parallel_lines
from .timing import PulseTiming
from .trajectory import COLUMNS, Trajectory

__all__ = [
    "COLUMNS",
    "FlightLine",
    "PulseTiming",
    "Trajectory",
    "TrajectoryError",
    "climb_limited",
    "euler_from_rotation",
    "make_continuous",
    "plan_parallel_lines",
    "quaternion_from_matrix",
    "rotation_body_to_enu",
]
