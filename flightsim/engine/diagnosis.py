"""Why a run made nothing: a run whose product is empty (no return, photon or waveform) says why, in one line, so
that zero output is never silent (the command line prints it and exits 2; summary.json records it)."""
from __future__ import annotations

import math

import numpy as np

from flightsim.engine.coverage import miss_distance

SAMPLE_SLOTS = 1 << 14  # rays sampled to measure how far apart the beams land
NEAREST = 32  # ground points nearest the scene whose spacing is the local spacing of the pattern


def empty_reason(tracer, counts) -> str:
    """The most specific reason ``tracer``'s run (its ``counts``) made nothing."""
    cfg = tracer.cfg
    if counts.pulses == 0:
        return _no_pulse(tracer, counts)
    altitude, max_range = cfg.flight.altitude_m, cfg.instrument.max_range_m
    if altitude >= max_range:
        return (f"the altitude flight.altitude_m = {altitude:g} m is beyond instrument.max_range_m = {max_range:g} m: "
                f"no beam reaches the ground (raise instrument.max_range_m or fly lower)")
    if counts.tir_dropped == counts.beams_fired:
        return (f"every one of the {counts.beams_fired} beams was totally internally reflected in the "
                f"{cfg.instrument.deflector} deflector: none left the instrument")
    if counts.dark > 0 and counts.dark + counts.misses + counts.tir_dropped == counts.beams_fired:
        d = cfg.discrete
        return (f"{counts.dark} beams hit the scene but every echo under the canopy stayed below discrete.threshold "
                f"= {d.threshold:g} (the surfaces' albedo discrete.reflectance = {d.reflectance:g} dimmed by the "
                f"leaves, the leaves' reflectance {tracer.scene.canopy.leaf_reflectance:g}): lower the threshold")
    if counts.misses + counts.tir_dropped < counts.beams_fired:
        return _hits_without_output(tracer, counts)
    return _uncovered(tracer, counts)


def _no_pulse(tracer, counts) -> str:
    if counts.pulses_culled == 0:
        return "the flight fires no pulse (its duration is shorter than one pulse interval)"
    miss = min(miss_distance(t, tracer.scene.world_to_local(t.position), tracer.scene.bounds(), tracer.cone_rad,
                             tracer.boresight_quat) for t in tracer.trajectories)
    return (f"the swath misses the scene by {max(miss, 0.0):.1f} m: none of the {counts.pulses_culled} pulses can "
            f"reach it (the beams reach at most {math.degrees(tracer.cone_rad):.2f} deg from the sensor axis; move "
            f"the flight over the scene, or the scene under it)")


def _hits_without_output(tracer, counts) -> str:
    hits = counts.beams_fired - counts.misses - counts.tir_dropped
    detector = tracer.instrument.detector
    gate = getattr(getattr(detector, "s", None), "gate_m", None)
    if gate is not None:
        return (f"{hits} beams hit the scene but no photon was detected: check the range gate photon.gate_m = "
                f"[{gate[0]:g}, {gate[1]:g}] m against the ranges flown (about {tracer.cfg.flight.altitude_m:g} m) "
                f"and the link budget of [photon]")
    return f"{hits} beams hit the scene but the {tracer.cfg.instrument.detector} detector made nothing of them"


def _uncovered(tracer, counts) -> str:
    """Every beam missed a scene within the swath's reach: the scan pattern leaves it uncovered, or it falls between
    the beams' footprints."""
    lo, hi = tracer.scene.bounds()
    size = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    ground = ground_points(tracer)
    gap = np.hypot(np.maximum(np.maximum(lo[0] - ground[:, 0], ground[:, 0] - hi[0]), 0.0),
                   np.maximum(np.maximum(lo[1] - ground[:, 1], ground[:, 1] - hi[1]), 0.0))
    spacing = _local_spacing_m(ground, 0.5 * (lo[:2] + hi[:2]))
    if len(gap) and gap.min() > 2.0 * spacing:
        return (f"all {counts.beams_fired} beams missed the scene ({size:.2f} m across): the scan pattern leaves it "
                f"uncovered, the nearest beam landing {gap.min():.2f} m from it while the beams land about "
                f"{spacing:.2f} m apart (e.g. inside a conical scan's ring: fly longer or move the flight)")
    footprint = tracer.cfg.flight.altitude_m * tracer.instrument.emitter.divergence_mrad * 1e-3
    return (f"all {counts.beams_fired} beams missed the scene: it is {size:.2f} m across, the beams land about "
            f"{spacing:.2f} m apart with {footprint:.2f} m footprints, so it falls between them (fly lower, denser "
            f"or longer, or widen the scene)")


def ground_points(tracer) -> np.ndarray:
    """(n, 2) local points [m] where the run's first beams (up to SAMPLE_SLOTS) meet the scene's lowest height."""
    starts, directions = (a.numpy().astype(np.float64) for a in tracer.sample_rays(SAMPLE_SLOTS))
    floor = tracer.scene.bounds()[0][2]
    down = directions[:, 2] < -1e-9
    t = (floor - starts[down, 2]) / directions[down, 2]
    return starts[down, :2] + t[:, None] * directions[down, :2]


def _local_spacing_m(ground: np.ndarray, centre: np.ndarray) -> float:
    """Median distance to its nearest neighbour of the NEAREST ground points closest to ``centre`` [m]: how far apart
    the beams land around the scene."""
    from scipy.spatial import cKDTree

    if len(ground) < 2:
        return math.inf
    tree = cKDTree(ground)
    _, near = tree.query(centre, k=min(NEAREST, len(ground)))
    distance, _ = tree.query(ground[np.atleast_1d(near)], k=2)
    return float(np.median(distance[:, 1]))
