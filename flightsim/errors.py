"""Errors raised for invalid user input (config values, files, flags).

The command line turns an :class:`InputError` into one line on stderr and exit status 2.
"""
from __future__ import annotations

import math


def describe_value(value: object) -> str:
    """Short, readable form of an offending value for an error message."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class InputError(ValueError):
    """Bad input, named by its field, its value and what is allowed.

    Args:
        field: dotted name of the offending setting, e.g. ``"flight.altitude_m"`` or ``"--scene"``.
        value: the value that was given.
        allowed: what would have been accepted, e.g. ``"a finite number in (0, 50000] m"``.
    """

    def __init__(self, field: str, value: object, allowed: str):
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f"invalid {field} = {describe_value(value)}: expected {allowed}")
