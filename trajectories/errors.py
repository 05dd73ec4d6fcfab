"""Errors raised for invalid trajectory input (flight-line plans, timing, trajectory files).

Same signature and message format as ``flightsim.core.errors.InputError``; this package does not
import flightsim, so the caller may catch :class:`TrajectoryError` (a ``ValueError``) and
report it the same way.
"""
from __future__ import annotations

import math


def describe_value(value: object) -> str:
    """Short, readable form of an offending value for an error message (at most 80 characters)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class TrajectoryError(ValueError):
    """Bad trajectory input, named by its field, its value and what is allowed.

    Args:
        field: dotted name of the offending setting, e.g. ``"flight.length_m"`` or
            ``"trajectory.gps_time"``.
        value: the value that was given.
        allowed: what would have been accepted, e.g. ``"a finite number > 0 [m]"``.
    """

    def __init__(self, field: str, value: object, allowed: str):
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f"invalid {field} = {describe_value(value)}: expected {allowed}")
