"""Errors raised for invalid user input (config values, files, flags).

The command line turns an :class:`InputError` into one line on stderr and exit status 2.
"""
from __future__ import annotations

import math

from trajectories.errors import TrajectoryError


class InputError(TrajectoryError):
    """Bad input, named by its field, its value and what is allowed.

    The same form as the trajectories package's error (which cannot import flightsim), so both
    read alike: ``invalid {field} = {value}: expected {allowed}``.

    Args:
        field: dotted name of the offending setting, e.g. ``"flight.altitude_m"`` or ``"--scene"``.
        value: the value that was given.
        allowed: what would have been accepted, e.g. ``"a finite number in (0, 50000] m"``.
    """


def positive(name: str, value, unit: str = "") -> float:
    """``value`` as a float, else an :class:`InputError` naming ``name``: it must be finite and > 0 [``unit``]."""
    allowed = "a finite number > 0" + (f" [{unit}]" if unit else "")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(name, value, allowed) from None
    if not (math.isfinite(number) and number > 0.0):
        raise InputError(name, value, allowed)
    return number
