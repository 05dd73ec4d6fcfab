"""Per-pulse sensor pose on the device: trajectory interpolation, prism phase, frame rotations.

One thread per pulse. The trajectory arrives as float64 samples in the scene's local frame
(world minus the scene origin, subtracted on the host in float64); the pose leaves as float32,
ready for the per-beam kernels (SPEC §2).
"""
import warp as wp

wp.set_module_options({"enable_backward": False})

TWO_PI = wp.constant(wp.float64(6.283185307179586))


@wp.struct
class PulsePose:
    """Sensor pose of one pulse, in the scene's local frame (float32)."""

    origin: wp.vec3f  # sensor origin (centre of the prism's front face) [m]
    rot: wp.mat33f  # R_local←sensor
    right: wp.vec3f  # aircraft's right wing (body +y) in the local frame, for the scan-angle sign
    phi: wp.float32  # prism angle, reduced to [0, 2π) [rad]
    origin64: wp.vec3d  # the same in float64, for the float64 optics path
    rot64: wp.mat33d
    phi64: wp.float64


@wp.func
def _segment(times: wp.array(dtype=wp.float64), t: wp.float64):
    """Index i of the trajectory segment [times[i], times[i+1]] that holds t (binary search)."""
    lo = int(0)
    hi = times.shape[0] - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if times[mid] <= t:
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


@wp.struct
class PulsePose64:
    """Sensor pose of one pulse in float64, for the reference path."""

    origin: wp.vec3d  # [m]
    rot: wp.mat33d  # R_local←sensor
    phi: wp.float64  # [rad]


@wp.func
def _pose(
    times: wp.array(dtype=wp.float64),
    positions: wp.array(dtype=wp.vec3d),
    attitudes: wp.array(dtype=wp.quatd),
    boresight: wp.quatd,
    lever_arm: wp.vec3d,
    pulse_period: wp.float64,
    k: wp.int64,
):
    """(sensor origin [m], R_local←sensor quaternion, R_local←body quaternion) of pulse k in float64."""
    t = wp.float64(k) * pulse_period
    i = _segment(times, t)
    w = (t - times[i]) / (times[i + 1] - times[i])
    w = wp.clamp(w, wp.float64(0.0), wp.float64(1.0))
    position = positions[i] + w * (positions[i + 1] - positions[i])
    body = wp.quat_slerp(attitudes[i], attitudes[i + 1], w)
    return position + wp.quat_rotate(body, lever_arm), body * boresight, body


@wp.kernel
def pulse_poses(
    # In: trajectory samples (local frame)
    times: wp.array(dtype=wp.float64),  # sample times relative to the line's first pulse [s]
    positions: wp.array(dtype=wp.vec3d),  # body origin [m]
    attitudes: wp.array(dtype=wp.quatd),  # R_local←body, sign-continuous
    # In: mounting and timing
    boresight: wp.quatd,  # R_body←sensor
    lever_arm: wp.vec3d,  # sensor origin in the body frame [m]
    pulse_period: wp.float64,  # 1 / PRF [s]
    cycles0: wp.float64,  # prism phase of pulse 0 [turns]
    cycles_per_pulse: wp.float64,  # f_rot / PRF [turns]
    first_pulse: wp.int64,  # index of this chunk's first pulse within the line
    # Out:
    poses: wp.array(dtype=PulsePose),
):
    """Pose of each pulse of a chunk: position linear, attitude slerped between samples."""
    p = wp.tid()
    k = first_pulse + wp.int64(p)
    origin, sensor, body = _pose(times, positions, attitudes, boresight, lever_arm, pulse_period, k)
    rot = wp.quat_to_matrix(sensor)
    phi = prism_angle(cycles0, cycles_per_pulse, k)
    pose = PulsePose()
    pose.origin = wp.vec3f(origin)
    pose.rot = wp.mat33f(rot)
    pose.right = wp.vec3f(wp.quat_rotate(body, wp.vec3d(0.0, 1.0, 0.0)))
    pose.phi = wp.float32(phi)
    pose.origin64 = origin
    pose.rot64 = rot
    pose.phi64 = phi
    poses[p] = pose


@wp.kernel
def pulse_poses64(
    times: wp.array(dtype=wp.float64),
    positions: wp.array(dtype=wp.vec3d),
    attitudes: wp.array(dtype=wp.quatd),
    boresight: wp.quatd,
    lever_arm: wp.vec3d,
    pulse_period: wp.float64,
    cycles0: wp.float64,
    cycles_per_pulse: wp.float64,
    first_pulse: wp.int64,
    # Out:
    poses: wp.array(dtype=PulsePose64),
):
    """The same poses as :func:`pulse_poses`, kept in float64 (reference path)."""
    p = wp.tid()
    k = first_pulse + wp.int64(p)
    origin, sensor, body = _pose(times, positions, attitudes, boresight, lever_arm, pulse_period, k)
    pose = PulsePose64()
    pose.origin = origin
    pose.rot = wp.quat_to_matrix(sensor)
    pose.phi = prism_angle(cycles0, cycles_per_pulse, k)
    poses[p] = pose
