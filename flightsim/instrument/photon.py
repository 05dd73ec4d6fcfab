"""The photon-counting detector (``instrument.detector = "photon"``, ``[photon]``): a SPAD pixel with its own TDC
behind every beam (kernels/photon.py), its parameters checked and as the kernels' struct."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, check_settings, setting

photon = lazy_module("kernels.photon")

H = 6.62607015e-34  # Planck constant [J s]
C = 299_792_458.0  # [m/s]
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


@dataclass
class PhotonSettings(Settings):
    """One SPAD pixel with its own TDC per beam: the lidar equation's link, timing, background and dead time."""

    wavelength_nm: float = setting(532.0, "laser wavelength", "nm", range=(100.0, 20000.0))
    pulse_energy_j: float = setting(1.0e-9, "pulse energy per beam", "J", range=(0.0, 10.0), lo_open=True)
    aperture_m: float = setting(0.05, "receiver diameter", "m", range=(0.0, 10.0), lo_open=True)
    optics_transmission: float = setting(0.5, "receiver optics transmission", "", range=(0.0, 1.0), lo_open=True)
    pde: float = setting(0.2, "photon detection efficiency", "", range=(0.0, 1.0), lo_open=True)
    pulse_fwhm_s: float = setting(1.0e-9, "pulse width, full width at half maximum", "s", range=(0.0, 1.0e-6),
                                  lo_open=True)
    jitter_s: float = setting(1.0e-10, "timing jitter, 1 sigma", "s", range=(0.0, 1.0e-6))
    tdc_bin_s: float = setting(0.0, "TDC resolution; 0 = exact times", "s", range=(0.0, 1.0e-6))
    gate_m: tuple[float, float] = setting((5.0, 600.0), "range gate: start, end (one-way)", "m", length=2,
                                          items=(0.0, 1.0e7))
    noise_hz: float = setting(1.0e5, "background and dark counts per pixel", "Hz", range=(0.0, 1.0e10))
    dead_time_s: float = setting(5.0e-8, "dead time, non-paralyzable", "s", range=(0.0, 1.0e-3))
    max_events: int = setting(8, "detections kept per pixel and pulse", "detections", range=(1, 256))
    reflectance: float = setting(0.2, "Lambertian albedo of every face, unless the scene carries its own "
                                 "(scene.landcover)", "", range=(0.0, 1.0), lo_open=True)

    def check(self, context) -> None:
        if not self.gate_m[0] < self.gate_m[1]:
            raise InputError("photon.gate_m", ",".join(map(str, self.gate_m)),
                             "start, end with 0 ≤ start < end ≤ 1e7 m")
        if context is not None and context.optics == "lut":
            raise InputError("run.optics", "lut", "float32 or float64 with the photon detector")

    def detections_per_pulse(self) -> float:
        """Upper bound of the mean detections of one pixel per pulse over one surface echo: one signal
        detection where the dead time outlasts the echo (6σ), ``max_events`` where it does not, plus the
        mean background counts over the gate (the dead time only takes counts away); at most ``max_events``.
        Sizes a frame's photon arrays (a CCR's second echo or a canopy's leaves can add to it)."""
        gate_s = 2.0 * (self.gate_m[1] - self.gate_m[0]) / C
        signal = 1.0 if self.dead_time_s > 6.0 * sigma_t(self) else float(self.max_events)
        return min(float(self.max_events), signal + self.noise_hz * gate_s)


@register("detector", "photon")
class PhotonDetector:
    """A SPAD pixel with its own TDC behind every beam: ``[photon]``."""

    settings = PhotonSettings
    readouts = ("photons",)
    output = "photons"
    scored = False

    def __init__(self, s: PhotonSettings):
        self.s = s

    def struct(self) -> photon.PhotonDetector:
        return detector_struct(self.s)


def sigma_t(s: PhotonSettings) -> float:
    """Echo spread: the pulse's σ and the jitter in quadrature [s]."""
    return math.hypot(s.pulse_fwhm_s * FWHM_TO_SIGMA, s.jitter_s)


def detector_struct(s: PhotonSettings) -> photon.PhotonDetector:
    """The kernels' struct of ``[photon]`` (checked first)."""
    check_settings("photon", s)
    d = photon.PhotonDetector()
    d.photons_per_joule = s.wavelength_nm * 1e-9 / (H * C)
    d.pulse_energy = s.pulse_energy_j
    d.aperture_area = math.pi * (s.aperture_m / 2.0) ** 2
    d.efficiency = s.optics_transmission * s.pde
    d.sigma_t = sigma_t(s)
    d.gate_open, d.gate_close = (2.0 * g / C for g in s.gate_m)
    d.noise_rate = s.noise_hz
    d.dead_time = s.dead_time_s
    d.max_events = s.max_events
    d.tdc_bin = s.tdc_bin_s
    return d


@dataclass
class Detections:
    """Per slot: detection times of flight (slots, max_events) [s], signal flags, counts."""

    times: np.ndarray
    signal: np.ndarray
    counts: np.ndarray


def detect(s: PhotonSettings, n_signal, t0, seed: int = 0, first_slot: int = 0, device: str = "cpu") -> Detections:
    """Sample the detections of slots with expected signal ``n_signal`` [photo-electrons] echoing at
    time of flight ``t0`` [s] (the detector alone, without a scene)."""
    n_signal = np.ascontiguousarray(n_signal, dtype=np.float64)
    if not (np.all(np.isfinite(n_signal)) and (n_signal >= 0).all()):
        raise InputError("photon.signal", "negative or non-finite expected counts", "finite counts ≥ 0")
    det = detector_struct(s)
    slots = len(n_signal)
    times = wp.zeros((slots, s.max_events), dtype=wp.float64, device=device)
    signal = wp.zeros((slots, s.max_events), dtype=wp.int8, device=device)
    counts = wp.zeros(slots, dtype=wp.int32, device=device)
    wp.launch(photon.photon_events_kernel(), slots,
              inputs=[det, int(seed), wp.int64(first_slot), wp.array(n_signal, dtype=wp.float64, device=device),
                      wp.array(np.ascontiguousarray(t0, dtype=np.float64), dtype=wp.float64, device=device)],
              outputs=[times, signal, counts], device=device)
    return Detections(times.numpy(), signal.numpy(), counts.numpy())


def first_photon_bias_s(n_signal, sigma_s: float):
    """Mean time of the first of the echo's photo-electrons minus the echo's centre [s] (negative: early),
    for a Gaussian echo of spread ``sigma_s`` [s] with Poisson(``n_signal``) photo-electrons, given one was
    detected and the dead time outlasts the echo: the density is n φ(z) e^{−n Φ(z)} / (1 − e^{−n}), integrated by
    the trapezoid rule over z in [−10, 10] at 1e-4. ``n_signal``: a number (a float returned) or an array of them
    (an array of the same shape); each value the same bits as ``np.trapezoid``'s of the density alone."""
    from flightsim.core.process_map import by_pieces

    n = np.asarray(n_signal, dtype=np.float64)
    flat = n.ravel()
    means = np.concatenate([np.empty(0), *by_pieces(flat.size, lambda piece: _first_photon_means(flat[piece]),
                                                    least=FIRST_PHOTON_PIECE)])
    return float(means[0] * sigma_s) if n.ndim == 0 else means.reshape(n.shape) * sigma_s


FIRST_PHOTON_PIECE = 16  # the fewest strengths a thread of first_photon_bias_s takes (~1 ms each)


def _first_photon_means(n: np.ndarray) -> np.ndarray:
    """first_photon_bias_s's mean in units of σ of each strength of ``n``, one at a time (its rows stay in the
    caches: faster than a batch's)."""
    z, pdf, cdf, dz = _first_photon_grid()
    means = np.empty(n.size)
    row = np.empty((1, z.size))
    pairs = np.empty((1, z.size - 1))
    for i, k in enumerate(n):
        k = np.full((1, 1), k)
        np.exp(np.multiply(-k, cdf, out=row), out=row)
        density = np.multiply(k, pdf) * row  # as n * pdf * exp(−n Φ(z))
        total = _trapezoid(density, dz, pairs)
        means[i] = _trapezoid(np.multiply(density, z, out=density), dz, pairs) / total
    return means


@functools.cache
def _first_photon_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """first_photon_bias_s's nodes z, φ(z) (scipy.stats.norm.pdf's own expression), Φ(z) and the nodes' steps."""
    from scipy.special import ndtr

    z = np.linspace(-10.0, 10.0, 200_001)
    return z, np.exp(-z**2 / 2.0) / np.sqrt(2.0 * np.pi), ndtr(z), np.diff(z)


def _trapezoid(y: np.ndarray, dz: np.ndarray, pairs: np.ndarray) -> float:
    """``np.trapezoid(y, z, axis=-1)`` of one row with z's steps ``dz`` given, its sums in ``pairs``: the same
    operations in the same order (``(d * (y[1:] + y[:-1]) / 2.0).sum()``), so the same bits."""
    np.add(y[:, 1:], y[:, :-1], out=pairs)
    pairs *= dz
    pairs /= 2.0
    return float(pairs.sum())
