"""Aircraft attitude: roll/pitch/heading ↔ rotation matrices ↔ quaternions (SPEC §2).

Conventions (float64, radians, vectorised over leading axes):

- Body frame: x forward, y right (starboard wing), z down.
- R_body→NED = Rz(heading)·Ry(pitch)·Rx(roll) with right-handed elementary rotations; heading is
  clockwise from grid north, positive pitch raises the nose, positive roll lowers the right wing.
- ENU = M·NED with M = [[0,1,0],[1,0,0],[0,0,-1]], so R_body→ENU = M·R_body→NED.
- Quaternions are (x, y, z, w), Warp's layout, and describe the same rotation as the matrix.
"""
from __future__ import annotations

import numpy as np

from . import rotation as quaternions

NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
TWO_PI = 2.0 * np.pi


def rotation_body_to_enu(roll, pitch, heading) -> np.ndarray:
    """R_body→ENU for roll, pitch, heading [rad] (broadcast together); shape (..., 3, 3)."""
    r, p, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (roll, pitch, heading)))
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    ch, sh = np.cos(h), np.sin(h)
    ned = np.empty(r.shape + (3, 3))
    ned[..., 0, 0] = ch * cp
    ned[..., 0, 1] = ch * sp * sr - sh * cr
    ned[..., 0, 2] = ch * sp * cr + sh * sr
    ned[..., 1, 0] = sh * cp
    ned[..., 1, 1] = sh * sp * sr + ch * cr
    ned[..., 1, 2] = sh * sp * cr - ch * sr
    ned[..., 2, 0] = -sp
    ned[..., 2, 1] = cp * sr
    ned[..., 2, 2] = cp * cr
    return NED_TO_ENU @ ned


def euler_from_rotation(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll, pitch [rad] in [−π/2, π/2], heading [rad] in [0, 2π) of R_body→ENU (..., 3, 3).

    Inverse of :func:`rotation_body_to_enu` away from pitch = ±90° (gimbal lock, where roll and
    heading are not separable).
    """
    ned = NED_TO_ENU @ np.asarray(rotation, dtype=np.float64)
    roll = np.arctan2(ned[..., 2, 1], ned[..., 2, 2])
    pitch = np.arctan2(-ned[..., 2, 0], np.hypot(ned[..., 0, 0], ned[..., 1, 0]))
    heading = np.mod(np.arctan2(ned[..., 1, 0], ned[..., 0, 0]), TWO_PI)
    heading = np.where(heading >= TWO_PI, 0.0, heading)
    return roll, pitch, heading


def quaternion_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of rotation matrices (..., 3, 3); shape (..., 4).

    SciPy's numbers (:func:`trajectories.rotation.from_matrix`); a matrix that is not a rotation to within
    1e-12 (as :func:`rotation_body_to_enu`'s always are) raises ValueError.
    """
    return quaternions.from_matrix(rotation)


def make_continuous(quat: np.ndarray) -> np.ndarray:
    """Copy of a sequence of quaternions (n, 4), or of several of equal length (..., n, 4), with signs flipped so
    that consecutive ones have a non-negative dot product (q and −q are the same rotation; interpolation between
    sign-continuous neighbours takes the short way round)."""
    quat = np.array(quat, dtype=np.float64)
    if quat.shape[-2] < 2:
        return quat
    dots = np.einsum("ij,ij->i", quat[..., 1:, :].reshape(-1, 4), quat[..., :-1, :].reshape(-1, 4))
    step = np.where(dots < 0.0, -1.0, 1.0).reshape(quat.shape[:-2] + (-1,))
    signs = np.concatenate((np.ones(quat.shape[:-2] + (1,)), np.cumprod(step, axis=-1)), axis=-1)
    return quat * signs[..., None]
