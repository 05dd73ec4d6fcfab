"""What is flown over what: the scene and the flight trajectories a config asks for."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable

import numpy as np

from flightsim.core.config import BUILTIN_SCENES, RunConfig
from flightsim.core.errors import InputError
from flightsim.platforms import rotating_body
from flightsim.scenes.meshio import load_mesh
from flightsim.scenes.scene import (Scene, calibration_min_half_extent, calibration_scene, parse_crs, plane_scene,
                             required_half_extent)
from trajectories import Trajectory, TrajectoryError, climb_limited, plan_parallel_lines

MIN_CLEARANCE_M = 1.0  # the sensor must stay at least this far above the terrain [m]
MAX_CLIMB_MPS = 5.0  # terrain following: the fastest climb or descent of a planned line [m/s]
MAX_REACH_DEG = 80.0  # built-in scenes are sized for beams up to this far from nadir [deg]
CLEARANCE_PIECES = 64  # a trajectory's clearance is checked over this many runs of samples


def line_length_m(cfg: RunConfig) -> float:
    """Length of each planned flight line [m]."""
    return cfg.flight.speed_kmh / 3.6 * cfg.flight.duration_s


def scene_half_extent(cfg: RunConfig) -> float:
    """Half side of the built-in scene's square ground that holds every scan circle of the flight [m].

    The lines' rectangle (any heading) grows by the reach of the widest beam: the cone
    half-angle, plus the fan's half-diagonal, plus the sensor axis' largest lean from nadir
    (roll and pitch of the plan and of the boresight), at most MAX_REACH_DEG.
    """
    from flightsim.instrument.parts import HostInstrument

    f, s = cfg.flight, cfg.sensor
    along = line_length_m(cfg) / 2.0 if f.platform == "lines" else 0.0
    if f.platform == "orbit":
        from flightsim.platforms.orbit import BODIES, ground_speed_mps

        along = ground_speed_mps(BODIES[f.body], f.altitude_m, f.eccentricity) * f.duration_s / 2.0
    across = (f.lines - 1) / 2.0 * f.line_spacing_m if f.platform == "lines" else 0.0
    sin_h, cos_h = abs(math.sin(math.radians(f.heading_deg))), abs(math.cos(math.radians(f.heading_deg)))
    reach = max(along * sin_h + across * cos_h, along * cos_h + across * sin_h)
    tilt = abs(f.roll_deg) + abs(f.pitch_deg) + abs(s.boresight_deg[0]) + abs(s.boresight_deg[1])
    angle = min(HostInstrument(cfg).reach_deg() + tilt, MAX_REACH_DEG)
    return required_half_extent(f.altitude_m, math.radians(angle), reach, cfg.scene.margin_m)


def build_scene(cfg: RunConfig, half_extent_m: float | None = None) -> Scene:
    """The scene named by ``cfg.scene``; built-in scenes get ground of ``half_extent_m`` (default:
    just enough for this config's flight, :func:`scene_half_extent`)."""
    crs = parse_crs(cfg.scene.crs, field="scene.crs")
    origin = np.asarray(cfg.scene.origin, dtype=np.float64)
    name = cfg.scene.name
    if name in ("sandbox", "ellipsoid"):  # fixed-size small-body scenes
        from flightsim.scenes import smallbody

        return getattr(smallbody, f"{name}_scene")(origin, crs, seed=cfg.run.seed)
    if name not in ("plane", "calibration", "lunar", "bump"):
        from flightsim.scenes.dem import dem_scene, is_dem

        if is_dem(name):
            return _from_file(cfg, lambda: dem_scene(name, crs, origin, cfg.scene.cell_m, cfg.scene.simplify_m,
                                                     cfg.scene.landcover, cfg.scene.buildings))
        if not Path(name).is_file():
            raise InputError("scene.name", name,
                             f"{', '.join(BUILTIN_SCENES)}, or the path of an existing .obj/.ply mesh or .tif/.npy height grid")
        return _from_file(cfg, lambda: load_mesh(name, crs, origin, planes=cfg.scene.planes))
    half = scene_half_extent(cfg) if half_extent_m is None else half_extent_m  # sized to the flight
    if name == "plane":
        return plane_scene(half, origin, crs, slope=cfg.scene.slope)
    if name == "bump":
        from flightsim.scenes.footprint import bump_scene

        return bump_scene(half, origin, crs)
    if name == "calibration":
        return calibration_scene(max(half, calibration_min_half_extent() + cfg.scene.margin_m), origin, crs)
    from flightsim.scenes.lunar import lunar_scene

    return lunar_scene(half, origin, crs, seed=cfg.run.seed, slope=cfg.scene.slope)


def _from_file(cfg: RunConfig, load: Callable[[], Scene]) -> Scene:
    """The scene of the file ``cfg.scene.name``: ``load()``, through the scene cache when ``cfg.run.scene_cache``
    (keyed on every ``scene`` setting, and on the files they name)."""
    if not cfg.run.scene_cache:
        return load()
    from flightsim.scenes.cache import cached_scene

    options = {f.name: getattr(cfg.scene, f.name) for f in dataclasses.fields(cfg.scene)}
    return cached_scene(cfg.scene.name, options, load, grid_device=cfg.run.device)


def _planned_lines(cfg: RunConfig, scene: Scene) -> list[Trajectory]:
    f = cfg.flight
    lo, hi = scene.bounds()
    centre = scene.local_to_world(np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, scene.ground_z]))
    lines = plan_parallel_lines(
        centre[0], centre[1], f.heading_deg, line_length_m(cfg), f.altitude_m, f.lines, f.line_spacing_m,
        speed_mps=f.speed_kmh / 3.6, roll_deg=f.roll_deg, pitch_deg=f.pitch_deg, start_gps_time=f.start_gps_time,
    )
    trajectories = [line.trajectory(ground_height_m=centre[2]) for line in lines]
    if not f.terrain_following:
        return trajectories
    return [_follow_terrain(t, scene, f.altitude_m, MAX_CLIMB_MPS / (f.speed_kmh / 3.6)) for t in trajectories]


def _follow_terrain(trajectory: Trajectory, scene: Scene, altitude_m: float, max_grade: float) -> Trajectory:
    """``trajectory`` at ``altitude_m`` [m] above the ground under each sample (the highest surface
    there, from :attr:`Scene.height_grid`; where there is none, the nearest samples' ground, else the
    scene's ground height), raised where needed so that it climbs and descends at most ``max_grade``
    (rise/run) and never comes lower than that: the least such profile. The attitude is kept."""
    local = scene.world_to_local(trajectory.position)
    ground = scene.height_grid.ground_height(local[:, 0], local[:, 1])
    known = np.isfinite(ground)
    along = np.r_[0.0, np.cumsum(np.hypot(*np.diff(local[:, :2], axis=0).T))]
    if not known.any():
        ground = np.full(len(local), scene.ground_z)
    elif not known.all():
        ground = np.interp(along, along[known], ground[known])
    height = climb_limited(along, ground + altitude_m, max_grade) + scene.origin[2]
    position = np.column_stack([trajectory.position[:, :2], height])
    return Trajectory(trajectory.gps_time, position, trajectory.attitude, trajectory.line_id)


def _clearance(trajectory: Trajectory, scene: Scene, pieces: int = CLEARANCE_PIECES) -> tuple[float, float, float]:
    """(clearance, sensor height, terrain top) [m, local heights] where a trajectory comes closest
    to the terrain.

    The trajectory is cut into up to ``pieces`` runs of consecutive samples; over each run's
    bounding rectangle the terrain's highest point is compared with the run's lowest sample
    (positions are linear between samples, so the rectangle holds the whole run).
    """
    local = scene.world_to_local(trajectory.position)
    bounds = np.unique(np.linspace(0, len(local) - 1, min(pieces, len(local) - 1) + 1).round().astype(int))
    rects, lowest = [], []
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        run = local[i0:i1 + 1]
        rects.append([run[:, 0].min(), run[:, 1].min(), run[:, 0].max(), run[:, 1].max()])
        lowest.append(run[:, 2].min())
    tops = scene.terrain_tops(rects)
    margin = np.asarray(lowest) - tops
    k = int(np.argmin(margin))
    return float(margin[k]), float(lowest[k]), float(tops[k])


def _clear_at_a_glance(trajectory: Trajectory, scene: Scene) -> bool:
    """True when the lowest sample is clear of the height grid's bound of the terrain under the
    trajectory's rectangle (a cheap sufficient test; the exact one runs only when this fails)."""
    local = scene.world_to_local(trajectory.position)
    top = scene.height_grid.top_bound(local[:, 0].min(), local[:, 1].min(), local[:, 0].max(), local[:, 1].max())
    return local[:, 2].min() - top >= MIN_CLEARANCE_M


def _check_clearance(trajectory: Trajectory, scene: Scene, cfg: RunConfig) -> None:
    """Reject a flight whose sensor does not stay at least MIN_CLEARANCE_M above the terrain beneath it
    (over a spinning body: outside the body's sweep)."""
    if cfg.flight.body_rotation_period_s > 0.0:
        rotating_body.check_clearance(trajectory, scene, cfg.flight.altitude_m, MIN_CLEARANCE_M)
        return
    if _clear_at_a_glance(trajectory, scene):
        return
    margin, height, top = _clearance(trajectory, scene)
    if margin >= MIN_CLEARANCE_M:
        return
    if cfg.flight.trajectory:
        raise InputError("flight.trajectory", cfg.flight.trajectory,
                         f"a trajectory at least {MIN_CLEARANCE_M:g} m above the terrain beneath it (it flies at "
                         f"{height + scene.origin[2]:.3f} m over terrain reaching {top + scene.origin[2]:.3f} m)")
    rise = top - scene.ground_z
    raise InputError("flight.altitude_m", cfg.flight.altitude_m,
                     f"an altitude above {rise + MIN_CLEARANCE_M:.3f} m: the terrain beneath the flight rises "
                     f"{rise:.3f} m above the scene's ground (to {top + scene.origin[2]:.3f} m)")


def _hover(cfg: RunConfig, scene: Scene) -> Trajectory:
    """A lander (or tripod) over the scene centre: flight.altitude_m above the ground at the start,
    sinking at flight.descent_mps, level, its sensor axis (body z) down; heading flight.heading_deg.
    Over a body spinning every flight.body_rotation_period_s, the same hover held in inertial space,
    seen from the body (:mod:`flightsim.platforms.rotating_body`)."""
    f = cfg.flight
    lo, hi = scene.bounds()
    centre = scene.local_to_world(np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, scene.ground_z]))
    times = f.start_gps_time + np.array([0.0, f.duration_s])
    heights = centre[2] + f.altitude_m - f.descent_mps * (times - f.start_gps_time)
    position = np.column_stack([np.full(2, centre[0]), np.full(2, centre[1]), heights])
    attitude = np.tile(np.radians([f.roll_deg, f.pitch_deg, f.heading_deg % 360.0]), (2, 1))
    hover = Trajectory(times, position, attitude, 1)
    if f.body_rotation_period_s == 0.0:
        return hover
    return rotating_body.spun_hover(hover, scene, f.body_rotation_period_s)


def flight_trajectories(cfg: RunConfig, scene: Scene) -> list[Trajectory]:
    """The trajectories to fly: the trajectory file if one is given, a hover, else the line plan."""
    if cfg.flight.body_rotation_period_s == 0.0:  # clearance and terrain following read the height grid
        scene.build_height_grid(cfg.run.device)
    try:
        if cfg.flight.platform == "hover":
            trajectories = [_hover(cfg, scene)]
        elif cfg.flight.platform == "orbit":
            from flightsim.platforms.orbit import orbit_trajectory

            trajectories = [orbit_trajectory(cfg.flight, scene)]
        elif cfg.flight.trajectory:
            trajectories = [Trajectory.read_csv(cfg.flight.trajectory)]
        else:
            trajectories = _planned_lines(cfg, scene)
    except TrajectoryError as exc:
        raise InputError(exc.field, exc.value, exc.allowed) from None
    for trajectory in trajectories:
        _check_clearance(trajectory, scene, cfg)
    return trajectories

