"""Comparing a point cloud with a reference cloud, and registering one frame to another from control points.

- :func:`c2c_distances`: cloud-to-cloud nearest-neighbour distance (CloudCompare's C2C without a local model):
  unsigned, and it includes the reference's point spacing (for a reference of planar density λ and a point at
  height z over it, P(D > r) = exp(−λπ(r² − z²)) for r ≥ |z|).
- :func:`plane_distances`: M3C2-style, the signed distance along the normal of a plane fitted (total least
  squares) through the k nearest reference points, the normal turned to +z: the reference's spacing drops out.
- :func:`rigid_fit`: the least-squares rotation and translation between matched points (Kabsch/Horn, SVD,
  float64); :func:`rigid_fit_error` its expected squared error at a point, to first order in the noise.
- :func:`total_station`: a total station's polar measurement of points: range noise a + b·ppm, horizontal and
  zenith angle noise in arcseconds.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

ARCSEC = math.pi / 648000.0
CHUNK = 200_000  # query points per block of the plane fits


def c2c_distances(points: np.ndarray, reference: np.ndarray | cKDTree) -> np.ndarray:
    """Unsigned distance [m] of each point (n, 3) to its nearest reference point."""
    tree = reference if isinstance(reference, cKDTree) else cKDTree(reference)
    return tree.query(points, k=1)[0]


def plane_distances(points: np.ndarray, reference: np.ndarray, tree: cKDTree | None = None, k: int = 12) -> np.ndarray:
    """Signed distance [m] of each point (n, 3) to the plane through its k nearest reference points (float64
    covariance, smallest eigenvector, turned to +z); positive above the reference."""
    tree = tree or cKDTree(reference)
    out = np.empty(len(points))
    for a in range(0, len(points), CHUNK):
        p = points[a:a + CHUNK]
        _, idx = tree.query(p, k=k)
        nb = reference[idx]  # (m, k, 3)
        centre = nb.mean(axis=1)
        d = nb - centre[:, None, :]
        cov = np.einsum("mki,mkj->mij", d, d)
        _, vectors = np.linalg.eigh(cov)
        normal = vectors[:, :, 0]
        normal *= np.where(normal[:, 2] < 0.0, -1.0, 1.0)[:, None]
        out[a:a + CHUNK] = np.einsum("mi,mi->m", p - centre, normal)
    return out


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising Σ |R·source_i + t − target_i|² (Kabsch, reflection excluded), float64."""
    s, t = np.asarray(source, np.float64), np.asarray(target, np.float64)
    cs, ct = s.mean(axis=0), t.mean(axis=0)
    u, _, vt = np.linalg.svd((s - cs).T @ (t - ct))
    sign = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    return r, ct - r @ cs


def rigid_fit_error(points: np.ndarray, sigma: float, x: np.ndarray) -> float:
    """Expected |error|² [m²] of a rigid fit's transform at point x, for isotropic noise σ (per axis, both sets'
    together) on the matched points: 3σ²/n from the translation plus trace((|x'|²I − x'x'ᵀ)·σ²M⁻¹) from the
    rotation, M = Σ(|p_i|²I − p_i p_iᵀ), p and x' taken from the points' centroid."""
    p = np.asarray(points, np.float64)
    c = p.mean(axis=0)
    q = p - c
    m = np.sum([np.dot(v, v) * np.eye(3) - np.outer(v, v) for v in q], axis=0)
    xc = np.asarray(x, np.float64) - c
    lever = np.dot(xc, xc) * np.eye(3) - np.outer(xc, xc)
    return 3.0 * sigma ** 2 / len(p) + float(np.trace(lever @ (sigma ** 2 * np.linalg.inv(m))))


def total_station(points: np.ndarray, station: np.ndarray, rng: np.random.Generator, mm: float = 2.0,
                  ppm: float = 2.0, arcsec: float = 2.0) -> np.ndarray:
    """The points (n, 3) as a total station at ``station`` measures them (same frame): range noise
    √(mm² + (ppm·d)²), horizontal and zenith angle noise ``arcsec`` each (1σ)."""
    v = np.asarray(points, np.float64) - station
    d = np.linalg.norm(v, axis=1)
    azimuth, zenith = np.arctan2(v[:, 0], v[:, 1]), np.arccos(v[:, 2] / d)
    d = d + rng.normal(0.0, 1.0, len(d)) * np.hypot(mm * 1e-3, ppm * 1e-6 * d)
    azimuth = azimuth + rng.normal(0.0, arcsec * ARCSEC, len(d))
    zenith = zenith + rng.normal(0.0, arcsec * ARCSEC, len(d))
    return station + d[:, None] * np.column_stack([np.sin(zenith) * np.sin(azimuth), np.sin(zenith) * np.cos(azimuth),
                                                   np.cos(zenith)])


def stats_cm(d: np.ndarray) -> dict[str, float]:
    """3σ, RMSE and mean of distances [cm], and their count."""
    d = d[np.isfinite(d)]
    return {"three_sigma_cm": 300.0 * float(np.std(d)), "rmse_cm": 100.0 * float(np.sqrt(np.mean(d ** 2))),
            "mean_cm": 100.0 * float(np.mean(d)), "n": int(len(d))}
