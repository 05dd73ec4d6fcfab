"""A flown trajectory: time-stamped positions and attitudes, interpolation, CSV files in and out.

Times are adjusted standard GPS time [s] (GPS seconds − 1e9, as in LAS). Positions are world
coordinates (easting, northing, height [m]) in float64; attitudes are roll, pitch, heading [rad]
in the conventions of :mod:`trajectories.attitude` (SPEC §2).
"""
from __future__ import annotations

import contextlib
import csv
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from . import rotation as quaternions
from .attitude import make_continuous, quaternion_from_matrix, rotation_body_to_enu
from .checks import integer_in
from .errors import TrajectoryError

COLUMNS = ("gps_time", "easting", "northing", "height", "roll", "pitch", "heading")
"""Columns of a trajectory CSV file; roll, pitch and heading are in degrees there."""

MAX_LINE_ID = 65535  # LAS point_source_id is an unsigned 16-bit integer


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Time-stamped poses of the aircraft's body frame along one flight line.

    Attributes:
        gps_time: (n,) adjusted standard GPS time [s], strictly increasing, n ≥ 2.
        position: (n, 3) world easting, northing, height of the body origin [m].
        attitude: (n, 3) roll, pitch, heading [rad].
        line_id: flight-line number (LAS point_source_id), 0…65535.

    The arrays are copied to read-only float64 arrays on construction.
    """

    gps_time: np.ndarray
    position: np.ndarray
    attitude: np.ndarray
    line_id: int = 1

    def __post_init__(self):
        gps_time = _float_array(self.gps_time, "trajectory.gps_time", "a 1-D array of times [s]")
        if gps_time.ndim != 1 or gps_time.shape[0] < 2:
            raise TrajectoryError(
                "trajectory.gps_time", f"shape {gps_time.shape}", "a 1-D array of at least 2 times [s]"
            )
        check_times(gps_time, lambda i: f"row {i}")
        n = gps_time.shape[0]
        position = _rows_of_three(self.position, n, "trajectory.position", "easting, northing, height [m]")
        attitude = _rows_of_three(self.attitude, n, "trajectory.attitude", "roll, pitch, heading [rad]")
        line_id = integer_in(self.line_id, "trajectory.line_id", 0, MAX_LINE_ID)
        for name, value in (("gps_time", gps_time), ("position", position), ("attitude", attitude)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "line_id", line_id)

    @classmethod
    def many(cls, gps_time: np.ndarray, position: np.ndarray, attitude: np.ndarray,
             line_ids: Sequence[int]) -> list["Trajectory"]:
        """Trajectories of n samples each at once: ``gps_time`` (L, n), ``position`` and ``attitude`` (L, n, 3),
        ``line_ids`` (L,); trajectory i is ``Trajectory(gps_time[i], position[i], attitude[i], line_ids[i])``, its
        arrays rows of three read-only float64 copies. The checks are made on all at once (a run of the shots
        platform flies one two-sample line per footprint, ~50 µs each one at a time); where one fails, the
        trajectories are made one by one, so the error is the first bad one's own."""
        times = _float_array(gps_time, "trajectory.gps_time", "an (L, n) array of times [s]")
        position = _float_array(position, "trajectory.position", "an (L, n, 3) array [m]")
        attitude = _float_array(attitude, "trajectory.attitude", "an (L, n, 3) array [rad]")
        ids = np.asarray(line_ids)
        fine = (times.ndim == 2 and times.shape[1] >= 2 and position.shape == attitude.shape == times.shape + (3,)
                and ids.shape == times.shape[:1] and ids.dtype.kind in "iu" and bool(np.isfinite(times).all())
                and bool((np.diff(times, axis=1) > 0.0).all()) and bool(np.isfinite(position).all())
                and bool(np.isfinite(attitude).all()) and bool(((ids >= 0) & (ids <= MAX_LINE_ID)).all()))
        if not fine:
            return [cls(*row) for row in zip(gps_time, position, attitude, ids.tolist())]
        for value in (times, position, attitude):
            value.setflags(write=False)
        made = []
        for t, p, a, line_id in zip(times, position, attitude, ids.tolist()):
            trajectory = object.__new__(cls)
            for name, value in (("gps_time", t), ("position", p), ("attitude", a), ("line_id", line_id)):
                object.__setattr__(trajectory, name, value)
            made.append(trajectory)
        return made

    @property
    def start_time(self) -> float:
        """GPS time of the first sample [s]."""
        return float(self.gps_time[0])

    @property
    def end_time(self) -> float:
        """GPS time of the last sample [s]."""
        return float(self.gps_time[-1])

    @property
    def duration(self) -> float:
        """end_time − start_time [s]."""
        return self.end_time - self.start_time

    def quaternions(self) -> np.ndarray:
        """(n, 4) unit quaternions (x, y, z, w) of R_body→ENU, sign-continuous (dot ≥ 0)."""
        return self._quaternions.copy()

    def interpolate(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Pose at GPS times t [s] (any shape) within [start_time, end_time].

        Returns (position, rotation): position (..., 3) [m], linear in time between samples;
        rotation (..., 3, 3) R_body→ENU, spherical linear interpolation between samples along
        the shorter arc (a heading going 179° → −179° passes through 180°).
        """
        t = np.asarray(t, dtype=np.float64)
        outside = ~((t >= self.gps_time[0]) & (t <= self.gps_time[-1]))  # NaN is outside too
        if outside.any():
            raise TrajectoryError(
                "trajectory.time",
                float(t[outside].flat[0]),
                f"a GPS time within the trajectory, [{self.start_time!r}, {self.end_time!r}] s",
            )
        if t.size == 0:
            return np.empty(t.shape + (3,)), np.empty(t.shape + (3, 3))
        i = np.clip(np.searchsorted(self.gps_time, t, side="right") - 1, 0, len(self.gps_time) - 2)
        u = ((t - self.gps_time[i]) / (self.gps_time[i + 1] - self.gps_time[i]))[..., None]
        position = self.position[i] + u * (self.position[i + 1] - self.position[i])
        start = quaternions.normalize(self._quaternions[i])
        partial = quaternions.from_rotvec(u * self._segment_rotvecs[i])
        return position, quaternions.as_matrix(quaternions.multiply(start, partial))

    @cached_property
    def _quaternions(self) -> np.ndarray:
        rotation = rotation_body_to_enu(self.attitude[:, 0], self.attitude[:, 1], self.attitude[:, 2])
        return make_continuous(quaternion_from_matrix(rotation))

    @cached_property
    def _segment_rotvecs(self) -> np.ndarray:
        """(n−1, 3) rotation vector of R_i⁻¹·R_(i+1) (body frame), angle ≤ π: the shorter arc."""
        quat = quaternions.normalize(self._quaternions)
        return quaternions.as_rotvec(quaternions.multiply(quaternions.inverse(quat[:-1]), quat[1:]))

    @classmethod
    def read_csv(cls, path: str | os.PathLike, line_id: int = 1) -> "Trajectory":
        """Read a trajectory CSV file with the header ``gps_time,easting,northing,height,roll,pitch,heading``.

        Columns are found by name (extra columns are ignored); angles are in degrees. Every
        problem (missing file, missing column, a row that is not numbers, NaN, times out of
        order) raises :class:`TrajectoryError` naming the column or the file and the line.
        """
        path = Path(path)
        header, rows = _read_rows(path)
        lines = [line for line, _ in rows]
        if len(rows) < 2:
            raise TrajectoryError("trajectory.file", str(path), "at least 2 data rows after the header")
        for line, row in rows:
            if len(row) != len(header):
                raise TrajectoryError(
                    "trajectory.file",
                    ",".join(row),
                    f"{len(header)} comma-separated values, as in the header (line {line} of {path})",
                )
        columns = list(zip(*(row for _, row in rows)))
        values = {name: _parse_column(columns[header.index(name)], name, lines, path) for name in COLUMNS}
        check_times(values["gps_time"], lambda i: f"line {lines[i]} of {path}")
        position = np.column_stack([values["easting"], values["northing"], values["height"]])
        attitude = np.radians(np.column_stack([values["roll"], values["pitch"], values["heading"]]))
        return cls(values["gps_time"], position, attitude, line_id)

    def write_csv(self, path: str | os.PathLike) -> None:
        """Write the trajectory as CSV (angles in degrees).

        Times and positions are written as Python's shortest round-trip repr, so reading the
        file back gives the same float64 bits; angles go through a degree conversion and come
        back within a few ulp. The file is written under a temporary name and renamed when
        complete.
        """
        path = Path(path)
        degrees = np.degrees(self.attitude)
        lines = [",".join(COLUMNS)]
        for t, p, a in zip(self.gps_time.tolist(), self.position.tolist(), degrees.tolist()):
            lines.append(",".join(repr(v) for v in (t, *p, *a)))
        text = "\n".join(lines) + "\n"
        temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with temporary.open("w", encoding="utf-8", newline="") as f:
                f.write(text)
            os.replace(temporary, path)
        except OSError as exc:
            with contextlib.suppress(OSError):
                temporary.unlink(missing_ok=True)
            raise TrajectoryError("trajectory.file", str(path), f"a writable file path ({exc})") from None


def prime_quaternions(trajectories: Sequence[Trajectory]) -> None:
    """Work out the attitude quaternions of many trajectories at once, each trajectory's own bit for bit (the
    conversion is per sample; sign continuity is made per trajectory): a run of the shots platform flies one
    two-sample trajectory per footprint, ~0.2 ms each one at a time."""
    todo = [t for t in trajectories if "_quaternions" not in t.__dict__]
    if not todo:
        return
    attitude = np.concatenate([t.attitude for t in todo])
    quat = quaternion_from_matrix(rotation_body_to_enu(attitude[:, 0], attitude[:, 1], attitude[:, 2]))
    sizes = np.array([len(t.attitude) for t in todo])
    first = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    for n in np.unique(sizes).tolist():  # the trajectories of n samples together
        group = np.flatnonzero(sizes == n)
        rows = make_continuous(quat[first[group][:, None] + np.arange(n)])
        for k, part in zip(group.tolist(), rows):
            todo[k].__dict__["_quaternions"] = part


def check_times(times: np.ndarray, where: Callable[[int], str]) -> None:
    """Raise TrajectoryError("trajectory.gps_time") unless times are finite and strictly increasing.

    where(i) names sample i in the message (a row number, or a file line).
    """
    finite = np.isfinite(times)
    if not finite.all():
        i = int(np.argmin(finite))
        raise TrajectoryError("trajectory.gps_time", float(times[i]), f"a finite time [s] ({where(i)})")
    not_after = np.flatnonzero(np.diff(times) <= 0.0)
    if not_after.size:
        i = int(not_after[0]) + 1
        raise TrajectoryError(
            "trajectory.gps_time",
            float(times[i]),
            f"strictly increasing times [s]: {where(i)} is not after {where(i - 1)} ({float(times[i - 1])!r})",
        )


def _float_array(value, field: str, allowed: str) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TrajectoryError(field, value, allowed) from None


def _rows_of_three(value, n: int, field: str, what: str) -> np.ndarray:
    array = _float_array(value, field, f"an (n, 3) array of {what}")
    if array.shape != (n, 3):
        raise TrajectoryError(field, f"shape {array.shape}", f"shape ({n}, 3), one row of {what} per time")
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise TrajectoryError(field, array[i].tolist(), f"finite {what} (row {i})")
    return array


def _read_rows(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header names and the non-blank data rows (with their 1-based line numbers) of a CSV file."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            rows = [(reader.line_num, row) for row in reader if len(row) > 1 or (row and row[0].strip())]
    except FileNotFoundError:
        raise TrajectoryError("trajectory.file", str(path), "an existing trajectory CSV file") from None
    except UnicodeDecodeError:
        raise TrajectoryError("trajectory.file", str(path), "a UTF-8 text CSV file") from None
    except (OSError, csv.Error) as exc:
        raise TrajectoryError("trajectory.file", str(path), f"a readable CSV file ({exc})") from None
    if not rows:
        raise TrajectoryError("trajectory.file", str(path), f"a header line {','.join(COLUMNS)}")
    header = [name.strip() for name in rows[0][1]]
    missing = [name for name in COLUMNS if name not in header]
    if missing:
        raise TrajectoryError(
            "trajectory.file",
            ",".join(header),
            f"a header with the columns {','.join(COLUMNS)} (missing: {','.join(missing)}) in {path}",
        )
    repeated = sorted({name for name in COLUMNS if header.count(name) > 1})
    if repeated:
        raise TrajectoryError(
            "trajectory.file",
            ",".join(header),
            f"each column named once (repeated: {','.join(repeated)}) in {path}",
        )
    return header, rows[1:]


def _parse_column(cells: Sequence[str], name: str, lines: list[int], path: Path) -> np.ndarray:
    """float64 values of one column; TrajectoryError("trajectory.<name>") names the first bad line."""
    try:
        values = np.array([float(cell) for cell in cells], dtype=np.float64)
    except ValueError:
        i = next(i for i, cell in enumerate(cells) if not _is_number(cell))
        raise TrajectoryError(f"trajectory.{name}", cells[i], f"a number (line {lines[i]} of {path})") from None
    finite = np.isfinite(values)
    if not finite.all():
        i = int(np.argmin(finite))
        allowed = f"a finite number (line {lines[i]} of {path})"
        raise TrajectoryError(f"trajectory.{name}", float(values[i]), allowed)
    return values


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
