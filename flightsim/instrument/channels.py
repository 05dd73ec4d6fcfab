"""The channel-array emitter (``instrument.emitter = "channels"``, ``[channels]``): a linear array of
channels fanned along the emitter's y axis (the Chang'e-3 imager's 16 beams, seed paper §2.3)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from kernels import emitters

MAX_CHANNELS = 255  # LAS beam_col is one byte
MAX_CHANNEL_MRAD = 500.0
CHANGE3_CHANNELS_MRAD = tuple(float(17 - 2 * i) for i in range(1, 17))  # θ_i = 17 − 2i (seed paper §2.3)


@dataclass
class ChannelsSettings(Settings):
    """A linear array of channels fanned along the emitter's y axis (a vertical fan behind a galvo)."""

    angles_mrad: tuple[float, ...] = setting(CHANGE3_CHANNELS_MRAD, "angle of each channel from the beam axis, "
                                             "towards +y", "mrad")
    divergence_mrad: float = setting(0.3, "full divergence angle of each channel's beam (sizes the footprint)",
                                     "mrad", range=(0.0, 100.0))

    def check(self, context) -> None:
        a = self.angles_mrad
        if not 1 <= len(a) <= MAX_CHANNELS or not all(abs(v) <= MAX_CHANNEL_MRAD for v in a):
            raise InputError("channels.angles_mrad", ",".join(f"{v:g}" for v in a),
                             f"1 to {MAX_CHANNELS} finite angles each within ±{MAX_CHANNEL_MRAD:g} mrad")


@register("emitter", "channels")
class ChannelEmitter:
    """The channels of ``[channels]``; beam b is channel b."""

    settings = ChannelsSettings
    kernel = emitters.CHANNELS  # the kernel side: its struct and device functions
    beam_columns = 256  # LAS beam_row 0, beam_col = the channel

    def __init__(self, s: ChannelsSettings):
        self.angles_mrad = tuple(s.angles_mrad)
        self.divergence_mrad = s.divergence_mrad


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

    def params(self, device: str):
        channels = emitters.Channels()
        channels.angles = wp.array(np.asarray(self.angles_mrad, dtype=np.float64) * 1e-3, dtype=wp.float64,
                                   device=device)
        return channels
