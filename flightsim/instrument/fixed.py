"""Host side of the fixed deflector: beams leave as the emitter fires them."""
from __future__ import annotations

import math

import numpy as np

from flightsim.core.config import RunConfig
from flightsim.instrument.risley import FSM_ONLY, GALVO_ONLY, RISLEY_ONLY, refuse_errors
from kernels import fixed
from trajectories import PulseTiming


class FixedDeflector:
    """A staring instrument: pulses at ``sensor.prf_hz``, no scan."""

    kernel = fixed.FIXED

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg

    def check(self) -> None:
        refuse_errors(self.cfg, GALVO_ONLY, "galvo")
        refuse_errors(self.cfg, RISLEY_ONLY, "risley")
        refuse_errors(self.cfg, FSM_ONLY, "fsm")

    def timing(self) -> PulseTiming:
        return PulseTiming(prf_hz=self.cfg.sensor.prf_hz, rotation_hz=0.0, phase0_rad=0.0, field_prefix="sensor")

    def params(self, believed: bool) -> fixed.Fixed:
        return fixed.Fixed()

    believed_is_truth = True

    def reach_deg(self, emitter) -> float:
        return math.degrees(self.max_off_axis_rad(emitter))

    def max_off_axis_rad(self, emitter) -> float:
        """Largest angle of a beam from the sensor axis [rad]."""
        return float(np.arccos(np.clip(emitter.directions()[:, 2], -1.0, 1.0)).max())
