"""Float64 reference model of the fast-steering-mirror path (NumPy only; the geometry of kernels/fsm.py).

Angles in radians, lengths in metres; directions and exit points in the sensor frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

H = np.sqrt(0.5)
SENSOR_AXES = np.array([[1.0, 0.0, 0.0], [0.0, H, -H], [0.0, H, H]])  # rows: sensor x, y, z in the FSM frame
FOLD_NORMAL = np.array([1.0, -H, H]) / np.sqrt(2.0)


@dataclass(frozen=True)
class FsmGeometry:
    b2_m: float = 0.03
    d_m: float = 0.04
    mode: str = "A"
    span_rad: tuple[float, float] = (2.62e-3, 1.80e-3)
    lines: int = 40
    frame_pulses: int = 43000


def scan_angles(g: FsmGeometry, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θx, θy) the encoders report for pulses k [rad] (kernels.fsm.scan_angles)."""
    f = np.asarray(k) % g.frame_pulses
    if g.mode == "A":
        per = g.frame_pulses // g.lines
        line = np.minimum(f // per, g.lines - 1)
        u = (f - line * per) / max(per - 1, 1)
        u = np.where(line % 2 == 1, 1.0 - u, u)
        v = line / max(g.lines - 1, 1)
    else:
        per = g.frame_pulses // (g.lines * g.lines)
        step = np.minimum(f // per, g.lines * g.lines - 1)
        u, v = (step % g.lines) / max(g.lines - 1, 1), (step // g.lines) / max(g.lines - 1, 1)
    return g.span_rad[0] * (u - 0.5), g.span_rad[1] * (v - 0.5)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _reflect(s, n):
    return s - 2.0 * _dot(s, n)[..., None] * n


def fsm_normal(theta_x, theta_y) -> np.ndarray:
    n = np.stack(np.broadcast_arrays(np.tan(theta_x), np.tan(theta_y), -1.0), axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def trace(g: FsmGeometry, theta_x, theta_y, emitted: np.ndarray):
    """(exit point [m], unit direction, hits (P1 off-centre, P2 off-centre) [m]) in the sensor frame of beams
    emitted along ``emitted`` (..., 3) (emitter frame) with the FSM at θx, θy; all broadcast."""
    e = np.asarray(emitted, dtype=np.float64)
    s0 = np.stack([e[..., 2], H * (e[..., 0] + e[..., 1]), H * (e[..., 1] - e[..., 0])], axis=-1)  # mounted
    s = _reflect(s0, FOLD_NORMAL)
    grating = np.array([-g.b2_m, -H * g.d_m, H * g.d_m])
    centre = np.array([0.0, -H * g.d_m, H * g.d_m])
    t1 = _dot(FOLD_NORMAL, centre - grating) / _dot(FOLD_NORMAL, s0)
    p1 = grating + t1[..., None] * s0
    n = fsm_normal(theta_x, theta_y)
    t2 = -_dot(n, p1) / _dot(n, s)
    p2 = p1 + t2[..., None] * s
    out = _reflect(s, n)
    return p2 @ SENSOR_AXES.T, out @ SENSOR_AXES.T, (np.linalg.norm(p1 - centre, axis=-1), np.linalg.norm(p2, axis=-1))
