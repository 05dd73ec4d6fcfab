"""The rotating wedge prism (Risley) deflector: one wedge turning at the scan rate (SPEC §4).

Stages: the direction inside the glass after the flat front face depends on the beam only; the
back face's normal depends on the prism angle only (three pulse-table rows); the exit through the
back face is the per-beam rest.
"""
from typing import Any

import warp as wp

from kernels.frames import ROW_PHI, ROW_PULSE, ROW_SEED, put3
from kernels.optics import back_face_normal, enter_prism, leave_prism
from kernels.parts import Deflector, get3_as, standard_normal64

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

ENCODER_STREAM = wp.constant(0x1B873593)  # seed key of the encoder-noise random stream


@wp.struct
class Prism:
    """Wedge prism parameters as one side (truth or processing) believes them."""

    n_glass: wp.float64  # refractive index of the glass (air = 1)
    apex: wp.float64  # apex angle α [rad]
    thickness: wp.float64  # d1, centre thickness [m]
    encoder: wp.float64  # prism-angle encoder zero error: the wedge stands this far past its reading [rad]
    encoder_sigma: wp.float64  # prism-angle noise per pulse, 1σ [rad]


@wp.func
def wedge_beam_stage(s1: Any, prism: Prism):
    """Per-beam part of the wedge: the direction inside the glass after the front face."""
    return enter_prism(s1, type(s1[0])(prism.n_glass))


@wp.func
def wedge_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, prism: Prism):
    """Per-pulse part of the wedge: the back face's normal at the pulse's prism angle, into rows row … row + 2.

    The angle is the encoder's reading plus the side's encoder error and noise (keyed by seed and pulse)."""
    phi = table[ROW_PHI, p] + prism.encoder
    if prism.encoder_sigma > wp.float64(0.0):
        state = wp.rand_init(int(table[ROW_SEED, p]) ^ ENCODER_STREAM,
                             int(wp.int64(table[ROW_PULSE, p]) % wp.int64(2147483647)))
        noise, state = standard_normal64(state)
        phi += prism.encoder_sigma * noise
    put3(table, row, p, back_face_normal(phi, prism.apex))


@wp.func
def wedge_finish(inside: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, prism: Prism):
    """Per-beam, per-pulse rest of the wedge: (exit direction, exit point [m], ok) in the inputs' precision."""
    return leave_prism(inside, get3_as(table, row, p, inside), type(inside[0])(prism.n_glass),
                       type(inside[0])(prism.thickness))


WEDGE = Deflector("risley", Prism, 3, wedge_beam_stage, wedge_pulse_stage, wedge_finish, rigid_nominal=True)
