"""Errors raised for invalid trajectory input (flight-line plans, timing, trajectory files).

Same signature and message format as ``flightsim.core.errors.InputError``; this package does not
import flightsim, so the caller may catch :class:`TrajectoryError` (a ``ValueError``) and
report it the same way.
"""
from __future__ import annotations

import math


SHORT = 80  # characters of a value other than a string (a list, an array) an error message shows
LONG = 1000  # characters of a string (a path, a name): its end, a file's name, is what the reader needs


def describe_value(value: object) -> str:
    """Short, readable form of an offending value for an error message: a string whole up to LONG characters
    (a longer one cut in the middle, keeping its end), anything else at most SHORT characters."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    text = repr(value)
    if isinstance(value, str):
        half = (LONG - 3) // 2
        return text if len(text) <= LONG else text[:half] + "..." + text[-half:]
    return text if len(text) <= SHORT else text[:SHORT - 3] + "..."


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

    def __reduce__(self):
        """Pickled by its three arguments (a worker process's error travels to its parent)."""
        return type(self), (self.field, self.value, self.allowed)
