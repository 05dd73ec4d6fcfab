"""The ranging chain's errors (seed paper §2.1): what each source adds to a one-way range.

Every source is one-way range [m]; c is the speed of light in vacuum.
- fixed delay of each channel: a constant per channel, drawn once per run (seed) with 1σ ``channel_delay_m``;
- clock frequency drift: a scale error, ε = R·e_df;
- TDC quantisation of resolution τ: the start and the stop stamps are each rounded on their own clock
  phase, so the range error is (c/2)·τ·(u1 − u2), u uniform: triangular, σ_n = (c/2)·τ/√6;
- rising-edge jitter σ_t of each stamp: σ_j = (c/2)·√2·σ_t;
- constant-fraction leading-edge timing on an echo of rise time t_r and signal-to-noise ratio SNR
  with fraction k: σ_t = (t_r / SNR)·√(1 + k²), σ_ie = (c/2)·σ_t (our model: the paper's formula
  for it is not in the text we have; see results/change3/REPORT.md);
jitter, constant-fraction noise and ``sensor.range_noise_m`` are independent Gaussians, drawn as one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.config import RunConfig
from kernels import trace

C = 299_792_458.0  # [m/s]


@dataclass(frozen=True)
class RangingSigmas:
    """1σ of each random ranging source [m]."""

    noise: float  # sensor.range_noise_m
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


def sigmas(cfg: RunConfig) -> RangingSigmas:
    """The random ranging sources of a config [m]."""
    e = cfg.errors
    cfd = (e.rise_time_s / e.snr) * math.sqrt(1.0 + e.cfd_fraction ** 2) if e.rise_time_s > 0.0 else 0.0
    return RangingSigmas(noise=cfg.sensor.range_noise_m, tdc=C / 2.0 * e.tdc_bin_s / math.sqrt(6.0),
                         jitter=C / 2.0 * math.sqrt(2.0) * e.jitter_s, cfd=C / 2.0 * cfd)


def has_systematics(cfg: RunConfig) -> bool:
    """Whether the kernels need the ranging-chain branch (delays, drift, quantisation)."""
    e = cfg.errors
    return e.channel_delay_m > 0.0 or e.clock_drift != 0.0 or e.tdc_bin_s > 0.0 or e.range_bias_m != 0.0


def channel_delays(cfg: RunConfig, beams: int) -> np.ndarray:
    """Each beam's fixed delay [m]: the ranging bias range_bias_m plus a Gaussian with 1σ channel_delay_m,
    drawn from the run's seed."""
    if cfg.errors.channel_delay_m == 0.0:
        return np.full(beams, cfg.errors.range_bias_m)
    rng = np.random.default_rng([cfg.run.seed, 0x5EED])
    return cfg.errors.range_bias_m + rng.normal(0.0, cfg.errors.channel_delay_m, beams)


def range_errors(cfg: RunConfig, beams: int, device: str) -> trace.RangeErrors:
    """The kernels' struct of the ranging chain's systematic and quantisation errors."""
    errors = trace.RangeErrors()
    errors.tdc_bin = C / 2.0 * cfg.errors.tdc_bin_s
    errors.drift = cfg.errors.clock_drift
    errors.delays = wp.array(channel_delays(cfg, beams).astype(np.float32), dtype=wp.float32, device=device)
    return errors
