"""Lines in the (E, N) plane of :mod:`flightsim.calibration.ccr` [m]: azimuths modulo 180°, total-least-
squares line fits, and the common tangents of two circles (patent step 4)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError

_TOUCH = 1e-12  # relative tolerance of two circles touching (one tangent where two meet)


def axial_difference_deg(a_deg, b_deg):
    """Difference of two line azimuths (defined modulo 180°), in [−90°, 90°) [deg]."""
    return (np.asarray(a_deg) - np.asarray(b_deg) + 90.0) % 180.0 - 90.0


@dataclass(frozen=True)
class Line:
    """A line in the (E, N) plane: a point on it [m] and its azimuth in [0°, 180°) [deg]."""

    point_en: np.ndarray
    azimuth_deg: float

    @property
    def direction(self) -> np.ndarray:
        """Unit vector along the line, (sin az, cos az)."""
        az = math.radians(self.azimuth_deg)
        return np.array([math.sin(az), math.cos(az)])

    @property
    def normal(self) -> np.ndarray:
        """Unit normal, to the right of :attr:`direction`."""
        d = self.direction
        return np.array([d[1], -d[0]])

    def signed_distance(self, points_en) -> np.ndarray:
        """Distance of points (n, 2) from the line, + on the side of :attr:`normal` [m]."""
        return (np.asarray(points_en, dtype=np.float64)[..., :2] - self.point_en) @ self.normal


def _line_from_direction(point_en, direction_en) -> Line:
    return Line(np.asarray(point_en, dtype=np.float64),
                float(math.degrees(math.atan2(direction_en[0], direction_en[1])) % 180.0))


def fit_line(points_en, weights=None) -> tuple[Line, float]:
    """Total-least-squares line through points (n ≥ 2, 2) [m], each weighted (default 1), and
    the weighted RMS distance of the points from it [m]."""
    p = np.asarray(points_en, dtype=np.float64)[:, :2]
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    centre = (w @ p) / w.sum()
    _, s, vt = np.linalg.svd((p - centre) * np.sqrt(w)[:, None], full_matrices=False)
    rms = s[1] / math.sqrt(w.sum()) if len(s) > 1 else 0.0
    return _line_from_direction(centre, vt[0]), float(rms)


@dataclass(frozen=True)
class Tangents:
    """Common tangent lines of two circles: points of tangency on each and each line's azimuth."""

    point1_en: np.ndarray  # (k, 2) [m]
    point2_en: np.ndarray  # (k, 2) [m]
    normal_en: np.ndarray  # (k, 2) unit normals
    kinds: tuple[str, ...]  # "external" (both circles on one side) or "internal"

    @property
    def azimuth_deg(self) -> np.ndarray:
        """Azimuth of each line in [0°, 180°) [deg]."""
        return np.degrees(np.arctan2(self.normal_en[:, 1], -self.normal_en[:, 0])) % 180.0

    def line(self, i: int) -> Line:
        """Tangent i as a :class:`Line`."""
        n = self.normal_en[i]
        return _line_from_direction(self.point1_en[i], (n[1], -n[0]))


def common_tangents(centre1, radius1: float, centre2, radius2: float) -> Tangents:
    """The common tangents of two circles (patent ¶6): 4 when they are apart, 3 when touching
    outside, 2 when they cross, 1 when touching inside, 0 when one holds the other.

    A line n·x = p (|n| = 1) is tangent to circle i when n·c_i − p = σ_i r_i; with σ1 = 1,
    n·(c2 − c1) = σ2 r2 − r1 fixes n up to the side of the centre line (σ2 = +1: external
    tangents, −1: internal). The points of tangency are c_i − σ_i r_i n.
    """
    c1, c2 = np.asarray(centre1, dtype=np.float64), np.asarray(centre2, dtype=np.float64)
    if not (radius1 >= 0 and radius2 >= 0):
        raise InputError("radius", (radius1, radius2), "two radii >= 0 [m]")
    d = c2 - c1
    dist = math.hypot(*d)
    if dist == 0.0:
        raise InputError("centre2", c2.tolist(), "a centre different from centre1")
    e, e_perp = d / dist, np.array([-d[1], d[0]]) / dist
    p1, p2, normals, kinds = [], [], [], []
    for sigma2, kind in ((1.0, "external"), (-1.0, "internal")):
        cos_t = (sigma2 * radius2 - radius1) / dist
        if abs(cos_t) > 1.0 + _TOUCH:
            continue
        touching = abs(cos_t) >= 1.0 - _TOUCH
        sin_t = 0.0 if touching else math.sqrt(1.0 - cos_t * cos_t)
        for side in ((1.0,) if touching else (1.0, -1.0)):
            n = cos_t * e + side * sin_t * e_perp
            p1.append(c1 - radius1 * n)
            p2.append(c2 - sigma2 * radius2 * n)
            normals.append(n)
            kinds.append(kind)
    return Tangents(np.array(p1).reshape(-1, 2), np.array(p2).reshape(-1, 2),
                    np.array(normals).reshape(-1, 2), tuple(kinds))
