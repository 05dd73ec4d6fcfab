"""The wedge prism's float64 relations and its exit fan at given prism angles, traced on a device (for
figures, checks and the deflector's reach)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from kernels.optics import exit_fan_kernel


def apex_for_cone(cone_half_angle: float, n_glass: float) -> float:
    """Apex angle α [rad] whose on-axis deviation is the cone half-angle θ [rad].

    The on-axis beam crosses Σ1 undeviated and meets Σ2 at incidence α, leaving at asin(n sin α),
    so θ = asin(n sin α) − α, i.e. tan α = sin θ / (n − cos θ).
    """
    return math.atan2(math.sin(cone_half_angle), n_glass - math.cos(cone_half_angle))


def cone_for_apex(apex: float, n_glass: float) -> float:
    """On-axis deviation θ [rad] of a wedge of apex α [rad]; NaN on total internal reflection."""
    s = n_glass * math.sin(apex)
    return math.asin(s) - apex if s < 1.0 else math.nan


@dataclass
class ExitFan:
    """Exit rays of an n×n fan at m prism angles; arrays are indexed [angle, i·n + j]."""

    phi: np.ndarray  # (m,) [rad]
    directions: np.ndarray  # (m, n², 3) unit exit directions S3 [sensor frame]
    exit_points: np.ndarray  # (m, n², 3) [m]
    nominal: np.ndarray  # (m, n², 3) rigid-array directions
    ok: np.ndarray  # (m, n²) False where the beam is totally internally reflected


def trace_fan(phi, n: int, spacing_rad: float, n_glass: float, apex_rad: float, thickness_m: float = 0.01,
              precision: str = "float32", device: str = "cpu") -> ExitFan:
    """Trace the fan through the prism at each prism angle ``phi`` [rad] with the device optics."""
    dtype = {"float32": wp.float32, "float64": wp.float64}[precision]
    device = resolve_device(device)
    vec3 = wp.types.vector(3, dtype)
    phis = wp.array(np.asarray(phi, dtype=np.float64).ravel(), dtype=dtype, device=device)
    shape = (phis.shape[0], n * n)
    out = [wp.empty(shape, dtype=vec3, device=device) for _ in range(3)] + [wp.empty(shape, dtype=wp.int32, device=device)]
    wp.launch(exit_fan_kernel(dtype), shape,
              inputs=[phis, n, dtype(spacing_rad), dtype(n_glass), dtype(apex_rad), dtype(thickness_m)],
              outputs=out, device=device)
    directions, points, nominal, ok = (a.numpy() for a in out)
    return ExitFan(np.asarray(phi, dtype=np.float64).ravel(), directions.astype(np.float64),
                   points.astype(np.float64), nominal.astype(np.float64), ok.astype(bool))
