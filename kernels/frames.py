"""Per-pulse sensor pose on the device: trajectory interpolation, prism phase, frame rotations.

One thread per pulse. The trajectories of every line of a run arrive once, concatenated, as
float64 samples in the scene's local frame (world minus the scene origin, subtracted on the host
in float64). A chunk of pulses may hold pieces (segments) of several lines, so short lines do not
cost a launch each. Poses leave in float64, in a table of rows the per-beam kernels read (SPEC §2).
"""
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

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


# The per-pulse table of a chunk: one float64 row per quantity, one column per pulse (a structure of
# arrays, so the stores of neighbouring pulses coalesce and the per-beam kernels read only what they
# use). Rows from POSE_ROWS on belong to the beam deflector (kernels.trace).
ROW_ORIGIN = wp.constant(0)  # 3 rows: sensor origin (centre of the prism's front face) [m, local]
ROW_ROT = wp.constant(3)  # 9 rows: R_local←sensor, row-major
ROW_RIGHT = wp.constant(12)  # 3 rows: the aircraft's right wing (body +y), for the scan-angle sign
ROW_PHI = wp.constant(15)  # prism angle, reduced to [0, 2π) [rad]
ROW_PULSE = wp.constant(16)  # pulse index within its line (exact: below 2^53)
ROW_SEED = wp.constant(17)  # noise seed of its line
POSE_ROWS = 18


@wp.func
def get3(table: wp.array2d(dtype=wp.float64), row: int, p: int):
    """The 3-vector in rows row … row + 2 of column p."""
    return wp.vec3d(table[row, p], table[row + 1, p], table[row + 2, p])


@wp.func
def put3(table: wp.array2d(dtype=wp.float64), row: int, p: int, v: wp.vec3d):
    for k in range(3):
        table[row + k, p] = v[k]


@wp.func
def get33(table: wp.array2d(dtype=wp.float64), row: int, p: int):
    """The row-major 3×3 matrix in rows row … row + 8 of column p."""
    return wp.mat33d(table[row, p], table[row + 1, p], table[row + 2, p],
                     table[row + 3, p], table[row + 4, p], table[row + 5, p],
                     table[row + 6, p], table[row + 7, p], table[row + 8, p])


@wp.func
def put33(table: wp.array2d(dtype=wp.float64), row: int, p: int, m: wp.mat33d):
    for i in range(3):
        for j in range(3):
            table[row + 3 * i + j, p] = m[i, j]


@wp.struct
class PulsePose64:
    """Sensor pose of one pulse in float64, for the reference path."""

    origin: wp.vec3d  # [m]
    rot: wp.mat33d  # R_local←sensor
    phi: wp.float64  # [rad]


@wp.func
def last_at_or_below(values: wp.array(dtype=Any), begin: int, count: int, x: Any):
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
    s = last_at_or_below(segments.pulse_start, 0, n_segments + 1, p)
    line = segments.line[s]
    k = segments.first_pulse[s] + wp.int64(p - segments.pulse_start[s])
    t = wp.float64(k) * lines.pulse_period
    begin = lines.sample_start[line]
    i = last_at_or_below(lines.times, begin, lines.sample_count[line], t)
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
    # Out: rows ROW_ORIGIN … POSE_ROWS − 1 of the chunk's pulse table
    table: wp.array2d(dtype=wp.float64),
):
    """Pose of each pulse of a chunk: position linear, attitude slerped between samples."""
    p = wp.tid()
    line, k, origin, sensor, body = _pose(lines, segments, n_segments, p)
    put3(table, ROW_ORIGIN, p, origin)
    put33(table, ROW_ROT, p, wp.quat_to_matrix(sensor))
    put3(table, ROW_RIGHT, p, wp.quat_rotate(body, wp.vec3d(0.0, 1.0, 0.0)))
    table[ROW_PHI, p] = prism_angle(lines.cycles0[line], lines.cycles_per_pulse, k)
    table[ROW_PULSE, p] = wp.float64(k)
    table[ROW_SEED, p] = wp.float64(lines.seed[line])


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
