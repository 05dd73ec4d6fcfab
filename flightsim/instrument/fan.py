"""The N×N DOE fan emitter (``instrument.emitter = "fan"``, ``[fan]``): a diffractive element splits each
pulse into an N×N fan of sub-beams (SPEC §3)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from kernels import emitters

MAX_HALF_FAN_DEG = 80.0  # the fan's outermost sub-beam from its axis


@dataclass
class FanSettings(Settings):
    """The N×N sub-beams of the DOE fan."""

    array: int = setting(3, "beams per side of the N×N fan", "beams per side", range=(1, 64))
    spacing_mrad: float = setting(2.314, "angular spacing of neighbouring sub-beams", "mrad", range=(0.0, 200.0))
    divergence_mrad: float = setting(0.3, "full divergence angle of each sub-beam (sizes the footprint)", "mrad",
                                     range=(0.0, 100.0))

    def check(self, context) -> None:
        half_fan = (self.array - 1) / 2 * self.spacing_mrad * 1e-3
        if half_fan >= math.radians(MAX_HALF_FAN_DEG):
            limit = math.radians(MAX_HALF_FAN_DEG) / max((self.array - 1) / 2, 0.5) * 1e3
            raise InputError("fan.spacing_mrad", self.spacing_mrad,
                             f"a spacing below {limit:.3f} mrad for a {self.array}x{self.array} array "
                             f"(fan within ±{MAX_HALF_FAN_DEG:g} deg)")


@register("emitter", "fan")
class FanEmitter:
    """The N×N DOE fan of ``[fan]``; beam b = i·N + j."""

    settings = FanSettings
    kernel = emitters.FAN  # the kernel side: its struct and device functions

    def __init__(self, s: FanSettings):
        self.n = s.array
        self.spacing_rad = s.spacing_mrad * 1e-3
        self.divergence_mrad = s.divergence_mrad


    @property
    def beams_per_pulse(self) -> int:
        return self.n * self.n

    @property
    def half_diagonal_rad(self) -> float:
        """Largest angle of a sub-beam from the fan axis, to first order [rad]."""
        return math.sqrt(2.0) * (self.n - 1) / 2.0 * self.spacing_rad

    def directions(self) -> np.ndarray:
        """(n², 3) unit directions in the emitter frame, as kernels.optics.doe_direction."""
        offsets = (np.arange(self.n) - (self.n - 1) / 2.0) * np.float64(np.float32(self.spacing_rad))
        a, b = np.meshgrid(offsets, offsets, indexing="ij")
        d = np.stack([np.tan(a), np.tan(b), np.ones_like(a)], axis=-1).reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    @property
    def beam_columns(self) -> int:
        """Beam b is written to LAS as row b // columns, column b % columns: the fan's row i and column j."""
        return self.n

    def params(self, device: str):
        beams = emitters.BeamArray()
        beams.n = self.n
        beams.spacing = self.spacing_rad
        return beams
