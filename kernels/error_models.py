"""The error models on the device: the ranging chain's systematic and quantisation errors and the pose the
processing believes against the truth (boresight error, POS noise per pulse)."""
import warp as wp

from kernels.frames import ROW_PULSE, ROW_SEED
from kernels.parts import standard_normal64

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.struct
class RangeErrors:
    """The ranging chain's systematic and quantisation errors (seed paper §2.1), applied to the truth."""

    tdc_bin: wp.float32  # TDC bin as one-way range, c·τ/2 [m]; start and stop each rounded on its own clock phase
    drift: wp.float32  # clock frequency drift e_df: the range reads R·(1 + e_df)
    delays: wp.array(dtype=wp.float32)  # fixed delay of each beam's channel, as one-way range [m]


@wp.struct
class PoseErrors:
    """Errors of the pose the processing believes (platform and mounting), applied to the truth."""

    mount: wp.mat33d  # boresight error: the true sensor axes in the believed sensor frame
    position_sigma: wp.float64  # POS position noise per local axis and pulse, 1σ [m]
    attitude_sigma: wp.float64  # POS attitude noise about each sensor axis per pulse, 1σ [rad]
POSE_STREAM = wp.constant(0x2545F491)  # seed key of the pose-noise random stream


@wp.func
def _small_rotation(a: wp.vec3d):
    """The rotation matrix of rotation vector ``a`` [rad] (Rodrigues)."""
    angle = wp.length(a)
    eye = wp.identity(n=3, dtype=wp.float64)
    if angle == wp.float64(0.0):
        return eye
    k = a / angle
    skew = wp.mat33d(wp.float64(0.0), -k[2], k[1], k[2], wp.float64(0.0), -k[0], -k[1], k[0], wp.float64(0.0))
    return eye + wp.sin(angle) * skew + (wp.float64(1.0) - wp.cos(angle)) * (skew * skew)


@wp.func
def true_pose(pulses: wp.array2d(dtype=wp.float64), p: int, pose: PoseErrors):
    """(position offset [m, local], rotation true sensor ← believed sensor) of pulse p: the boresight
    error, then the POS noise keyed by (seed, pulse); pulse_optics writes it once for the pulse's beams."""
    shift = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    turn = pose.mount
    if pose.position_sigma > wp.float64(0.0) or pose.attitude_sigma > wp.float64(0.0):
        state = wp.rand_init(int(pulses[ROW_SEED, p]) ^ POSE_STREAM,
                             int(wp.int64(pulses[ROW_PULSE, p]) % wp.int64(2147483647)))
        x, state = standard_normal64(state)
        y, state = standard_normal64(state)
        z, state = standard_normal64(state)
        shift = pose.position_sigma * wp.vec3d(x, y, z)
        rx, state = standard_normal64(state)
        ry, state = standard_normal64(state)
        rz, state = standard_normal64(state)
        turn = turn * _small_rotation(pose.attitude_sigma * wp.vec3d(rx, ry, rz))
    return shift, turn
