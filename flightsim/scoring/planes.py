"""Plane fitting: total-least-squares planes from float64 moment sums (SPEC §9).

Points are grouped by plane id and reduced to moment sums about a per-plane reference point
(count, Σd, Σd·dᵀ with d = p − ref); the fit is the eigen-decomposition of the centred
covariance. Sums combine by addition, so chunks, processes and devices can each accumulate
their share and the host finishes the fit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PlaneFit:
    """Total-least-squares plane through a set of points."""

    plane_id: int
    n: int
    centroid: np.ndarray  # (3,) [m], in the frame the points were given in
    normal: np.ndarray  # (3,) unit, z ≥ 0
    rms_m: float  # RMS of orthogonal residuals [m]

    @property
    def pitch_deg(self) -> float:
        """Angle between the plane and the horizontal [deg]."""
        return float(np.degrees(np.arccos(np.clip(abs(self.normal[2]), 0.0, 1.0))))

    @property
    def azimuth_deg(self) -> float:
        """Azimuth of the down-slope direction, clockwise from grid north [deg]; NaN if level."""
        east, north = self.normal[0], self.normal[1]
        if np.hypot(east, north) < 1e-12:
            return float("nan")
        return float(np.degrees(np.arctan2(east, north)) % 360.0)


class PlaneMoments:
    """Per-plane float64 moment sums: count, Σd and Σd·dᵀ of d = p − reference[plane]."""

    def __init__(self, references: np.ndarray):
        """references: (P, 3) float64 reference point of each plane id [m]."""
        self.references = np.asarray(references, dtype=np.float64)
        n_planes = len(self.references)
        self.count = np.zeros(n_planes, dtype=np.int64)
        self.first = np.zeros((n_planes, 3))
        self.second = np.zeros((n_planes, 3, 3))

    def add(self, points: np.ndarray, plane_id: np.ndarray) -> None:
        """Accumulate points (m, 3) [m] labelled by plane id (m,)."""
        if len(points) == 0:
            return
        d = np.asarray(points, dtype=np.float64) - self.references[plane_id]
        n_planes = len(self.references)
        self.count += np.bincount(plane_id, minlength=n_planes)
        for a in range(3):
            self.first[:, a] += np.bincount(plane_id, weights=d[:, a], minlength=n_planes)
            for b in range(a, 3):
                s = np.bincount(plane_id, weights=d[:, a] * d[:, b], minlength=n_planes)
                self.second[:, a, b] += s
                if b != a:
                    self.second[:, b, a] += s

    def add_sums(self, count: np.ndarray, first: np.ndarray, second: np.ndarray) -> None:
        """Add sums accumulated elsewhere: count (P,), Σd (P, 3), Σd·dᵀ (P, 3, 3), same references."""
        self.count += count.astype(np.int64)
        self.first += first
        self.second += second

    def merge(self, other: "PlaneMoments") -> None:
        """Add another accumulator's sums (same references)."""
        self.add_sums(other.count, other.first, other.second)

    def fits(self, min_points: int = 3) -> list[PlaneFit]:
        """A plane fit for every plane with at least ``min_points`` points: :meth:`fit`'s, every plane's
        eigen-decomposition in one batched call (LAPACK's, matrix by matrix: the same numbers)."""
        keep = np.flatnonzero(self.count >= min_points)
        if keep.size == 0:
            return []
        n, mean, covariance = self._centred(keep)
        values, vectors = np.linalg.eigh(covariance)
        normals = vectors[:, :, 0] * np.where(vectors[:, 2, 0] >= 0, 1.0, -1.0)[:, None]
        rms = np.sqrt(np.maximum(values[:, 0], 0.0))
        centroids = self.references[keep] + mean
        return [PlaneFit(int(p), int(k), centroids[i].copy(), normals[i].copy(), float(rms[i]))
                for i, (p, k) in enumerate(zip(keep, n))]

    def rms_all(self, min_points: int = 3) -> np.ndarray:
        """(P,) plane-fit RMS of every plane at once [m] (the least eigenvalue of each centred
        covariance, batched); NaN for planes with fewer than ``min_points`` points."""
        rms = np.full(len(self.count), np.nan)
        keep = np.flatnonzero(self.count >= max(min_points, 3))
        rms[keep] = np.sqrt(np.maximum(np.linalg.eigvalsh(self._centred(keep)[2])[:, 0], 0.0))
        return rms

    def fit(self, plane_id: int) -> PlaneFit:
        """Fit one plane from its sums."""
        n, mean, covariance = (a[0] for a in self._centred(np.array([plane_id])))
        values, vectors = np.linalg.eigh(covariance)
        normal = vectors[:, 0] * (1.0 if vectors[2, 0] >= 0 else -1.0)
        return PlaneFit(plane_id, int(n), self.references[plane_id] + mean, normal,
                        float(np.sqrt(max(values[0], 0.0))))

    def _centred(self, planes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(count (k,), mean offset from the reference (k, 3) [m], centred covariance (k, 3, 3) [m²]) of ``planes``."""
        n = self.count[planes]
        mean = self.first[planes] / n[:, None]
        return n, mean, self.second[planes] / n[:, None, None] - mean[:, :, None] * mean[:, None, :]


def pooled_rms(fits: list[PlaneFit]) -> float:
    """RMS of the residuals of all planes together: sqrt(Σ n·rms² / Σ n) [m]; NaN if none."""
    total = sum(f.n for f in fits)
    if total == 0:
        return float("nan")
    return float(np.sqrt(sum(f.n * f.rms_m**2 for f in fits) / total))


def _fit_from_covariance(plane_id: int, n: int, centroid: np.ndarray, covariance: np.ndarray) -> PlaneFit:
    """PlaneFit from a centred covariance (3, 3) [m²]: normal = eigenvector of the least eigenvalue."""
    values, vectors = np.linalg.eigh(covariance)
    normal = vectors[:, 0] * (1.0 if vectors[2, 0] >= 0 else -1.0)
    return PlaneFit(int(plane_id), int(n), np.asarray(centroid, dtype=np.float64), normal,
                    float(np.sqrt(max(values[0], 0.0))))


def fit_points(xyz: np.ndarray, plane_id: int = -1) -> PlaneFit:
    """Exact two-pass total-least-squares plane of points (n, 3) [m], n ≥ 3.

    Pass one takes the float64 centroid, pass two the covariance of the centred points, so large
    world coordinates cost no precision; the RMS is that of the residuals themselves (not the
    square root of an eigenvalue, which would bottom out near sqrt(ε)·extent).
    """
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        raise ValueError(f"a plane fit needs at least 3 points, got {len(points)}")
    centroid = points.mean(axis=0)
    d = points - centroid
    fit = _fit_from_covariance(plane_id, len(points), centroid, d.T @ d / len(points))
    fit.rms_m = float(np.sqrt(np.mean((d @ fit.normal) ** 2)))
    return fit


def group_moments(xyz: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-pass moments of the points (n, 3) [m] grouped by label (n,) (negative: no group).

    Returns count (G,), centroid (G, 3) [m] and centred covariance (G, 3, 3) [m²] for labels
    0..G-1 (G = largest label + 1; empty groups have zeros). Pass one takes per-group centroids,
    pass two the second moments of the centred points, both by ``np.bincount``.
    """
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.int64)
    keep = labels >= 0
    points, labels = points[keep], labels[keep]
    size = int(labels.max()) + 1 if len(labels) else 0
    count = np.bincount(labels, minlength=size)
    safe = np.maximum(count, 1)
    centroid = np.stack([np.bincount(labels, weights=points[:, a], minlength=size) for a in range(3)], axis=-1)
    centroid = centroid.reshape(size, 3) / safe[:, None]
    d = points - centroid[labels]
    covariance = np.empty((size, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            s = np.bincount(labels, weights=d[:, a] * d[:, b], minlength=size) / safe
            covariance[:, a, b] = s
            covariance[:, b, a] = s
    return count, centroid, covariance


def fit_groups(xyz: np.ndarray, labels: np.ndarray, min_points: int = 3) -> list[PlaneFit]:
    """Two-pass TLS fit of every group of points sharing a label ≥ 0 with at least ``min_points``.

    xyz: (n, 3) [m]; labels: (n,) int, negative = no group. The fits come in label order and
    carry the label as ``plane_id``; vectorised over groups (:func:`group_moments`), with each
    RMS taken from the residuals themselves, as in :func:`fit_points`.
    """
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.int64)
    count, centroid, covariance = group_moments(points, labels)
    fits = {g: _fit_from_covariance(g, count[g], centroid[g], covariance[g])
            for g in np.flatnonzero(count >= max(min_points, 3))}
    if not fits:
        return []
    normal = np.zeros((len(count), 3))
    for g, fit in fits.items():
        normal[g] = fit.normal
    keep = labels >= 0
    residual = np.einsum("ij,ij->i", points[keep] - centroid[labels[keep]], normal[labels[keep]])
    mean_square = np.bincount(labels[keep], weights=residual**2, minlength=len(count)) / np.maximum(count, 1)
    for g, fit in fits.items():
        fit.rms_m = float(np.sqrt(mean_square[g]))
    return list(fits.values())


def residuals(xyz: np.ndarray, fit: PlaneFit) -> np.ndarray:
    """Signed orthogonal distances (n,) [m] of points (n, 3) [m] from a fitted plane."""
    return (np.asarray(xyz, dtype=np.float64) - fit.centroid) @ fit.normal
