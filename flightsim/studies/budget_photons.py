"""Photon-counting budgets' shared parts (the spad and atlas budgets): a run's photons simulated through the
simulator (trace, SPAD sampling, each photon placed on its believed beam), their height errors over a sloped plane,
and the float64 first-order propagation of range and pointing errors into that height error.

The scene is the plane z = −s·y (local frame, descending towards grid north, s = ``scene.slope``); a photon placed
at p has the height error e = p_z + s·p_y, i.e. g·p with g = (0, s, 1). To first order a range error δr along the
believed beam d moves it by δr·d (e changes by δr·g·d), and a true beam d_t off the believed one d_b by
r·(d_b − d_t) at range r (e changes by r·g·(d_b − d_t)).
"""
from __future__ import annotations

import math

import numpy as np

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.studies.budgets import Simulated, fly

C = 299_792_458.0  # [m/s]
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
NARROW_PULSE_S = 1.0e-12  # the pulse width of a source run that leaves the pulse out (the setting must be > 0; 0.06 mm
# of range spread): 1 fs, the photon sampler's inversion tolerance, loses photo-electrons of a shot [s]


def configured(base: RunConfig, settings: dict) -> RunConfig:
    """A validated copy of ``base`` with ``settings`` ({dotted key: value}) applied."""
    from flightsim.engine.config import copy_config

    cfg = copy_config(base)
    for key, value in settings.items():
        set_value(cfg, key, value)
    return validate(cfg)


def simulate_photons(cfg: RunConfig, signal_only: bool = True) -> Simulated:
    """Run ``cfg`` (a photon-detector config over the plane scene) through the simulator and return every signal
    photon's height error [m] (``signal_only``; else every photon's), with its geometry: ``directions`` (n, 3)
    believed beam [local], ``range_m`` c·t/2, ``pulse``, ``pixel``, ``kind`` and the tracer ``sim``."""
    from flightsim.engine.readouts.photons import Photons

    _, sim, chunks, wall = fly(cfg, Photons())
    cat = {name: (np.concatenate([getattr(c, name) for c in chunks]) if chunks else np.empty(0))
           for name in ("pulse", "pixel", "time_of_flight_s", "kind", "points", "directions")}
    keep = cat["kind"] == 1 if signal_only else np.ones(len(cat["kind"]), dtype=bool)
    points = np.asarray(cat["points"], dtype=np.float64).reshape(-1, 3)[keep]
    slope = float(cfg.scene.slope)
    geometry = {"directions": np.asarray(cat["directions"], dtype=np.float64).reshape(-1, 3)[keep],
                "range_m": 0.5 * C * np.asarray(cat["time_of_flight_s"], dtype=np.float64)[keep],
                "pulse": np.asarray(cat["pulse"])[keep], "pixel": np.asarray(cat["pixel"])[keep],
                "kind": np.asarray(cat["kind"])[keep], "points": points, "slope": slope, "sim": sim,
                "shots": sim.planned_pulses(), "beams": sim.beams_per_pulse}
    return Simulated(height_errors(points, slope), geometry, wall)


def height_errors(points: np.ndarray, slope: float) -> np.ndarray:
    """Height of each point above the plane z = −s·y [m]."""
    return points[:, 2] + slope * points[:, 1]


def gradient(slope: float) -> np.ndarray:
    """g of e = g·p: the height error's gradient in the local frame."""
    return np.array([0.0, slope, 1.0])


def range_first_order(sim: Simulated, sigma_r: float, bias_r: float = 0.0) -> tuple[float, float]:
    """(mean, σ) of the height error [m] of a range error of mean ``bias_r`` and 1σ ``sigma_r`` along each
    photon's believed beam (its geometry): e = δr·g·d, so mean = bias_r·⟨g·d⟩, σ² = σ_r²·⟨(g·d)²⟩ + bias_r²·var(g·d)."""
    gd = sim.geometry["directions"] @ gradient(sim.geometry["slope"])
    if gd.size == 0:
        return math.nan, math.nan
    return float(bias_r * gd.mean()), float(math.sqrt(sigma_r ** 2 * np.mean(gd ** 2) + bias_r ** 2 * gd.var()))


def tdc_sigma_m(bin_s: float) -> float:
    """Range σ of a TDC that reads the centre of its bin, the true time uniform over it: (c/2)·τ/√12 [m]."""
    return 0.5 * C * bin_s / math.sqrt(12.0)


def pile_up_bias_first_order_s(n_signal: float, sigma_t: float) -> float:
    """First-photon bias [s] to first order in the expected signal n: the first of Poisson(n) photo-electrons of a
    Gaussian echo, given one, comes at ⟨z⟩ = −n ∫ z φ(z) Φ(z) dz = −n / (2√π) σ_t (exact: flightsim.instrument.photon.
    first_photon_bias_s, whose magnitude grows only like σ_t √(2 ln n))."""
    return -n_signal * sigma_t / (2.0 * math.sqrt(math.pi))


def expected_signal(cfg: RunConfig, sim: Simulated) -> np.ndarray:
    """Expected signal photo-electrons per shot of each photon's slot (the lidar equation over the plane, float64:
    E·λ/hc · ρ cos θ / π · A / R² · η)."""
    from flightsim.instrument.photon import C as LIGHT, H

    p = cfg.photon
    d = sim.geometry["directions"]
    normal = np.array([0.0, sim.geometry["slope"], 1.0]) / math.hypot(1.0, sim.geometry["slope"])
    cos_i = np.abs(d @ normal)
    r = sim.geometry["range_m"]
    return (p.pulse_energy_j * p.wavelength_nm * 1e-9 / (H * LIGHT) * p.reflectance * cos_i / math.pi
            * math.pi * (p.aperture_m / 2.0) ** 2 / r ** 2 * p.optics_transmission * p.pde)
