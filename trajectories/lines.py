"""Straight flight lines and parallel-line plans, turned into trajectories.

A line is flown at constant speed, height and attitude along a grid heading (clockwise from
grid north): a point s metres along it lies at easting + s·sin(h), northing + s·cos(h).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .checks import finite_number, integer_in, positive_number
from .errors import TrajectoryError
from .trajectory import MAX_LINE_ID, Trajectory

DEFAULT_SPEED_MPS = 200.0 / 3.6
"""200 km/h [m/s] (SPEC §1)."""
DEFAULT_START_GPS_TIME = 450_000_000.0
"""Adjusted standard GPS time of the first line's start [s] (mid-2024)."""
MAX_TILT_DEG = 30.0
"""Roll and pitch must stay below this magnitude [°]."""
MIN_SAMPLE_INTERVAL_S = 1e-5
"""Smallest trajectory sample interval [s]."""
END_GAP_S = 1e-6
"""A uniform sample closer than this to a line's end is dropped in favour of the end point [s]."""


@dataclass(frozen=True)
class FlightLine:
    """One straight line flown at constant speed, height above ground and attitude.

    Attributes:
        start_easting, start_northing: world coordinates of the start of the line [m].
        heading_deg: grid heading, clockwise from grid north [°].
        length_m: length of the line [m], > 0.
        altitude_m: flying height above ground [m], > 0.
        speed_mps: ground speed [m/s], > 0; default 200 km/h.
        roll_deg, pitch_deg: constant attitude [°], |·| < 30.
        start_gps_time: adjusted standard GPS time at the start [s].
        line_id: flight-line number (LAS point_source_id), 0…65535.
        field_prefix: prefix of the field names in error messages, e.g. "flight" gives
            "flight.length_m" (not part of the line's identity).
    """

    start_easting: float
    start_northing: float
    heading_deg: float
    length_m: float
    altitude_m: float
    speed_mps: float = DEFAULT_SPEED_MPS
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    start_gps_time: float = DEFAULT_START_GPS_TIME
    line_id: int = 1
    field_prefix: str = field(default="flight", compare=False, repr=False)

    def __post_init__(self):
        prefix = self.field_prefix
        for name in ("start_easting", "start_northing", "heading_deg", "start_gps_time"):
            value = finite_number(getattr(self, name), f"{prefix}.{name}", "a finite number")
            object.__setattr__(self, name, value)
        for name in ("length_m", "altitude_m"):
            object.__setattr__(self, name, positive_number(getattr(self, name), f"{prefix}.{name}", "[m]"))
        object.__setattr__(self, "speed_mps", _speed(self.speed_mps, f"{prefix}.speed_kmh"))
        tilt = f"a number in (-{MAX_TILT_DEG:g}, {MAX_TILT_DEG:g}) [°]"
        for name in ("roll_deg", "pitch_deg"):
            value = finite_number(getattr(self, name), f"{prefix}.{name}", tilt)
            if not abs(value) < MAX_TILT_DEG:
                raise TrajectoryError(f"{prefix}.{name}", value, tilt)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "line_id", integer_in(self.line_id, f"{prefix}.line_id", 0, MAX_LINE_ID))

    @classmethod
    def centred(
        cls,
        centre_easting: float,
        centre_northing: float,
        heading_deg: float,
        length_m: float,
        altitude_m: float,
        **kw,
    ) -> "FlightLine":
        """The line of the given heading and length [m] centred over (centre_easting, centre_northing) [m].

        Other keywords (speed_mps, start_gps_time, line_id, …) go to the constructor.
        """
        prefix = kw.get("field_prefix", "flight")
        east = finite_number(centre_easting, f"{prefix}.centre_easting", "a finite number [m]")
        north = finite_number(centre_northing, f"{prefix}.centre_northing", "a finite number [m]")
        heading = finite_number(heading_deg, f"{prefix}.heading_deg", "a finite number [°]")
        half = 0.5 * positive_number(length_m, f"{prefix}.length_m", "[m]")
        h = math.radians(heading)
        return cls(east - half * math.sin(h), north - half * math.cos(h), heading, length_m, altitude_m, **kw)

    @property
    def end_easting(self) -> float:
        """Easting of the end of the line [m]."""
        return self.start_easting + self.length_m * math.sin(math.radians(self.heading_deg))

    @property
    def end_northing(self) -> float:
        """Northing of the end of the line [m]."""
        return self.start_northing + self.length_m * math.cos(math.radians(self.heading_deg))

    @property
    def duration_s(self) -> float:
        """Time to fly the line, length / speed [s]."""
        return self.length_m / self.speed_mps

    @property
    def end_gps_time(self) -> float:
        """GPS time at the end of the line [s]."""
        return self.start_gps_time + self.duration_s

    def trajectory(self, ground_height_m: float, sample_interval_s: float = 0.1) -> Trajectory:
        """Trajectory of the line: samples every sample_interval_s [s] from the start, plus the exact end.

        Height = ground_height_m + altitude_m [m]; attitude is constant. Positions are exactly
        linear in the stored (float64) times: s = speed·(t − start_gps_time).
        """
        prefix = self.field_prefix
        ground = finite_number(ground_height_m, f"{prefix}.ground_height_m", "a finite number [m]")
        allowed = f"a finite number >= {MIN_SAMPLE_INTERVAL_S:g} [s]"
        interval = finite_number(sample_interval_s, f"{prefix}.sample_interval_s", allowed)
        if not interval >= MIN_SAMPLE_INTERVAL_S:
            raise TrajectoryError(f"{prefix}.sample_interval_s", interval, allowed)
        duration = self.duration_s
        uniform = np.arange(math.ceil(duration / interval)) * interval
        uniform = uniform[uniform < duration - END_GAP_S]
        times = self.start_gps_time + np.append(uniform, duration)
        along = self.speed_mps * (times - self.start_gps_time)
        h = math.radians(self.heading_deg)
        position = np.column_stack(
            [
                self.start_easting + along * math.sin(h),
                self.start_northing + along * math.cos(h),
                np.full(times.shape, ground + self.altitude_m),
            ]
        )
        attitude = np.radians([self.roll_deg, self.pitch_deg, self.heading_deg % 360.0])
        return Trajectory(times, position, np.tile(attitude, (times.size, 1)), self.line_id)


def plan_parallel_lines(
    centre_easting: float,
    centre_northing: float,
    heading_deg: float,
    length_m: float,
    altitude_m: float,
    n_lines: int,
    spacing_m: float,
    turn_time_s: float = 60.0,
    **kw,
) -> list[FlightLine]:
    """n_lines parallel lines centred over a point, flown back and forth.

    Line i (0-based) is offset (i − (n_lines−1)/2)·spacing_m to the right of heading_deg, flies
    heading_deg when i is even and the reciprocal heading when odd, has line_id i+1, and starts
    turn_time_s after the previous line ends (the first at start_gps_time, default
    DEFAULT_START_GPS_TIME). Other keywords (speed_mps, roll_deg, …) go to every FlightLine.
    """
    prefix = kw.get("field_prefix", "flight")
    count = integer_in(n_lines, f"{prefix}.n_lines", 1, MAX_LINE_ID)
    spacing = positive_number(spacing_m, f"{prefix}.spacing_m", "[m]")
    turn = finite_number(turn_time_s, f"{prefix}.turn_time_s", "a finite number >= 0 [s]")
    if turn < 0.0:
        raise TrajectoryError(f"{prefix}.turn_time_s", turn, "a finite number >= 0 [s]")
    east = finite_number(centre_easting, f"{prefix}.centre_easting", "a finite number [m]")
    north = finite_number(centre_northing, f"{prefix}.centre_northing", "a finite number [m]")
    heading = finite_number(heading_deg, f"{prefix}.heading_deg", "a finite number [°]")
    h = math.radians(heading)
    right = (math.cos(h), -math.sin(h))
    start_time = kw.pop("start_gps_time", DEFAULT_START_GPS_TIME)
    lines = []
    for i in range(count):
        offset = (i - 0.5 * (count - 1)) * spacing
        line = FlightLine.centred(
            east + offset * right[0],
            north + offset * right[1],
            heading if i % 2 == 0 else (heading + 180.0) % 360.0,
            length_m,
            altitude_m,
            start_gps_time=start_time,
            line_id=i + 1,
            **kw,
        )
        lines.append(line)
        start_time = line.end_gps_time + turn
    return lines


def _speed(speed_mps, field_name: str) -> float:
    """speed_mps [m/s] as a float; errors report it in km/h, the unit of the configuration."""
    allowed = "a finite number > 0 [km/h]"
    speed = finite_number(speed_mps, field_name, allowed)
    if not speed > 0.0:
        raise TrajectoryError(field_name, speed * 3.6, allowed)
    return speed


def climb_limited(along_m, height_m, max_grade: float) -> np.ndarray:
    """The lowest profile over ``height_m`` that climbs and descends at most ``max_grade`` (rise/run).

    Args:
        along_m: (n,) distance along the path [m], non-decreasing.
        height_m: (n,) the least height at each point [m].
        max_grade: steepest climb or descent, > 0.

    Returns:
        (n,) heights z_i = max_j (height_j − max_grade·|along_i − along_j|) [m]: never below
        ``height_m``, and |Δz| ≤ max_grade·Δalong between any two points.
    """
    along = np.asarray(along_m, dtype=np.float64)
    height = np.asarray(height_m, dtype=np.float64)
    grade = positive_number(max_grade, "max_grade", "(rise/run)")
    ahead = np.maximum.accumulate(height + grade * along) - grade * along
    behind = (np.maximum.accumulate((height - grade * along)[::-1]) + grade * along[::-1])[::-1]
    return np.maximum(ahead, behind)
