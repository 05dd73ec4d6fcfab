"""Unit quaternions (x, y, z, w) as SciPy's Rotation computes them, without importing SciPy.

Importing ``scipy.spatial`` costs about a second of the simulator's start-up on the GPU host (SciPy's
array-API layer brings NumPy submodules with it), for a handful of rotations: trajectory samples, the
boresight.
Each function here repeats, operation for operation, what ``scipy.spatial.transform.Rotation`` does for
NumPy arrays (its compiled backend, SciPy 1.17): the same roundings in the same order, the C library's
sin, cos and atan2 (through :mod:`math`; NumPy's own SIMD versions may differ in the last bit), so the
results are the same float64 bits and the products pinned by digest do not move. tests/test_rotation.py
holds every function to SciPy bit for bit.

Quaternions are float64 arrays (..., 4), vector part first; angles are in radians unless said otherwise.
A function that makes a rotation (``from_*``, :func:`multiply`) returns the quaternion SciPy stores.
"""
from __future__ import annotations

import math

import numpy as np

SMALL_ANGLE_RAD = 1e-3  # SciPy's switch to Taylor series for rotation vectors

_ORTHOGONAL_ATOL = 1e-12  # SciPy's test of a matrix's Gramian against the identity (np.isclose, rtol 1e-5)


def _libm(function, *args) -> np.ndarray:
    """``function`` of :mod:`math` (the C library's, which SciPy's compiled code calls) applied elementwise."""
    return np.asarray(np.frompyfunc(function, len(args), 1)(*args), dtype=np.float64)


def _norm3(v: np.ndarray) -> np.ndarray:
    """Euclidean norm of the last axis of v (..., 3), summed left to right; shape (...)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def normalize(quat) -> np.ndarray:
    """quat (..., 4) divided by its norm (``Rotation.from_quat``); ValueError for a zero quaternion."""
    quat = np.asarray(quat, dtype=np.float64)
    norm = np.sqrt(quat[..., 0] * quat[..., 0] + quat[..., 1] * quat[..., 1] + quat[..., 2] * quat[..., 2]
                   + quat[..., 3] * quat[..., 3])
    if np.any(norm == 0.0):
        raise ValueError("a quaternion of zero norm is no rotation")
    return quat / norm[..., None]


def from_matrix(matrix) -> np.ndarray:
    """Quaternion (..., 4) of rotation matrices (..., 3, 3) (``Rotation.from_matrix``).

    SciPy raises for a non-positive determinant, and orthogonalises by SVD a matrix whose Gramian is not
    within 1e-12 of the identity; this raises a ValueError for both (rotation matrices built from angles,
    such as :func:`trajectories.attitude.rotation_body_to_enu`'s, are orthogonal to a few ulp).
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    m = matrix.reshape(-1, 3, 3)
    if np.any(np.linalg.det(m) <= 0.0):
        raise ValueError("a matrix with a non-positive determinant is no rotation")
    if not np.all(np.isclose(m @ np.swapaxes(m, -1, -2), np.eye(3), atol=_ORTHOGONAL_ATOL)):
        raise ValueError(f"a matrix whose M·Mᵀ differs from the identity by more than {_ORTHOGONAL_ATOL:g} "
                         "is no rotation (SciPy would orthogonalise it)")
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    choice = np.argmax(np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], trace], axis=-1), axis=-1)
    quat = np.empty((m.shape[0], 4))
    for i in range(3):  # the largest diagonal element: its axis' component is the best conditioned
        j, k = (i + 1) % 3, (i + 2) % 3
        rows = choice == i
        c = m[rows]
        quat[rows, i] = 1 - trace[rows] + 2 * c[:, i, i]
        quat[rows, j] = c[:, j, i] + c[:, i, j]
        quat[rows, k] = c[:, k, i] + c[:, i, k]
        quat[rows, 3] = c[:, k, j] - c[:, j, k]
    rows = choice == 3  # the trace: w is the best conditioned
    c = m[rows]
    quat[rows] = np.stack([c[:, 2, 1] - c[:, 1, 2], c[:, 0, 2] - c[:, 2, 0], c[:, 1, 0] - c[:, 0, 1],
                           1 + trace[rows]], axis=-1)
    return normalize(quat).reshape(matrix.shape[:-2] + (4,))


def from_rotvec(rotvec) -> np.ndarray:
    """Quaternion (..., 4) of rotation vectors (..., 3) [rad] (``Rotation.from_rotvec``)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = _norm3(rotvec)
    angle2 = angle * angle
    large = ~(angle <= SMALL_ANGLE_RAD)
    divisor = np.where(large, angle, 1.0)  # no 0/0 where the Taylor series is taken
    scale = np.where(large, _libm(math.sin, divisor / 2) / divisor,
                     0.5 - angle2 / 48 + angle2 * angle2 / 3840)  # sin(θ/2)/θ
    return np.concatenate([scale[..., None] * rotvec, _libm(math.cos, angle / 2)[..., None]], axis=-1)


def from_euler_zyx(angles, degrees: bool = False) -> np.ndarray:
    """Quaternion (..., 4) of intrinsic Z-Y'-X'' angles (..., 3): yaw, then pitch, then roll
    (``Rotation.from_euler("ZYX", angles, degrees)``); [rad], or [deg] with ``degrees``."""
    angles = np.asarray(angles, dtype=np.float64)
    if degrees:
        angles = np.deg2rad(angles)
    quat = _elementary(2, angles[..., 0])
    quat = _compose(quat, _elementary(1, angles[..., 1]))
    return _compose(quat, _elementary(0, angles[..., 2]))


def _elementary(axis: int, angle: np.ndarray) -> np.ndarray:
    """Quaternion (..., 4) of rotations by angle (...) [rad] about coordinate axis 0, 1 or 2."""
    quat = np.zeros(angle.shape + (4,))
    quat[..., 3] = _libm(math.cos, angle / 2)
    quat[..., axis] = _libm(math.sin, angle / 2)
    return quat


def _compose(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p·q (..., 4) of quaternions p, q (broadcast together), not normalised."""
    px, py, pz, pw = (p[..., n] for n in range(4))
    qx, qy, qz, qw = (q[..., n] for n in range(4))
    return np.stack([pw * qx + qw * px + (py * qz - pz * qy),
                     pw * qy + qw * py + (pz * qx - px * qz),
                     pw * qz + qw * pz + (px * qy - py * qx),
                     pw * qw - px * qx - py * qy - pz * qz], axis=-1)


def multiply(p, q) -> np.ndarray:
    """Quaternion (..., 4) of the rotation p then q in p's frame, R_p·R_q, for p, q (..., 4) broadcast
    together (``Rotation * Rotation``: the product, normalised)."""
    return normalize(_compose(np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)))


def inverse(quat) -> np.ndarray:
    """Quaternion (..., 4) of the inverse rotations (``Rotation.inv``): the vector part negated."""
    return np.asarray(quat, dtype=np.float64) * np.array([-1.0, -1.0, -1.0, 1.0])


def as_matrix(quat) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (``Rotation.as_matrix``)."""
    quat = np.asarray(quat, dtype=np.float64)
    x, y, z, w = (quat[..., n] for n in range(4))
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    rows = [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
            2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
            2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]
    return np.stack(rows, axis=-1).reshape(quat.shape[:-1] + (3, 3))


def as_rotvec(quat) -> np.ndarray:
    """Rotation vectors (..., 3) [rad], angle in [0, π], of unit quaternions (..., 4) (``Rotation.as_rotvec``)."""
    quat = _canonical(np.asarray(quat, dtype=np.float64))
    angle = 2 * _libm(math.atan2, _norm3(quat[..., :3]), quat[..., 3])
    angle2 = angle * angle
    large = ~(angle <= SMALL_ANGLE_RAD)
    divisor = _libm(math.sin, np.where(large, angle, 2.0) / 2)  # no 0/0 where the Taylor series is taken
    scale = np.where(large, angle / divisor, 2 + angle2 / 12 + 7 * angle2 * angle2 / 2880)  # θ/sin(θ/2)
    return scale[..., None] * quat[..., :3]


def _canonical(quat: np.ndarray) -> np.ndarray:
    """quat (..., 4) with SciPy's canonical sign: w ≥ 0, and where w = 0 the first non-zero of x, y, z > 0."""
    x, y, z, w = (quat[..., n] for n in range(4))
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    return np.where(flip[..., None], -quat, quat)


def rotate(quat, vectors) -> np.ndarray:
    """Vectors (n, 3) turned by n rotations (n, 4) (``Rotation.apply``): vectors (3,) is one vector for all
    of them, (n, 3) one each."""
    matrix = as_matrix(quat)
    vectors = np.atleast_2d(np.asarray(vectors, dtype=np.float64))
    if matrix.shape[0] == 1 and vectors.shape[0] == 1:  # SciPy's matrix-vector product for one of each
        return np.matmul(matrix, vectors[0])
    return np.einsum("ijk,ik->ij", matrix, vectors)
