"""Per-pulse sensor pose on the device: trajectory interpolation, prism phase, frame rotations.

One thread per pulse. The trajectories of every line of a run arrive once, concatenated, as
float64 samples in the scene's local frame (world minus the scene origin, subtracted on the host
in float64). A chunk of pulses may hold pieces (segments) of several lines, so short lines do not
cost a launch each. Poses leave in float32 and float64, ready for the per-beam kernels (SPEC §2).
"""
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

TWO_PI = wp.constant(wp.float64(6.283185307179586))


@wp.struct
class Lines:
    """Every flight line of a run, samples concatenated (local frame)."""

    times: wp.array(dtype=wp.float64)  # sample times relative to the line's pulse 0 [s]
    positions: wp.array(dtype=wp.vec3d)  # body origin [m]
    attitudes: wp.array(dtype=wp.quatd)  # R_local←body, sign-continuous within a line
    sample_start: wp.array(dtype=wp.int32)  # first sample of each line
    sample_count: wp.array(dtype=wp.int32)  # samples of each line (≥ 2)
    cycles0: wp.array(dtype=wp.float64)  # prism phase of each line's pulse 0 [turns]
    seed: wp.array(dtype=wp.int32)  # noise seed of each line
    boresight: wp.quatd  # R_body←sensor
    lever_arm: wp.vec3d  # sensor origin in the body frame [m]
    pulse_period: wp.float64  # 1 / PRF [s]
    cycles_per_pulse: wp.float64  # f_rot / PRF [turns]


@wp.struct
class Segments:
    """The pieces of lines one chunk of pulses holds, in chunk order."""

    pulse_start: wp.array(dtype=wp.int32)  # first chunk pulse of each segment, ascending
    line: wp.array(dtype=wp.int32)  # index of the segment's line in Lines
    first_pulse: wp.array(dtype=wp.int64)  # line pulse index of the segment's first pulse


@wp.struct
class PulsePose:
    """Sensor pose of one pulse, in the scene's local frame."""

    origin: wp.vec3f  # sensor origin (centre of the prism's front face) [m]
    rot: wp.mat33f  # R_local←sensor
    right: wp.vec3f  # aircraft's right wing (body +y) in the local frame, for the scan-angle sign
    phi: wp.float32  # prism angle, reduced to [0, 2π) [rad]
    origin64: wp.vec3d  # the same in float64, for the float64 optics path
    rot64: wp.mat33d
    phi64: wp.float64
    pulse: wp.int64  # pulse index within its line
    seed: wp.int32  # noise seed of its line


@wp.struct
class PulsePose64:
    """Sensor pose of one pulse in float64, for the reference path."""

    origin: wp.vec3d  # [m]
    rot: wp.mat33d  # R_local←sensor
    phi: wp.float64  # [rad]


@wp.func
def _last_at_or_below(values: wp.array(dtype=Any), begin: int, count: int, x: Any):
    """Largest i in [begin, begin + count − 1) with values[i] ≤ x (binary search; ascending values)."""
    lo = begin
    hi = begin + count - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if values[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def prism_angle(cycles0: wp.float64, cycles_per_pulse: wp.float64, k: wp.int64):
    """Prism angle of pulse k [rad] in [0, 2π): 2π·frac(cycles0 + k·cycles_per_pulse), in float64.

    cycles0 = frac(f_rot·t_start + φ0/2π) is computed exactly on the host, so the phase stays
    exact for any GPS start time; k·cycles_per_pulse is small enough for float64.
    """
    c = cycles0 + wp.float64(k) * cycles_per_pulse
    return TWO_PI * (c - wp.floor(c))


@wp.func
def _pose(lines: Lines, segments: Segments, n_segments: int, p: int):
    """(line, pulse k, sensor origin [m], R_local←sensor, R_local←body) of chunk pulse p, in float64."""
    s = _last_at_or_below(segments.pulse_start, 0, n_segments + 1, p)
    line = segments.line[s]
    k = segments.first_pulse[s] + wp.int64(p - segments.pulse_start[s])
    t = wp.float64(k) * lines.pulse_period
    begin = lines.sample_start[line]
    i = _last_at_or_below(lines.times, begin, lines.sample_count[line], t)
    w = (t - lines.times[i]) / (lines.times[i + 1] - lines.times[i])
    w = wp.clamp(w, wp.float64(0.0), wp.float64(1.0))
    position = lines.positions[i] + w * (lines.positions[i + 1] - lines.positions[i])
    body = wp.quat_slerp(lines.attitudes[i], lines.attitudes[i + 1], w)
    origin = position + wp.quat_rotate(body, lines.lever_arm)
    return line, k, origin, body * lines.boresight, body


@wp.kernel
def pulse_poses(
    # In:
    lines: Lines,
    segments: Segments,
    n_segments: int,
    # Out:
    poses: wp.array(dtype=PulsePose),
):
    """Pose of each pulse of a chunk: position linear, attitude slerped between samples."""
    p = wp.tid()
    line, k, origin, sensor, body = _pose(lines, segments, n_segments, p)
    rot = wp.quat_to_matrix(sensor)
    phi = prism_angle(lines.cycles0[line], lines.cycles_per_pulse, k)
    pose = PulsePose()
    pose.origin = wp.vec3f(origin)
    pose.rot = wp.mat33f(rot)
    pose.right = wp.vec3f(wp.quat_rotate(body, wp.vec3d(0.0, 1.0, 0.0)))
    pose.phi = wp.float32(phi)
    pose.origin64 = origin
    pose.rot64 = rot
    pose.phi64 = phi
    pose.pulse = k
    pose.seed = lines.seed[line]
    poses[p] = pose


@wp.kernel
def pulse_poses64(
    lines: Lines,
    segments: Segments,
    n_segments: int,
    # Out:
    poses: wp.array(dtype=PulsePose64),
):
    """The same poses as :func:`pulse_poses`, kept in float64 only (reference path)."""
    p = wp.tid()
    line, k, origin, sensor, body = _pose(lines, segments, n_segments, p)
    pose = PulsePose64()
    pose.origin = origin
    pose.rot = wp.quat_to_matrix(sensor)
    pose.phi = prism_angle(lines.cycles0[line], lines.cycles_per_pulse, k)
    poses[p] = pose
