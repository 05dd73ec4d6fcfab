"""Pulse timing and prism phase: exact for any GPS start time (SPEC §4).

Pulses fire at t_k = t_start + k/PRF, k = 0, 1, …; the prism angle is
φ(t) = φ0 + 2π·f_rot·t. At GPS times ~1e9 s, f_rot·t ~ 2e10 turns, so a float64 product
2π·f_rot·t is only good to ~1e-5 rad. Instead the phase at t_start, in turns, is reduced to
[0, 1) exactly with rational arithmetic on the host, and each pulse adds k·(f_rot/PRF) turns,
a number small enough for float64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from .checks import finite_number, positive_number

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class PulseTiming:
    """Pulse repetition and prism rotation.

    Attributes:
        prf_hz: pulse repetition frequency [Hz], > 0.
        rotation_hz: prism rotation frequency f_rot [turns/s], finite (negative turns the other way).
        phase0_rad: prism angle φ0 at GPS time 0 [rad], finite.
        field_prefix: prefix of the field names in error messages, e.g. "scan.prf_hz".
    """

    prf_hz: float = 5000.0
    rotation_hz: float = 20.0
    phase0_rad: float = 0.0
    field_prefix: str = field(default="scan", compare=False, repr=False)

    def __post_init__(self):
        prefix = self.field_prefix
        object.__setattr__(self, "prf_hz", positive_number(self.prf_hz, f"{prefix}.prf_hz", "[Hz]"))
        for name, unit in (("rotation_hz", "[Hz]"), ("phase0_rad", "[rad]")):
            value = finite_number(getattr(self, name), f"{prefix}.{name}", f"a finite number {unit}")
            object.__setattr__(self, name, value)

    @property
    def pulse_period_s(self) -> float:
        """1 / PRF [s]."""
        return 1.0 / self.prf_hz

    @property
    def cycles_per_pulse(self) -> float:
        """Prism turns between consecutive pulses, f_rot / PRF (float64) [turns]."""
        return self.rotation_hz / self.prf_hz

    def pulse_times(self, t_start: float, k) -> np.ndarray:
        """GPS times of pulses k [s]: t_start + k/PRF, in float64."""
        return t_start + np.asarray(k, dtype=np.float64) / self.prf_hz

    def pulse_count(self, t_start: float, t_end: float) -> int:
        """Number of pulses k ≥ 0 with pulse_times(t_start, k) ≤ t_end (0 if t_end < t_start).

        The estimate floor((t_end − t_start)·PRF) is corrected by evaluating pulse_times itself at
        the boundary, so every counted pulse lies in [t_start, t_end] and the next one does not,
        whatever the float64 rounding.
        """
        t_start = finite_number(t_start, f"{self.field_prefix}.t_start", "a finite GPS time [s]")
        t_end = finite_number(t_end, f"{self.field_prefix}.t_end", "a finite GPS time [s]")
        if t_end < t_start:
            return 0
        last = math.floor((t_end - t_start) * self.prf_hz)
        while last > 0 and self.pulse_times(t_start, last) > t_end:
            last -= 1
        while self.pulse_times(t_start, last + 1) <= t_end:
            last += 1
        return last + 1

    def phase_cycles_at(self, t_start: float) -> float:
        """Prism phase at GPS time t_start in turns, in [0, 1): frac(f_rot·t_start + φ0/2π).

        f_rot·t_start is formed and reduced exactly (fractions.Fraction of the float64 inputs),
        so the result is good to float64 rounding (~1e-16 turn) for any t_start; only the
        φ0/2π term is rounded before the reduction.
        """
        t_start = finite_number(t_start, f"{self.field_prefix}.t_start", "a finite GPS time [s]")
        if self.rotation_hz == 0.0:  # no turns to reduce (the exact sum's 0.0, without the fractions: a run of the
            whole = 0.0  # shots platform asks once per footprint)
        else:
            turns = Fraction(self.rotation_hz) * Fraction(t_start)
            whole = float(turns - math.floor(turns))
        cycles = whole + self.phase0_rad / TWO_PI
        frac = cycles - math.floor(cycles)
        return 0.0 if frac >= 1.0 else frac  # frac(−1e-20) rounds to 1.0

    def prism_angles(self, t_start: float, k) -> np.ndarray:
        """Prism angle φ of pulses k [rad] in [0, 2π), in float64, shaped like k.

        φ_k = 2π·frac(c0 + k·c), c0 = phase_cycles_at(t_start), c = cycles_per_pulse. This is
        exactly the formula the device kernel evaluates per pulse (``kernels.frames.prism_angle``,
        float64, with c0 and c passed from here), so host and device agree (the kernel does not
        fold a rounded 2π back to 0, the same angle). Against exact rational arithmetic the error
        is ~1e-10 rad for an hour of pulses at any t_start.
        """
        cycles = self.phase_cycles_at(t_start) + np.asarray(k, dtype=np.float64) * self.cycles_per_pulse
        angle = TWO_PI * (cycles - np.floor(cycles))
        return np.where(angle >= TWO_PI, 0.0, angle)
