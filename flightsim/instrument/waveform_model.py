"""Float64 reference model of a large-footprint full-waveform lidar echo (NumPy and SciPy only, no Warp).

Source: patent CN1959431 (``seeds/large-footprint-echo-waveform-patent.txt``), a Chang'e-1-like lunar
laser altimeter: a Gaussian pulse in time (eqs. 2–3) and in angle (eq. 4), the lidar equation (eq. 1),
the footprint cut into rings × sectors each taken as a plane at one height (eqs. 13, 15) and the echo
as the sum of the cells' delayed pulses (eqs. 14–18). This module is the reference that the device
kernels of a full-waveform detector are tested against.

Conventions (SI units throughout: m, s, W, J, rad):
- The sensor is at (0, 0, H) above the datum z = 0; a surface is a height z(x, y) above the datum.
- Time t counts from the instant the transmitted pulse rises through half its peak: eq. 2 centres
  the Gaussian at τ/2, and (τ/2)² / 2σ² = ln 2 with σ of eq. 3, so P(0) = P_max / 2. A point at range
  r returns P(t − 2r/c) (eq. 11), so an echo's leading half-power time reads 2r/c directly.
- The footprint edge is R = Hα, the 1/e² radius of the profile exp(−2 tan²φ / α²) (eq. 4), which on
  the datum (tan φ = ρ/H) is exp(−2ρ²/R²) (eq. 6). The patent truncates the beam there and scales
  the profile so the disc holds the whole pulse (eq. 7, the factor 1 − e⁻²); ``footprint_holds_all_energy``
  = False keeps the untruncated Gaussian's share instead, 1 − e⁻² ≈ 0.865 of the pulse inside R.

Where the patent is silent or loose, chosen here:
- Receiver aperture D, the efficiencies η_t, η_r, the transmission T_A and the backscatter f are 1,
  as the patent's embodiment sets "every other parameter" (T_A = 1: no atmosphere on the Moon).
- ``geometry="ray"`` (default) intersects each sample's ray with the surface; ``"vertical"`` is the
  patent's eq. 10, the height at the sample's datum point (x, y) and r = √(ρ² + (H − h)²).
- ``incidence_cosine`` multiplies eq. 1 by the Lambertian cos θ_i (the patent's f is a constant).
- The cell weights of ``scheme="polar"`` are the profile integrated over each ring × sector, as eqs.
  17–18 do (only the delay and 1/r² term is taken at the cell's point of eq. 15); ``"polar_midpoint"``
  takes the profile at that point times the cell's area instead.
- The bump of Fig. 5 ("flat all round, a bump in the middle") has no stated size: a raised-cosine
  hill 5 m high, 20 m in radius, centred on nadir (the surfaces: :mod:`flightsim.instrument.waveform_surfaces`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from flightsim.core.errors import InputError
from flightsim.instrument.waveform_surfaces import BumpSurface, PlaneSurface

C = 299_792_458.0  # speed of light [m/s]
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # a Gaussian's FWHM / σ (eq. 3)
SCHEMES = ("polar", "polar_midpoint", "equal_energy")
GEOMETRIES = ("ray", "vertical")
PATENT_SLOPE = 0.20  # rise/run of the patent's Fig. 4
_CHUNK = 16  # samples per block of the analytic echo (8·_CHUNK·bins bytes)
_PAD_SIGMAS = 10.0  # time base margin beyond the first and last pulse centres [σ]


def _check(ok: bool, name: str, value, allowed: str) -> None:
    if not ok:
        raise InputError(f"waveform.{name}", value, allowed)


@dataclass(frozen=True)
class WaveformSystem:
    """The altimeter, its footprint sampling and the model's choices; patent values by default."""

    altitude_m: float = 200e3  # H, sensor above the datum (the nadir point of flat ground) [m]
    half_divergence_rad: float = 3e-4  # α, half beam width: profile exp(−2 tan²φ/α²) (eq. 4) [rad]
    pulse_fwhm_s: float = 7e-9  # τ, half-power pulse width (eqs. 2–3) [s]
    peak_power_w: float = 0.05  # P_max, transmitted peak power (eq. 3) [W]
    aperture_m: float = 1.0  # D, receiver aperture diameter (eq. 1) [m]
    transmitter_efficiency: float = 1.0  # η_t (eq. 1)
    receiver_efficiency: float = 1.0  # η_r (eq. 1)
    atmosphere_transmission: float = 1.0  # T_A, one way (eq. 1)
    reflectance: float = 1.0  # f, the surface's backscatter of eq. 1 (Lambertian albedo ρ: f = ρ/π)
    n_rings: int = 60  # rings of the footprint (eq. 13)
    n_sectors: int = 120  # sectors of 2π/n_sectors each (eq. 13: π/60)
    sample_interval_s: float = 1e-11  # dt of the echo's time base: 0.01 ns, 1.5 mm of range
    scheme: str = "polar"  # footprint sampling: one of SCHEMES
    geometry: str = "ray"  # one of GEOMETRIES
    incidence_cosine: bool = True  # Lambertian cos θ_i in eq. 1
    footprint_holds_all_energy: bool = True  # eq. 7: the disc of radius Hα carries the whole pulse

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "float" and not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise InputError(f"waveform.{f.name}", value, "a finite number")
        _check(self.altitude_m > 0, "altitude_m", self.altitude_m, "> 0 m")
        _check(0 < self.half_divergence_rad < math.pi / 2, "half_divergence_rad", self.half_divergence_rad,
               "in (0, π/2) rad")
        _check(self.pulse_fwhm_s > 0, "pulse_fwhm_s", self.pulse_fwhm_s, "> 0 s")
        for name in ("peak_power_w", "aperture_m", "reflectance"):
            _check(getattr(self, name) > 0, name, getattr(self, name), "> 0")
        for name in ("transmitter_efficiency", "receiver_efficiency", "atmosphere_transmission"):
            _check(0 < getattr(self, name) <= 1, name, getattr(self, name), "in (0, 1]")
        for name in ("n_rings", "n_sectors"):
            value = getattr(self, name)
            _check(isinstance(value, int) and value >= 1, name, value, "an integer ≥ 1 (a non-empty footprint)")
        _check(0 < self.sample_interval_s <= self.pulse_fwhm_s, "sample_interval_s", self.sample_interval_s,
               f"in (0, pulse_fwhm_s = {self.pulse_fwhm_s:g}] s")
        _check(self.scheme in SCHEMES, "scheme", self.scheme, " or ".join(SCHEMES))
        _check(self.geometry in GEOMETRIES, "geometry", self.geometry, " or ".join(GEOMETRIES))


PATENT = WaveformSystem(geometry="vertical", incidence_cosine=False)  # the patent's eqs. 10 and 1 literally


# --- the transmitted pulse (eqs. 2–3) ---------------------------------------------------------

def pulse_sigma_s(system: WaveformSystem) -> float:
    """σ = τ / (2√(2 ln 2)) of the Gaussian pulse (eq. 3) [s]."""
    return system.pulse_fwhm_s / FWHM_PER_SIGMA


def pulse_energy_j(system: WaveformSystem) -> float:
    """A = √(2π) σ P_max = √π τ P_max / (2√(ln 2)), the pulse energy (eq. 3) [J]."""
    return math.sqrt(2.0 * math.pi) * pulse_sigma_s(system) * system.peak_power_w


def pulse_power_w(system: WaveformSystem, t_s) -> np.ndarray:
    """P(t) = A / (√(2π) σ) · exp(−(t − τ/2)² / 2σ²), the transmitted power (eq. 2) [W]."""
    x = (np.asarray(t_s, dtype=np.float64) - 0.5 * system.pulse_fwhm_s) / pulse_sigma_s(system)
    return system.peak_power_w * np.exp(-0.5 * x * x)


@dataclass(frozen=True)
class PulseMoments:
    """Closed-form moments of P(t): ∫P dt [J], mean and RMS width of P as a density [s], FWHM [s], peak [W]."""

    energy_j: float
    mean_s: float
    rms_width_s: float
    fwhm_s: float
    peak_w: float


def pulse_moments(system: WaveformSystem) -> PulseMoments:
    """The pulse's moments (eqs. 2–3): energy A, mean τ/2, RMS width σ, FWHM τ, peak P_max."""
    return PulseMoments(pulse_energy_j(system), 0.5 * system.pulse_fwhm_s, pulse_sigma_s(system),
                        system.pulse_fwhm_s, system.peak_power_w)


# --- footprint sampling (eqs. 4–7, 13, 15) ----------------------------------------------------

@dataclass(frozen=True)
class Footprint:
    """Samples of the transmitted beam: ``x_m``, ``y_m`` where each sample's direction meets the datum
    [m]; ``weight`` its fraction of the transmitted energy; ``direction`` (N, 3) unit vectors from the
    sensor."""

    x_m: np.ndarray
    y_m: np.ndarray
    weight: np.ndarray
    direction: np.ndarray


def edge_radius_m(system: WaveformSystem) -> float:
    """R = Hα, the footprint's radius on the datum (eqs. 6, 15) [m]."""
    return system.altitude_m * system.half_divergence_rad


def _disc_fraction(system: WaveformSystem) -> float:
    """Share of the transmitted energy in the disc ρ ≤ R: 1 (eq. 7) or the untruncated 1 − e⁻²."""
    return 1.0 if system.footprint_holds_all_energy else 1.0 - math.exp(-2.0)


def _profile_mass(u_inner: np.ndarray, u_outer: np.ndarray) -> np.ndarray:
    """Share of an untruncated Gaussian beam between u = 2ρ²/R² values: e^(−u_inner) − e^(−u_outer)."""
    return np.exp(-u_inner) - np.exp(-u_outer)


def _sectors(system: WaveformSystem) -> np.ndarray:
    """Mid-angles θ_n = (n − ½)·2π/N of the sectors (eq. 15) [rad]."""
    return (np.arange(system.n_sectors) + 0.5) * (2.0 * math.pi / system.n_sectors)


def _polar_rings(system: WaveformSystem) -> tuple[np.ndarray, np.ndarray]:
    """(ρ_m, ring share) of the patent's rings of equal width R/M: ρ_m = (m − ½)R/M (eq. 15); the share is
    the profile integrated over the annulus (eqs. 17–18) or, for ``polar_midpoint``, the profile at ρ_m
    times the annulus area 2πρ_m·R/M, each over πR²/2 (the untruncated beam's ∫ e^(−2ρ²/R²) dA)."""
    m = np.arange(system.n_rings, dtype=np.float64)
    rho_over_r = (m + 0.5) / system.n_rings
    if system.scheme == "polar_midpoint":
        share = 4.0 * rho_over_r * np.exp(-2.0 * rho_over_r ** 2) / system.n_rings
    else:
        share = _profile_mass(2.0 * (m / system.n_rings) ** 2, 2.0 * ((m + 1.0) / system.n_rings) ** 2)
    return rho_over_r * edge_radius_m(system), share


def _equal_energy_rings(system: WaveformSystem) -> tuple[np.ndarray, np.ndarray]:
    """(ρ_m, ring share) of rings holding equal energy, each sampled at its weighted RMS radius: with
    u = 2ρ²/R², the bounds are e^(−u_m) = 1 − (m/M)(1 − e⁻²) and a ring [a, b] has
    E[u] = [(1 + a)e^(−a) − (1 + b)e^(−b)] / (e^(−a) − e^(−b)), so the footprint's E[ρ²] is exact."""
    m = np.arange(system.n_rings + 1, dtype=np.float64)
    u = -np.log1p(-(m / system.n_rings) * (1.0 - math.exp(-2.0)))
    a, b = u[:-1], u[1:]
    mean_u = ((1.0 + a) * np.exp(-a) - (1.0 + b) * np.exp(-b)) / _profile_mass(a, b)
    return edge_radius_m(system) * np.sqrt(0.5 * mean_u), _profile_mass(a, b)


def footprint(system: WaveformSystem) -> Footprint:
    """The footprint's samples by ``system.scheme``: ``polar`` and ``polar_midpoint``, the patent's
    n_rings × n_sectors cells out to R = Hα (eqs. 13, 15); ``equal_energy``, rings of equal energy each
    at its RMS radius. Weights sum to the disc's share of the pulse (1 by eq. 7, else 1 − e⁻²)."""
    rings = _equal_energy_rings if system.scheme == "equal_energy" else _polar_rings
    rho, share = rings(system)
    theta = _sectors(system)
    x = (rho[:, None] * np.cos(theta)[None, :]).ravel()
    y = (rho[:, None] * np.sin(theta)[None, :]).ravel()
    scale = _disc_fraction(system) / (1.0 - math.exp(-2.0))
    weight = np.repeat(share * scale / system.n_sectors, system.n_sectors)
    d = np.stack([x, y, np.full_like(x, -system.altitude_m)], axis=-1)
    return Footprint(x, y, weight, d / np.linalg.norm(d, axis=-1, keepdims=True))


# --- per-sample returns (eqs. 1, 8–11) --------------------------------------------------------

@dataclass(frozen=True)
class Returns:
    """Each sample's return: ``point_m`` (N, 3) where it meets the surface, ``range_m`` from the
    sensor [m], ``delay_s`` = 2r/c [s], ``cos_incidence``, and ``gain`` = its received power / the
    transmitted power at the same instant (eq. 1 times its weight)."""

    point_m: np.ndarray
    range_m: np.ndarray
    delay_s: np.ndarray
    cos_incidence: np.ndarray
    gain: np.ndarray


def sample_returns(system: WaveformSystem, fp: Footprint, surface) -> Returns:
    """Range, delay and received share of each sample off ``surface`` (``PlaneSurface``, ``BumpSurface``):
    ray geometry (the sample's ray meets the surface) or the patent's vertical one (eq. 10); then
    P_r / P_s = w · π f T_A² D² η_t η_r cos θ_i / (4 r²) (eq. 1, cos θ_i = 1 without ``incidence_cosine``)."""
    sensor = np.array([0.0, 0.0, system.altitude_m])
    if system.geometry == "ray":
        r = surface.intersect(system.altitude_m, fp.direction)
        point = sensor + r[:, None] * fp.direction
        toward = fp.direction
    else:
        point = np.stack([fp.x_m, fp.y_m, surface.height(fp.x_m, fp.y_m)], axis=-1)
        r = np.linalg.norm(point - sensor, axis=-1)
        toward = (point - sensor) / r[:, None]
    cos_i = -np.sum(toward * surface.normal(point[:, 0], point[:, 1]), axis=-1)
    link = (math.pi * system.reflectance * system.atmosphere_transmission ** 2 * system.aperture_m ** 2
            * system.transmitter_efficiency * system.receiver_efficiency / 4.0)
    lambert = cos_i if system.incidence_cosine else 1.0
    return Returns(point, r, 2.0 * r / C, cos_i, fp.weight * link * lambert / r ** 2)


# --- the echo (eqs. 14, 18) -------------------------------------------------------------------

def time_base(system: WaveformSystem, rets: Returns) -> np.ndarray:
    """Times [s], multiples of dt, from 10σ before the first pulse centre (2r_min/c + τ/2) to 10σ after
    the last: the whole echo, where the patent's window [t_min − τ, t_max + τ] cuts its trailing tail."""
    dt, centre, pad = system.sample_interval_s, 0.5 * system.pulse_fwhm_s, _PAD_SIGMAS * pulse_sigma_s(system)
    first = math.floor((rets.delay_s.min() + centre - pad) / dt)
    last = math.ceil((rets.delay_s.max() + centre + pad) / dt)
    return dt * np.arange(first, last + 1, dtype=np.float64)


def patent_window(system: WaveformSystem, rets: Returns) -> tuple[float, float]:
    """The patent's sampling interval [t_min − τ, t_max + τ] (step 2c) [s]."""
    return float(rets.delay_s.min() - system.pulse_fwhm_s), float(rets.delay_s.max() + system.pulse_fwhm_s)


def echo_analytic(system: WaveformSystem, rets: Returns, times_s: np.ndarray) -> np.ndarray:
    """Received power [W] at ``times_s``: Σ_i gain_i · P(t − 2r_i/c) (eqs. 14, 18), each Gaussian
    evaluated at every time, so the only approximation is the footprint's sampling."""
    sigma = pulse_sigma_s(system)
    x = times_s / sigma
    centre = (rets.delay_s + 0.5 * system.pulse_fwhm_s) / sigma  # pulse centres [σ]
    echo = np.zeros_like(x)
    for lo in range(0, centre.size, _CHUNK):
        g = np.subtract.outer(centre[lo:lo + _CHUNK], x)  # in place from here: the block stays in cache
        g *= g
        g *= -0.5
        echo += rets.gain[lo:lo + _CHUNK] @ np.exp(g, out=g)
    return system.peak_power_w * echo


def echo_binned(system: WaveformSystem, rets: Returns, times_s: np.ndarray, binning: str = "linear") -> np.ndarray:
    """Received power [W] at ``times_s`` (uniform, step dt) as a device computes it: each sample's gain
    added to the dt bins of its delay, ``nearest`` bin or ``linear`` (split between the two neighbours in
    proportion), then convolved with P sampled at multiples of dt."""
    if binning not in ("linear", "nearest"):
        raise InputError("waveform.binning", binning, "linear or nearest")
    dt = times_s[1] - times_s[0]
    u = (rets.delay_s - times_s[0]) / dt
    if binning == "linear":
        k = np.floor(u)
        bins = np.concatenate([k, k + 1.0]).astype(np.int64)
        gains = np.concatenate([rets.gain * (k + 1.0 - u), rets.gain * (u - k)])
    else:
        bins, gains = np.rint(u).astype(np.int64), rets.gain
    lo = bins.min()
    histogram = np.bincount(bins - lo, weights=gains)
    n, length = times_s.size, histogram.size
    lags = np.arange(-(lo + length - 1), n - lo, dtype=np.float64)  # every j − k, output j, bin k
    from scipy.signal import fftconvolve  # here, not at import: scipy.signal costs every run 0.6 s

    return fftconvolve(histogram, pulse_power_w(system, lags * dt))[length - 1:length - 1 + n]


# --- ranging ----------------------------------------------------------------------------------

def _crossing(times_s: np.ndarray, echo: np.ndarray, j: int, level: float) -> float:
    """Time where the echo crosses ``level`` between samples j and j + 1, linearly interpolated [s]."""
    return times_s[j] + (level - echo[j]) / (echo[j + 1] - echo[j]) * (times_s[j + 1] - times_s[j])


def half_power_time_s(times_s: np.ndarray, echo: np.ndarray) -> float:
    """Leading edge: the first crossing of half the echo's maximum [s] (the patent's half-power point);
    the echo must start below half its maximum, as on ``time_base``."""
    above = np.flatnonzero(echo >= 0.5 * echo.max())
    return _crossing(times_s, echo, above[0] - 1, 0.5 * echo.max())


def fwhm_s(times_s: np.ndarray, echo: np.ndarray) -> float:
    """Last minus first crossing of half the maximum [s]."""
    above = np.flatnonzero(echo >= 0.5 * echo.max())
    return _crossing(times_s, echo, above[-1], 0.5 * echo.max()) - half_power_time_s(times_s, echo)


def centroid_time_s(times_s: np.ndarray, echo: np.ndarray) -> float:
    """Σ t·P / Σ P [s]."""
    return float(np.sum(times_s * echo) / np.sum(echo))


def rms_width_s(times_s: np.ndarray, echo: np.ndarray) -> float:
    """√(Σ (t − t̄)² P / Σ P) [s]; NaN where that moment is not ≥ 0 (a noisy window's samples below its mean weigh
    negative), as the device's measures make it."""
    with np.errstate(invalid="ignore", divide="ignore"):
        moment = float(np.sum((times_s - centroid_time_s(times_s, echo)) ** 2 * echo) / np.sum(echo))
    return math.sqrt(moment) if moment >= 0.0 else math.nan


def peak_time_s(times_s: np.ndarray, echo: np.ndarray) -> float:
    """Time of the maximum, refined by the parabola through it and its two neighbours [s]."""
    j = int(np.clip(np.argmax(echo), 1, echo.size - 2))
    y0, y1, y2 = echo[j - 1:j + 2]
    return times_s[j] + 0.5 * (y0 - y2) / (y0 - 2.0 * y1 + y2) * (times_s[j + 1] - times_s[j])


@dataclass(frozen=True)
class EchoMeasures:
    """The echo's times [s] and widths [s], and the ranges [m] each time reads: half-power c·t/2
    (the pulse's own half-power point is t = 0), centroid and peak c·(t − τ/2)/2."""

    half_power_s: float
    centroid_s: float
    peak_s: float
    fwhm_s: float
    rms_width_s: float
    half_power_range_m: float
    centroid_range_m: float
    peak_range_m: float


NOISE_END_SAMPLES = 64  # samples at each end of a window that its noise is taken from (as l2a.h5's default)
NOISE_FALSE_ECHO = 0.01  # share of noise-only windows in which Gaussian noise would still cross the floor somewhere


def window_noise(echo_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, floor) [W] of each row's receiver noise: the mean and standard deviation σ (ddof 1) of its first and
    last NOISE_END_SAMPLES samples pooled (at most a quarter of the window each), and the floor k·σ above the mean
    that Gaussian noise alone exceeds somewhere in an N-sample window in NOISE_FALSE_ECHO of windows
    (k = Φ⁻¹(1 − NOISE_FALSE_ECHO / N): 4.5 for N = 3000)."""
    from scipy.special import ndtri

    rows = np.asarray(echo_rows, dtype=np.float64)
    n = rows.shape[1]
    mean, sigma = end_noise(rows, max(2, min(NOISE_END_SAMPLES, n // 4)))
    return mean, float(ndtri(1.0 - NOISE_FALSE_ECHO / n)) * sigma


def end_noise(rows: np.ndarray, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, σ) of each row's first and last ``samples`` samples pooled (σ with ddof 1): a window's noise where its
    echo is away from both ends (rows (S, N) float64, N ≥ 2·samples)."""
    ends = np.concatenate([rows[:, :samples], rows[:, -samples:]], axis=1)
    return ends.mean(axis=1), ends.std(axis=1, ddof=1)


def measure(system: WaveformSystem, times_s: np.ndarray, echo: np.ndarray,
            noise: tuple[float, float] | None = None) -> EchoMeasures:
    """Half-power, centroid and peak times, FWHM and RMS width of ``echo``, and their ranges.

    ``noise``: (mean, floor) [W] of the receiver's noise (:func:`window_noise`), or None for a noise-free echo. The
    mean is taken off every sample, and the centroid and RMS width are the moments of the samples from the first to
    the last above the floor (over the whole window, a noisy echo's moments are the noise's); where no sample is
    above it, every measure is NaN."""
    mean, floor = (0.0, -np.inf) if noise is None else noise
    echo = echo - mean
    above = np.flatnonzero(echo > floor)
    if above.size == 0:
        return EchoMeasures(*[math.nan] * 8)
    extent = slice(above[0], above[-1] + 1)
    half, peak = half_power_time_s(times_s, echo), peak_time_s(times_s, echo)
    centroid = centroid_time_s(times_s[extent], echo[extent])
    centre = 0.5 * system.pulse_fwhm_s
    return EchoMeasures(half, centroid, peak, fwhm_s(times_s, echo), rms_width_s(times_s[extent], echo[extent]),
                        0.5 * C * half, 0.5 * C * (centroid - centre), 0.5 * C * (peak - centre))


@dataclass(frozen=True)
class GaussianComponent:
    """One fitted Gaussian a·exp(−(t − t₀)²/2s²): t₀ ``time_s`` [s], a ``amplitude_w`` [W], s ``sigma_s`` [s]."""

    time_s: float
    amplitude_w: float
    sigma_s: float


def _gaussians(x: np.ndarray, *p: float) -> np.ndarray:
    """Σ_k a_k exp(−(x − μ_k)²/2s_k²) with p = (a_1, μ_1, s_1, a_2, ...)."""
    a, mu, s = (np.asarray(p[i::3])[:, None] for i in range(3))
    return np.sum(a * np.exp(-0.5 * ((x[None, :] - mu) / s) ** 2), axis=0)


def decompose(system: WaveformSystem, times_s: np.ndarray, echo: np.ndarray, min_prominence: float = 0.05,
              noise: tuple[float, float] | None = None) -> tuple[GaussianComponent, ...]:
    """Gaussian decomposition: k = the local maxima of the echo smoothed by the pulse's σ (a matched
    filter) standing out by ``min_prominence`` of its maximum; then k Gaussians fitted by least squares
    (scipy ``curve_fit``), started at those maxima. Components in time order; none where no maximum stands out
    (a window of noise alone).

    ``noise``: (mean, floor) [W] of the receiver's noise (:func:`window_noise`), or None for a noise-free echo. The
    mean is taken off every sample (the Gaussians have no offset: a background left in is fitted into them), a
    maximum counts only where the smoothed echo stands above the floor scaled to the smoothing
    (:func:`smoothing_gain`: noise alone crosses it no more often than it crosses the floor), and each fit starts
    from the smoothed echo's height at its maximum (a noisy sample there can be below zero, outside a ≥ 0)."""
    from scipy.ndimage import gaussian_filter1d
    from scipy.optimize import curve_fit
    from scipy.signal import find_peaks, peak_widths

    mean, floor = (0.0, -np.inf) if noise is None else noise
    echo = echo - mean
    sigma, dt = pulse_sigma_s(system), times_s[1] - times_s[0]
    smooth = gaussian_filter1d(echo, sigma / dt)
    height = None if noise is None else floor * smoothing_gain(sigma / dt)
    peaks, _ = find_peaks(smooth, height=height, prominence=min_prominence * smooth.max())
    if peaks.size == 0:
        return ()
    widths = peak_widths(smooth, peaks, rel_height=0.5)[0] * dt / FWHM_PER_SIGMA
    scale = echo.max()
    start = echo if noise is None else smooth
    x = (times_s - times_s[0]) / sigma  # fit in units of σ and of the maximum: well conditioned
    p0 = np.ravel([[start[j] / scale, x[j], max(math.sqrt(max(w * w - sigma * sigma, 0.0)), 0.5 * sigma) / sigma]
                   for j, w in zip(peaks, widths)])
    lower = np.tile([0.0, x[0], dt / sigma], peaks.size)
    upper = np.tile([np.inf, x[-1], x[-1] - x[0]], peaks.size)
    p, _ = curve_fit(_gaussians, x, echo / scale, p0=p0, bounds=(lower, upper))
    parts = [GaussianComponent(float(times_s[0] + mu * sigma), float(a * scale), float(s * sigma))
             for a, mu, s in p.reshape(-1, 3)]
    return tuple(sorted(parts, key=lambda g: g.time_s))


def smoothing_weights(sd: float) -> np.ndarray:
    """The 2R + 1 weights of gaussian_filter1d(·, ``sd`` samples), by scipy's formula (``_gaussian_kernel1d``,
    truncated at R = int(4·sd + 0.5))."""
    radius = int(4.0 * sd + 0.5)
    phi = np.exp(-0.5 / (sd * sd) * np.arange(-radius, radius + 1) ** 2)
    return phi / phi.sum()


def smoothing_gain(sd: float) -> float:
    """The standard deviation of white noise of unit σ after gaussian_filter1d(·, ``sd`` samples): the root of its
    weights' sum of squares."""
    return float(np.sqrt(np.sum(smoothing_weights(sd) ** 2)))


# --- truth and the patent's figures -----------------------------------------------------------

def nadir_range_m(system: WaveformSystem, surface) -> float:
    """H − z(0, 0), the sensor's distance to the nadir point [m]."""
    return system.altitude_m - float(surface.height(0.0, 0.0))


def mean_height_m(fp: Footprint, rets: Returns) -> float:
    """Σ w·z / Σ w over the samples' surface points: the footprint-weighted mean height [m]."""
    return float(np.sum(fp.weight * rets.point_m[:, 2]) / np.sum(fp.weight))


def patent_figures(system: WaveformSystem = PATENT) -> dict[str, dict]:
    """The numbers of the patent's Figs. 3–5 (flat, slope 0.20, flat with a bump in the middle): the
    first and last returns' delays and the patent's window [s], the echo's half-power, peak and centroid
    times and widths [s], the nadir's time 2R_n/c [s] and range [m], the weighted mean height [m], the
    half-power range and its error against nadir [m], and the Gaussian components (t, a, s)."""
    surfaces = {"flat": PlaneSurface(0.0), "slope": PlaneSurface(PATENT_SLOPE), "bump": BumpSurface()}
    fp = footprint(system)
    figures = {}
    for name, surface in surfaces.items():
        rets = sample_returns(system, fp, surface)
        times = time_base(system, rets)
        echo = echo_analytic(system, rets, times)
        m = measure(system, times, echo)
        nadir = nadir_range_m(system, surface)
        figures[name] = {
            "first_return_s": float(rets.delay_s.min()), "last_return_s": float(rets.delay_s.max()),
            "window_s": patent_window(system, rets),
            "half_power_s": m.half_power_s, "peak_s": m.peak_s, "centroid_s": m.centroid_s,
            "fwhm_s": m.fwhm_s, "rms_width_s": m.rms_width_s, "peak_w": float(echo.max()),
            "nadir_time_s": 2.0 * nadir / C, "nadir_range_m": nadir, "mean_height_m": mean_height_m(fp, rets),
            "half_power_range_m": m.half_power_range_m, "range_error_m": m.half_power_range_m - nadir,
            "components": [(g.time_s, g.amplitude_w, g.sigma_s) for g in decompose(system, times, echo)],
        }
    return figures
