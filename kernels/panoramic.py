"""The panoramic deflector of a terrestrial laser scanner (TLS): a line mirror draws vertical scan lines, a
rotating head turns them in azimuth (RIEGL VZ series, HELIOS++'s "rotate" optics).

Sensor frame (the body frame of a level tripod): x forward, y right, z down; +z is the head's rotation axis.
A measurement at elevation ε (above the head's horizontal plane, up positive) and azimuth φ (clockwise from
sensor x seen from above) leaves along
    d(ε, φ) = (cos ε cos φ, cos ε sin φ, −sin ε)
from the scanner's origin (the intersection of the mirror's and the head's axes, RIEGL's SOCS origin).
An emitter beam s (emitter frame, +z its axis) leaves along s.x·e_ε + s.y·e_φ + s.z·d, with
e_ε = ∂d/∂ε and e_φ = ∂d/∂φ / cos ε (unit), so a single on-axis beam leaves along d.

Scan (pulse k of a scan of ``lines`` lines of ``per_line`` measurements, repeated after its last pulse):
    k_s = k mod (lines · per_line), i = k_s mod per_line,
    ε = ε_lo + i·Δε,    φ = φ_start + Δφ · k_s / per_line
(the head turns on while a line is drawn, so a line leans by Δφ over its length). The truth adds the
encoders' zero errors.
"""
from typing import Any

import warp as wp

from kernels.frames import ROW_PULSE
from kernels.parts import Deflector

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.struct
class Panoramic:
    """The scan pattern as one side (truth or processing) believes it."""

    elev_lo: wp.float64  # elevation of a line's first measurement [rad]
    elev_step: wp.float64  # Δε between measurements of a line [rad]
    az_start: wp.float64  # azimuth of the first line [rad]
    az_step: wp.float64  # Δφ between lines [rad]
    per_line: wp.int32  # measurements per line
    lines: wp.int32  # lines per scan
    zero_az: wp.float64  # encoder zero errors: the head / mirror stand this far past their readings [rad]
    zero_elev: wp.float64


@wp.func
def scan_angles(g: Panoramic, k: wp.int64):
    """(ε, φ) the encoders report for pulse k [rad]."""
    ks = k % (wp.int64(g.lines) * wp.int64(g.per_line))
    i = int(ks % wp.int64(g.per_line))
    elev = g.elev_lo + wp.float64(i) * g.elev_step
    az = g.az_start + g.az_step * wp.float64(ks) / wp.float64(g.per_line)
    return elev, az


@wp.func
def panoramic_beam_stage(s1: Any, g: Panoramic):
    """Nothing depends on the beam alone: the emitter's direction."""
    return s1


@wp.func
def panoramic_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Panoramic):
    """The pulse's true (or believed) elevation and azimuth [rad] into rows row, row + 1."""
    elev, az = scan_angles(g, wp.int64(table[ROW_PULSE, p]))
    table[row, p] = elev + g.zero_elev
    table[row + 1, p] = az + g.zero_az


@wp.func
def panoramic_finish(s: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, g: Panoramic):
    """(direction, exit point = the scanner's origin [m], True) in the sensor frame, of emitter beam s."""
    elev = type(s[0])(table[row, p])
    az = type(s[0])(table[row + 1, p])
    ce, se = wp.cos(elev), wp.sin(elev)
    ca, sa = wp.cos(az), wp.sin(az)
    d = type(s)(ce * ca, ce * sa, -se)
    e_elev = type(s)(-se * ca, -se * sa, -ce)
    e_az = type(s)(-sa, ca, type(s[0])(0.0))
    return s[0] * e_elev + s[1] * e_az + s[2] * d, type(s)(), True


PANORAMIC = Deflector("panoramic", Panoramic, 2, panoramic_beam_stage, panoramic_pulse_stage, panoramic_finish)
