"""The shots platform (``flight.platform = "shots"``): one pulse per footprint centre of a CSV file, as a
simulation of given GEDI shots is asked for (the GEDI simulator's list of coordinates).

``flight.footprints`` is a CSV file with a header naming the columns ``x``, ``y`` (world easting, northing in the
scene's CRS [m]) and optionally ``delta_time`` (the shot's time, adjusted standard GPS time [s], as waveforms.h5's
``delta_time``); other columns are ignored. Row i (0-based, in file order) is footprint i: a flight line of its
own, ``line_id`` = i, firing one pulse at its time (``delta_time``, else ``flight.start_gps_time`` + i ·
``flight.shot_interval_s``) from ``flight.altitude_m`` straight above the highest surface of the scene at (x, y),
looking at nadir (body z down, heading north), so the beam axis meets that surface at the footprint centre.

Each line is two samples at the same pose, the second one float64 step after the first: the line fires exactly
one pulse for any pulse rate whose period exceeds that step (at GPS times below 2²⁹ s ≈ 5.4e8 s, the default
flight.start_gps_time of 4.5e8 s included, any rate up to 1e7 Hz).
Every problem — a missing file or column, a value that is not a finite number, no row, more rows than line ids,
a footprint with no scene beneath it — is an InputError naming ``flight.footprints`` and the row.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.platforms.flight import MIN_CLEARANCE_M
from flightsim.scenes.scene import Scene
from trajectories import Trajectory
from trajectories.trajectory import MAX_LINE_ID

FIELD = "flight.footprints"
COLUMNS = ("x", "y")
TIME_COLUMN = "delta_time"


@dataclass(frozen=True)
class Footprints:
    """The footprint centres of a CSV file: world ``x``, ``y`` [m] and ``delta_time`` [s] (NaN where the file
    gives none), ``lines`` the file's line number of each row."""

    x: np.ndarray
    y: np.ndarray
    delta_time: np.ndarray
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    def name(self, i: int) -> str:
        """How an error names footprint ``i``."""
        return f"footprint {i} (line {self.lines[i]}) at x = {self.x[i]:.3f}, y = {self.y[i]:.3f} m"


def read_footprints(path: str) -> Footprints:
    """The footprint centres of the CSV file at ``path`` (see the module's notes); InputError naming the row."""
    header, rows = _rows(path)
    names = [h.strip() for h in header]
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise InputError(FIELD, path, f"a CSV whose header names the columns x, y (and optionally delta_time); "
                                      f"it has {', '.join(names) or 'none'}")
    wanted = [c for c in (*COLUMNS, TIME_COLUMN) if c in names]
    if not rows:
        raise InputError(FIELD, path, "a CSV with at least one footprint row after its header")
    if len(rows) > MAX_LINE_ID + 1:
        raise InputError(FIELD, path, f"at most {MAX_LINE_ID + 1} footprints (one flight line each; it has {len(rows)})")
    values = np.full((len(rows), 3), np.nan)
    columns = [names.index(c) for c in wanted]
    try:  # every row at once; a row that fails is found again one at a time, for its message
        values[:, :len(wanted)] = [[float(row[k]) for k in columns] for _, row in rows]
        parsed = bool(np.isfinite(values[:, :len(wanted)]).all())
    except (ValueError, IndexError):
        parsed = False
    if not parsed:
        for i, (line, row) in enumerate(rows):
            values[i, :len(wanted)] = [_number(row, k, i, line, path) for k in columns]
    return Footprints(values[:, 0], values[:, 1], values[:, 2], np.array([line for line, _ in rows]))


def _rows(path: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """(header, [(file line, values)]) of the non-blank rows of a CSV file."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            lines = [(n, row) for n, row in enumerate(csv.reader(f), start=1) if any(v.strip() for v in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(FIELD, path, f"a readable CSV file of footprint centres ({exc})") from None
    if not lines:
        raise InputError(FIELD, path, "a CSV whose header names the columns x, y (and optionally delta_time); "
                                      "the file is empty")
    return lines[0][1], lines[1:]


def _number(row: list[str], column: int, i: int, line: int, path: str) -> float:
    text = row[column].strip() if column < len(row) else ""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise InputError(FIELD, f"row {i} (line {line} of {path}): {','.join(row)}",
                         "finite numbers in the columns x, y (and delta_time when given) of every row")
    return value


@dataclass
class ShotsSettings(Settings):
    """One nadir pulse per footprint centre of a CSV file."""

    footprints: str = setting("", "CSV file of footprint centres: columns x, y (world E, N in the scene's CRS [m]) "
                              "and optionally delta_time (adjusted GPS time [s]); one nadir pulse per row from "
                              "altitude_m above the surface there")
    shot_interval_s: float = setting(1.0 / 242.0, "time between rows without delta_time (default: GEDI's 242 Hz)",
                                     "s", range=(0.0, 1.0e6), lo_open=True)

    def check(self, context) -> None:
        if not self.footprints.strip():
            raise InputError(FIELD, self.footprints, "a CSV file of footprint centres (columns x, y, optionally "
                                                     "delta_time) for the shots platform")


@register("platform", "shots")
class ShotsPlatform:
    """The footprints of ``flight.footprints``, one nadir pulse each (common and shots settings of ``[flight]``)."""

    settings = ShotsSettings

    def __init__(self, flight):
        self.f = flight

    def spans(self) -> tuple[float, float, float]:
        """(0, 0, 0): a built-in scene is not sized to the footprints (widen it with ``scene.margin_m``)."""
        return 0.0, 0.0, 0.0

    def tilt_deg(self) -> float:
        return 0.0

    def trajectories(self, scene: Scene) -> list[Trajectory]:
        """A two-sample line per footprint, ``line_id`` its row (see the module's notes)."""
        f, shots = self.f, read_footprints(self.f.footprints)
        if f.altitude_m < MIN_CLEARANCE_M:
            raise InputError("flight.altitude_m", f.altitude_m, f"at least {MIN_CLEARANCE_M:g} m above the surface "
                                                                "under each footprint")
        local = scene.world_to_local(np.column_stack([shots.x, shots.y, np.zeros(len(shots))]))
        ground = _surface_under(scene, shots, local)
        times = np.where(np.isnan(shots.delta_time), f.start_gps_time + np.arange(len(shots)) * f.shot_interval_s,
                         shots.delta_time)
        heights = ground + f.altitude_m + scene.origin[2]
        t = np.column_stack([times, np.nextafter(times, np.inf)])  # each line's two samples
        position = np.repeat(np.column_stack([shots.x, shots.y, heights])[:, None, :], 2, axis=1)
        return Trajectory.many(t, position, np.zeros_like(position), np.arange(len(shots)))


def _surface_under(scene: Scene, shots: Footprints, local: np.ndarray) -> np.ndarray:
    """The highest local z of the scene's surface straight under each footprint centre [m]; InputError naming
    the first footprint with none."""
    ground = scene.height_grid.ground_height(local[:, 0], local[:, 1])
    lost = np.flatnonzero(~np.isfinite(ground))
    if lost.size:
        lo, hi = (scene.local_to_world(corner) for corner in scene.bounds())
        raise InputError(FIELD, shots.name(int(lost[0])),
                         f"footprints over the scene's surface (it spans x {lo[0]:.1f} … {hi[0]:.1f}, y {lo[1]:.1f} "
                         f"… {hi[1]:.1f} m; a built-in scene grows with scene.margin_m)")
    return ground
