"""Risley self-calibration: the wedge's refractive index and apex angle, the prism-angle encoder's zero offset and the
boresight (roll, pitch, yaw of the true sensor axes in the believed ones) estimated from blindly segmented planes.

Every point is re-georeferenced from its raw observables (the pulse's believed pose and prism-angle reading, the
sub-beam, the one-way range) with trial parameters through the exact vector-optics wedge of
:func:`flightsim.instrument.risley_model.trace_fan` (float64; the one refraction of the project) and the boresight
convention of :class:`flightsim.platforms.pose_errors.PoseErrors`:

    P = O + R_local←sensor · M(roll, pitch, yaw) · (exit(φ + δφ; n, α) + r · S3(φ + δφ; n, α))

Each segment's plane is eliminated (a total-least-squares fit of its trial points at every evaluation), and
``scipy.optimize.least_squares`` minimises the point-to-plane distances with a robust loss (soft_l1 by default) whose
scale follows the residuals' median absolute deviation, so that rough or non-planar segments (outliers) weigh little.
The 1-σ uncertainties come from the Gauss-Newton covariance s² (Jᵀ W J)⁻¹ with the loss's IRLS weights W.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from flightsim.core.constants import ARCSEC
from flightsim.core.errors import InputError
from flightsim.instrument import risley_model
from flightsim.platforms.pose_errors import PoseErrors, PoseSettings

PARAMETERS = ("refractive_index", "apex_angle", "encoder_offset", "boresight_roll", "boresight_pitch", "boresight_yaw")
"""The unknowns, in the order of the parameter vector x = (n, α [rad], δφ [rad], roll, pitch, yaw [rad])."""

UNITS = np.array([1e-5, ARCSEC, ARCSEC, ARCSEC, ARCSEC, ARCSEC])
"""The solver's unit of each unknown (1e-5 in n, 1 arcsec in each angle): its variables are x − x0 in these units."""

REPORT_SCALE = np.array([1.0, 1.0 / ARCSEC, 1.0 / ARCSEC, 1.0 / ARCSEC, 1.0 / ARCSEC, 1.0 / ARCSEC])
REPORT_UNITS = ("", "arcsec", "arcsec", "arcsec", "arcsec", "arcsec")
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")
MIN_SEGMENTS = 3
MIN_POINTS_PER_SEGMENT = 4


@dataclass
class Observations:
    """The raw observables of the points of blindly segmented planes (float64, local frame).

    Per pulse: ``origin`` (P, 3) sensor origin [m], ``rot`` (P, 3, 3) believed R_local←sensor, ``phi`` (P,) the prism
    angle the encoder read [rad]. Per point: ``pulse`` (m,) index into the pulses, ``beam`` (m,) sub-beam i·N + j,
    ``range_m`` (m,) one-way range from the exit point [m], ``segment`` (m,) segment id 0 … S − 1.
    The fan: ``array`` N, ``spacing_rad`` Δ, the wedge's ``thickness_m``.
    """

    origin: np.ndarray
    rot: np.ndarray
    phi: np.ndarray
    pulse: np.ndarray
    beam: np.ndarray
    range_m: np.ndarray
    segment: np.ndarray
    array: int
    spacing_rad: float
    thickness_m: float

    def check(self) -> None:
        """Reject observations that cannot calibrate anything, with a one-line message."""
        m, p = len(self.range_m), len(self.phi)
        for name in ("pulse", "beam", "segment"):
            if len(getattr(self, name)) != m:
                raise InputError(f"selfcal.{name}", len(getattr(self, name)), f"one per point ({m})")
        if self.origin.shape != (p, 3) or self.rot.shape != (p, 3, 3):
            raise InputError("selfcal.poses", self.origin.shape, f"(pulses, 3) origins and (pulses, 3, 3) rotations "
                                                                 f"for {p} pulses")
        if m and (self.pulse.min() < 0 or self.pulse.max() >= p):
            raise InputError("selfcal.pulse", int(self.pulse.max()), f"indices of the {p} pulses")
        if m and (self.beam.min() < 0 or self.beam.max() >= self.array ** 2):
            raise InputError("selfcal.beam", int(self.beam.max()), f"beams 0 … {self.array ** 2 - 1}")
        if not np.all(np.isfinite(self.range_m)) or (m and self.range_m.min() <= 0.0):
            raise InputError("selfcal.range_m", "non-finite or non-positive", "positive finite ranges [m]")
        counts = np.bincount(self.segment, minlength=1) if m else np.zeros(0, dtype=int)
        if m and self.segment.min() < 0:
            raise InputError("selfcal.segment", int(self.segment.min()), "segment ids ≥ 0")
        if int(np.sum(counts >= MIN_POINTS_PER_SEGMENT)) < MIN_SEGMENTS:
            raise InputError("selfcal.segments", int(np.sum(counts >= MIN_POINTS_PER_SEGMENT)),
                             f"at least {MIN_SEGMENTS} segments of {MIN_POINTS_PER_SEGMENT} or more points")

    def subset(self, keep: np.ndarray) -> "Observations":
        """The observations of the points ``keep`` (bool mask or indices), segments renumbered 0 … S' − 1."""
        segment = np.unique(self.segment[keep], return_inverse=True)[1]
        return Observations(self.origin, self.rot, self.phi, self.pulse[keep], self.beam[keep], self.range_m[keep],
                            segment.astype(np.int64), self.array, self.spacing_rad, self.thickness_m)


def mount_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The boresight rotation (true sensor axes in the believed ones) of angles [rad], by the pose error model."""
    return PoseErrors(PoseSettings(boresight_arcsec=(roll / ARCSEC, pitch / ARCSEC, yaw / ARCSEC))).mount_rotation()


class Georeferencer:
    """The exact model's points of fixed observations for any parameters x = (n, α, δφ, roll, pitch, yaw): the
    observations' lookups made once, and the fan's rays of each point kept for the last few prisms (n, α, δφ) (a
    Jacobian's steps in the boresight reuse those of its base point). The same bits as a fresh evaluation."""

    def __init__(self, obs: Observations, device: str = "cpu"):
        self.obs, self.device = obs, device
        self.pulses = np.unique(obs.pulse)
        self.row = np.searchsorted(self.pulses, obs.pulse)
        self.origin, self.rot = obs.origin[obs.pulse], obs.rot[obs.pulse]
        self._rays = functools.lru_cache(maxsize=4)(self._trace)

    def _trace(self, n_glass: float, apex: float, encoder: float) -> tuple[np.ndarray, np.ndarray]:
        """Each point's exit point [m] and unit direction through the prism (n, α, δφ), sensor frame, float64."""
        obs = self.obs
        fan = risley_model.trace_fan(obs.phi[self.pulses] + encoder, obs.array, obs.spacing_rad, n_glass, apex,
                                     obs.thickness_m, precision="float64", device=self.device)
        return fan.exit_points[self.row, obs.beam], fan.directions[self.row, obs.beam]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """(m, 3) points [m, local], float64."""
        exit_points, s3 = self._rays(float(x[0]), float(x[1]), float(x[2]))
        sensor = exit_points + self.obs.range_m[:, None] * s3
        sensor = sensor @ mount_rotation(*x[3:6]).T
        return self.origin + np.einsum("mij,mj->mi", self.rot, sensor)


def georeference(obs: Observations, x: np.ndarray, device: str = "cpu") -> np.ndarray:
    """(m, 3) points [m, local] of the exact model with parameters x = (n, α, δφ, roll, pitch, yaw), float64."""
    return Georeferencer(obs, device)(x)


def plane_fits(points: np.ndarray, segment: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares plane of each segment: (centroids (S, 3), unit normals (S, 3), points (S,))."""
    counts = np.bincount(segment).astype(np.float64)
    safe = np.maximum(counts, 1.0)
    centroid = np.stack([np.bincount(segment, points[:, k], len(counts)) for k in range(3)], axis=1) / safe[:, None]
    d = points - centroid[segment]
    cov = np.empty((len(counts), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(segment, d[:, a] * d[:, b], len(counts))
    _, vectors = np.linalg.eigh(cov)
    return centroid, vectors[:, :, 0], counts


def plane_residuals(points: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Signed orthogonal distance of each point to its segment's TLS plane [m]."""
    centroid, normal, _ = plane_fits(points, segment)
    return np.einsum("mk,mk->m", points - centroid[segment], normal[segment])


def segment_rms(points: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Plane-fit RMS of each segment [m]."""
    r = plane_residuals(points, segment)
    return np.sqrt(np.bincount(segment, r * r) / np.maximum(np.bincount(segment), 1))


def pooled_rms(points: np.ndarray, segment: np.ndarray, keep: np.ndarray | None = None) -> float:
    """RMS of the orthogonal residuals of every point (of the segments ``keep``, a bool per segment) [m]."""
    r = plane_residuals(points, segment)
    if keep is not None:
        r = r[keep[segment]]
    return float(np.sqrt(np.mean(r * r))) if len(r) else math.nan


@dataclass
class Calibration:
    """The estimate: ``x`` (n, α, δφ, roll, pitch, yaw) with its covariance; ``free`` marks the estimated unknowns
    (the others held at their start)."""

    x: np.ndarray
    x0: np.ndarray
    free: np.ndarray
    covariance: np.ndarray  # (6, 6), zero rows and columns for held unknowns
    sigma0_m: float  # robust 1-σ of the residuals at the solution [m]
    f_scale_m: float  # the robust loss's scale [m]
    loss: str
    points: int
    segments: int
    evaluations: int
    weights: np.ndarray = field(repr=False, default=None)  # IRLS weight of each point at the solution

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def correlation(self) -> np.ndarray:
        s = self.sigma
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.covariance / np.outer(s, s)
        return np.where(np.outer(s, s) > 0.0, c, 0.0)


class _Problem:
    """Residuals and forward-difference Jacobian in the solver's variables u = (x − x0) / UNITS (free ones)."""

    def __init__(self, obs: Observations, x0: np.ndarray, free: np.ndarray, device: str, step: float = 0.5):
        self.obs, self.x0, self.free, self.step = obs, np.asarray(x0, float), free, step
        self.georeference = Georeferencer(obs, device)
        self.evaluations = 0
        self._last: tuple[bytes, np.ndarray] | None = None

    def x(self, u: np.ndarray) -> np.ndarray:
        x = self.x0.copy()
        x[self.free] += u * UNITS[self.free]
        return x

    def fun(self, u: np.ndarray) -> np.ndarray:
        key = np.asarray(u, float).tobytes()
        if self._last is None or self._last[0] != key:
            self.evaluations += 1
            self._last = (key, plane_residuals(self.georeference(self.x(u)), self.obs.segment))
        return self._last[1]

    def jac(self, u: np.ndarray) -> np.ndarray:
        f0 = self.fun(u)
        columns = []
        for k in range(len(u)):
            v = np.array(u, float)
            v[k] += self.step
            self.evaluations += 1
            f = plane_residuals(self.georeference(self.x(v)), self.obs.segment)
            columns.append((f - f0) / self.step)
        return np.stack(columns, axis=1)


def _weights(r: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weights ρ'(z), z = (r/c)², of scipy's losses."""
    z = (r / c) ** 2
    return {"linear": np.ones_like(z), "soft_l1": 1.0 / np.sqrt(1.0 + z), "huber": np.minimum(1.0, 1.0 / np.sqrt(
        np.maximum(z, 1e-300))), "cauchy": 1.0 / (1.0 + z), "arctan": 1.0 / (1.0 + z * z)}[loss]


def _robust_scale(r: np.ndarray, floor: float = 1e-5) -> float:
    """1.4826 × the median absolute residual [m] (a Gaussian's σ), at least ``floor``."""
    return max(1.4826 * float(np.median(np.abs(r))), floor)


def calibrate(obs: Observations, x0, free=None, loss: str = "soft_l1", scale_factor: float = 2.5, stages: int = 3,
              device: str = "cpu") -> Calibration:
    """Estimate the free unknowns from the believed start ``x0``; the robust loss's scale is ``scale_factor`` times
    the residuals' robust σ, re-estimated after each of ``stages`` solves."""
    x0 = np.asarray(x0, dtype=np.float64)
    if x0.shape != (len(PARAMETERS),) or not np.all(np.isfinite(x0)):
        raise InputError("selfcal.x0", x0.tolist() if x0.ndim == 1 else x0.shape, f"{len(PARAMETERS)} finite numbers "
                                                                                  f"({', '.join(PARAMETERS)})")
    if loss not in LOSSES:
        raise InputError("selfcal.loss", loss, ", ".join(LOSSES))
    obs.check()
    free = np.ones(len(PARAMETERS), bool) if free is None else np.asarray(free, bool)
    problem = _Problem(obs, x0, free, device)
    u = np.zeros(int(free.sum()))
    c = _robust_scale(problem.fun(u))
    for _ in range(max(1, stages)):
        c = scale_factor * c if loss != "linear" else 1.0
        result = least_squares(problem.fun, u, jac=problem.jac, loss=loss, f_scale=c, method="trf", x_scale=1.0,
                               xtol=1e-10, ftol=1e-12, gtol=1e-12, max_nfev=50)
        u = result.x
        c = _robust_scale(problem.fun(u))
    return _finish(problem, u, loss, scale_factor * c if loss != "linear" else 1.0)


def _finish(problem: _Problem, u: np.ndarray, loss: str, c: float) -> Calibration:
    """The covariance s² (Jᵀ W J)⁻¹ at the solution, in the unknowns' own units."""
    obs, free = problem.obs, problem.free
    r = problem.fun(u)
    J = problem.jac(u)
    w = _weights(r, loss, c)
    dof = max(1, len(r) - J.shape[1] - 3 * int(obs.segment.max() + 1))
    s2 = float(np.sum(w * r * r) / dof)
    cov_u = s2 * np.linalg.pinv(J.T @ (w[:, None] * J), rcond=1e-15)
    cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    scale = UNITS[free]
    cov[np.ix_(free, free)] = cov_u * np.outer(scale, scale)
    return Calibration(problem.x(u), problem.x0, free, cov, math.sqrt(s2), c, loss, len(r),
                       int(obs.segment.max() + 1), problem.evaluations, w)


def cone_angle(x: np.ndarray) -> float:
    """On-axis deviation θ(n, α) [rad] of the wedge of parameters x (the scan cone's half angle)."""
    return risley_model.cone_for_apex(float(x[1]), float(x[0]))


def combinations(cal: Calibration) -> dict[str, tuple[float, float]]:
    """The combinations a plane fit observes even where n and α, or δφ and yaw, are not separable:
    {name: (value, 1-σ)} — the cone half-angle θ(n, α) [arcsec, from its believed value] and δφ + yaw [arcsec]."""
    h = 1e-7
    grad = np.zeros(len(PARAMETERS))
    for k in (0, 1):
        x = cal.x.copy()
        x[k] += h
        grad[k] = (cone_angle(x) - cone_angle(cal.x)) / h
    theta_sigma = math.sqrt(max(float(grad @ cal.covariance @ grad), 0.0))
    g2 = np.zeros(len(PARAMETERS))
    g2[2] = g2[5] = 1.0
    sum_sigma = math.sqrt(max(float(g2 @ cal.covariance @ g2), 0.0))
    return {"cone_half_angle": ((cone_angle(cal.x) - cone_angle(cal.x0)) / ARCSEC, theta_sigma / ARCSEC),
            "encoder_plus_yaw": ((cal.x[2] + cal.x[5]) / ARCSEC, sum_sigma / ARCSEC)}
