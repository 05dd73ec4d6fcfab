"""Validation of single numbers, shared by the flight-line, trajectory and timing classes."""
from __future__ import annotations

import math
import operator

from .errors import TrajectoryError


def finite_number(value, field: str, allowed: str) -> float:
    """value as a float; TrajectoryError(field, value, allowed) unless it is a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not math.isfinite(number):
        raise TrajectoryError(field, value, allowed)
    return number


def positive_number(value, field: str, unit: str) -> float:
    """value as a float; TrajectoryError unless it is finite and > 0 (unit goes in the message, e.g. "[m]")."""
    allowed = f"a finite number > 0 {unit}"
    number = finite_number(value, field, allowed)
    if not number > 0.0:
        raise TrajectoryError(field, value, allowed)
    return number


def integer_in(value, field: str, low: int, high: int) -> int:
    """value as an int; TrajectoryError unless it is an integer (not bool) in [low, high]."""
    try:
        number = operator.index(value)
    except TypeError:
        number = None
    if isinstance(value, bool) or number is None or not low <= number <= high:
        raise TrajectoryError(field, value, f"an integer in [{low}, {high}]")
    return number
