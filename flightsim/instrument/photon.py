"""Host side of the photon-counting detector (kernels/photon.py): its parameters, checked, as the
kernels' struct, and a launch that returns a pixel's detections."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from kernels import photon

H = 6.62607015e-34  # Planck constant [J s]
C = 299_792_458.0  # [m/s]
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


@dataclass(frozen=True)
class PhotonSettings:
    """A SPAD pixel and its share of the laser (SI units; field names as in the config's [photon])."""

    wavelength_nm: float = 532.0
    pulse_energy_j: float = 1e-6  # energy in this pixel's sub-beam [J]
    aperture_m: float = 0.05  # receiver aperture diameter [m]
    optics_transmission: float = 0.5
    pde: float = 0.2  # photon detection efficiency
    pulse_fwhm_s: float = 1e-9
    jitter_s: float = 1e-10  # TDC and SPAD timing jitter, 1σ [s]
    gate_m: tuple[float, float] = (5.0, 600.0)  # range gate, one-way [m]
    noise_hz: float = 1e5  # solar background and dark counts [Hz]
    dead_time_s: float = 5e-8
    max_events: int = 8

    def check(self) -> None:
        """InputError naming the first field out of its range."""
        checks = [
            ("photon.wavelength_nm", self.wavelength_nm, 100.0 <= self.wavelength_nm <= 20000.0, "in [100, 20000] nm"),
            ("photon.pulse_energy_j", self.pulse_energy_j, 0.0 < self.pulse_energy_j <= 10.0, "in (0, 10] J"),
            ("photon.aperture_m", self.aperture_m, 0.0 < self.aperture_m <= 10.0, "in (0, 10] m"),
            ("photon.optics_transmission", self.optics_transmission, 0.0 < self.optics_transmission <= 1.0,
             "in (0, 1]"),
            ("photon.pde", self.pde, 0.0 < self.pde <= 1.0, "in (0, 1]"),
            ("photon.pulse_fwhm_s", self.pulse_fwhm_s, 0.0 < self.pulse_fwhm_s <= 1e-6, "in (0, 1e-6] s"),
            ("photon.jitter_s", self.jitter_s, 0.0 <= self.jitter_s <= 1e-6, "in [0, 1e-6] s"),
            ("photon.noise_hz", self.noise_hz, 0.0 <= self.noise_hz <= 1e10, "in [0, 1e10] Hz"),
            ("photon.dead_time_s", self.dead_time_s, 0.0 <= self.dead_time_s <= 1e-3, "in [0, 1e-3] s"),
            ("photon.max_events", self.max_events, 1 <= self.max_events <= 256, "an integer in [1, 256]"),
        ]
        for name, value, ok, allowed in checks:
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise InputError(name, value, allowed)
        lo, hi = self.gate_m
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi <= 1e7):
            raise InputError("photon.gate_m", f"{lo},{hi}", "0 ≤ start < end ≤ 1e7 m")

    @property
    def sigma_t(self) -> float:
        """Echo spread: the pulse's σ and the jitter in quadrature [s]."""
        return math.hypot(self.pulse_fwhm_s * FWHM_TO_SIGMA, self.jitter_s)

    def struct(self) -> photon.PhotonDetector:
        self.check()
        d = photon.PhotonDetector()
        d.photons_per_joule = self.wavelength_nm * 1e-9 / (H * C)
        d.pulse_energy = self.pulse_energy_j
        d.aperture_area = math.pi * (self.aperture_m / 2.0) ** 2
        d.efficiency = self.optics_transmission * self.pde
        d.sigma_t = self.sigma_t
        d.gate_open, d.gate_close = (2.0 * g / C for g in self.gate_m)
        d.noise_rate = self.noise_hz
        d.dead_time = self.dead_time_s
        d.max_events = self.max_events
        return d


@dataclass
class Detections:
    """Per slot: detection times of flight (slots, max_events) [s], signal flags, counts."""

    times: np.ndarray
    signal: np.ndarray
    counts: np.ndarray


def detect(settings: PhotonSettings, n_signal, t0, seed: int = 0, first_slot: int = 0,
           device: str = "cpu") -> Detections:
    """Sample the detections of slots with expected signal ``n_signal`` [photo-electrons] echoing at
    time of flight ``t0`` [s]."""
    n_signal = np.ascontiguousarray(n_signal, dtype=np.float64)
    if not (np.all(np.isfinite(n_signal)) and (n_signal >= 0).all()):
        raise InputError("photon.signal", "negative or non-finite expected counts", "finite counts ≥ 0")
    det = settings.struct()
    slots = len(n_signal)
    times = wp.zeros((slots, settings.max_events), dtype=wp.float64, device=device)
    signal = wp.zeros((slots, settings.max_events), dtype=wp.int8, device=device)
    counts = wp.zeros(slots, dtype=wp.int32, device=device)
    wp.launch(photon.photon_events, slots,
              inputs=[det, int(seed), wp.int64(first_slot), wp.array(n_signal, dtype=wp.float64, device=device),
                      wp.array(np.ascontiguousarray(t0, dtype=np.float64), dtype=wp.float64, device=device)],
              outputs=[times, signal, counts], device=device)
    return Detections(times.numpy(), signal.numpy(), counts.numpy())
