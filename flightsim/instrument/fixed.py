"""The fixed deflector (``instrument.deflector = "fixed"``, ``[fixed]``): a staring instrument whose beams leave
as the emitter fires them."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.instrument.base import footprint_buffer_m
from trajectories import PulseTiming

fixed = lazy_module("kernels.fixed")


@dataclass
class FixedSettings(Settings):
    """Pulse timing of a staring instrument."""

    prf_hz: float = setting(5000.0, "pulse repetition frequency", "Hz", range=(0.0, 1.0e7), lo_open=True)


@register("deflector", "fixed")
class FixedDeflector:
    """No scan: pulses at ``prf_hz``."""

    settings = FixedSettings
    rigid_nominal = False
    believed_is_truth = True

    @property
    def kernel(self):
        """The kernel side: its struct and device functions."""
        return fixed.FIXED

    def __init__(self, s: FixedSettings, emitter):
        self.s = s
        self.emitter = emitter

    def timing(self) -> PulseTiming:
        return PulseTiming(prf_hz=self.s.prf_hz, rotation_hz=0.0, phase0_rad=0.0, field_prefix="fixed")

    def params(self, believed: bool):
        return fixed.Fixed()

    def max_off_axis_rad(self) -> float:
        """Largest angle of a beam from the sensor axis [rad]."""
        return float(np.arccos(np.clip(self.emitter.directions()[:, 2], -1.0, 1.0)).max())

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint at the slant range of the widest beam (no rigid-array model)."""
        return footprint_buffer_m(altitude_m, self.max_off_axis_rad(), divergence_mrad)
