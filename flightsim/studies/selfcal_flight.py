"""The flights of the self-calibration study: a nominal-model flight over the calibration field with the wedge, encoder
and boresight errors injected through the error-model settings, the returns of 10 % of the roof planes turned into
outliers, and the raw observables of the points the blind plane finder segments.

Geometry: two lines with reciprocal headings, ``LINE_SPACING_M`` apart, the field's centre between them (a roll error
is a rigid rotation of one straight line's cloud, so a single line cannot see it); the conical scan's front edge
sweeps the house block while the aircraft is h·tanθ before it and its back edge h·tanθ after it, so only the pulses
of those sweeps are traced (pulse windows), and only the points over the block (its bounding box plus a margin) are
segmented, as a user crops a calibration field.

Outliers: before anything else sees them, the ranges of the returns from a seeded 10 % of the roof planes hit are
changed along their rays: half of them by a vegetation-like roughness (Gaussian, ``ROUGH_SIGMA_M``), half by a
smooth dome (``DOME_HEIGHT_M`` at the plane's centre, zero at its rim), a non-planar patch. Every georeferencing
model sees the same corrupted range, as if the surface were there.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.constants import ARCSEC
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.instrument import Instrument
from flightsim.studies.selfcal import Observations

ROUGH_SIGMA_M = 0.25  # range scatter of a vegetation-like outlier plane, 1σ [m]
DOME_HEIGHT_M = 0.6  # peak of a non-planar (dome) outlier plane [m]
OUTLIER_FRACTION = 0.10
BLOCK_MARGIN_M = 25.0  # ground kept around the house block [m]
CLASS_BUILDING = 6
LINE_SPACING_M = 100.0  # the two lines (reciprocal headings) pass this far apart, the field's centre between [m]


@dataclass(frozen=True)
class Injected:
    """The errors injected (truth against what the processing believes) and the range noise."""

    refractive_index_error: float = 1.0e-3  # believed − true index
    apex_error_arcsec: float = 36.0  # believed − true apex angle
    encoder_arcsec: float = 30.0  # the wedge stands this far past its reading
    boresight_arcsec: tuple[float, float, float] = (60.0, -40.0, 90.0)  # roll, pitch, yaw
    range_noise_m: float = 0.02

    def apply(self, cfg: RunConfig) -> RunConfig:
        """``cfg`` with these errors set through the risley, pose and ranging settings (validated)."""
        cfg = validate(cfg)
        r = cfg.risley.resolved()
        set_value(cfg, "instrument.errors", "pose,ranging")
        cfg.parts["risley"] = dataclasses.replace(
            cfg.risley, believed_refractive_index=r.refractive_index + self.refractive_index_error,
            believed_apex_angle_deg=r.apex_angle_deg + self.apex_error_arcsec / 3600.0,
            encoder_arcsec=self.encoder_arcsec)
        cfg.parts["pose"] = dataclasses.replace(cfg.pose, boresight_arcsec=tuple(self.boresight_arcsec))
        cfg.parts["ranging"] = dataclasses.replace(cfg.ranging, noise_m=self.range_noise_m)
        return validate(cfg)


def parameters(cfg: RunConfig) -> tuple[np.ndarray, np.ndarray]:
    """(true x, believed x0) of a config: (n, α [rad], δφ [rad], roll, pitch, yaw [rad])."""
    r = cfg.risley.resolved()
    boresight = cfg.pose.boresight_arcsec if "pose" in cfg.instrument.errors else (0.0, 0.0, 0.0)
    truth = np.array([r.refractive_index, math.radians(r.apex_angle_deg), r.encoder_arcsec * ARCSEC,
                      *(b * ARCSEC for b in boresight)])
    believed = np.array([r.believed_refractive_index, math.radians(r.believed_apex_angle_deg), 0.0, 0.0, 0.0, 0.0])
    return truth, believed


def flight_config(altitude_m: float, array: int, device: str = "cpu", injected: Injected = Injected(),
                  seed: int = 0) -> RunConfig:
    """Two lines over the calibration field, long enough for both sweeps of the block, errors injected."""
    from flightsim.scenes.calibration import calibration_min_half_extent

    cfg = RunConfig()
    half = calibration_min_half_extent()
    reach = altitude_m * math.tan(math.radians(cfg.risley.cone_half_angle_deg))
    speed = cfg.flight.speed_kmh / 3.6
    for key, value in (("scene.name", "calibration"), ("flight.altitude_m", altitude_m), ("fan.array", array),
                       ("flight.duration_s", round((2 * (reach + half) + 2 * BLOCK_MARGIN_M) / speed, 2)),
                       ("flight.lines", 2), ("flight.line_spacing_m", LINE_SPACING_M),
                       ("output.models", "exact,nominal"), ("run.device", device), ("run.seed", seed)):
        set_value(cfg, key, value)
    return injected.apply(cfg)


def sweep_windows(trajectory, timing, reach_m: float, half_m: float) -> list[tuple[int, int]]:
    """Pulse windows [k0, k1) of the front and back sweeps: the aircraft's along-track distance from the field's
    centre (the line's middle) within reach ± half [m] (one window where they overlap)."""
    count = timing.pulse_count(trajectory.start_time, trajectory.end_time)
    t = timing.pulse_times(trajectory.start_time, np.arange(count))
    xy = trajectory.position[:, :2]
    along = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
    s = np.interp(t, trajectory.gps_time, along) - along[-1] / 2.0
    windows = []
    for centre in (-reach_m, reach_m):
        k = np.flatnonzero(np.abs(s - centre) <= half_m)
        if len(k):
            windows.append((int(k[0]), int(k[-1]) + 1))
    windows.sort()
    if len(windows) == 2 and windows[1][0] <= windows[0][1]:
        windows = [(windows[0][0], max(windows[0][1], windows[1][1]))]
    return windows


@dataclass
class Flight:
    """The returns of a flight (host arrays, one row per return) and every traced pulse's believed pose."""

    cfg: RunConfig
    scene: object
    pulse: np.ndarray  # (m,) index into the pose arrays
    beam: np.ndarray
    range_m: np.ndarray  # float64 [m]
    face: np.ndarray
    nominal: np.ndarray  # (m, 3) the flight's nominal-model points [m, local]
    true_points: np.ndarray  # (m, 3) the true hits [m, local]
    origin: np.ndarray  # (P, 3)
    rot: np.ndarray  # (P, 3, 3)
    phi: np.ndarray  # (P,)


def fly(cfg: RunConfig) -> Flight:
    """Trace the two sweeps of the config's line on its device (the engine, points readout, truth kept)."""
    from flightsim.engine.meshes import SceneMeshes
    from flightsim.engine.readouts.points import Points
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories
    from flightsim.core.warp_runtime import resolve_device
    from flightsim.scenes.calibration import calibration_min_half_extent

    scene = build_scene(cfg)
    trajectories = flight_trajectories(cfg, scene)
    meshes = SceneMeshes(scene, resolve_device(cfg.run.device))
    timing = Instrument(cfg).deflector.timing()
    reach = cfg.flight.altitude_m * math.tan(math.radians(cfg.risley.resolved().cone_half_angle_deg))
    parts, poses = [], []
    windows = [(t, w) for t in trajectories
               for w in sweep_windows(t, timing, reach, calibration_min_half_extent() + BLOCK_MARGIN_M)]
    for trajectory, (k0, k1) in windows:
        sim = Tracer(cfg, scene, [trajectory], with_truth=True, meshes=meshes,
                     pulse_limits={trajectory.line_id: (k0, k1)})
        chunks, offset = [], sum(len(p["phi"]) for p in poses)
        sim.run(Points(), lambda c: chunks.append(_columns(c, offset - k0)))
        pose = sim.poses64(trajectory.line_id, k0, k1 - k0).numpy()
        poses.append({"origin": pose["origin"], "rot": pose["rot"].reshape(-1, 3, 3), "phi": pose["phi"]})
        parts += chunks
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return Flight(cfg, scene, origin=np.concatenate([p["origin"] for p in poses]).astype(np.float64),
                  rot=np.concatenate([p["rot"] for p in poses]).astype(np.float64),
                  phi=np.concatenate([p["phi"] for p in poses]).astype(np.float64), **cat)


def _columns(c, shift: int) -> dict:
    """A host chunk's columns the self-calibration uses (float64), pulses shifted to the pose rows."""
    return dict(pulse=c.pulse + shift, beam=c.beam, range_m=c.range_m.astype(np.float64), face=c.face,
                nominal=c.points["nominal"].astype(np.float64), true_points=c.true_points.astype(np.float64))


def inject_outliers(flight: Flight, fraction: float = OUTLIER_FRACTION, seed: int = 0) -> np.ndarray:
    """Corrupt the ranges of a seeded ``fraction`` of the roof planes hit (in place), and move the flight's nominal
    points along their rays by the same amounts; return the planes' ids.

    Even draws get the roughness, odd ones the dome (on the true hits' horizontal distance from the plane's centroid).
    """
    scene = flight.scene
    plane = scene.plane_id[flight.face]
    roofs = np.unique(plane[scene.classification[flight.face] == CLASS_BUILDING])
    roofs = np.array([p for p in roofs if scene.planes[p].kind == "roof"], dtype=np.int64)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(roofs, size=math.ceil(fraction * len(roofs)), replace=False) if len(roofs) else []
    for k, p in enumerate(chosen):
        on = np.flatnonzero(plane == p)
        if k % 2 == 0:
            change = rng.normal(0.0, ROUGH_SIGMA_M, len(on))
        else:
            xy = flight.true_points[on, :2]
            d = np.hypot(*(xy - xy.mean(axis=0)).T)
            change = -DOME_HEIGHT_M * np.clip(1.0 - (d / max(d.max(), 1e-9)) ** 2, 0.0, 1.0)
        flight.range_m[on] += change
        ray = flight.nominal[on] - flight.origin[flight.pulse[on]]  # the nominal ray, to 1e-5 of the change
        flight.nominal[on] += change[:, None] * ray / np.linalg.norm(ray, axis=1, keepdims=True)
    return np.asarray(chosen, dtype=np.int64)


def observations(flight: Flight, index: np.ndarray, segment: np.ndarray | None = None) -> Observations:
    """The raw observables of the flight's returns ``index`` (segment ids given, or all 0)."""
    fan = Instrument(flight.cfg).emitter
    segment = np.zeros(len(index), np.int64) if segment is None else np.asarray(segment, np.int64)
    return Observations(flight.origin, flight.rot, flight.phi, flight.pulse[index], flight.beam[index],
                        flight.range_m[index], segment, fan.n, fan.spacing_rad,
                        flight.cfg.risley.resolved().thickness_mm * 1e-3)


def crop(flight: Flight) -> np.ndarray:
    """Indices of the returns whose nominal points lie over the house block (plus a margin), as a user crops."""
    from flightsim.scenes.calibration import calibration_min_half_extent

    half = calibration_min_half_extent() + BLOCK_MARGIN_M
    return np.flatnonzero(np.all(np.abs(flight.nominal[:, :2]) <= half, axis=1))


def segment_blindly(flight: Flight, inside: np.ndarray, xyz: np.ndarray):
    """Blind planes of the points ``xyz`` of the returns ``inside`` (the LAS classification a user has, no plane
    ids): (the returns fitted, their segment ids 0 … S − 1, the blind result)."""
    from flightsim.scoring.blind import extract_planes

    result = extract_planes(xyz, flight.scene.classification[flight.face[inside]])
    used = np.flatnonzero(result.used)
    segment = np.unique(result.labels[used], return_inverse=True)[1]
    return inside[used], segment.astype(np.int64), result


def solver_subset(obs: Observations, max_points: int = 40_000, per_segment: int = 1500, seed: int = 0):
    """At most ``per_segment`` points of each segment and ``max_points`` in all, chosen by pulse (whole pulses
    first, so that the fans traced per evaluation are few)."""
    rng = np.random.default_rng(seed)
    priority = rng.permutation(len(obs.phi))[obs.pulse]
    order = np.lexsort((priority, obs.segment))
    rank = np.arange(len(order)) - np.searchsorted(obs.segment[order], obs.segment[order])
    chosen = order[rank < per_segment]
    if len(chosen) > max_points:
        chosen = chosen[np.argsort(priority[chosen], kind="stable")[:max_points]]
    return obs.subset(np.sort(chosen))


def compile_selfcal(device: str = "cpu") -> int:
    """Compile into Warp's kernel cache (or load from it) the kernels `flightsim selfcal` launches (``flightsim compile
    --for selfcal``): the flight of its quick configuration (3×3 at 1 km) traced once, whose kernels are every
    configuration's; the calibration's own fan tracing is the Risley instrument's (prebuilt with it); returns the
    modules loaded."""
    from flightsim.core.warp_runtime import loaded_modules

    fly(flight_config(1000.0, 3, device))
    return loaded_modules()
