"""Host side of the emitters: validate their config, count and tabulate their beams, fill their structs."""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from flightsim.core.config import RunConfig
from flightsim.core.errors import InputError
from kernels import emitters

MAX_CHANNELS = 255  # LAS beam_col is one byte
MAX_CHANNEL_MRAD = 500.0


class FanEmitter:
    """The N×N DOE fan of ``[sensor]`` (array, spacing_mrad)."""

    kernel = emitters.FAN

    def __init__(self, cfg: RunConfig):
        self.n = cfg.sensor.array
        self.spacing_rad = cfg.sensor.spacing_mrad * 1e-3

    def check(self) -> None:
        """Fan limits are checked with the wedge optics (config._check_optics)."""

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

    def params(self, device: str) -> emitters.BeamArray:
        beams = emitters.BeamArray()
        beams.n = self.n
        beams.spacing = self.spacing_rad
        return beams


class ChannelEmitter:
    """A linear array of channels (``[channels] angles_mrad``), fanned along the emitter's y axis."""

    kernel = emitters.CHANNELS

    def __init__(self, cfg: RunConfig):
        self.angles_mrad = tuple(cfg.channels.angles_mrad)

    def check(self) -> None:
        a = self.angles_mrad
        allowed = f"1 to {MAX_CHANNELS} finite angles each within ±{MAX_CHANNEL_MRAD:g} mrad"
        if not 1 <= len(a) <= MAX_CHANNELS or not all(math.isfinite(v) and abs(v) <= MAX_CHANNEL_MRAD for v in a):
            raise InputError("channels.angles_mrad", ",".join(f"{v:g}" for v in a), allowed)

    @property
    def beams_per_pulse(self) -> int:
        return len(self.angles_mrad)

    @property
    def half_diagonal_rad(self) -> float:
        return max(abs(v) for v in self.angles_mrad) * 1e-3

    def directions(self) -> np.ndarray:
        """(channels, 3) unit directions (0, sin θ, cos θ) in the emitter frame."""
        theta = np.asarray(self.angles_mrad, dtype=np.float64) * 1e-3
        return np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], axis=-1)

    def params(self, device: str) -> emitters.Channels:
        channels = emitters.Channels()
        channels.angles = wp.array(np.asarray(self.angles_mrad, dtype=np.float64) * 1e-3, dtype=wp.float64,
                                   device=device)
        return channels
