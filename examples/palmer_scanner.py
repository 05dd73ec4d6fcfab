"""A new deflector written outside the package: a Palmer (nutating-mirror) scanner, flown over the calibration field.

A Palmer scanner draws a cone: the laser fires along the spin axis at a mirror whose normal is tilted by τ from that
axis, and the mirror spins, so the reflected beam turns around the axis at 2τ from it (a circle on the ground beneath
a hovering sensor, an ellipse when the sensor is tilted, overlapping loops from a moving aircraft). The whole part is
in this file: its settings (the `[palmer]` table), its kernel side (a `@wp.struct` and the `@wp.func` stages of a
`kernels.parts.Deflector`) and its host class, registered with `flightsim.register_part`. Run as a script it flies
one second over the calibration field and prints the points and the plane RMS of the exact model (the only one: a
Palmer scanner has no rigid-array nominal model). Installed as a plug-in (the `flightsim.parts` entry point) it
gives the command line `instrument.deflector = "palmer"` too; [Write a part](../write-a-part.md) walks through it.

Geometry (sensor frame: +z the scan axis, towards the scene; x forward): the source fires up the spin axis (along
−z) at the mirror's centre, the sensor origin; at scan phase φ the mirror's normal is the tilted normal
(sin τ, 0, cos τ) turned by φ about z, n(φ) = (sin τ cos φ, sin τ sin φ, cos τ), and each beam leaves by exact
vector reflection, d' = d − 2 (d·n) n: the on-axis beam along (sin 2τ cos φ, sin 2τ sin φ, cos 2τ).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

import flightsim
from flightsim.core.settings import Settings, setting
from flightsim.instrument.base import footprint_buffer_m
from kernels.frames import ROW_PHI, put3
from kernels.parts import Deflector, get3_as
from trajectories import PulseTiming


# --- the settings: the [palmer] table -------------------------------------------------------------------------


@dataclass
class PalmerSettings(Settings):
    """A nutating mirror spinning about the beam's axis: a conical scan of half angle twice the mirror's tilt."""

    prf_hz: float = setting(10000.0, "pulse repetition frequency", "Hz", range=(0.0, 1.0e7), lo_open=True)
    rotation_hz: float = setting(20.0, "mirror turns per second", "Hz", range=(0.0, 1000.0))
    tilt_deg: float = setting(7.5, "tilt τ of the mirror's normal from its spin axis; the scan cone's half angle "
                              "is 2τ", "deg", range=(0.0, 30.0), lo_open=True)
    phase0_deg: float = setting(0.0, "mirror azimuth φ at GPS time 0 (φ = 0 sends the beam along the sensor's +x)",
                                "deg", range=(-360.0, 360.0))


# --- the kernel side: a struct and the three stages ----------------------------------------------------------


@wp.struct
class Palmer:
    """The mirror as one side (truth or processing) believes it."""

    tilt: wp.float64  # τ: angle of the mirror's normal from the spin axis [rad]


@wp.func
def palmer_beam_stage(s1: Any, m: Palmer):
    """Per beam: the source's mounting, emitter frame → sensor frame (turned 180° about x): it fires along −z."""
    return type(s1)(s1[0], -s1[1], -s1[2])


@wp.func
def palmer_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, m: Palmer):
    """Per pulse: the mirror's normal n(φ) at the pulse's scan phase (ROW_PHI) into rows row … row + 2."""
    phi = table[ROW_PHI, p]
    sin_tilt = wp.sin(m.tilt)
    put3(table, row, p, wp.vec3d(sin_tilt * wp.cos(phi), sin_tilt * wp.sin(phi), wp.cos(m.tilt)))


@wp.func
def palmer_finish(s: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, m: Palmer):
    """Per beam and pulse: (exit direction d − 2 (d·n) n, exit point: the mirror's centre, ok: hit from the front)."""
    n = get3_as(table, row, p, s)
    along = wp.dot(s, n)
    return s - type(s[0])(2.0) * along * n, type(s)(), along < type(s[0])(0.0)


PALMER = Deflector("palmer", Palmer, 3, palmer_beam_stage, palmer_pulse_stage, palmer_finish)


# --- the host class: what the engine asks of a deflector (flightsim.instrument.base.Deflector) -----------------


@flightsim.register_part("deflector", "palmer")
class PalmerScanner:
    """The `[palmer]` mirror in front of any emitter; the processing believes the true mirror."""

    settings = PalmerSettings
    kernel = PALMER
    rigid_nominal = False  # only the exact georeferencing model
    believed_is_truth = True

    def __init__(self, s: PalmerSettings, emitter):
        self.s = s
        self.emitter = emitter

    def timing(self) -> PulseTiming:
        """Pulses at prf_hz; the scan phase (ROW_PHI) turns at rotation_hz from phase0_deg at GPS time 0."""
        s = self.s
        return PulseTiming(prf_hz=s.prf_hz, rotation_hz=s.rotation_hz, phase0_rad=math.radians(s.phase0_deg),
                           field_prefix="palmer")

    def params(self, believed: bool) -> Palmer:
        m = Palmer()
        m.tilt = math.radians(self.s.tilt_deg)
        return m

    def exit_directions(self, phi: np.ndarray) -> np.ndarray:
        """(phases, beams, 3) exit directions of every beam at scan phases `phi` [rad], float64 (the host's copy)."""
        d = self.emitter.directions() * np.array([1.0, -1.0, -1.0])
        tau = math.radians(self.s.tilt_deg)
        n = np.stack([math.sin(tau) * np.cos(phi), math.sin(tau) * np.sin(phi), np.full_like(phi, math.cos(tau))], -1)
        return d[None] - 2.0 * np.einsum("bk,pk->pb", d, n)[..., None] * n[:, None, :]

    def max_off_axis_rad(self, samples: int = 360) -> float:
        """Largest angle of any exit beam from the scan axis over a turn [rad]."""
        d = self.exit_directions(np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False))
        return float(np.arccos(np.clip(d[..., 2], -1.0, 1.0)).max())

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The footprint's half width at the slant range of the widest beam (there is no rigid-array model to err)."""
        return footprint_buffer_m(altitude_m, self.max_off_axis_rad(), divergence_mrad)


# --- run as a script -------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description="Fly the Palmer scanner over the calibration field.")
    parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    parser.add_argument("--out", help="also write the run's files to this directory")
    args = parser.parse_args()
    cfg = flightsim.load_config(overrides={"instrument.deflector": "palmer", "palmer.tilt_deg": 7.5,
                                           "output.models": ["exact"], "flight.duration_s": 1.0,
                                           "run.device": args.device})
    result = flightsim.simulate(cfg)
    if args.out:
        result.write(args.out)
    print(f"palmer: {len(result.points['exact'].points)} points, plane RMS exact "
          f"{result.stats['rms_m']['exact'] * 1e3:.3g} mm")


if __name__ == "__main__":
    main()
