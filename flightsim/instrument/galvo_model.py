"""Float64 reference model of the two-mirror galvanometer scanner (NumPy only, no Warp).

The geometry is that of ``kernels/galvo.py`` (galvo frame = sensor frame: +z the optical axis, x
horizontal, y vertical; source at (−b, −e, 0) firing along +x; mirror 1 turning about z through
(0, −e, 0), mirror 2 about x through the origin). This module serves the host: the geometry
checks of the config, the first-order error propagation of the budget (seed paper eqs. 11–22)
and the per-source deviation tables (seed paper Table 1). Angles in radians, lengths in metres.

A frame's slots are ordered pulse-major, channel-minor (slot = pulse · channels + channel), the
pulses in raster order (``raster_angles``), as the device numbers them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flightsim.instrument.channels import CHANGE3_CHANNELS_MRAD

PARAMS = ("b1", "b2", "b3", "c1", "n_h", "n_v", "range")  # the sources of the propagation, in Jacobian order
SIGMA_Z_M = 0.20 / 3.0  # allowed 1σ of Z at 100 m: the 20 cm requirement taken as 3σ (seed paper §3)
_STEP_RAD = 1e-7  # central-difference step of the angle derivatives [rad]


@dataclass(frozen=True)
class GalvoGeometry:
    """The scanner as built (or believed): mirror separations, channel angles and the raster."""

    b_m: float = 0.05  # source to mirror 1 along x [m]
    e_m: float = 0.02  # mirror 1 to mirror 2 along y [m]
    channel_angles_rad: tuple[float, ...] = field(default=tuple(a * 1e-3 for a in CHANGE3_CHANNELS_MRAD))
    field_deg: tuple[float, float] = (30.0, 30.0)  # full beam field (horizontal, vertical) [deg]
    strips: int = 17
    columns: int = 256

    @property
    def channels(self) -> int:
        return len(self.channel_angles_rad)


@dataclass(frozen=True)
class MirrorHits:
    """Where the beams meet the mirrors: ``front`` where both are met on their reflecting sides,
    ``off_pivot1`` and ``off_pivot2`` the hit distances from the mirrors' pivots [m]."""

    front: np.ndarray
    off_pivot1: np.ndarray
    off_pivot2: np.ndarray


def raster_angles(geom: GalvoGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(δ, γ, dir) the encoders report for each pulse of one frame: mirror angles [rad], strip direction ±1."""
    k = np.arange(geom.strips * geom.columns)
    strip, column = np.divmod(k, geom.columns)
    odd = strip % 2 == 1
    column = np.where(odd, geom.columns - 1 - column, column)
    h_half, v_half = (np.radians(f) / 4.0 for f in geom.field_deg)  # a mirror turns half the beam
    delta = -h_half + 2.0 * h_half * column / max(geom.columns - 1, 1)
    gamma = -v_half + 2.0 * v_half * strip / max(geom.strips - 1, 1)
    return delta, gamma, np.where(odd, -1.0, 1.0)


def mirror_normals(delta, gamma) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (n1, n2), each (..., 3), of the mirrors at angles δ, γ [rad]."""
    delta, gamma = np.broadcast_arrays(np.asarray(delta, dtype=np.float64), np.asarray(gamma, dtype=np.float64))
    a1, a2 = 0.75 * np.pi - delta, 0.75 * np.pi - gamma
    zero = np.zeros_like(delta)
    return (np.stack([np.cos(a1), np.sin(a1), zero], axis=-1),
            np.stack([zero, np.cos(a2), np.sin(a2)], axis=-1))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1)


def _reflect(s: np.ndarray, n: np.ndarray) -> np.ndarray:
    return s - 2.0 * _dot(s, n)[..., None] * n


def _propagate(geom: GalvoGeometry, delta, gamma, channel):
    """Every intermediate of the trace: (s, n1, n2, t1, q1, s2, t2, q2, s3), broadcast over the inputs."""
    theta = np.asarray(geom.channel_angles_rad, dtype=np.float64)[np.asarray(channel)]
    delta, gamma, theta = np.broadcast_arrays(np.asarray(delta, dtype=np.float64),
                                              np.asarray(gamma, dtype=np.float64), theta)
    s = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], axis=-1)  # emitter (0, sin, cos) mounted
    n1, n2 = mirror_normals(delta, gamma)
    source = np.array([-geom.b_m, -geom.e_m, 0.0])
    t1 = n1[..., 0] * geom.b_m / _dot(n1, s)  # n1·(P1 − S) / n1·s with P1 − S = (b, 0, 0)
    q1 = source + t1[..., None] * s
    s2 = _reflect(s, n1)
    t2 = -_dot(n2, q1) / _dot(n2, s2)  # the pivot of mirror 2 is the origin
    q2 = q1 + t2[..., None] * s2
    return s, n1, n2, t1, q1, s2, t2, q2, _reflect(s2, n2)


def trace(geom: GalvoGeometry, delta, gamma, channel) -> tuple[np.ndarray, np.ndarray]:
    """(exit point on mirror 2 [m], unit exit direction), each (..., 3), of channel ``channel`` at δ, γ."""
    *_, q2, s3 = _propagate(geom, delta, gamma, channel)
    return q2, s3


def mirror_hits(geom: GalvoGeometry, delta, gamma, channel) -> MirrorHits:
    """Whether and how far from the pivots the beams meet the two mirrors."""
    s, n1, n2, t1, q1, s2, t2, q2, _ = _propagate(geom, delta, gamma, channel)
    front = (_dot(n1, s) < 0.0) & (_dot(n2, s2) < 0.0) & (t1 > 0.0) & (t2 > 0.0)
    pivot1 = np.array([0.0, -geom.e_m, 0.0])
    return MirrorHits(front, np.linalg.norm(q1 - pivot1, axis=-1), np.linalg.norm(q2, axis=-1))


def deviation(geom: GalvoGeometry, distance_m: float, errors: dict[str, float] | None = None,
              believed: GalvoGeometry | None = None) -> np.ndarray:
    """Processed point − true hit, (pulses, channels, 3) in the sensor frame [m], of one frame over the
    plane z = ``distance_m``, with the angle errors of ``errors`` ({b1, b2, b3, c1, n_h, n_v} [rad],
    range [m]; absent = 0) on the truth and the processing believing ``believed`` (default ``geom``)
    without errors. Each error is one constant over the frame (B1's sign follows the strip)."""
    e = {k: 0.0 for k in PARAMS} | (errors or {})
    delta, gamma, direction = (a[:, None] for a in raster_angles(geom))
    channel = np.arange(geom.channels)[None, :]
    true_delta = delta + e["b1"] * direction + e["b2"] / np.cos(gamma) + e["b3"] * np.tan(gamma) + e["n_h"]
    true_gamma = gamma + e["c1"] + e["n_v"]
    start, ray = trace(geom, true_delta, true_gamma, channel)
    t = (distance_m - start[..., 2]) / ray[..., 2]
    hit = start + t[..., None] * ray
    start_b, ray_b = trace(believed or geom, delta, gamma, channel)
    return start_b + (t + e["range"])[..., None] * ray_b - hit


def table1(geom: GalvoGeometry, distance_m: float, values: dict[str, float]) -> dict[str, dict[str, tuple]]:
    """Seed paper Table 1: each source of ``values`` ({name: value [rad or m]}) alone at its value;
    {name: {axis: (max, min) of |deviation| over the frame}} [m]."""
    out = {}
    for name, value in values.items():
        a = np.abs(deviation(geom, distance_m, {name: value})).reshape(-1, 3)
        out[name] = {axis: (float(a[:, k].max()), float(a[:, k].min())) for k, axis in enumerate("XYZ")}
    return out


def jacobian(geom: GalvoGeometry, distance_m: float) -> np.ndarray:
    """∂(deviation)/∂(source) at zero error, (slots, 3, len(PARAMS)) [m per rad, m per m].

    The angle columns are central differences of the exact model (step 1e-7 rad: truncation ~1e-14
    relative, rounding ~1e-9 relative); the range column is the believed beam direction."""
    columns = []
    for name in PARAMS:
        step = _STEP_RAD if name != "range" else 1.0
        plus = deviation(geom, distance_m, {name: step})
        minus = deviation(geom, distance_m, {name: -step})
        columns.append(((plus - minus) / (2.0 * step)).reshape(-1, 3))
    return np.stack(columns, axis=-1)


def analytic_sigma(geom: GalvoGeometry, sigmas: dict[str, float], distance_m: float) -> np.ndarray:
    """First-order 1σ of each slot's deviation, (slots, 3) [m], of independent zero-mean sources with
    1σ ``sigmas`` ({name of PARAMS: σ}; absent = 0): the diagonal of J Σ Jᵀ (seed paper eqs. 16–18)."""
    variance = np.array([sigmas.get(name, 0.0) ** 2 for name in PARAMS])
    return np.sqrt(jacobian(geom, distance_m) ** 2 @ variance)


def allowed_errors(geom: GalvoGeometry, sigma_r_m: float, distance_m: float,
                   sigma_z_m: float = SIGMA_Z_M) -> dict[str, float]:
    """Allowed encoder errors (seed paper §3.3, eqs. 19–22) from the ranging σ_r.

    Per slot, with equal angle σθ on both mirrors (eq. 20): σz² = (∂z/∂r)² σ_r² + [(∂z/∂δ)² + (∂z/∂γ)²] σθ²;
    σθ is the largest value that keeps every slot's σz within ``sigma_z_m`` (the binding slot sets it).
    The horizontal angle's systematic part σθx = σB (1 + sec γ + tan γ) (eq. 22) then gives σB, γ being
    the binding slot's vertical angle observation (half its beam's vertical angle, |·|).
    """
    jac = jacobian(geom, distance_m)[:, 2, :]  # the Z row
    j_r = jac[:, PARAMS.index("range")]
    j_angle = np.hypot(jac[:, PARAMS.index("n_h")], jac[:, PARAMS.index("n_v")])
    room = sigma_z_m ** 2 - (j_r * sigma_r_m) ** 2
    if (room <= 0).any():
        raise ValueError(f"σ_r = {sigma_r_m} m alone exceeds σz = {sigma_z_m} m: no angle error is allowed")
    theta = np.sqrt(room) / j_angle
    binding = int(np.argmin(theta))
    delta, gamma, _ = raster_angles(geom)
    _, ray = trace(geom, delta[:, None], gamma[:, None], np.arange(geom.channels)[None, :])
    gamma_obs = 0.5 * abs(float(np.arctan2(ray[..., 1], ray[..., 2]).reshape(-1)[binding]))
    arcsec = np.degrees(1.0) * 3600.0
    sigma_theta = float(theta[binding])
    return {"sigma_z_m": sigma_z_m, "sigma_r_m": sigma_r_m, "sigma_theta_arcsec": sigma_theta * arcsec,
            "gamma_deg": float(np.degrees(gamma_obs)),
            "sigma_b_arcsec": sigma_theta / (1.0 + 1.0 / np.cos(gamma_obs) + np.tan(gamma_obs)) * arcsec,
            "binding_slot": binding}
