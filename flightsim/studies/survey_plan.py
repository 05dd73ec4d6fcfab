"""The plan of a survey (:mod:`flightsim.studies.survey`), decided before any task runs.

The scene is a square grid of scene tiles of ``tile_m`` — each a copy of the calibration field
(or flat ground, for ``scene.name = "plane"``) with its own float64 origin at its centre (SPEC §2) —
flown by parallel north–south lines whose spacing is the swath width (the scan circle's diameter
2·h·tan θ) less the sidelap.

Each line is cut along track into segments of ``segment_m``, one task each: its pulses only, over the
tiles its beams can reach (the reach radius h·tan(θ_max + tilt + 1°) plus the scene margin around its
ground track, the local origin being the tile under the middle of the segment), writing into the LAS
tiles its points can fall in.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.engine.config import RunConfig, copy_config, validate
from flightsim.engine.instrument import Instrument
from flightsim.platforms.flight import MIN_CLEARANCE_M
from flightsim.scenes.calibration import calibration_min_half_extent, calibration_scene
from flightsim.scenes.plane import plane_scene
from flightsim.scenes.scene import Scene, parse_crs
from trajectories import FlightLine, PulseTiming, TrajectoryError, plan_parallel_lines

REACH_MARGIN_DEG = 1.0  # added to the widest beam's angle from nadir when finding the tiles a task can reach
MAX_REACH_DEG = 80.0


@dataclass(frozen=True)
class SurveySpec:
    """The extent of a survey and how it is cut into tasks."""

    size_km: float = 5.0  # side of the square survey area [km] (rounded up to whole tiles)
    tile_m: int = 1000  # side of a scene tile [m]
    sidelap: float = 0.3  # overlap of neighbouring swaths, as a fraction of the swath width
    lines: int = 0  # flight lines; 0: enough to cover the area
    segment_m: float = 1000.0  # along-track length of one task [m]

    def validated(self) -> SurveySpec:
        """This spec, if every field is in range; else InputError naming the field."""
        for name, lo, hi, unit in (("size_km", 0.0, 10000.0, "km"), ("sidelap", 0.0, 0.9, "of the swath width"),
                                   ("segment_m", 1.0, 1.0e6, "m")):
            value = getattr(self, name)
            number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not (number and lo <= value <= hi) or (name == "size_km" and value == lo):
                interval = f"({lo:g}, {hi:g}]" if name == "size_km" else f"[{lo:g}, {hi:g}]"
                raise InputError(f"survey.{name}", value, f"a number in {interval} {unit}")
        for name, lo, hi in (("tile_m", 1, 100_000), ("lines", 0, 65535)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise InputError(f"survey.{name}", value, f"an integer in [{lo}, {hi}]")
        return self

    def to_toml(self) -> str:
        return "[survey]\n" + "".join(f"{f.name} = {getattr(self, f.name)!r}\n" for f in dataclasses.fields(self))


# ---------------------------------------------------------------------------------------------
# the tiled scene


@dataclass(frozen=True)
class TileGrid:
    """n × n scene tiles of ``tile_m`` centred on ``centre``; tile (i, j) is column i (east), row j (north)."""

    kind: str  # "calibration" or "plane"
    crs: str
    centre: tuple[float, float, float]  # world E, N, H of the grid's centre [m]; H is the ground
    tile_m: int
    n: int

    @property
    def side_m(self) -> float:
        return self.n * self.tile_m

    def tile_origin(self, i: int, j: int) -> np.ndarray:
        """World E, N, H of tile (i, j)'s centre, its local origin [m]."""
        half = 0.5 * self.side_m
        return np.array([self.centre[0] - half + (i + 0.5) * self.tile_m,
                         self.centre[1] - half + (j + 0.5) * self.tile_m, self.centre[2]])

    def tile_at(self, east: float, north: float) -> tuple[int, int]:
        """The tile under a world position (the nearest edge tile outside the grid)."""
        half = 0.5 * self.side_m
        return tuple(int(np.clip(math.floor((v - c + half) / self.tile_m), 0, self.n - 1))
                     for v, c in ((east, self.centre[0]), (north, self.centre[1])))

    def tiles_within(self, lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int]]:
        """Tiles whose square meets the world rectangle [lo, hi] (E, N) [m], row by row."""
        half = 0.5 * self.side_m
        first = [max(0, math.floor((lo[a] - self.centre[a] + half) / self.tile_m)) for a in range(2)]
        last = [min(self.n - 1, math.floor((hi[a] - self.centre[a] + half) / self.tile_m)) for a in range(2)]
        return [(i, j) for j in range(first[1], last[1] + 1) for i in range(first[0], last[0] + 1)]

    def template(self) -> Scene:
        """One tile's scene about its own origin (every tile is a copy)."""
        return _template(self.kind, self.tile_m, self.crs)

    def assemble(self, tiles: list[tuple[int, int]], origin_tile: tuple[int, int]) -> tuple[Scene, np.ndarray]:
        """The scene of ``tiles`` in the local frame of ``origin_tile``, and the survey-wide plane id of
        each of its triangles (tile (i, j)'s plane p is j·n·P + i·P + p, P planes per tile)."""
        template = self.template()
        origin = self.tile_origin(*origin_tile)
        n_planes = len(template.planes)
        vertices, triangles, plane_id, planes, global_plane = [], [], [], [], []
        for k, (i, j) in enumerate(tiles):
            shift = self.tile_origin(i, j) - origin  # whole tiles: exact in float64
            vertices.append(template.vertices + shift)
            triangles.append(template.triangles + k * len(template.vertices))
            plane_id.append(template.plane_id + k * n_planes)
            planes += [dataclasses.replace(p, id=k * n_planes + p.id, point=p.point + shift) for p in template.planes]
            global_plane.append(template.plane_id + (j * self.n + i) * n_planes)
        scene = Scene(name="survey", crs=template.crs, origin=origin, vertices=np.concatenate(vertices),
                      triangles=np.concatenate(triangles), plane_id=np.concatenate(plane_id),
                      classification=np.tile(template.classification, len(tiles)), planes=planes,
                      ground_z=template.ground_z)
        return scene, np.concatenate(global_plane).astype(np.int32)


@functools.lru_cache(maxsize=4)
def _template(kind: str, tile_m: int, crs: str) -> Scene:
    half = 0.5 * tile_m
    if kind == "plane":
        return plane_scene(half, (0.0, 0.0, 0.0), parse_crs(crs))
    return calibration_scene(half, (0.0, 0.0, 0.0), parse_crs(crs))


# ---------------------------------------------------------------------------------------------
# the plan: lines, tasks and merges


@dataclass(frozen=True)
class SegmentTask:
    """One task: pulses [k0, k1) of one flight line, over the tiles they can reach."""

    name: str  # "L<line>-S<segment>", in task order
    line: FlightLine
    pulses: tuple[int, int]
    tiles: tuple[tuple[int, int], ...]  # scene tiles within reach
    origin_tile: tuple[int, int]  # the tile whose origin is the task's local origin
    las_tiles: tuple[str, ...]  # LAS tiles (file names) its points can fall in


@dataclass
class SurveyPlan:
    """Everything decided before any task runs."""

    cfg: RunConfig  # resolved; flight.lines, line_spacing_m and duration_s as flown
    spec: SurveySpec
    grid: TileGrid
    swath_m: float
    reach_m: float
    tasks: list[SegmentTask]

    @property
    def merges(self) -> dict[tuple[str, str], list[str]]:
        """{(model, LAS tile): names of the tasks that can write points into it, in task order}."""
        merges: dict[tuple[str, str], list[str]] = {}
        for task in self.tasks:
            for tile in task.las_tiles:
                for model in self.cfg.output.models:
                    merges.setdefault((model, tile), []).append(task.name)
        return dict(sorted(merges.items()))

    @property
    def pulses(self) -> int:
        return sum(t.pulses[1] - t.pulses[0] for t in self.tasks)


def plan_survey(cfg: RunConfig, spec: SurveySpec) -> SurveyPlan:
    """Lay out the tile grid, the flight lines and the tasks of a survey (validated config and spec)."""
    spec = spec.validated()
    f, s = cfg.flight, cfg.risley
    _check_survey_config(cfg, spec)
    n = max(1, math.ceil(spec.size_km * 1000.0 / spec.tile_m - 1e-9))
    grid = TileGrid(cfg.scene.name, cfg.scene.crs, tuple(cfg.scene.origin), spec.tile_m, n)
    template = grid.template()
    top = float(template.vertices[:, 2].max())
    if f.altitude_m <= top + MIN_CLEARANCE_M:
        raise InputError("flight.altitude_m", f.altitude_m,
                         f"an altitude above {top + MIN_CLEARANCE_M:g} m (the tiles' roofs reach {top:g} m)")
    swath = 2.0 * f.altitude_m * math.tan(math.radians(s.cone_half_angle_deg))
    spacing = swath * (1.0 - spec.sidelap)
    lines = spec.lines or max(1, math.ceil(grid.side_m / spacing - 1e-9))
    flown = copy_config(cfg)
    flown.flight.lines, flown.flight.line_spacing_m = lines, spacing
    flown.flight.duration_s = grid.side_m / (f.speed_kmh / 3.6)
    flown = validate(flown)
    boresight = cfg.instrument.boresight_deg
    tilt = abs(f.roll_deg) + abs(f.pitch_deg) + abs(boresight[0]) + abs(boresight[1])
    angle = math.degrees(Instrument(cfg).max_off_axis_rad()) + tilt + REACH_MARGIN_DEG
    if angle >= MAX_REACH_DEG:
        raise InputError("risley.cone_half_angle_deg", s.cone_half_angle_deg,
                         f"a scan whose beams stay within {MAX_REACH_DEG:g} deg of nadir (with tilt and fan)")
    reach = f.altitude_m * math.tan(math.radians(angle)) + cfg.scene.margin_m
    try:
        planned = plan_parallel_lines(grid.centre[0], grid.centre[1], f.heading_deg, grid.side_m, f.altitude_m,
                                      lines, spacing, speed_mps=f.speed_kmh / 3.6, roll_deg=f.roll_deg,
                                      pitch_deg=f.pitch_deg, start_gps_time=f.start_gps_time)
    except TrajectoryError as exc:
        raise InputError(exc.field, exc.value, exc.allowed) from None
    timing = Instrument(flown).deflector.timing()
    tasks = [task for line in planned for task in _segments(line, grid, flown, spec, timing, reach)]
    return SurveyPlan(flown, spec, grid, swath, reach, tasks)


def _check_survey_config(cfg: RunConfig, spec: SurveySpec) -> None:
    f = cfg.flight
    for name, value, allowed in (("instrument.deflector", cfg.instrument.deflector, "risley"),
                                 ("instrument.detector", cfg.instrument.detector, "discrete"),
                                 ("flight.platform", f.platform, "lines")):
        if value != allowed:
            raise InputError(name, value, f"{allowed} for a survey (the airborne instrument's flight lines)")
    if cfg.scene.name not in ("calibration", "plane"):
        raise InputError("scene.name", cfg.scene.name, "calibration or plane (the content of every survey tile)")
    if cfg.scene.values().get("slope", 0.0) != 0.0:
        raise InputError("scene.slope", cfg.scene.slope, "0 for a survey (tiles of flat ground join up)")
    if f.trajectory:
        raise InputError("flight.trajectory", f.trajectory, "no trajectory file for a survey (it plans its lines)")
    if f.heading_deg % 180.0 != 0.0:
        raise InputError("flight.heading_deg", f.heading_deg, "0 or 180 for a survey (lines run north-south)")
    if cfg.scene.name == "calibration" and spec.tile_m <= 2 * calibration_min_half_extent():
        raise InputError("survey.tile_m", spec.tile_m,
                         f"more than {2 * calibration_min_half_extent():g} m (the calibration block and a margin)")


def _segments(line: FlightLine, grid: TileGrid, cfg: RunConfig, spec: SurveySpec, timing: PulseTiming,
              reach: float) -> list[SegmentTask]:
    """The tasks of one line: consecutive pulse ranges of ``segment_m`` along track."""
    trajectory = line.trajectory(ground_height_m=grid.centre[2])
    n_pulses = timing.pulse_count(trajectory.start_time, trajectory.end_time)
    per_task = max(1, round(spec.segment_m / line.speed_mps * timing.prf_hz))
    size = cfg.output.tile_size_m
    tasks = []
    for k, k0 in enumerate(range(0, n_pulses, per_task)):
        k1 = min(k0 + per_task, n_pulses)
        ends, _ = trajectory.interpolate(timing.pulse_times(trajectory.start_time, [k0, k1 - 1]))
        lo, hi = ends[:, :2].min(axis=0) - reach, ends[:, :2].max(axis=0) + reach
        middle = ends[:, :2].mean(axis=0)
        las = [f"{i * size}_{j * size}.las" for j in range(math.floor(lo[1] / size), math.floor(hi[1] / size) + 1)
               for i in range(math.floor(lo[0] / size), math.floor(hi[0] / size) + 1)]
        tasks.append(SegmentTask(f"L{line.line_id:05d}-S{k:05d}", line, (k0, k1), tuple(grid.tiles_within(lo, hi)),
                                 grid.tile_at(*middle), tuple(las)))
    return tasks
