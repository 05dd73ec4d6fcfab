"""The ranging error model (``instrument.errors`` holds ``"ranging"``, ``[ranging]``): the ranging chain's errors
(seed paper §2.1), what each source adds to a one-way range.

Every source is one-way range [m]; c is the speed of light in vacuum.
- fixed delay of each channel: a constant per channel, drawn once per run (seed) with 1σ ``channel_delay_m``;
- clock frequency drift: a scale error, ε = R·e_df;
- TDC quantisation of resolution τ: the start and the stop stamps are each rounded on their own clock
  phase, so the range error is (c/2)·τ·(u1 − u2), u uniform: triangular, σ_n = (c/2)·τ/√6;
- rising-edge jitter σ_t of each stamp: σ_j = (c/2)·√2·σ_t;
- constant-fraction leading-edge timing on an echo of rise time t_r and signal-to-noise ratio SNR
  with fraction k: σ_t = (t_r / SNR)·√(1 + k²), σ_ie = (c/2)·σ_t (our model: the paper's formula
  for it is not in the text we have; see results/change3/REPORT.md);
jitter, constant-fraction noise and the range noise ``noise_m`` are independent Gaussians, drawn as one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from kernels import error_models

C = 299_792_458.0  # [m/s]


@dataclass(frozen=True)
class RangingSigmas:
    """1σ of each random ranging source [m]."""

    noise: float  # noise_m
    tdc: float  # quantisation
    jitter: float
    cfd: float  # constant-fraction leading edge

    @property
    def gaussian(self) -> float:
        """The Gaussian part: noise, jitter and constant-fraction timing together [m]."""
        return math.sqrt(self.noise ** 2 + self.jitter ** 2 + self.cfd ** 2)

    @property
    def random(self) -> float:
        """Every random source together [m]."""
        return math.sqrt(self.gaussian ** 2 + self.tdc ** 2)


@dataclass
class RangingSettings(Settings):
    """The ranging chain: range noise, each channel's fixed delay, a bias, clock drift, TDC, jitter and
    constant-fraction timing (all off by default)."""

    noise_m: float = setting(0.0, "Gaussian range noise of every return, 1 sigma", "m", range=(0.0, 100.0))
    channel_delay_m: float = setting(0.0, "each channel's fixed delay (drawn once per run from the seed), 1 sigma",
                                     "m", range=(0.0, 10.0))
    range_bias_m: float = setting(0.0, "added to every range (a ranging bias)", "m", range=(-100.0, 100.0))
    clock_drift: float = setting(0.0, "clock frequency drift e_df: the range reads R·(1 + e_df)", "",
                                 range=(-1.0e-3, 1.0e-3))
    tdc_bin_s: float = setting(0.0, "TDC resolution τ; 0 = exact stamps", "s", range=(0.0, 1.0e-6))
    jitter_s: float = setting(0.0, "rising-edge jitter of each time stamp, 1 sigma", "s", range=(0.0, 1.0e-6))
    rise_time_s: float = setting(0.0, "echo rise time t_r of the constant-fraction timing noise; 0 = off", "s",
                                 range=(0.0, 1.0e-6))
    cfd_fraction: float = setting(0.3, "constant fraction k", "", range=(0.0, 1.0))
    snr: float = setting(31.0, "echo signal-to-noise ratio of the constant-fraction timing", "", range=(0.0, 1.0e6),
                         lo_open=True)


@register("errors", "ranging")
class RangingErrors:
    """The ranging chain of ``[ranging]``; the default settings are no error at all."""

    settings = RangingSettings

    def __init__(self, s: RangingSettings | None = None, seed: int = 0):
        self.s = s or RangingSettings()
        self.seed = seed

    def sigmas(self) -> RangingSigmas:
        """The random ranging sources [m]."""
        e = self.s
        cfd = (e.rise_time_s / e.snr) * math.sqrt(1.0 + e.cfd_fraction ** 2) if e.rise_time_s > 0.0 else 0.0
        return RangingSigmas(noise=e.noise_m, tdc=C / 2.0 * e.tdc_bin_s / math.sqrt(6.0),
                             jitter=C / 2.0 * math.sqrt(2.0) * e.jitter_s, cfd=C / 2.0 * cfd)

    @property
    def has_systematics(self) -> bool:
        """Whether the kernels need the ranging-chain branch (delays, drift, quantisation)."""
        e = self.s
        return e.channel_delay_m > 0.0 or e.clock_drift != 0.0 or e.tdc_bin_s > 0.0 or e.range_bias_m != 0.0

    def channel_delays(self, beams: int) -> np.ndarray:
        """Each beam's fixed delay [m]: the ranging bias plus a Gaussian with 1σ channel_delay_m, drawn from the
        run's seed."""
        if self.s.channel_delay_m == 0.0:
            return np.full(beams, self.s.range_bias_m)
        rng = np.random.default_rng([self.seed, 0x5EED])
        return self.s.range_bias_m + rng.normal(0.0, self.s.channel_delay_m, beams)

    def struct(self, beams: int, device: str) -> error_models.RangeErrors:
        """The kernels' struct of the ranging chain's systematic and quantisation errors."""
        errors = error_models.RangeErrors()
        errors.tdc_bin = C / 2.0 * self.s.tdc_bin_s
        errors.drift = self.s.clock_drift
        errors.delays = wp.array(self.channel_delays(beams).astype(np.float32), dtype=wp.float32, device=device)
        return errors
