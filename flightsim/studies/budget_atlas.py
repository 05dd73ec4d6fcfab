"""Per-photon ranging budget of the ATLAS-style spaceborne single-photon altimeter (seed:
corner-cube-single-photon-calibration-patent.txt; the ``atlas`` preset's single strong beam, every setting given here
(BEAM) on the default config, so that the budget does not follow changes of the preset's beam layout).

The instrument hovers 500 km over the plane z = −s·y (s = SLOPE) and fires ``shots`` nadir pulses; the quantity is
the height above the true plane of every photon inside the signal window (±WINDOW_M of the true surface height):
signal photons, and background photons once the background is on. A source's run has every other source off
(pulse narrowed to NARROW_PULSE_S, no jitter, no background, no dead time, the pointing known). First order, float64:
range terms along the beam (budget_photons), the pointing knowledge error through the believed and true beam
directions (r·g·(d_b − d_t), the mount rotation built with SciPy from the documented convention), the background
as the mixture of the signal and a uniform height over the window, the first-photon bias to first order in the signal.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from flightsim.core.constants import ARCSEC
from flightsim.engine.config import RunConfig
from flightsim.studies import budget_photons as bp
from flightsim.studies.budgets import Simulated, Source

ALTITUDE_M = 500_000.0  # the patent's ≈ 500 km
SLOPE = 0.1  # rise/run of the plane (5.7°)
WINDOW_M = 3.0  # half height of the signal window around the true surface [m]
POINTING_ARCSEC = 3.0  # assumed: pointing knowledge per axis (ATLAS's 6.5 m geolocation requirement at 496 km ≈ 2.7″)
BEAM = {  # the atlas preset's single strong beam (presets/atlas.toml as of this budget), every value explicit
    "instrument.emitter": "fan", "instrument.deflector": "fixed", "instrument.detector": "photon",
    "instrument.max_range_m": 600_000.0, "fan.array": 1, "fan.divergence_mrad": 0.024, "photon.wavelength_nm": 532.0, "photon.pulse_energy_j": 1.2e-4,
    "photon.aperture_m": 0.8, "photon.optics_transmission": 0.5, "photon.pde": 0.15, "photon.reflectance": 0.2,
    "photon.max_events": 16, "photon.gate_m": [ALTITUDE_M - 1000.0, ALTITUDE_M + 1000.0]}
PULSE_FWHM_S, JITTER_S, NOISE_HZ, DEAD_TIME_S = 1.5e-9, 1.0e-10, 1.0e6, 3.2e-9

SOURCES = (
    Source("pulse", PULSE_FWHM_S, "s FWHM", "ATLAS's < 1.5 ns pulse: the echo's spread, σ_r = (c/2)·σ_p"),
    Source("jitter", JITTER_S, "s", "detector and timing jitter (assumed, as the preset): σ_r = (c/2)·σ_t"),
    Source("pointing", POINTING_ARCSEC, "arcsec", "pointing knowledge error on roll and pitch (assumed): the photon "
           "is placed on the believed beam, r·|δφ| ≈ 2 m off at 500 km, which the slope turns into height, "
           "r·δφ·tan(slope)"),
    Source("background", NOISE_HZ, "Hz", "daytime solar background (preset, assumed): false photons uniform over "
           "the ±3 m signal window mixed with the signal, σ² = f·W²/3 with f the false photons' share"),
    Source("first_photon", DEAD_TIME_S, "s dead time", "ATLAS's dead time with the preset's echo (pulse and jitter on): "
           "only a shot's first photo-electron counts, early, so the surface reads high", role="bias",
           breaks="linear in the ~3 signal photo-electrons per shot, the bias −n σ_t/(2√π) overstates the true "
           "one, which saturates"),
)


@dataclass
class AtlasBudget:
    """The atlas preset's single-beam per-photon budget (see the module docstring)."""

    name: str = "atlas"
    title: str = "ATLAS-style single-photon altimeter (atlas preset, one strong beam, 500 km)"
    quantity: str = "height above the true plane z = −0.1·y of every photon within ±3 m of it, 500 km below"
    seed: str = "corner-cube-single-photon-calibration-patent.txt"
    sources: tuple = SOURCES
    default_shots: int = 20000

    def config(self, names: tuple[str, ...], device: str, shots: int, seed: int) -> RunConfig:
        base = RunConfig()  # not the preset: its beam layout may change; BEAM holds the single beam's values
        on = set(names)
        prf = 10_000.0
        pointing = [POINTING_ARCSEC, POINTING_ARCSEC, 0.0] if "pointing" in on else [0.0, 0.0, 0.0]
        settings = {**BEAM, "scene.name": "plane", "scene.slope": SLOPE, "scene.margin_m": 50.0,
                    "flight.platform": "hover", "flight.altitude_m": ALTITUDE_M, "fixed.prf_hz": prf,
                    "flight.duration_s": (shots - 0.5) / prf, "run.device": device, "run.seed": seed,
                    "instrument.errors": ["pose"], "pose.boresight_arcsec": pointing,
                    "photon.pulse_fwhm_s": PULSE_FWHM_S if on & {"pulse", "first_photon"} else bp.NARROW_PULSE_S,
                    "photon.jitter_s": JITTER_S if on & {"jitter", "first_photon"} else 0.0, "photon.tdc_bin_s": 0.0,
                    "photon.dead_time_s": DEAD_TIME_S if "first_photon" in on else 0.0,
                    "photon.noise_hz": NOISE_HZ if "background" in on else 0.0}
        return bp.configured(base, settings)

    def simulate(self, names: tuple[str, ...], device: str, shots: int, seed: int) -> Simulated:
        cfg = self.config(names, device, shots, seed)
        out = bp.simulate_photons(cfg, signal_only=False)
        inside = np.abs(out.errors) <= WINDOW_M
        out.errors = out.errors[inside]
        out.geometry = {k: (v[inside] if isinstance(v, np.ndarray) and len(v) == len(inside) else v)
                        for k, v in out.geometry.items()}
        out.geometry["cfg"] = cfg
        return out

    def first_order(self, name: str, sim: Simulated) -> tuple[float, float]:
        cfg = sim.geometry["cfg"]
        if name == "pulse":
            return bp.range_first_order(sim, 0.5 * bp.C * PULSE_FWHM_S / bp.FWHM_PER_SIGMA)
        if name == "jitter":
            return bp.range_first_order(sim, 0.5 * bp.C * JITTER_S)
        if name == "pointing":
            return _pointing_first_order(sim)
        if name == "background":
            return _background_first_order(cfg, sim)
        if name == "first_photon":
            return _first_photon_first_order(cfg, sim)
        raise KeyError(name)

    def notes(self, n: dict) -> str:
        return NOTES


def _pointing_first_order(sim: Simulated) -> tuple[float, float]:
    """δe = r·g·(d_b − d_t), d_t = R·M·Rᵀ·d_b: the true sensor axes turned by M (yaw, then pitch, then roll, the
    documented boresight convention) in the believed ones, R the believed sensor-to-local rotation."""
    g = sim.geometry
    if len(g["range_m"]) == 0:
        return math.nan, math.nan
    a = POINTING_ARCSEC * ARCSEC
    mount = Rotation.from_euler("ZYX", [0.0, a, a]).as_matrix()
    rot = np.asarray(g["sim"].poses64(g["sim"].trajectories[0].line_id, 0, 1).numpy()["rot"],
                     dtype=np.float64).reshape(3, 3)
    d_b = g["directions"] / np.linalg.norm(g["directions"], axis=1, keepdims=True)
    d_t = d_b @ (rot @ mount @ rot.T).T
    de = g["range_m"] * ((d_b - d_t) @ bp.gradient(g["slope"]))
    return float(de.mean()), float(de.std())


def _background_first_order(cfg: RunConfig, sim: Simulated) -> tuple[float, float]:
    """Mixture of the signal (at zero height error: no other source on) and false photons uniform over ±W: per shot
    N_b = rate · (2W/|g·d|) · 2/c in the window, N_s = n signal detections (no dead time: every photo-electron counts); f = N_b/(N_b + N_s), mean 0, σ² = f·W²/3."""
    n = float(np.mean(bp.expected_signal(cfg, sim)[sim.geometry["kind"] == 1])) if np.any(sim.geometry["kind"] == 1) \
        else _nadir_signal(cfg)
    gd = abs(float(np.array([0.0, 0.0, -1.0]) @ bp.gradient(SLOPE)))
    background = NOISE_HZ * (2.0 * WINDOW_M / gd) * 2.0 / bp.C
    f = background / (background + n)
    return 0.0, WINDOW_M * math.sqrt(f / 3.0)


def _nadir_signal(cfg: RunConfig) -> float:
    """Expected signal photo-electrons of a nadir shot (the lidar equation, float64)."""
    from flightsim.instrument.photon import C as LIGHT, H

    p = cfg.photon
    cos_i = 1.0 / math.hypot(1.0, SLOPE)
    return (p.pulse_energy_j * p.wavelength_nm * 1e-9 / (H * LIGHT) * p.reflectance * cos_i / math.pi
            * math.pi * (p.aperture_m / 2.0) ** 2 / ALTITUDE_M ** 2 * p.optics_transmission * p.pde)


def _first_photon_first_order(cfg: RunConfig, sim: Simulated) -> tuple[float, float]:
    """The first-photon bias, first order in the expected signal n of a shot: δt = −n σ_t/(2√π), a height
    −(c/2)·δt·g·d (early → high); σ the echo's own."""
    from flightsim.instrument.photon import sigma_t

    st = sigma_t(cfg.photon)
    gd = float(np.array([0.0, 0.0, -1.0]) @ bp.gradient(SLOPE))
    bias = 0.5 * bp.C * bp.pile_up_bias_first_order_s(_nadir_signal(cfg), st) * gd
    return bias, 0.5 * bp.C * st * abs(gd)


NOTES = """## Reading

- The pulse dominates a single photon's error: ATLAS's 1.5 ns pulse alone is (c/2)·0.64 ns ≈ 9.5 cm of range.
- Pointing knowledge: a 3″ error on roll and pitch puts the photon r·δφ = 7.3 m off its true beam per axis at
  500 km (10.3 m in all); over the 0.1 slope the along-slope one is a systematic height error r·δφ·tan(slope) =
  0.73 m, the patent's reason to calibrate the pointing with corner cubes.
- The device traces in float32: at 500 km a range is a multiple of 1/32 m. The pointing row is a systematic shift,
  the same for every shot: the true range 500,000.7273 m rounds to 500,000.71875 m, and the first-order −727.33 mm
  with that rounding gives −718.750 mm, the simulator's value to the µm. Ranging at 500 km needs float64 ranges
  where a centimetre matters.
- Background: the σ interval assumes normal errors; the mixture's heavy tails (a few per cent of photons spread
  over ±3 m) make the true uncertainty of its σ several times wider. At 1 MHz a ±3 m window holds ~0.04 false
  photons per shot beside ~3 signal photo-electrons (alone: no dead time), and each false one is uniform over the
  window (σ = W/√3 = 1.7 m), so even a few per cent of them dominate the σ of the window's photons; a narrower
  window or a signal-finding step (ATL03's) removes most.
- The sources interact: alone, the background meets ~3 signal photo-electrons per shot (no dead time); with every
  source on, the dead time keeps one signal detection per shot, the false photons' share f grows from ~1.3 % to
  ~4 % and the window's σ with it (the all-sources σ exceeds the sources' root-sum-square of σ's); the total's
  agreement is carried by the pointing bias, which dominates.
- The first-photon bias: with the 3.2 ns dead time longer than the echo and ~3 signal photo-electrons per shot, the
  first one comes early and the surface reads high (ATLAS's first-photon bias, corrected in ATL03). The first-order
  model in n overstates it, as expected.
"""

BUDGET = AtlasBudget()
