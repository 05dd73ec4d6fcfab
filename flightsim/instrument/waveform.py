"""The full-waveform detector part (``instrument.detector = "waveform"``, ``[waveform]``): each beam's
footprint sampled by sub-rays over its Gaussian profile, every sub-ray traced against the scene and
its echo summed into the beam's waveform on the device (kernels/waveform.py).

The sub-ray table (directions as offsets tan φ·(cos θ, sin θ) from the beam axis, and each one's
share of the pulse energy) is the float64 reference model's footprint
(:func:`flightsim.instrument.waveform_model.footprint`), so the device and the reference sample the
same rays.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from flightsim.core.config import RunConfig, WaveformConfig, check_fields
from flightsim.instrument import waveform_model as model
from kernels import waveform as kw


def system(s: WaveformConfig, altitude_m: float = 1.0) -> model.WaveformSystem:
    """The reference model's system of a ``[waveform]`` section (validated there, naming the field)."""
    return model.WaveformSystem(
        altitude_m=altitude_m, half_divergence_rad=s.half_divergence_rad, pulse_fwhm_s=s.pulse_fwhm_s,
        peak_power_w=s.peak_power_w, aperture_m=s.aperture_m, transmitter_efficiency=s.transmitter_efficiency,
        receiver_efficiency=s.receiver_efficiency, atmosphere_transmission=s.atmosphere_transmission,
        reflectance=s.reflectance, n_rings=s.n_rings, n_sectors=s.n_sectors, sample_interval_s=s.sample_interval_s,
        scheme=s.scheme)


@dataclasses.dataclass
class SubRays:
    """The footprint's sub-rays on a device: offsets (tan φ cos θ, tan φ sin θ) and energy shares."""

    offsets: wp.array  # vec2d
    weights: wp.array  # float64, summing to 1 (the disc of radius Hα holds the pulse, the patent's eq. 7)

    def __len__(self) -> int:
        return len(self.weights)


class WaveformDetector:
    """A full waveform per beam: ``[waveform]``."""

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg

    def check(self) -> None:
        check_fields("waveform", self.cfg.waveform)
        system(self.cfg.waveform)

    def footprint_deg(self) -> float:
        """Angle of the footprint's edge (tan φ = α) from its beam's axis [deg]."""
        return math.degrees(math.atan(self.cfg.waveform.half_divergence_rad))

    def subrays(self, device: str) -> SubRays:
        fp = model.footprint(system(self.cfg.waveform))
        offsets = np.column_stack([fp.x_m, fp.y_m])  # at unit altitude: tan φ (cos θ, sin θ)
        return SubRays(wp.array(offsets, dtype=wp.vec2d, device=device),
                       wp.array(fp.weight, dtype=wp.float64, device=device))

    def struct(self) -> kw.WaveformParams:
        s = self.cfg.waveform
        sys = system(s)
        params = kw.WaveformParams()
        params.link = (np.pi * s.reflectance * s.atmosphere_transmission ** 2 * s.aperture_m ** 2
                       * s.transmitter_efficiency * s.receiver_efficiency / 4.0)
        params.dt = s.sample_interval_s
        params.samples = s.samples
        params.sigma = model.pulse_sigma_s(sys)
        params.centre = 0.5 * s.pulse_fwhm_s
        params.peak_power = s.peak_power_w
        return params

    def pulse_taps(self, device: str) -> tuple[wp.array, int]:
        """(P at multiples of dt over its ±PULSE_SIGMAS σ, the first tap's lag in samples): the kernel the
        binned echo is convolved with [W]."""
        sys = system(self.cfg.waveform)
        dt, sigma, centre = sys.sample_interval_s, model.pulse_sigma_s(sys), 0.5 * sys.pulse_fwhm_s
        first = int(np.floor((centre - kw.PULSE_SIGMAS * sigma) / dt))
        last = int(np.ceil((centre + kw.PULSE_SIGMAS * sigma) / dt))
        lags = np.arange(first, last + 1, dtype=np.float64)
        return wp.array(model.pulse_power_w(sys, lags * dt), dtype=wp.float64, device=device), first
