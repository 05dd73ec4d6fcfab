"""The two-mirror galvanometer scanner (Chang'e-3 imager, seed paper §1–§2).

Galvo frame = sensor frame: +z the optical axis towards the scene, x horizontal, y vertical.
The source sits at S = (−b, −e, 0) and fires along +x (the emitter frame's +z; its x and y become
the galvo's y and z). Mirror 1 (horizontal scan) turns about the z axis through P1 = (0, −e, 0),
normal n1(δ) = (cos(135° − δ), sin(135° − δ), 0); mirror 2 (vertical scan) turns about the x axis
through the origin, normal n2(γ) = (0, cos(135° − γ), sin(135° − γ)). At δ = γ = 0 a beam leaves as
it was emitted; the central ray leaves along (sin 2δ, cos 2δ sin 2γ, cos 2δ cos 2γ): a mirror turned
by ε turns the beam by 2ε. Each beam is reflected exactly (vector law) at its own hit point on each
mirror, so the exit point (on mirror 2) moves with the angles and the mirror separations b, e.

One frame is ``strips`` horizontal strips of ``columns`` pulses, the vertical mirror stepping
between strips and the strips scanned in alternating directions. The mirror angles a pulse's
encoders report are the raster's; the truth adds the angle errors of seed paper §2.2 (eqs. 6–9):
  δ = δ_obs + B1·dir + B2·sec γ_obs + B3·tan γ_obs + n_h,   γ = γ_obs + C1 + n_v,
dir = ±1 the strip's direction (the horizontal encoder's zero error changes sign between strips),
n_h, n_v Gaussian noise keyed by (seed, pulse). The processing's instance has no errors.
"""
from typing import Any

import warp as wp

from kernels.frames import ROW_PULSE, ROW_SEED, put3
from kernels.parts import Deflector, get3_as, standard_normal64

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

QUARTER_PI3 = wp.constant(wp.float64(2.356194490192345))  # 135° [rad]


@wp.struct
class Galvo:
    """Two-mirror scanner parameters as one side (truth or processing) believes them."""

    b: wp.float64  # source to mirror 1 along x [m]
    e: wp.float64  # mirror 1 to mirror 2 along y [m]
    aperture: wp.float64  # half size of each mirror: a beam must hit within this of the pivot [m]
    h_half: wp.float64  # half the horizontal mirror-angle range of a strip [rad]
    v_half: wp.float64  # half the vertical mirror-angle range of a frame [rad]
    strips: wp.int32  # strips per frame
    columns: wp.int32  # pulses per strip
    b1: wp.float64  # horizontal encoder zero error, sign alternating by strip [rad]
    b2: wp.float64  # collimation-axis error (× sec γ) [rad]
    b3: wp.float64  # horizontal-axis error (× tan γ) [rad]
    c1: wp.float64  # vertical encoder zero error [rad]
    sigma_h: wp.float64  # horizontal mirror-angle noise, 1σ [rad]
    sigma_v: wp.float64  # vertical mirror-angle noise, 1σ [rad]


@wp.func
def raster_angles(g: Galvo, k: wp.int64):
    """(δ, γ, dir) the encoders report for pulse k of a frame sequence: mirror angles [rad] and the strip's direction."""
    per_frame = wp.int64(g.strips) * wp.int64(g.columns)
    f = int(k % per_frame)
    strip = f // g.columns
    column = f % g.columns
    direction = wp.float64(1.0)
    if strip % 2 == 1:
        column = g.columns - 1 - column
        direction = wp.float64(-1.0)
    delta = -g.h_half + wp.float64(2.0) * g.h_half * wp.float64(column) / wp.float64(wp.max(g.columns - 1, 1))
    gamma = -g.v_half + wp.float64(2.0) * g.v_half * wp.float64(strip) / wp.float64(wp.max(g.strips - 1, 1))
    return delta, gamma, direction


@wp.func
def mirror_normals(delta: wp.float64, gamma: wp.float64):
    """Unit normals (n1, n2) of the two mirrors at mirror angles δ, γ [rad]."""
    a1 = QUARTER_PI3 - delta
    a2 = QUARTER_PI3 - gamma
    return (wp.vec3d(wp.cos(a1), wp.sin(a1), wp.float64(0.0)),
            wp.vec3d(wp.float64(0.0), wp.cos(a2), wp.sin(a2)))


@wp.func
def galvo_beam_stage(s1: Any, g: Galvo):
    """The source's mounting: emitter frame (x, y, z) → galvo frame (z, x, y), so it fires along +x."""
    return type(s1)(s1[2], s1[0], s1[1])


@wp.func
def galvo_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Galvo):
    """The mirror normals of the pulse's true (or believed) angles into rows row … row + 5."""
    k = wp.int64(table[ROW_PULSE, p])
    delta, gamma, direction = raster_angles(g, k)
    true_delta = delta + g.b1 * direction + g.b2 / wp.cos(gamma) + g.b3 * wp.tan(gamma)
    true_gamma = gamma + g.c1
    if g.sigma_h > wp.float64(0.0) or g.sigma_v > wp.float64(0.0):
        state = wp.rand_init(int(table[ROW_SEED, p]), int((k * wp.int64(2)) % wp.int64(2147483647)))
        n_h, state = standard_normal64(state)
        n_v, state = standard_normal64(state)
        true_delta += g.sigma_h * n_h
        true_gamma += g.sigma_v * n_v
    n1, n2 = mirror_normals(true_delta, true_gamma)
    put3(table, row, p, n1)
    put3(table, row + 3, p, n2)


@wp.func
def _reflect(s: Any, n: Any):
    return s - type(s[0])(2.0) * wp.dot(s, n) * n


@wp.func
def galvo_finish(s: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Galvo):
    """(exit direction, exit point on mirror 2 [m], ok) of a beam leaving the source along s.

    ok is False where the beam meets a mirror from behind or outside its aperture.
    """
    zero = type(s[0])(0.0)
    b = type(s[0])(g.b)
    e = type(s[0])(g.e)
    n1 = get3_as(table, row, p, s)
    n2 = get3_as(table, row + 3, p, s)
    source = type(s)(-b, -e, zero)
    t1 = n1[0] * b / wp.dot(n1, s)  # n1·(P1 − S), P1 − S = (b, 0, 0)
    q1 = source + t1 * s
    s2 = _reflect(s, n1)
    t2 = -wp.dot(n2, q1) / wp.dot(n2, s2)
    q2 = q1 + t2 * s2
    s3 = _reflect(s2, n2)
    pivot1 = type(s)(zero, -e, zero)
    r = type(s[0])(g.aperture)
    ok = wp.dot(n1, s) < zero and wp.dot(n2, s2) < zero and t1 > zero and t2 > zero
    ok = ok and wp.length(q1 - pivot1) <= r and wp.length(q2) <= r
    return s3, q2, ok


GALVO = Deflector("galvo", Galvo, 6, galvo_beam_stage, galvo_pulse_stage, galvo_finish)
