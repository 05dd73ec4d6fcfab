"""Flight paths for flightsim: flight-line plans, attitude, pulse timing, trajectory files.

Depends only on numpy and the standard library (never on flightsim or warp; SciPy's rotations are repeated
bit for bit by :mod:`trajectories.rotation`, which keeps scipy.spatial out of the simulator's start-up).
"""
import importlib

_HOMES = {
    "euler_from_rotation": "attitude", "make_continuous": "attitude", "quaternion_from_matrix": "attitude",
    "rotation_body_to_enu": "attitude", "TrajectoryError": "errors", "FlightLine": "lines",
    "climb_limited": "lines", "plan_parallel_lines": "lines", "PulseTiming": "timing", "COLUMNS": "trajectory",
    "Trajectory": "trajectory", "prime_quaternions": "trajectory",
}
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    """Each name imported from its module on first use: importing one module (``trajectories.errors``)
    does not import the rest."""
    if name in _HOMES:
        return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
    raise AttributeError(f"module 'trajectories' has no attribute {name!r}")
