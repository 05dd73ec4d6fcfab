"""The generic estimator of :mod:`flightsim.calibration.ccr`: the pointing and ranging biases from the
same CCR photons as the patent's method, by the maximum likelihood of every searched shot's count of CCR
photons and of the CCR photons' ranges, with Fisher-information covariances."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from flightsim.calibration.ccr_field import CcrField
from flightsim.calibration.ccr_tracks import Identification
from flightsim.calibration.geolocation import ARCSEC, Bias, Shots, Track


@dataclass(frozen=True)
class LeastSquaresCalibration:
    """The generic estimator's result."""

    bias: Bias
    covariance: np.ndarray  # (3, 3) of (δa [arcsec], δc [arcsec], b [m]), the inverse Fisher information
    footprint_radius_m: float  # fitted e⁻² radius w of the footprint's energy profile [m]
    ccr_photons_per_shot: float  # fitted CCR response N0 (mean photons at the footprint centre)
    background_per_shot: float  # fitted λ_b, background photons per shot in a CCR's height window
    range_sigma_m: float  # scatter of the CCR photons' ranges about the fit [m]
    n_trials: int  # (shot, CCR) photon counts in the likelihood
    n_photons: int  # CCR photon ranges in the likelihood

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations of (δa [arcsec], δc [arcsec], b [m])."""
        return np.sqrt(np.diag(self.covariance))


def _detection_trials(shot, identification: Identification):
    """Every searched (shot, CCR) pair of the pass and its count of candidate photons."""
    shots, ccr, counts = [], [], []
    for j, (k0, k1) in identification.windows.items():
        k = np.arange(max(k0, int(shot.min())), min(k1, int(shot.max())) + 1)
        if k.size == 0:
            continue
        shots.append(k)
        ccr.append(np.full(k.size, j))
        counts.append(np.bincount(shot[identification.candidates == j] - k[0], minlength=k.size)[: k.size])
    return np.concatenate(shots), np.concatenate(ccr), np.concatenate(counts)


class _PhotonRate:
    """Mean matching photons per shot λ = N0·exp(−2r²/w²) + λ_b of x = (δa, δc, w, ln N0, ln λ_b) on fixed
    (shot, CCR) trials; r, which only (δa, δc) move, kept for the last few pointings (a numerical
    Jacobian's steps in w, N0 and λ_b reuse the r of its base point)."""

    def __init__(self, track, shots, points):
        self.shots, self.points = Shots(track, shots), points
        self._offset = functools.lru_cache(maxsize=4)(self._footprint_offset)

    def _footprint_offset(self, along_arcsec: float, across_arcsec: float) -> np.ndarray:
        return self.shots.offset(self.points, Bias(along_arcsec, across_arcsec))

    def __call__(self, x) -> np.ndarray:
        r = self._offset(float(x[0]), float(x[1]))
        return np.exp(x[3] - 2.0 * (r / x[2]) ** 2) + np.exp(x[4])


def _deviance_residuals(lam, counts):
    """Signed √(2(y ln(y/λ) − (y − λ))) of Poisson counts y of mean λ: Σ r² = −2 ln L + const."""
    y_log = np.where(counts > 0, counts * np.log(np.maximum(counts, 1) / lam), 0.0)
    return np.sign(counts - lam) * np.sqrt(np.maximum(2.0 * (y_log - (counts - lam)), 0.0))


def _fisher(rate: _PhotonRate, x):
    """Fisher information of x from Poisson counts: Σ (∂λ/∂x)(∂λ/∂x)ᵀ / λ."""
    jac = np.empty((len(rate.points), x.size))
    for i in range(x.size):
        h = 1e-4 * max(1.0, abs(x[i]))
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        jac[:, i] = (rate(up) - rate(down)) / (2.0 * h)
    return jac.T @ (jac / rate(x)[:, None])


def calibrate_least_squares(track: Track, shot, range_m, field: CcrField, identification: Identification,
                            *, footprint_radius_m: float, start: Bias = Bias()) -> LeastSquaresCalibration:
    """Generic estimator of the pointing and ranging biases from the CCR photons.

    Pointing: on every shot searched for every reachable CCR (``identification.windows``), the
    number of candidate photons (matching the CCR's height) is Poisson with mean λ = N0·exp(−2r²/w²)
    + λ_b, r the CCR's distance from the footprint centre that eq. (1) gives for (δa, δc) and λ_b
    the background in the CCR's height window (no dead time: a multi-channel detector, as ATLAS's
    16 channels per strong beam). (δa, δc, w, ln N0, ln λ_b) maximise the likelihood, as
    ``scipy.optimize.least_squares`` on the deviance residuals, started from ``start`` at the best
    of a grid of δc over ±1.5·R/H (``start``: e.g. the patent's coarse calibration, step 2).
    Triggered or not, every CCR in reach counts. Ranging: a CCR photon's range is |X_ccr − P_laser|
    + b whatever the pointing, so b is the mean range residual of the tracks' photons.
    Covariance: the inverse Fisher information, (JᵀJ)⁻¹ with J the Jacobian of (λ − y)/√λ for the
    pointing, and σ²/n for b (σ the ranges' scatter).
    """
    shot, range_m = np.asarray(shot), np.asarray(range_m, dtype=np.float64)
    shots, ccr, counts = _detection_trials(shot, identification)
    rate = _PhotonRate(track, shots, field.positions_m[ccr])

    def residuals(x):
        return _deviance_residuals(rate(x), counts)

    half = 1.5 * footprint_radius_m / track.altitude_m / ARCSEC
    grid = [np.array([start.along_arcsec, c, footprint_radius_m, 2.0, math.log(0.01)])
            for c in start.across_arcsec + np.linspace(-half, half, 13)]
    x0 = min(grid, key=lambda x: float(np.sum(residuals(x) ** 2)))
    fit = least_squares(residuals, x0, bounds=([-np.inf, -np.inf, 0.1 * footprint_radius_m, -5.0, -20.0],
                                               [np.inf, np.inf, 10.0 * footprint_radius_m, 10.0, 2.0]))
    cov_pointing = np.linalg.inv(_fisher(rate, fit.x))[:2, :2]
    photons = np.flatnonzero(identification.labels >= 0)
    ccr_points = field.positions_m[identification.labels[photons]]
    dr = range_m[photons] - np.linalg.norm(ccr_points - track.position(shot[photons]), axis=-1)
    b, s = float(dr.mean()), float(dr.std(ddof=1))
    cov = np.zeros((3, 3))
    cov[:2, :2], cov[2, 2] = cov_pointing, s * s / dr.size
    return LeastSquaresCalibration(Bias(float(fit.x[0]), float(fit.x[1]), b), cov, float(fit.x[2]),
                                   float(math.exp(fit.x[3])), float(math.exp(fit.x[4])), s,
                                   int(shots.size), int(dr.size))
