"""A spacecraft hovering over a small body that spins beneath it (``flight.body_rotation_period_s``).

Physics. The body spins about its local y axis (the ellipsoid scene's b axis) through the scene's
local origin (the ellipsoid's centre), right-handed, with period P [s]: a point fixed on the body
at b [m, local] lies at R_y(ω t)·b in inertial space, ω = 2π/P, t measured from
flight.start_gps_time. For the uniform ellipsoid with b = c < a the moments of inertia are
I_x = 2mc²/5 < I_y = I_z = m(a² + c²)/5, so y is a principal axis of largest inertia: the stable
spin of a relaxed body. The spacecraft hovers fixed in inertial space (``plan._hover``: over the
scene centre at flight.altitude_m above its ground, descending at flight.descent_mps, constant
attitude, sensor body z down). The simulator traces in the body-fixed (scene) frame, so the
platform is expressed there: position p(t) = R_y(−ω t)·q(t) and attitude R_body→local(t) =
R_y(−ω t)·R₀, q(t) and R₀ being the inertial hover's.

Sampling. The simulator interpolates positions linearly and attitudes by slerp between samples
(``kernels.frames._pose``, as ``Trajectory.interpolate``). Attitude: R_i⁻¹·R_(i+1) = R₀ᵀ·R_y(−ωΔt)·R₀
is one rotation by ωΔt about a fixed body axis, and slerp turns through it uniformly, so the
interpolated attitude is exact. Position: with q̈ = 0,
p̈ = R̈·q + 2Ṙ·q̇, |p̈| ≤ ω²ρ + 2ω|q̇⊥| (ρ: largest distance of the sensor from the spin axis, q̇⊥:
its inertial velocity across the axis), and the chord of a C² curve over a step Δt departs from
it by at most Δt²/8·max|p̈|. Without descent this is the sagitta ρ(1 − cos(ωΔt/2)) ≤ ρ(ωΔt)²/8.
The step is chosen so that the bound is MAX_CHORD_ERROR_M (1 mm).

Light time is ignored: each shot is traced through the body as it is at emission. During the
round trip 2R/c the body turns by ω·2R/c (P = 60 s, R = 500 m: 3.5e-7 rad, a surface 250 m from
the axis moves 87 µm).
"""
from __future__ import annotations

import math

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.scene import Scene
from trajectories import Trajectory, rotation_body_to_enu
from trajectories.attitude import NED_TO_ENU

MAX_CHORD_ERROR_M = 1.0e-3  # largest distance of the interpolated sensor position from its true path [m]
MAX_SAMPLES = 1_000_000  # trajectory samples of one rotating hover (64 bytes each on the device)
MAX_STEP_RAD = 0.1  # the body turns at most this much between samples (slerp needs less than π) [rad]


def spin_matrix(angle) -> np.ndarray:
    """R_y(angle) (..., 3, 3): right-handed rotation by ``angle`` [rad] about the local y axis."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.zeros(angle.shape + (3, 3))
    rotation[..., 0, 0], rotation[..., 0, 2] = c, s
    rotation[..., 1, 1] = 1.0
    rotation[..., 2, 0], rotation[..., 2, 2] = -s, c
    return rotation


def spun_hover(hover: Trajectory, scene: Scene, period_s: float) -> Trajectory:
    """The inertial ``hover`` (two samples: straight, uniform, constant attitude, as ``plan._hover``)
    seen from a body spinning with period ``period_s`` [s] about the local y axis, sampled uniformly at
    most :func:`sample_step` seconds apart."""
    omega = 2.0 * math.pi / period_s
    ends = scene.world_to_local(hover.position)
    duration = hover.duration
    velocity = (ends[1] - ends[0]) / duration
    step = sample_step(omega, float(np.hypot(ends[:, 0], ends[:, 2]).max()), float(np.hypot(velocity[0], velocity[2])))
    count = math.ceil(duration / step) + 1
    if count > MAX_SAMPLES:
        raise InputError("flight.duration_s", duration,
                         f"at most {(MAX_SAMPLES - 1) * step:.6g} s for a body turning every {period_s:g} s (the "
                         f"trajectory needs a sample every {step:.3g} s to stay within {MAX_CHORD_ERROR_M * 1e3:g} mm "
                         f"of its path; at most {MAX_SAMPLES} samples)")
    times = np.linspace(hover.start_time, hover.end_time, count)
    elapsed = times - hover.start_time
    spin = spin_matrix(-omega * elapsed)
    position = np.einsum("nij,nj->ni", spin, ends[0] + elapsed[:, None] * velocity)
    attitude = attitude_angles(spin @ rotation_body_to_enu(*hover.attitude[0]))
    return Trajectory(times, scene.local_to_world(position), attitude, hover.line_id)


def sample_step(omega: float, radius_m: float, speed_mps: float) -> float:
    """Longest sample step [s] whose chord stays within MAX_CHORD_ERROR_M of the path, Δt²/8·(ω²ρ +
    2ω|q̇⊥|) ≤ MAX_CHORD_ERROR_M, and over which the body turns at most MAX_STEP_RAD; for spin rate
    ``omega`` [rad/s], largest distance from the spin axis ``radius_m`` [m] and inertial speed
    across the axis ``speed_mps`` [m/s]."""
    limit = MAX_STEP_RAD / omega
    curvature = omega * omega * radius_m + 2.0 * omega * speed_mps  # bound on |p̈| [m/s²]
    return min(limit, math.sqrt(8.0 * MAX_CHORD_ERROR_M / curvature)) if curvature > 0.0 else limit


def attitude_angles(rotation: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, heading [rad] of R_body→local (n, 3, 3) (``trajectories.attitude``:
    R_body→NED = Rz(heading)·Ry(pitch)·Rx(roll)), roll and heading unwrapped along the samples.

    Heading comes from the body x axis, then pitch and roll from Rz(heading)ᵀ·R_body→NED =
    Ry(pitch)·Rx(roll), so the angles reproduce the matrix to rounding even where the body x axis
    passes the vertical (pitch ±90°, reached when heading is ±90° and the body spins beneath), where
    heading alone is ill-defined. There heading and roll turn by π together; the simulator slerps
    quaternions of the matrices, so this never reaches the interpolation.
    """
    ned = NED_TO_ENU @ rotation
    heading = np.arctan2(ned[:, 1, 0], ned[:, 0, 0])
    ch, sh = np.cos(heading), np.sin(heading)
    cos_pitch = ch * ned[:, 0, 0] + sh * ned[:, 1, 0]
    cos_roll = ch * ned[:, 1, 1] - sh * ned[:, 0, 1]
    sin_roll = sh * ned[:, 0, 2] - ch * ned[:, 1, 2]
    pitch = np.arctan2(-ned[:, 2, 0], cos_pitch)
    roll = np.arctan2(sin_roll, cos_roll)
    return np.column_stack([np.unwrap(roll), pitch, np.unwrap(heading)])


def check_clearance(trajectory: Trajectory, scene: Scene, altitude_m: float, min_clearance_m: float) -> None:
    """Reject a hover that the spinning body would strike: every position the simulator interpolates
    (the chords between samples) must stay ``min_clearance_m`` [m] farther from the spin axis than
    any triangle meeting the sensor's y range (a triangle's farthest point from the axis is a
    vertex). Raises InputError naming flight.altitude_m (value ``altitude_m``)."""
    local = scene.world_to_local(trajectory.position)
    closest = _closest_to_axis(local[:, [0, 2]])
    corners = scene.vertices[scene.triangles]
    meets = (corners[:, :, 1].max(axis=1) >= local[:, 1].min()) & (corners[:, :, 1].min(axis=1) <= local[:, 1].max())
    reach = float(np.hypot(corners[meets, :, 0], corners[meets, :, 2]).max()) if meets.any() else 0.0
    if closest - reach >= min_clearance_m:
        return
    raise InputError("flight.altitude_m", altitude_m,
                     f"an altitude keeping the sensor {min_clearance_m:g} m clear of the spinning body: it sweeps "
                     f"out to {reach:.3f} m from its spin axis (local y through the local origin) and the sensor "
                     f"comes within {closest:.3f} m of the axis")


def _closest_to_axis(xz: np.ndarray) -> float:
    """Smallest distance [m] from the origin of the polyline through the points ``xz`` (n, 2)."""
    a, b = xz[:-1], xz[1:]
    d = b - a
    length2 = np.einsum("ij,ij->i", d, d)
    u = np.clip(-np.einsum("ij,ij->i", a, d) / np.where(length2 > 0.0, length2, 1.0), 0.0, 1.0)
    return float(np.hypot(*(a + u[:, None] * d).T).min())
