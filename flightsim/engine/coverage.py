"""Which pulses can reach the scene: time windows culled on the host before anything is launched.

A pulse's sub-beams all leave within the cone of half-angle θ_max about the sensor axis (the
largest exit angle of the fan over a prism turn). Over flat-topped ground the cone's footprint
lies within horizontal distance (height above the scene's lowest point)·tan(tilt + θ_max) of
the sensor, tilt being the sensor axis' angle from nadir. A trajectory segment whose footprint
cannot reach the scene's bounding rectangle launches no pulse.
"""
from __future__ import annotations

import math

import numpy as np

from trajectories import PulseTiming, Trajectory, prime_quaternions, rotation

MARGIN_RAD = math.radians(1.0)  # added to the fan's largest exit angle
NO_CULLING_RAD = math.radians(80.0)  # cones wider than this reach everywhere: keep every pulse


def _reach(quat: np.ndarray, local_position: np.ndarray, boresight: np.ndarray, cone: float,
           floor_z: float) -> np.ndarray:
    """Horizontal reach of each sample's beam cone [m]; inf where the cone is too wide to bound.

    quat: (n, 4) quaternions (x, y, z, w) of the body frame; boresight: (4,) quaternion of the sensor
    frame in the body frame."""
    sensor = rotation.multiply(rotation.normalize(quat), boresight)
    axis = rotation.rotate(sensor, [0.0, 0.0, 1.0])
    tilt = np.arccos(np.clip(-axis[:, 2], -1.0, 1.0))
    half_angle = tilt + cone
    depth = np.maximum(local_position[:, 2] - floor_z, 0.0)
    return np.where(half_angle < NO_CULLING_RAD, depth * np.tan(np.minimum(half_angle, NO_CULLING_RAD)), np.inf)


def _gap(local_position: np.ndarray, bounds: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Horizontal distance of each sample to the scene's bounding rectangle [m] (0 inside)."""
    lo, hi = bounds
    dx = np.maximum(np.maximum(lo[0] - local_position[:, 0], local_position[:, 0] - hi[0]), 0.0)
    dy = np.maximum(np.maximum(lo[1] - local_position[:, 1], local_position[:, 1] - hi[1]), 0.0)
    return np.hypot(dx, dy)


def miss_distance(trajectory: Trajectory, local_position: np.ndarray, bounds: tuple[np.ndarray, np.ndarray],
                  cone_rad: float, boresight: np.ndarray) -> float:
    """How far the beams' reach stays from the scene's bounding rectangle over a trajectory's samples [m]: the
    least gap less reach (without the culling margin); ≤ 0 where they can reach it."""
    reach = _reach(trajectory.quaternions(), local_position, boresight, cone_rad, bounds[0][2])
    return float(np.min(_gap(local_position, bounds) - reach))


def pulse_windows(trajectories: list[Trajectory], local_positions: list[np.ndarray],
                  bounds: tuple[np.ndarray, np.ndarray], timing: PulseTiming, cone_rad: float,
                  boresight: np.ndarray, counts: list[int] | None = None) -> list[list[tuple[int, int]]]:
    """For each trajectory, the ranges [k0, k1) of pulse indices (from its first pulse) that can reach the scene.

    local_positions: each trajectory's (n, 3) positions in the scene's local frame [m]; bounds: the scene's local
    (lo, hi) corners; cone_rad: the fan's largest off-axis angle [rad]; boresight: (4,) quaternion (x, y, z, w) of
    the sensor frame in the body frame; counts: each trajectory's pulse count (``timing.pulse_count`` over it), when
    the caller has them. The samples of all trajectories are worked out together (a shots run flies a two-sample
    line per footprint, their quaternions too: :func:`trajectories.trajectory.prime_quaternions`), and so are the
    lines with a single segment near the scene.
    """
    sizes = np.array([len(p) for p in local_positions])
    position = np.concatenate(local_positions)
    prime_quaternions(trajectories)
    quat = np.concatenate([t.quaternions() for t in trajectories])
    reach = _reach(quat, position, boresight, cone_rad + MARGIN_RAD, bounds[0][2])
    beyond = _gap(position, bounds) - reach  # horizontal distance from the reach to the scene's rectangle [m]
    step = np.linalg.norm(np.diff(position[:, :2], axis=0), axis=1)
    # a segment may come closer than its ends by up to half its length (segments across two lines left out below)
    near = np.minimum(beyond[:-1], beyond[1:]) - 0.5 * step <= 0.0
    ends = np.cumsum(sizes)
    near[ends[:-1] - 1] = False
    if counts is None:
        counts = [timing.pulse_count(t.start_time, t.end_time) for t in trajectories]
    first = ends - sizes  # each trajectory's first segment (segment j joins samples j and j + 1)
    rel = np.concatenate([t.gps_time for t in trajectories]) - np.repeat([t.start_time for t in trajectories], sizes)
    near_count = np.add.reduceat(near.astype(np.int64), first) if len(near) else np.zeros(len(sizes), np.int64)
    lone = _lone_windows(near, first, rel, np.array(counts, dtype=np.int64), timing.prf_hz)
    return [lone.get(i, []) if c <= 1 else _windows(t, near[f:f + size - 1], count, timing.prf_hz)
            for i, (t, c, f, size, count) in enumerate(zip(trajectories, near_count.tolist(), first.tolist(),
                                                           sizes.tolist(), counts))]


def _lone_windows(near: np.ndarray, first: np.ndarray, rel: np.ndarray, counts: np.ndarray,
                  prf_hz: float) -> dict[int, list[tuple[int, int]]]:
    """:func:`_windows` of every trajectory with one near segment at once: {trajectory: [(k0, k1)]} where k1 > k0
    (``rel``: every sample's time from its line's start [s])."""
    segment = np.flatnonzero(near)
    owner = np.searchsorted(first, segment, side="right") - 1
    alone = np.bincount(owner, minlength=len(first))[owner] == 1
    segment, owner = segment[alone], owner[alone]
    k0 = np.maximum(0, np.floor(rel[segment] * prf_hz).astype(np.int64))
    k1 = np.minimum(counts[owner], np.floor(rel[segment + 1] * prf_hz).astype(np.int64) + 2)
    keep = k1 > k0
    return {t: [(a, b)] for t, a, b in zip(owner[keep].tolist(), k0[keep].tolist(), k1[keep].tolist())}


def _windows(trajectory: Trajectory, near: np.ndarray, n_pulses: int, prf_hz: float) -> list[tuple[int, int]]:
    """Pulse index ranges [k0, k1) of a trajectory's segments ``near`` the scene (of its ``n_pulses`` at ``prf_hz``),
    those that meet merged."""
    rel = trajectory.gps_time - trajectory.start_time
    windows: list[tuple[int, int]] = []
    for i in np.flatnonzero(near):
        k0 = max(0, math.floor(rel[i] * prf_hz))
        k1 = min(n_pulses, math.floor(rel[i + 1] * prf_hz) + 2)
        if windows and k0 <= windows[-1][1]:
            windows[-1] = (windows[-1][0], max(windows[-1][1], k1))
        elif k1 > k0:
            windows.append((k0, k1))
    return windows
