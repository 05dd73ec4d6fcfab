"""The full-waveform detector part (``instrument.detector = "waveform"``, ``[waveform]``): each beam's
footprint sampled by sub-rays over its Gaussian profile, every sub-ray traced against the scene and
its echo summed into the beam's waveform on the device (kernels/waveform.py).

The sub-ray table (directions as offsets tan φ·(cos θ, sin θ) from the beam axis, and each one's
share of the pulse energy) is the float64 reference model's footprint
(:func:`flightsim.instrument.waveform_model.footprint`), so the device and the reference sample the
same rays.

Eq. 1's backscatter f is ``waveform.reflectance`` on every face, unless the scene carries a Lambertian
albedo ρ per triangle (``Scene.reflectance``, from a land-cover raster): then each sub-ray's f is ρ/π
of the triangle it hits (a Lambertian surface's bidirectional reflectance), and ``waveform.reflectance``
is not used.

Over a point-cloud scene (``scene.name`` a .las/.laz) the detector's waveforms are, by default
(``waveform.cloud_method = "gedi"``), the ALS points summed by the GEDI simulator's method through the same footprint
(σ_f = r α / 2, :meth:`WaveformDetector.footprint_sigma_m`), pulse and receiver (readout ``cloud_waveforms``);
``"rays"`` traces the sub-rays against the cloud's ground mesh (and ``scene.canopy``) as over any mesh.
``waveform.l2a`` makes the run write the GEDI L2A metrics of its waveforms too (``l2a.h5``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.instrument import waveform_model as model

kw = lazy_module("kernels.waveform")

H = 6.62607015e-34  # Planck constant [J s]
C = 299_792_458.0  # [m/s]
WAVEFORM_STREAM = 0x2F6A91  # seed key of the receiver noise
CLOUD_METHODS = ("gedi", "rays")
CONVOLUTIONS = ("direct", "fft")  # the pulse convolution: kernels/waveform.py convolve; kernels/waveform_fft.py
PROCESSINGS = ("host", "device")  # where waveforms.h5's measures and Gaussian decomposition are computed
L2A_NOISE_SAMPLES = 64  # samples at each end of a waveform that L2A takes its noise from (l2a.noise_samples)


@dataclasses.dataclass
class WaveformSettings(Settings):
    """Each beam's footprint sampled by sub-rays over its Gaussian profile exp(−2 tan²φ/α²), their echoes summed
    into one waveform per beam; the defaults are the waveform patent's Chang'e-1-like altimeter."""

    half_divergence_rad: float = setting(3.0e-4, "α: the 1/e² half angle of the beam", "rad", range=(0.0, 0.1),
                                         lo_open=True)
    pulse_fwhm_s: float = setting(7.0e-9, "pulse width, full width at half maximum", "s", range=(0.0, 1.0e-6),
                                  lo_open=True)
    peak_power_w: float = setting(0.05, "peak power of the transmitted pulse", "W", range=(0.0, 1.0e9), lo_open=True)
    scheme: str = setting("polar", "footprint sub-rays: polar (the patent's rings × sectors), polar_midpoint, "
                          "equal_energy", choices=model.SCHEMES)
    n_rings: int = setting(60, "rings of the footprint", "rings", range=(1, 4096))
    n_sectors: int = setting(120, "sectors of the footprint", "sectors", range=(1, 4096))
    sample_interval_s: float = setting(1.0e-11, "waveform sample interval", "s", range=(0.0, 1.0e-6), lo_open=True)
    samples: int = setting(32768, "samples per waveform", "samples", range=(16, 1 << 22))
    aperture_m: float = setting(1.0, "receiver diameter D", "m", range=(0.0, 100.0), lo_open=True)
    transmitter_efficiency: float = setting(1.0, "η_t", "", range=(0.0, 1.0), lo_open=True)
    receiver_efficiency: float = setting(1.0, "η_r", "", range=(0.0, 1.0), lo_open=True)
    atmosphere_transmission: float = setting(1.0, "T_A, one way", "", range=(0.0, 1.0), lo_open=True)
    reflectance: float = setting(1.0, "f, the backscatter of eq. 1 on every face, unless the scene carries its own "
                                 "albedo (scene.landcover)", "", range=(0.0, 1.0), lo_open=True)
    receiver_fwhm_s: float = setting(0.0, "Gaussian impulse response of the receiver; 0 = none", "s",
                                     range=(0.0, 1.0e-6))
    shot_noise: bool = setting(False, "Poisson photo-electrons of signal and background in every sample")
    wavelength_nm: float = setting(1064.0, "laser wavelength", "nm", range=(100.0, 20000.0))
    quantum_efficiency: float = setting(0.4, "quantum efficiency of the detector", "", range=(0.0, 1.0), lo_open=True)
    background_w: float = setting(0.0, "optical background at the detector", "W", range=(0.0, 1.0e3))
    thermal_noise_w: float = setting(0.0, "receiver noise per sample, rms", "W", range=(0.0, 1.0e3))
    bits: int = setting(0, "digitiser resolution; 0 = no digitiser", "bits", range=(0, 16))
    full_scale_w: float = setting(0.0, "the digitiser's top code; needed with bits", "W", range=(0.0, 1.0e9))
    l2a: bool = setting(False, "also write l2a.h5: the GEDI L2A metrics of every waveform (after the receiver), "
                        "with the truth: the ground under the beam axis and the rh of the noise-free waveform")
    cloud_method: str = setting("gedi", "over a point-cloud scene (.las/.laz): gedi sums the ALS points' pulses over "
                                "the Gaussian footprint (the GEDI simulator's method); rays traces the sub-rays "
                                "against the cloud's ground mesh and scene.canopy", choices=CLOUD_METHODS)
    convolution: str = setting("fft", "the echo's convolution with the pulse on the device: fft (overlap-save over "
                               "float64 FFTs; an echo narrower than 256 samples still by direct sums) or direct "
                               "sums for every echo; the same float32 waveforms to ~1e-7 of the peak",
                               choices=CONVOLUTIONS)
    processing: str = setting("device", "where waveforms.h5's ranging (measures, Gaussian decomposition) is "
                              "computed: device (batched kernels on the run's device, its fits' sums of squares at "
                              "most SciPy's) or host (NumPy/SciPy's curve_fit, one waveform at a time: the reference; "
                              "docs/waveform-processing.md)", choices=PROCESSINGS)

    def check(self, context) -> None:
        system(self)
        if self.bits and self.full_scale_w <= 0.0:
            raise InputError("waveform.full_scale_w", self.full_scale_w, f"a power > 0 W with waveform.bits = {self.bits}")
        if self.l2a and self.samples <= 2 * L2A_NOISE_SAMPLES:
            raise InputError("waveform.samples", self.samples,
                             f"more than {2 * L2A_NOISE_SAMPLES} samples with waveform.l2a = true (L2A takes each "
                             f"waveform's noise from {L2A_NOISE_SAMPLES} samples at each end)")


def system(s: WaveformSettings, altitude_m: float = 1.0) -> model.WaveformSystem:
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


@register("detector", "waveform")
class WaveformDetector:
    """A full waveform per beam: ``[waveform]``."""

    settings = WaveformSettings
    readouts = ("waveforms", "cloud_waveforms")  # sub-rays traced; or, over a point cloud, its points summed
    output = None  # waveforms.h5 has no settings of its own
    scored = False

    def __init__(self, s: WaveformSettings):
        self.s = s

    def receiver(self) -> kw.Receiver | None:
        """The noise and digitiser of ``[waveform]``, or None when the reading is the noiseless power."""
        s = self.s
        if not (s.shot_noise or s.background_w or s.thermal_noise_w or s.bits):
            return None
        r = kw.Receiver()
        r.shot_noise = int(s.shot_noise)
        r.joules_per_electron = H * C / (s.wavelength_nm * 1e-9 * s.quantum_efficiency)
        r.background, r.thermal = s.background_w, s.thermal_noise_w
        r.top = float(2 ** s.bits - 1)
        r.lsb = s.full_scale_w / r.top if s.bits else 0.0
        r.stream = WAVEFORM_STREAM
        return r

    def footprint_deg(self) -> float:
        """Angle of the footprint's edge (tan φ = α) from its beam's axis [deg]."""
        return math.degrees(math.atan(self.s.half_divergence_rad))

    def subrays(self, device: str) -> SubRays:
        fp = model.footprint(system(self.s))
        offsets = np.column_stack([fp.x_m, fp.y_m])  # at unit altitude: tan φ (cos θ, sin θ)
        return SubRays(wp.array(offsets, dtype=wp.vec2d, device=device),
                       wp.array(fp.weight, dtype=wp.float64, device=device))

    def struct(self, per_face: bool, leaf_reflectance: float = 0.0) -> kw.WaveformParams:
        """The kernels' constants. ``link`` is eq. 1's π f T_A² D² η_t η_r / 4 with f = ``waveform.reflectance``;
        with ``per_face`` (the scene carries a Lambertian albedo ρ per triangle, e.g. from land cover) each
        triangle's backscatter is f = ρ/π, so π f = ρ and ``link`` is T_A² D² η_t η_r / 4, which the deposit
        kernel multiplies by the hit triangle's ρ (``waveform.reflectance`` is then not used). ``leaf_link`` is
        T_A² D² η_t η_r / 4 times ``leaf_reflectance``, the canopy's leaves' albedo (they scatter as a Lambertian
        surface facing the beam)."""
        s = self.s
        sys = system(s)
        params = kw.WaveformParams()
        pi_f = 1.0 if per_face else np.pi * s.reflectance  # per face: π f = ρ, applied in the kernel
        params.link = pi_f * self.link_m2()
        params.dt = s.sample_interval_s
        params.samples = s.samples
        params.sigma = model.pulse_sigma_s(sys)
        params.centre = 0.5 * s.pulse_fwhm_s
        params.peak_power = s.peak_power_w
        params.leaf_link = leaf_reflectance * self.link_m2()
        return params

    def link_m2(self) -> float:
        """T_A² D² η_t η_r / 4 [m²]: received / transmitted energy times r² of a Lambertian surface of albedo 1
        facing the beam (eq. 1 with π f = 1, cos θ_i = 1)."""
        s = self.s
        return s.atmosphere_transmission ** 2 * s.aperture_m ** 2 * s.transmitter_efficiency * s.receiver_efficiency / 4.0

    def pulse_energy_j(self) -> float:
        """Energy of the transmitted pulse, √(2π) σ P_max [J]."""
        return model.pulse_energy_j(system(self.s))

    def pulse_sigma_s(self) -> float:
        """σ of the pulse as read through the receiver [s]: the transmitted pulse's, widened in quadrature by a
        Gaussian receiver response of FWHM ``waveform.receiver_fwhm_s``."""
        return math.hypot(model.pulse_sigma_s(system(self.s)), self.s.receiver_fwhm_s / model.FWHM_PER_SIGMA)

    def footprint_sigma_m(self, range_m: float) -> float:
        """σ_f of the Gaussian footprint across the beam at ``range_m`` [m]: the profile exp(−2 tan²φ/α²) is
        exp(−ρ²/2σ_f²) at ρ = r tan φ, so σ_f = r α / 2; the footprint's edge (tan φ = α, where the sub-rays stop)
        is its 1/e² radius 2σ_f."""
        return 0.5 * range_m * self.s.half_divergence_rad

    def pulse_taps(self, device: str) -> tuple[wp.array, int]:
        """(the pulse as read through the receiver at multiples of dt over ±PULSE_SIGMAS σ, the first tap's
        lag in samples): the kernel the binned echo is convolved with [W]. With a Gaussian receiver impulse
        response of FWHM τ_r (unit area) the pulse stays Gaussian, its σ² grows by σ_r² and its peak falls
        by σ/σ' (the energy is kept); without one it is the transmitted P(t) of eq. 2."""
        s = self.s
        sys = system(s)
        dt, sigma, centre = sys.sample_interval_s, model.pulse_sigma_s(sys), 0.5 * sys.pulse_fwhm_s
        widened = self.pulse_sigma_s()
        first = int(np.floor((centre - kw.PULSE_SIGMAS * widened) / dt))
        last = int(np.ceil((centre + kw.PULSE_SIGMAS * widened) / dt))
        t = np.arange(first, last + 1, dtype=np.float64) * dt
        taps = s.peak_power_w * sigma / widened * np.exp(-0.5 * ((t - centre) / widened) ** 2)
        return wp.array(taps, dtype=wp.float64, device=device), first
