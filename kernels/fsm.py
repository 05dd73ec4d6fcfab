"""The fast-steering-mirror (FSM) deflector of the small-body SPAD lidar (seed paper §1.2, eqs. 2–5).

FSM frame = the paper's O_c-XYZ: origin at the large FSM's centre, X and Y its two tilt axes. The
Dammann grating's fan leaves the grating centre G = (−b₂, −d/√2, d/√2) along +X (the emitter's x, y
along (0, 1, −1)/√2 and (0, 1, 1)/√2, so that at rest the fan leaves square to the sensor axes); the fixed 45° mirror centred at F = (0, −d/√2, d/√2) folds the
fan's axis by 90° onto u₀ = (0, 1/√2, −1/√2), towards O_c at distance d; the large FSM, of normal
N(θx, θy) ∝ (tan θx, tan θy, −1) (the paper's eq. 2), reflects it to the target. At θx = θy = 0
the axis leaves along a₀ = (0, 1/√2, 1/√2). Sensor frame: +z = a₀, x = X, y = z × x; exit points
lie on the FSM, directions and points are turned into the sensor frame. Each beam is reflected
exactly (vector law) at its own hit points P₁ (45° mirror) and P₂ (FSM).

Scan (the recorded observations θx, θy of pulse k at time k / prf within its frame):
- MODE-A (global mapping): θx a triangle wave over ±span_x/2, one sweep every ``frame_pulses /
  sweeps`` pulses, direction alternating; θy steps from −span_y/2 to +span_y/2 after each sweep,
  so the array interleaves to sub-pixels;
- MODE-B (step scanning): a ``steps`` × ``steps`` grid of (θx, θy), ``frame_pulses / steps²``
  pulses dwelling at each, row by row.
The truth adds the encoder zero errors and the per-pulse angle noise (keyed by seed and pulse).
"""
from typing import Any

import warp as wp

from kernels.frames import ROW_PULSE, ROW_SEED, put3
from kernels.parts import Deflector, get3_as, standard_normal64

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

MODE_A = wp.constant(0)
MODE_B = wp.constant(1)
HALF_SQRT2 = wp.constant(wp.float64(0.7071067811865476))
FSM_STREAM = wp.constant(0x3C6EF372)  # seed key of the FSM angle-noise stream


@wp.struct
class Fsm:
    """The FSM path and scan as one side (truth or processing) believes them."""

    b2: wp.float64  # grating centre to the 45° mirror centre [m]
    d: wp.float64  # 45° mirror centre to the FSM centre [m]
    aperture: wp.float64  # half size of the FSM and the 45° mirror [m]
    mode: wp.int32  # MODE_A or MODE_B
    span_x: wp.float64  # full θx span of the pattern [rad]
    span_y: wp.float64  # full θy span of the pattern [rad]
    frame_pulses: wp.int32  # pulses per frame
    lines: wp.int32  # MODE-A: sweeps per frame; MODE-B: steps per axis
    zero_x: wp.float64  # encoder zero errors: the mirror stands this far past its reading [rad]
    zero_y: wp.float64
    sigma: wp.float64  # angle noise of each axis per pulse, 1σ [rad]


@wp.func
def scan_angles(g: Fsm, k: wp.int64):
    """(θx, θy) the encoders report for pulse k of a frame sequence [rad]."""
    f = int(k % wp.int64(g.frame_pulses))
    if g.mode == MODE_A:
        per_sweep = g.frame_pulses // g.lines
        sweep = wp.min(f // per_sweep, g.lines - 1)
        u = wp.float64(f - sweep * per_sweep) / wp.float64(wp.max(per_sweep - 1, 1))
        if sweep % 2 == 1:
            u = wp.float64(1.0) - u
        v = wp.float64(sweep) / wp.float64(wp.max(g.lines - 1, 1))
    else:
        per_step = g.frame_pulses // (g.lines * g.lines)
        step = wp.min(f // per_step, g.lines * g.lines - 1)
        u = wp.float64(step % g.lines) / wp.float64(wp.max(g.lines - 1, 1))
        v = wp.float64(step // g.lines) / wp.float64(wp.max(g.lines - 1, 1))
    return (g.span_x * (u - wp.float64(0.5)), g.span_y * (v - wp.float64(0.5)))


@wp.func
def fsm_normal(theta_x: wp.float64, theta_y: wp.float64):
    """Unit normal of the FSM at tilts θx, θy (the paper's eq. 2)."""
    n = wp.vec3d(wp.tan(theta_x), wp.tan(theta_y), wp.float64(-1.0))
    return n / wp.length(n)


@wp.func
def _fold_normal():
    """Unit normal of the 45° mirror: it reflects +X onto u₀ = (0, 1/√2, −1/√2)."""
    n = wp.vec3d(wp.float64(1.0), -HALF_SQRT2, HALF_SQRT2)
    return n / wp.length(n)


@wp.func
def _reflect(s: Any, n: Any):
    return s - type(s[0])(2.0) * wp.dot(s, n) * n


@wp.func
def fsm_beam_stage(s1: Any, g: Fsm):
    """The beam after the 45° mirror (FSM frame): the emitter mounted with its z along +X and its x, y along
    (0, 1, −1)/√2, (0, 1, 1)/√2, so that at rest the fan leaves with its own axes along sensor x, y."""
    h = type(s1[0])(HALF_SQRT2)
    return _reflect(type(s1)(s1[2], h * (s1[0] + s1[1]), h * (s1[1] - s1[0])), type(s1)(_fold_normal()))


@wp.func
def fsm_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Fsm):
    """The FSM's normal at the pulse's true (or believed) tilts into rows row … row + 2."""
    k = wp.int64(table[ROW_PULSE, p])
    theta_x, theta_y = scan_angles(g, k)
    theta_x += g.zero_x
    theta_y += g.zero_y
    if g.sigma > wp.float64(0.0):
        state = wp.rand_init(int(table[ROW_SEED, p]) ^ FSM_STREAM, int(k % wp.int64(2147483647)))
        nx, state = standard_normal64(state)
        ny, state = standard_normal64(state)
        theta_x += g.sigma * nx
        theta_y += g.sigma * ny
    put3(table, row, p, fsm_normal(theta_x, theta_y))


@wp.func
def fsm_finish(s: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Fsm):
    """(exit direction, exit point on the FSM [m], ok) in the sensor frame, of a beam folded to s."""
    zero = type(s[0])(0.0)
    h = type(s[0])(HALF_SQRT2)
    d = type(s[0])(g.d)
    fold = type(s)(_fold_normal())
    incoming = _reflect(s, fold)  # the beam before the 45° mirror (a reflection undoes itself)
    grating = type(s)(-type(s[0])(g.b2), -h * d, h * d)
    centre = type(s)(zero, -h * d, h * d)
    t1 = wp.dot(fold, centre - grating) / wp.dot(fold, incoming)
    p1 = grating + t1 * incoming
    n = get3_as(table, row, p, s)
    t2 = -wp.dot(n, p1) / wp.dot(n, s)
    p2 = p1 + t2 * s
    out = _reflect(s, n)
    r = type(s[0])(g.aperture)
    ok = t1 > zero and t2 > zero and wp.length(p1 - centre) <= r and wp.length(p2) <= r
    sensor_x = type(s)(type(s[0])(1.0), zero, zero)
    sensor_y = type(s)(zero, h, -h)
    sensor_z = type(s)(zero, h, h)
    exit_point = type(s)(wp.dot(sensor_x, p2), wp.dot(sensor_y, p2), wp.dot(sensor_z, p2))
    direction = type(s)(wp.dot(sensor_x, out), wp.dot(sensor_y, out), wp.dot(sensor_z, out))
    return direction, exit_point, ok


FSM = Deflector("fsm", Fsm, 3, fsm_beam_stage, fsm_pulse_stage, fsm_finish)
