"""Surfaces of the full-waveform reference model (:mod:`flightsim.instrument.waveform_model`): heights
z(x, y) above the datum [m], upward unit normals and the range [m] from the sensor at (0, 0, H) along a
ray. The plane of the patent's Figs. 3–4 and the bump of its Fig. 5 ("flat all round, a bump in the
middle"), whose size the patent does not state: a raised-cosine hill 5 m high, 20 m in radius, centred on
nadir, by default.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError


def _unit_normal(zx: np.ndarray, zy: np.ndarray) -> np.ndarray:
    """Upward unit normal (−z_x, −z_y, 1)/‖·‖ of a height field with gradient (z_x, z_y)."""
    n = np.stack(np.broadcast_arrays(-zx, -zy, 1.0), axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@dataclass(frozen=True)
class PlaneSurface:
    """The plane z = s·x, rising ``slope`` = s (rise/run) towards +x; flat ground when s = 0."""

    slope: float = 0.0

    def __post_init__(self):
        if not math.isfinite(self.slope):
            raise InputError("surface.slope", self.slope, "a finite rise/run")

    def height(self, x, y) -> np.ndarray:
        """z(x, y) [m]."""
        x, _ = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return self.slope * x

    def normal(self, x, y) -> np.ndarray:
        """Upward unit normal (..., 3)."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return _unit_normal(np.full_like(x, self.slope), np.zeros_like(y))

    def intersect(self, altitude_m: float, direction: np.ndarray) -> np.ndarray:
        """Range t [m] from (0, 0, H) along unit ``direction`` (N, 3) to the plane: H + t·d_z = s·t·d_x."""
        return altitude_m / (self.slope * direction[:, 0] - direction[:, 2])


@dataclass(frozen=True)
class BumpSurface:
    """Flat ground with a raised-cosine hill in the middle (the patent's Fig. 5; size chosen here):
    z = (h/2)(1 + cos(πρ/a)) for ρ = √(x² + y²) < a, else 0."""

    height_m: float = 5.0
    radius_m: float = 20.0

    def __post_init__(self):
        if not math.isfinite(self.height_m):
            raise InputError("surface.height_m", self.height_m, "a finite height [m]")
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise InputError("surface.radius_m", self.radius_m, "a finite radius > 0 m")

    def height(self, x, y) -> np.ndarray:
        """z(x, y) [m]."""
        rho = np.hypot(x, y)
        return np.where(rho < self.radius_m, 0.5 * self.height_m * (1.0 + np.cos(np.pi * rho / self.radius_m)), 0.0)

    def _gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(∂z/∂x, ∂z/∂y): dz/dρ = −(πh/2a) sin(πρ/a) along (x, y)/ρ."""
        rho = np.hypot(x, y)
        inside = (rho < self.radius_m) & (rho > 0.0)
        dz_drho = -0.5 * np.pi * self.height_m / self.radius_m * np.sin(np.pi * rho / self.radius_m)
        per_rho = np.where(inside, dz_drho / np.where(inside, rho, 1.0), 0.0)
        return per_rho * x, per_rho * y

    def normal(self, x, y) -> np.ndarray:
        """Upward unit normal (..., 3)."""
        return _unit_normal(*self._gradient(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)))

    def intersect(self, altitude_m: float, direction: np.ndarray) -> np.ndarray:
        """Range t [m] from (0, 0, H) along unit ``direction`` (N, 3): Newton on f(t) = H + t·d_z − z(t·d_x,
        t·d_y) from the datum's hit; f' = d_z − ∇z·(d_x, d_y) ≈ d_z, so each step gains ~4 digits."""
        t = altitude_m / -direction[:, 2]
        for _ in range(20):
            x, y = t * direction[:, 0], t * direction[:, 1]
            zx, zy = self._gradient(x, y)
            step = (altitude_m + t * direction[:, 2] - self.height(x, y)) / (
                direction[:, 2] - zx * direction[:, 0] - zy * direction[:, 1])
            t = t - step
            if np.max(np.abs(step)) < 1e-9:
                break
        return t
