"""trajectories.rotation against SciPy's Rotation, bit for bit (the products pinned by digest depend on it),
and the start-up import path without SciPy or laspy."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trajectories import rotation

ROOT = Path(__file__).resolve().parent.parent
N = 4000


def assert_same_bits(got, expected):
    """Same shape, dtype and float64 bits (−0.0 ≠ 0.0)."""
    got, expected = np.asarray(got), np.asarray(expected)
    assert got.shape == expected.shape and got.dtype == expected.dtype == np.float64
    differ = got.view(np.uint64) != expected.view(np.uint64)
    assert not differ.any(), f"{differ.sum()} of {differ.size} values differ, first at {np.argwhere(differ)[0]}"


def random_quaternions(rng, n=N):
    """n unit quaternions (n, 4) spread over the sphere, with either sign of w."""
    return Rotation.random(n, rng=rng).as_quat() * rng.choice([-1.0, 1.0], size=(n, 1))


def edge_quaternions():
    """Unit quaternions at the ties: w = 0 (angle π) with each sign pattern of x, y, z, signed zeros, identity."""
    h = np.sqrt(0.5)
    rows = [[0, 0, 0, 1], [0, 0, 0, -1], [-0.0, 0.0, -0.0, 1], [-0.0, -0.0, 0.0, -1]]
    for w in (0.0, -0.0):
        for x, y, z in ((1, 0, 0), (-1, 0, 0), (0, -1, 0), (0, 0, -1), (-0.0, 0, -1), (0, -0.0, 1), (-h, h, 0),
                        (h, -h, 0), (0, -h, -h), (-0.6, -0.8, 0), (0.0, -0.0, -1.0)):
            rows.append([x, y, z, w])
    return np.array(rows, dtype=np.float64)


def small_angle_rotvecs(rng, n=N):
    """Rotation vectors (n, 3) whose angles straddle SciPy's Taylor-series switch at 1e-3 rad, down to 0."""
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    angle = np.concatenate([rng.uniform(0.0, 2e-3, n // 2), np.exp(rng.uniform(-40.0, -6.0, n - n // 2))])
    angle[:4] = (0.0, 1e-3, np.nextafter(1e-3, 0.0), np.nextafter(1e-3, 1.0))
    return direction * angle[:, None]


def test_normalize_is_from_quat():
    rng = np.random.default_rng(1)
    quat = rng.normal(size=(N, 4)) * np.exp(rng.uniform(-5.0, 5.0, (N, 1)))
    assert_same_bits(rotation.normalize(quat), Rotation.from_quat(quat).as_quat())
    assert_same_bits(rotation.normalize(quat[7]), Rotation.from_quat(quat[7]).as_quat())
    with pytest.raises(ValueError, match="zero norm"):
        rotation.normalize(np.zeros(4))


def test_from_matrix_takes_every_branch_as_scipy_does():
    rng = np.random.default_rng(2)
    quat = np.concatenate([random_quaternions(rng), edge_quaternions()])
    matrix = Rotation.from_quat(quat).as_matrix()
    trace = np.trace(matrix, axis1=1, axis2=2)
    choice = np.argmax(np.stack([matrix[:, 0, 0], matrix[:, 1, 1], matrix[:, 2, 2], trace], axis=1), axis=1)
    assert set(choice.tolist()) == {0, 1, 2, 3}
    assert_same_bits(rotation.from_matrix(matrix), Rotation.from_matrix(matrix).as_quat())
    assert_same_bits(rotation.from_matrix(matrix[5]), Rotation.from_matrix(matrix[5]).as_quat())
    grid = matrix[:24].reshape(2, 3, 4, 3, 3)
    assert_same_bits(rotation.from_matrix(grid), Rotation.from_matrix(matrix[:24]).as_quat().reshape(2, 3, 4, 4))


def test_from_matrix_of_attitudes_is_scipys():
    from trajectories import rotation_body_to_enu

    rng = np.random.default_rng(3)
    rpy = rng.uniform(-np.pi, np.pi, (3, N))
    rpy[1] /= 2.0
    matrix = rotation_body_to_enu(*rpy)
    assert_same_bits(rotation.from_matrix(matrix), Rotation.from_matrix(matrix).as_quat())


def test_from_matrix_refuses_what_scipy_would_orthogonalise_or_refuse():
    turn = Rotation.from_euler("ZYX", [0.3, -0.2, 0.1]).as_matrix()
    with pytest.raises(ValueError, match="determinant"):
        rotation.from_matrix(turn * [1.0, 1.0, -1.0])
    sheared = turn @ np.array([[1.0, 2e-12, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="identity"):
        rotation.from_matrix(np.stack([turn, sheared]))
    nearly = turn @ np.array([[1.0, 2e-13, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # within SciPy's 1e-12
    assert_same_bits(rotation.from_matrix(nearly), Rotation.from_matrix(nearly).as_quat())


def test_from_rotvec_is_scipys_on_both_sides_of_the_taylor_switch():
    rng = np.random.default_rng(4)
    large = rng.normal(size=(N, 3)) * np.exp(rng.uniform(-7.0, 1.5, (N, 1)))
    for rotvec in (large, small_angle_rotvecs(rng), np.zeros((3, 3))):
        assert_same_bits(rotation.from_rotvec(rotvec), Rotation.from_rotvec(rotvec).as_quat())
    assert_same_bits(rotation.from_rotvec(large[0]), Rotation.from_rotvec(large[0]).as_quat())
    assert_same_bits(rotation.from_rotvec(large[:12].reshape(3, 4, 3)),
                     Rotation.from_rotvec(large[:12]).as_quat().reshape(3, 4, 4))


def test_from_euler_zyx_is_scipys_in_radians_and_degrees():
    rng = np.random.default_rng(5)
    radians = rng.uniform(-4.0, 4.0, (N, 3)) * np.exp(rng.uniform(-12.0, 0.0, (N, 1)))
    assert_same_bits(rotation.from_euler_zyx(radians), Rotation.from_euler("ZYX", radians).as_quat())
    degrees = rng.uniform(-360.0, 360.0, (N, 3))
    degrees[:3] = ([0.0, 0.0, 0.0], [90.0, -90.0, 180.0], [0.005, 12.5, -7.25])
    assert_same_bits(rotation.from_euler_zyx(degrees, degrees=True),
                     Rotation.from_euler("ZYX", degrees, degrees=True).as_quat())
    # one rotation, as the tracer's boresight (roll, pitch, yaw in the config, reversed) and the pose error's mount
    for boresight_deg in ([0.0, 0.0, 0.0], [1.5, -0.25, 90.0], [-3.0, 20.0, -0.125]):
        assert_same_bits(rotation.from_euler_zyx(boresight_deg[::-1], degrees=True),
                         Rotation.from_euler("ZYX", boresight_deg[::-1], degrees=True).as_quat())
    yaw_pitch_roll = [7e-5, -2e-5, 4.8e-5]
    assert_same_bits(rotation.as_matrix(rotation.from_euler_zyx(yaw_pitch_roll)),
                     Rotation.from_euler("ZYX", yaw_pitch_roll).as_matrix())


def test_multiply_and_inverse_are_scipys():
    rng = np.random.default_rng(6)
    P, Q = Rotation.from_quat(random_quaternions(rng)), Rotation.from_quat(random_quaternions(rng))
    p, q = P.as_quat(), Q.as_quat()
    assert_same_bits(rotation.multiply(p, q), (P * Q).as_quat())
    assert_same_bits(rotation.inverse(p), P.inv().as_quat())
    assert_same_bits(rotation.multiply(rotation.inverse(p), q), (P.inv() * Q).as_quat())
    one = Rotation.from_quat(q[0])  # many times one, as the trajectory's samples times the boresight
    assert_same_bits(rotation.multiply(p, q[0]), (P * one).as_quat())
    assert_same_bits(rotation.multiply(q[0], p[1]), (one * Rotation.from_quat(p[1])).as_quat())
    edges = edge_quaternions()
    assert_same_bits(rotation.inverse(edges), Rotation.from_quat(edges).inv().as_quat())


def test_as_matrix_is_scipys():
    rng = np.random.default_rng(7)
    raw = np.concatenate([random_quaternions(rng), edge_quaternions()])
    assert_same_bits(rotation.as_matrix(rotation.normalize(raw)), Rotation.from_quat(raw).as_matrix())
    assert_same_bits(rotation.as_matrix(rotation.normalize(raw[3])), Rotation.from_quat(raw[3]).as_matrix())


def test_as_rotvec_is_scipys_for_small_angles_near_pi_and_at_the_sign_ties():
    rng = np.random.default_rng(8)
    turns = Rotation.from_rotvec(np.concatenate([small_angle_rotvecs(rng), small_angle_rotvecs(rng)]))
    near_pi = rng.normal(size=(N, 3))
    near_pi *= (np.pi - np.exp(rng.uniform(-30.0, -1.0, (N, 1)))) / np.linalg.norm(near_pi, axis=1, keepdims=True)
    for raw in (random_quaternions(rng), turns.as_quat(), Rotation.from_rotvec(near_pi).as_quat(),
                -turns.as_quat(), edge_quaternions()):
        assert_same_bits(rotation.as_rotvec(rotation.normalize(raw)), Rotation.from_quat(raw).as_rotvec())
    assert_same_bits(rotation.as_rotvec(rotation.normalize(raw[2])), Rotation.from_quat(raw[2]).as_rotvec())


def test_rotate_is_scipys_apply():
    rng = np.random.default_rng(9)
    turns = Rotation.from_quat(random_quaternions(rng))
    quat = turns.as_quat()
    vectors = rng.normal(size=(N, 3)) * 100.0
    assert_same_bits(rotation.rotate(quat, vectors), turns.apply(vectors))
    for vector in ([0.0, 0.0, 1.0], vectors[0]):  # one vector for every rotation, as the beam cones' axes
        assert_same_bits(rotation.rotate(quat, vector), turns.apply(vector))
    one = Rotation.from_quat(quat[:1])  # one rotation (SciPy's matrix-vector product)
    assert_same_bits(rotation.rotate(quat[:1], vectors[0]), one.apply(vectors[0]))
    assert_same_bits(rotation.rotate(quat[:1], vectors[:1]), one.apply(vectors[:1]))


@pytest.mark.parametrize("module", ["trajectories.trajectory", "flightsim.engine.tracer", "flightsim.cli",
                                    "flightsim.engine.run"])
def test_start_up_imports_neither_scipy_nor_laspy(module):
    """What a run loads before its first ray (the command line registers every part): no SciPy (about a second on the
    GPU host, with the NumPy submodules its array-API layer loads), no laspy (its COPC reader's HTTP stack); LAS
    tiles import laspy in their writer threads."""
    code = f"import sys, {module}; print(sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'laspy')))"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
