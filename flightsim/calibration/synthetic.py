"""Synthetic pass of a spaceborne single-photon altimeter over a corner-cube (CCR) field (float64 NumPy).

What the instrument measures, for the calibration of :mod:`flightsim.calibration.ccr` to work on:
every photon is (shot index, measured range), the range carrying the true ranging bias and the
photon's timing jitter, the footprint placed by the true pointing bias (:mod:`.geolocation`).

Per shot k, independently (no detector dead time):
- **ground photons**: Poisson(n_g) of them, from points of flat ground at ``ground_height_m`` drawn
  from the footprint's Gaussian energy profile exp(−2r²/w²) (σ = w/2 per horizontal axis);
- **CCR photons**: for each CCR, Poisson(λ) of them with λ = N0·exp(−2r²/w²), r the horizontal
  distance of the CCR from the footprint centre at the CCR's height and N0 the CCR's response (mean
  photons per shot at the centre); all at the CCR's range;
- **background** (solar and dark counts): Poisson(B·2g/c) of them, ranges uniform over a range gate
  of g metres centred on the nominal nadir range to the ground.

Every range gets Gaussian jitter of σ_ρ. Defaults are ICESat-2 ATLAS-like (10 kHz, 0.7 m between
shots, footprint 13 m across at e⁻²: w = 6.5 m; σ_ρ = 0.10 m, c·σ_t/2 for a 1.5 ns FWHM pulse).
The default N0 = e² makes λ = 1 at r = w, so the edge of a CCR's photon track sits near the
theoretical radius R = w.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.calibration.ccr_field import CcrField
from flightsim.calibration.geolocation import Bias, Track, footprint_centre, footprint_offset, measured_range
from flightsim.core.errors import InputError

C = 299_792_458.0  # speed of light [m/s]
BACKGROUND, GROUND = -2, -1  # source codes of non-CCR photons (a CCR photon's source is its index)


@dataclass(frozen=True)
class Altimeter:
    """Photon-counting receiver and footprint of one beam."""

    footprint_radius_m: float = 6.5  # w, e⁻² radius of the Gaussian energy profile on the ground [m]
    range_sigma_m: float = 0.10  # σ_ρ, per-photon range jitter [m]
    ground_photons_per_shot: float = 2.0  # n_g, mean signal photons from the ground
    ccr_photons_per_shot: float = math.e**2  # N0, mean photons from a CCR at the footprint centre
    background_rate_hz: float = 1e6  # B, background count rate [Hz]
    gate_m: float = 60.0  # g, range gate length [m]

    def __post_init__(self):
        for name in ("footprint_radius_m", "range_sigma_m", "ccr_photons_per_shot", "gate_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"altimeter.{name}", value, "a finite number > 0")
        for name in ("ground_photons_per_shot", "background_rate_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"altimeter.{name}", value, "a finite number >= 0")

    def divergence_rad(self, range_m: float) -> float:
        """Full divergence θ with ρ·tan(θ/2) = w at range ρ [rad]."""
        return 2.0 * math.atan(self.footprint_radius_m / range_m)


@dataclass(frozen=True)
class SyntheticPass:
    """Photons of one pass, sorted by shot, with the truth that made them."""

    track: Track
    field: CcrField
    altimeter: Altimeter
    truth: Bias
    ground_height_m: float
    shot: np.ndarray  # (n,) shot index of each photon
    range_m: np.ndarray  # (n,) measured range [m]
    source: np.ndarray  # (n,) CCR index, GROUND or BACKGROUND


def _ground_photons(rng, track, alt, truth, shots, ground_height_m):
    shot = np.repeat(shots, rng.poisson(alt.ground_photons_per_shot, shots.size))
    centre = footprint_centre(track, shot, np.full(shot.size, ground_height_m), truth)
    centre[:, :2] += rng.normal(0.0, alt.footprint_radius_m / 2.0, (shot.size, 2))
    return shot, measured_range(track, shot, centre, truth)


def _ccr_photons(rng, track, alt, truth, shots, field):
    shot, rng_m, source = [], [], []
    for j, point in enumerate(field.positions_m):
        r = footprint_offset(track, shots, np.broadcast_to(point, (shots.size, 3)), truth)
        lam = alt.ccr_photons_per_shot * np.exp(-2.0 * (r / alt.footprint_radius_m) ** 2)
        s = np.repeat(shots, rng.poisson(lam))
        shot.append(s)
        rng_m.append(measured_range(track, s, np.broadcast_to(point, (s.size, 3)), truth))
        source.append(np.full(s.size, j))
    return np.concatenate(shot), np.concatenate(rng_m), np.concatenate(source)


def _background_photons(rng, track, alt, shots, ground_height_m):
    mean = alt.background_rate_hz * 2.0 * alt.gate_m / C
    shot = np.repeat(shots, rng.poisson(mean, shots.size))
    centre = track.altitude_m - ground_height_m
    return shot, rng.uniform(centre - alt.gate_m / 2.0, centre + alt.gate_m / 2.0, shot.size)


def simulate_pass(track: Track, field: CcrField, truth: Bias, n_shots: int, *,
                  altimeter: Altimeter = Altimeter(), ground_height_m: float = 0.0,
                  seed: int = 0) -> SyntheticPass:
    """Photons of ``n_shots`` shots from shot 0 over flat ground and the CCR field (module docstring).

    Args:
        track: the laser track (the truth and the nominal model share it).
        field: the CCRs; their heights above ground are ``field.heights_m``.
        truth: the injected pointing [arcsec] and ranging [m] biases.
        n_shots: number of shots.
        altimeter: receiver, footprint and photon rates.
        ground_height_m: the flat ground's height in the local frame [m].
        seed: NumPy random seed.
    """
    if not (isinstance(n_shots, int) and n_shots > 0):
        raise InputError("n_shots", n_shots, "an integer > 0")
    rng = np.random.default_rng(seed)
    shots = np.arange(n_shots)
    g_shot, g_range = _ground_photons(rng, track, altimeter, truth, shots, ground_height_m)
    c_shot, c_range, c_source = _ccr_photons(rng, track, altimeter, truth, shots, field)
    b_shot, b_range = _background_photons(rng, track, altimeter, shots, ground_height_m)
    shot = np.concatenate([g_shot, c_shot, b_shot])
    signal = np.concatenate([g_range, c_range])
    range_m = np.concatenate([signal + rng.normal(0.0, altimeter.range_sigma_m, signal.size), b_range])
    source = np.concatenate([np.full(g_shot.size, GROUND), c_source, np.full(b_shot.size, BACKGROUND)])
    order = np.argsort(shot, kind="stable")
    return SyntheticPass(track, field, altimeter, truth, ground_height_m,
                         shot[order], range_m[order], source[order])
