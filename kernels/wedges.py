"""Two or three rotating wedge prisms in a row on one axis (multi-prism Risley deflector).

Sensor frame as for the single wedge (kernels/optics.py): +z the common axis. Prism i has a flat front
face, the plane z = z_i (z_0 = 0), and a back face through (0, 0, z_i + d_i) of normal N2(φ_i, α_i);
an air gap g_i on the axis separates it from prism i + 1 (z_{i+1} = z_i + d_i + g_i). Each face is
crossed by the vector Snell law of :func:`kernels.optics.refract` (through enter_prism / leave_prism),
each ray meeting each face at its own point, so the exit point walks with the prism angles.

Prism angles: every prism turns at a whole multiple m_i (signed) of one pattern frequency f_p, so the
pulse table's scan phase ψ = 2π·frac(f_p·t) (kernels.frames, exact at any GPS time) gives each prism's
angle exactly: φ_i = φ0_i + 2π·frac(m_i·ψ/2π), plus the side's encoder errors.

Stages: entering the first prism depends on the beam only; the back-face normals depend on the pulse
only (three pulse-table rows per prism); the rest is per beam.
"""
from typing import Any

import warp as wp

from kernels.frames import ROW_PHI, ROW_PULSE, ROW_SEED, TWO_PI, put3
from kernels.optics import back_face_normal, enter_prism, leave_prism
from kernels.parts import Deflector, get3_as, standard_normal64

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

MAX_PRISMS = 3
ENCODER_STREAM = wp.constant(0x2E1B2138)  # seed key of the prisms' encoder-noise random stream


@wp.struct
class Prisms:
    """The prisms as one side (truth or processing) believes them; item i of each vector is prism i."""

    count: wp.int32  # prisms in use (2 or 3)
    n_glass: wp.vec3d  # refractive index of each prism's glass (air = 1)
    apex: wp.vec3d  # apex angle α_i [rad]
    thickness: wp.vec3d  # centre thickness d_i [m]
    front: wp.vec3d  # z_i, the front face's position on the axis [m] (z_0 = 0)
    turns: wp.vec3d  # m_i, signed whole turns of prism i per turn of the scan phase
    phase0: wp.vec3d  # prism angle at scan phase 0, with the side's encoder zero error [rad]
    encoder_sigma: wp.float64  # prism-angle noise per pulse and prism, 1σ [rad]


@wp.func
def prisms_beam_stage(s1: Any, prisms: Prisms):
    """Per-beam part: the direction inside the first prism after its flat front face."""
    return enter_prism(s1, type(s1[0])(prisms.n_glass[0]))


@wp.func
def prism_angle_at(psi: wp.float64, turns: wp.float64, phase0: wp.float64):
    """Angle of a prism turning ``turns`` times per turn of the scan phase ψ [rad]: φ0 + 2π·frac(m·ψ/2π)."""
    c = turns * (psi / TWO_PI)
    return phase0 + TWO_PI * (c - wp.floor(c))


@wp.func
def prisms_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, prisms: Prisms):
    """Per-pulse part: the back-face normal of prism i at its angle into rows row + 3i … row + 3i + 2.

    The scan phase is the pulse table's ROW_PHI; the noise (keyed by seed and pulse) is drawn per prism."""
    psi = table[ROW_PHI, p]
    state = wp.rand_init(int(table[ROW_SEED, p]) ^ ENCODER_STREAM,
                         int(wp.int64(table[ROW_PULSE, p]) % wp.int64(2147483647)))
    for i in range(prisms.count):
        phi = prism_angle_at(psi, prisms.turns[i], prisms.phase0[i])
        if prisms.encoder_sigma > wp.float64(0.0):
            noise, state = standard_normal64(state)
            phi += prisms.encoder_sigma * noise
        put3(table, row + 3 * i, p, back_face_normal(phi, prisms.apex[i]))


@wp.func
def prisms_finish(inside: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, prisms: Prisms):
    """Per-beam, per-pulse rest: (exit direction, exit point on the last back face [m], ok) in the inputs' precision.

    inside: the direction in the first prism (its beam stage). ok is False where a face reflects the beam
    totally or the beam would meet the next prism's front face behind the back face it leaves (prisms
    touching across a too small gap).
    """
    zero = type(inside[0])(0.0)
    s = inside
    entry = type(inside)(zero, zero, zero)  # where the beam enters the current prism [m]
    ok = bool(True)
    for i in range(prisms.count):
        n2 = get3_as(table, row + 3 * i, p, inside)
        # the back face seen from the entry point: through (0, 0, d_eff) of a frame moved to it (optics.leave_prism)
        d_eff = type(inside[0])(prisms.thickness[i]) - (n2[0] * entry[0] + n2[1] * entry[1]) / n2[2]
        s3, walk, passed = leave_prism(s, n2, type(inside[0])(prisms.n_glass[i]), d_eff)
        entry = entry + walk
        s = s3
        ok = ok and passed
        if i + 1 < prisms.count:
            t = (type(inside[0])(prisms.front[i + 1]) - entry[2]) / s3[2]
            ok = ok and t >= zero
            entry = entry + t * s3
            s = enter_prism(s3, type(inside[0])(prisms.n_glass[i + 1]))
    return s, entry, ok


RISLEY_N = Deflector("risley_n", Prisms, 3 * MAX_PRISMS, prisms_beam_stage, prisms_pulse_stage, prisms_finish,
                     rigid_nominal=True)
