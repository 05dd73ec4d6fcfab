"""Independent float64 NumPy model of the beam optics, written from SPEC §3–§5 without the kernels.

Refraction is done by the tangential-component construction (the tangential part of the
direction scales by n_in/n_out, the normal part fills the unit length), not by the closed
vector formula the kernels use, so an error in either shows up as a disagreement.
"""
import numpy as np


def fan_directions(n: int, spacing: float) -> np.ndarray:
    """(n², 3) incident unit directions S1, row-major over (i, j) [sensor frame]."""
    offsets = (np.arange(n) - (n - 1) / 2.0) * spacing
    a, b = np.meshgrid(offsets, offsets, indexing="ij")
    s = np.stack([np.tan(a), np.tan(b), np.ones_like(a)], axis=-1).reshape(-1, 3)
    return s / np.linalg.norm(s, axis=1, keepdims=True)


def refract_tangential(s: np.ndarray, normal: np.ndarray, n_in: float, n_out: float):
    """Refracted unit directions and a TIR mask; normal oriented along propagation."""
    s = np.atleast_2d(s)
    normal = np.broadcast_to(normal, s.shape)
    along = np.sum(s * normal, axis=-1, keepdims=True)
    tangential = (s - along * normal) * (n_in / n_out)
    tangential_sq = np.sum(tangential**2, axis=-1, keepdims=True)
    tir = tangential_sq[..., 0] > 1.0
    normal_part = np.sqrt(np.clip(1.0 - tangential_sq, 0.0, None))
    return tangential + normal_part * normal, tir


def back_normal(phi: float, apex: float) -> np.ndarray:
    return np.array([np.sin(apex) * np.cos(phi), np.sin(apex) * np.sin(phi), np.cos(apex)])


def ray_plane(origin: np.ndarray, direction: np.ndarray, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Seed paper eqs. (3)–(4): where rays origin + t·direction meet the plane through ``point``."""
    t = np.sum((point - origin) * normal, axis=-1, keepdims=True) / np.sum(direction * normal, axis=-1, keepdims=True)
    return origin + t * direction


def prism_exit(s1: np.ndarray, phi: float, n_glass: float, apex: float, thickness: float):
    """(S3, exit point, TIR mask) for incident directions s1 (k, 3) at prism angle phi."""
    s2, _ = refract_tangential(s1, np.array([0.0, 0.0, 1.0]), 1.0, n_glass)
    n2 = back_normal(phi, apex)
    exit_point = ray_plane(np.zeros_like(s2), s2, n2, np.array([0.0, 0.0, thickness]))
    s3, tir = refract_tangential(s2, n2, n_glass, 1.0)
    return s3, exit_point, tir


def rotation_z_to(v: np.ndarray) -> np.ndarray:
    """Rodrigues matrix of the smallest rotation taking ẑ to the unit vector v."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, v)
    s, c = np.linalg.norm(axis), float(np.dot(z, v))
    if s < 1e-15:
        return np.eye(3)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def nominal_directions(n: int, spacing: float, phi: float, n_glass: float, apex: float) -> np.ndarray:
    """(n², 3) rigid-array directions Q_ij · S3_center(φ)."""
    center, _, _ = prism_exit(np.array([[0.0, 0.0, 1.0]]), phi, n_glass, apex, 0.01)
    return np.array([rotation_z_to(s1) @ center[0] for s1 in fan_directions(n, spacing)])


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors [rad], accurate for tiny angles (atan2 of |a×b| and a·b)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))
