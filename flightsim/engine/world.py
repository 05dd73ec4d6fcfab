"""What is flown over what: the scene a config asks for, sized to its flight, the trajectories its platform
flies over it, and the edge buffer its returns are scored with."""
from __future__ import annotations

import math

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.engine.instrument import Instrument
from flightsim.platforms.earth_orientation import USE_CACHE
from flightsim.scenes.build import build_scene as build_scene_of
from flightsim.scenes.scene import Scene, required_half_extent
from trajectories import Trajectory, TrajectoryError

MAX_REACH_DEG = 80.0  # built-in scenes are sized for beams up to this far from nadir [deg]


def platform(cfg):
    """The platform part of ``cfg``'s [flight]."""
    return registry.part("platform", cfg.flight.platform, "flight.platform")(cfg.flight)


def scene_half_extent(cfg) -> float:
    """Half side of the built-in scene's square ground that holds every scan circle of the flight [m].

    The lines' rectangle (any heading) grows by the reach of the widest beam: the deflector's reach, plus the
    detector's footprint, plus the sensor axis' largest lean from nadir (the platform's roll and pitch and the
    boresight's), at most MAX_REACH_DEG.
    """
    along, across, heading = platform(cfg).spans()
    sin_h, cos_h = abs(math.sin(math.radians(heading))), abs(math.cos(math.radians(heading)))
    reach = max(along * sin_h + across * cos_h, along * cos_h + across * sin_h)
    boresight = cfg.instrument.boresight_deg
    tilt = platform(cfg).tilt_deg() + abs(boresight[0]) + abs(boresight[1])
    angle = min(Instrument(cfg).reach_deg() + tilt, MAX_REACH_DEG)
    return required_half_extent(cfg.flight.altitude_m, math.radians(angle), reach, cfg.scene.margin_m)


def build_scene(cfg, half_extent_m: float | None = None, cloud_leaves: bool = True) -> Scene:
    """The scene named by ``cfg.scene``; built-in scenes get ground of ``half_extent_m`` (default: just enough
    for this config's flight, :func:`scene_half_extent`); ``cloud_leaves``: see
    :func:`flightsim.scenes.build.build_scene`."""
    from flightsim.scenes.build import scene_part

    sized = getattr(scene_part(cfg.scene), "sized", False)
    half = (scene_half_extent(cfg) if half_extent_m is None else half_extent_m) if sized else 0.0
    return build_scene_of(cfg.scene, half, cfg.run.seed, cfg.run.scene_cache, cfg.run.device, cloud_leaves)


def planning_kernels(cfg, scene: Scene) -> list:
    """The kernels :func:`flight_trajectories` launches over ``scene`` (its height grid, unless built or read from
    the scene cache already), for :func:`flightsim.engine.run.compile_setup`: (kernel, None = the run's device)."""
    if getattr(platform(cfg), "rotating", False) or scene.height_grid_built:
        return []
    from kernels import height_grid

    return [(height_grid.triangle_boxes, None)]


def flight_trajectories(cfg, scene: Scene) -> list[Trajectory]:
    """The trajectories the platform flies over ``scene``, each checked clear of the terrain."""
    flying = platform(cfg)
    if not getattr(flying, "rotating", False):  # clearance and terrain following read the height grid
        scene.build_height_grid(cfg.run.device)
    caching = USE_CACHE.set(cfg.run.scene_cache)  # an orbit's Earth orientation table, as the scene
    try:
        return flying.trajectories(scene)
    except TrajectoryError as exc:
        raise InputError(exc.field, exc.value, exc.allowed) from None
    finally:
        USE_CACHE.reset(caching)


def edge_buffer_m(cfg) -> float:
    """The run's edge buffer [m]: ``scoring.edge_buffer_m``, or when it is negative (automatic) one covering the
    footprint and the rigid-array distortion at the altitude flown: slant range h / cos θ times (divergence/2 +
    the largest distortion angle)."""
    value = cfg.scoring.edge_buffer_m
    if value >= 0.0:
        return value
    instrument = Instrument(cfg)
    return instrument.deflector.edge_buffer_m(cfg.flight.altitude_m, instrument.emitter.divergence_mrad)
