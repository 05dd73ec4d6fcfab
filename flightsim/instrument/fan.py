"""The exit fan of the prism at given prism angles, traced on a device (for figures and checks)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from kernels.optics import exit_fan_kernel


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
