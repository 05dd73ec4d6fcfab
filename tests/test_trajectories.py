"""Tests of the trajectories package against independent geometry and exact rational arithmetic."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trajectories import (
    FlightLine,
    PulseTiming,
    Trajectory,
    TrajectoryError,
    euler_from_rotation,
    make_continuous,
    plan_parallel_lines,
    quaternion_from_matrix,
    rotation_body_to_enu,
)

DEG = math.pi / 180.0
EAST, NORTH, UP = np.eye(3)


def angle_difference(a, b):
    """Signed difference a − b of angles [rad], wrapped to [−π, π)."""
    return np.mod(np.asarray(a) - np.asarray(b) + math.pi, 2.0 * math.pi) - math.pi


def rotation_angle(r1, r2):
    """Angle [rad] of the rotation taking r1 to r2 (3×3 rotation matrices)."""
    cos = (np.trace(r1.T @ r2) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, cos)))


def body_axes_enu(roll, pitch, heading):
    """Body x, y, z in ENU, built geometrically: yaw, then pitch the nose up, then roll about the nose."""
    forward = np.array([math.sin(heading) * math.cos(pitch), math.cos(heading) * math.cos(pitch), math.sin(pitch)])
    level_right = np.array([math.cos(heading), -math.sin(heading), 0.0])
    down = np.cross(forward, level_right)  # body z before roll: x × y
    right = math.cos(roll) * level_right + math.sin(roll) * down
    belly = -math.sin(roll) * level_right + math.cos(roll) * down
    return forward, right, belly


def matrix_of_quaternion(q):
    """Rotation matrix of a unit quaternion (x, y, z, w), textbook formula."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp(q0, q1, u):
    """Textbook quaternion slerp along the shorter arc."""
    if np.dot(q0, q1) < 0:
        q1 = -q1
    omega = math.acos(min(1.0, np.dot(q0, q1)))
    if omega < 1e-12:
        return q0
    return (math.sin((1 - u) * omega) * q0 + math.sin(u * omega) * q1) / math.sin(omega)


angles = st.floats(-math.pi, math.pi, allow_nan=False)
tilts = st.floats(-80 * DEG, 80 * DEG, allow_nan=False)


# ---------------------------------------------------------------- attitude


def test_level_heading_north_axes():
    rot = rotation_body_to_enu(0.0, 0.0, 0.0)
    np.testing.assert_allclose(rot @ [1, 0, 0], NORTH, atol=1e-15)
    np.testing.assert_allclose(rot @ [0, 1, 0], EAST, atol=1e-15)
    np.testing.assert_allclose(rot @ [0, 0, 1], -UP, atol=1e-15)


def test_heading_90_flies_east_with_right_wing_south():
    rot = rotation_body_to_enu(0.0, 0.0, 90 * DEG)
    np.testing.assert_allclose(rot @ [1, 0, 0], EAST, atol=1e-15)
    np.testing.assert_allclose(rot @ [0, 1, 0], -NORTH, atol=1e-15)
    np.testing.assert_allclose(rot @ [0, 0, 1], -UP, atol=1e-15)


def test_positive_roll_lowers_right_wing_and_positive_pitch_raises_nose():
    right = rotation_body_to_enu(10 * DEG, 0.0, 0.0) @ [0, 1, 0]
    assert right[2] == pytest.approx(-math.sin(10 * DEG))
    nose = rotation_body_to_enu(0.0, 10 * DEG, 0.0) @ [1, 0, 0]
    assert nose[2] == pytest.approx(math.sin(10 * DEG))


@settings(max_examples=200, deadline=None)
@given(tilts, tilts, angles)
def test_rotation_matches_geometric_construction(roll, pitch, heading):
    rot = rotation_body_to_enu(roll, pitch, heading)
    forward, right, belly = body_axes_enu(roll, pitch, heading)
    np.testing.assert_allclose(rot[:, 0], forward, atol=1e-14)
    np.testing.assert_allclose(rot[:, 1], right, atol=1e-14)
    np.testing.assert_allclose(rot[:, 2], belly, atol=1e-14)


def test_rotation_is_orthonormal_with_det_plus_one_and_broadcasts():
    rng = np.random.default_rng(1)
    roll, pitch, heading = rng.uniform(-math.pi, math.pi, (3, 50))
    rot = rotation_body_to_enu(roll, pitch, heading)
    assert rot.shape == (50, 3, 3)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-14)
    assert rotation_body_to_enu(0.1, 0.2, np.zeros((4, 2))).shape == (4, 2, 3, 3)


@settings(max_examples=200, deadline=None)
@given(tilts, tilts, st.floats(-4 * math.pi, 4 * math.pi, allow_nan=False))
def test_euler_round_trip(roll, pitch, heading):
    r, p, h = euler_from_rotation(rotation_body_to_enu(roll, pitch, heading))
    assert abs(angle_difference(r, roll)) < 1e-12
    assert abs(p - pitch) < 1e-12
    assert abs(angle_difference(h, heading)) < 1e-12
    assert 0.0 <= h < 2 * math.pi


def test_euler_heading_in_zero_to_two_pi():
    _, _, h = euler_from_rotation(rotation_body_to_enu(0.0, 0.0, [-1e-300, -90 * DEG, 270 * DEG, 0.0]))
    np.testing.assert_allclose(h, [0.0, 270 * DEG, 270 * DEG, 0.0], atol=1e-15)
    assert np.all((h >= 0) & (h < 2 * math.pi))


def test_quaternion_rotates_vectors_like_matrix():
    rng = np.random.default_rng(2)
    roll, pitch, heading = rng.uniform(-math.pi, math.pi, (3, 40))
    rot = rotation_body_to_enu(roll, pitch, heading)
    quat = quaternion_from_matrix(rot)
    assert quat.shape == (40, 4)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-15)
    v = rng.normal(size=3)
    for q, r in zip(quat, rot):
        u, w = q[:3], q[3]  # (x, y, z, w): vector part first
        rotated = v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))
        np.testing.assert_allclose(rotated, r @ v, atol=1e-13)


def test_make_continuous_flips_signs_only():
    rng = np.random.default_rng(3)
    smooth = quaternion_from_matrix(rotation_body_to_enu(0.0, 0.0, np.linspace(0, 6 * math.pi, 200)))
    signs = rng.choice([-1.0, 1.0], size=200)
    fixed = make_continuous(smooth * signs[:, None])
    assert np.all(np.einsum("ij,ij->i", fixed[1:], fixed[:-1]) >= 0.0)
    given_ = smooth * signs[:, None]
    assert np.all(np.all(fixed == given_, axis=1) | np.all(fixed == -given_, axis=1))
    np.testing.assert_array_equal(fixed[0], smooth[0] * signs[0])


# ---------------------------------------------------------------- trajectory


def line_trajectory(headings_deg, t0=450_000_000.0, dt=1.0):
    n = len(headings_deg)
    times = t0 + dt * np.arange(n)
    position = np.column_stack([500_000.0 + 10.0 * np.arange(n), 3_400_000.0 + np.zeros(n), 1000.0 + np.zeros(n)])
    attitude = np.column_stack([np.zeros(n), np.zeros(n), np.radians(headings_deg)])
    return Trajectory(times, position, attitude, line_id=7)


def test_trajectory_properties_and_read_only_copies():
    times = np.array([10.0, 11.0, 13.0])
    traj = Trajectory(times, np.zeros((3, 3)), np.zeros((3, 3)))
    times[0] = -5.0
    assert traj.start_time == 10.0 and traj.end_time == 13.0 and traj.duration == 3.0
    assert traj.line_id == 1
    assert traj.gps_time.dtype == np.float64
    with pytest.raises(ValueError):
        traj.position[0, 0] = 1.0


@pytest.mark.parametrize(
    "times, field, row",
    [
        ([0.0, 2.0, 1.0, 3.0], "trajectory.gps_time", "row 2"),
        ([0.0, 1.0, 1.0, 3.0], "trajectory.gps_time", "row 2"),
        ([0.0, 1.0, np.nan, 3.0], "trajectory.gps_time", "row 2"),
    ],
)
def test_trajectory_rejects_bad_times(times, field, row):
    with pytest.raises(TrajectoryError) as info:
        Trajectory(times, np.zeros((4, 3)), np.zeros((4, 3)))
    assert info.value.field == field
    assert row in str(info.value)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(gps_time=[0.0]), "trajectory.gps_time"),
        (dict(gps_time=[[0.0, 1.0]]), "trajectory.gps_time"),
        (dict(gps_time=["a", "b"]), "trajectory.gps_time"),
        (dict(position=np.zeros((3, 3))), "trajectory.position"),
        (dict(position=[[0, 0, 0], [0, np.inf, 0]]), "trajectory.position"),
        (dict(attitude=[[0, 0, 0], [0, 0, np.nan]]), "trajectory.attitude"),
        (dict(line_id=70000), "trajectory.line_id"),
        (dict(line_id=1.5), "trajectory.line_id"),
    ],
)
def test_trajectory_rejects_bad_fields(kwargs, field):
    args = dict(gps_time=[0.0, 1.0], position=np.zeros((2, 3)), attitude=np.zeros((2, 3)))
    args.update(kwargs)
    with pytest.raises(TrajectoryError) as info:
        Trajectory(**args)
    assert info.value.field == field
    assert str(info.value).startswith(f"invalid {field} = ")


def test_interpolate_hits_samples_and_is_linear_in_position():
    traj = line_trajectory([10.0, 20.0, 40.0])
    pos, rot = traj.interpolate(traj.gps_time)
    np.testing.assert_array_equal(pos, traj.position)
    expected = rotation_body_to_enu(0.0, 0.0, np.radians([10.0, 20.0, 40.0]))
    np.testing.assert_allclose(rot, expected, atol=1e-14)
    pos, rot = traj.interpolate(traj.start_time + 1.25)
    assert pos.shape == (3,) and rot.shape == (3, 3)
    np.testing.assert_allclose(pos, [500_012.5, 3_400_000.0, 1000.0], rtol=0, atol=1e-9)
    _, _, heading = euler_from_rotation(rot)
    assert heading == pytest.approx(25.0 * DEG, abs=1e-12)
    pos, rot = traj.interpolate(np.array([]))
    assert pos.shape == (0, 3) and rot.shape == (0, 3, 3)


def test_interpolate_rejects_times_outside():
    traj = line_trajectory([0.0, 0.0])
    for bad in (traj.start_time - 1e-3, traj.end_time + 1e-3, math.nan):
        with pytest.raises(TrajectoryError) as info:
            traj.interpolate([traj.start_time, bad])
        assert info.value.field == "trajectory.time"


def test_slerp_across_heading_wrap_goes_through_180():
    traj = line_trajectory([179.0, -179.0])
    _, rot = traj.interpolate(traj.start_time + 0.5)
    _, _, heading = euler_from_rotation(rot)
    assert heading == pytest.approx(math.pi, abs=1e-12)
    np.testing.assert_allclose(rot @ [1, 0, 0], -NORTH, atol=1e-12)  # nose due south, not north
    traj_360 = line_trajectory([359.0, 1.0])
    _, _, heading = euler_from_rotation(traj_360.interpolate(traj_360.start_time + 0.25)[1])
    assert angle_difference(heading, -0.5 * DEG) == pytest.approx(0.0, abs=1e-12)


def test_slerp_steps_are_uniform_across_wrap():
    traj = line_trajectory([179.0, -179.0])
    _, rot = traj.interpolate(traj.start_time + np.linspace(0.0, 1.0, 11))
    steps = [rotation_angle(rot[j], rot[j + 1]) for j in range(10)]
    np.testing.assert_allclose(steps, 0.2 * DEG, rtol=1e-6)


def test_slerp_matches_textbook_formula_for_general_attitudes():
    attitude = np.radians([[5.0, -3.0, 350.0], [-10.0, 4.0, 20.0], [2.0, 1.0, 100.0]])
    traj = Trajectory([100.0, 101.0, 103.0], np.zeros((3, 3)), attitude)
    q = quaternion_from_matrix(rotation_body_to_enu(*attitude.T))
    for t, i, u in [(100.3, 0, 0.3), (100.9, 0, 0.9), (102.5, 1, 0.75)]:
        expected = matrix_of_quaternion(slerp(q[i], q[i + 1], u))
        np.testing.assert_allclose(traj.interpolate(t)[1], expected, atol=1e-13)


def test_quaternions_are_sign_continuous_and_match_attitude():
    traj = line_trajectory(np.linspace(0.0, 1080.0, 73))  # three full turns, 15° apart
    quat = traj.quaternions()
    assert quat.shape == (73, 4)
    assert np.all(np.einsum("ij,ij->i", quat[1:], quat[:-1]) > 0.0)
    expected = rotation_body_to_enu(*traj.attitude.T)
    for q, r in zip(quat, expected):
        np.testing.assert_allclose(matrix_of_quaternion(q), r, atol=1e-14)


# ---------------------------------------------------------------- CSV files


def nasty_trajectory():
    rng = np.random.default_rng(4)
    n = 50
    times = 450_000_000.123456789 + np.cumsum(rng.uniform(0.001, 0.2, n))
    position = np.column_stack(
        [
            rng.uniform(4e5, 6e5, n),
            rng.uniform(3.3e6, 3.5e6, n),
            rng.uniform(-50.0, 5000.0, n),
        ]
    )
    attitude = np.column_stack(
        [rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-math.pi, math.pi, n)]
    )
    return Trajectory(times, position, attitude, line_id=3)


def test_csv_round_trip_is_bit_exact(tmp_path):
    traj = nasty_trajectory()
    path = tmp_path / "traj.csv"
    traj.write_csv(path)
    back = Trajectory.read_csv(path, line_id=3)
    np.testing.assert_array_equal(back.gps_time, traj.gps_time)
    np.testing.assert_array_equal(back.position, traj.position)
    np.testing.assert_allclose(back.attitude, traj.attitude, rtol=0, atol=4e-16 * math.pi)
    assert back.line_id == 3
    assert [p.name for p in tmp_path.iterdir()] == ["traj.csv"]  # no temporary left behind


def test_csv_has_header_and_degrees(tmp_path):
    traj = Trajectory([1.5, 2.5], [[1, 2, 3], [4, 5, 6]], [[0.0, 0.0, math.pi / 2], [math.pi / 6, 0.0, math.pi]])
    path = tmp_path / "t.csv"
    traj.write_csv(path)
    lines = path.read_text().splitlines()
    assert lines[0] == "gps_time,easting,northing,height,roll,pitch,heading"
    row = [float(v) for v in lines[2].split(",")]
    assert row[:4] == [2.5, 4.0, 5.0, 6.0]
    assert row[4] == pytest.approx(30.0, abs=1e-12) and row[6] == pytest.approx(180.0, abs=1e-12)


def test_csv_columns_found_by_name(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(
        "heading,extra,gps_time,easting,northing,height,roll,pitch\n90,x,1,10,20,30,0,0\n\n180,y,2,11,21,31,0,0\n"
    )
    traj = Trajectory.read_csv(path)
    np.testing.assert_array_equal(traj.gps_time, [1.0, 2.0])
    np.testing.assert_array_equal(traj.position[1], [11.0, 21.0, 31.0])
    np.testing.assert_allclose(traj.attitude[:, 2], [math.pi / 2, math.pi])


HEADER = "gps_time,easting,northing,height,roll,pitch,heading\n"


@pytest.mark.parametrize(
    "text, field, fragment",
    [
        (HEADER + "1,0,0,0,0,0,0\n2,abc,0,0,0,0,0\n", "trajectory.easting", "line 3"),
        (HEADER + "1,0,0,0,0,0,0\n2,0,0,nan,0,0,0\n", "trajectory.height", "line 3"),
        (HEADER + "1,0,0,0,0,0,0\n2,0,0,0,0,0,inf\n", "trajectory.heading", "line 3"),
        (HEADER + "1,0,0,0,0,0,0\n3,0,0,0,0,0,0\n2,0,0,0,0,0,0\n", "trajectory.gps_time", "line 4"),
        (HEADER + "1,0,0,0,0,0,0\n1,0,0,0,0,0,0\n", "trajectory.gps_time", "line 3"),
        (HEADER + "1,0,0,0,0,0,0\n2,0,0,0,0,0\n", "trajectory.file", "line 3"),
        (HEADER.replace(",heading", "") + "1,0,0,0,0,0\n2,0,0,0,0,0\n", "trajectory.file", "missing: heading"),
        (HEADER + HEADER.replace("gps_time", "heading") + "1,0,0,0,0,0,0\n", "trajectory.gps_time", "line 2"),
        (HEADER + "1,0,0,0,0,0,0\n", "trajectory.file", "at least 2 data rows"),
        ("", "trajectory.file", "header"),
        (HEADER.strip() + ",heading\n1,0,0,0,0,0,0,0\n2,0,0,0,0,0,0,0\n", "trajectory.file", "repeated: heading"),
    ],
)
def test_csv_errors_name_the_field(tmp_path, text, field, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TrajectoryError) as info:
        Trajectory.read_csv(path)
    assert info.value.field == field
    assert fragment in str(info.value)


def test_csv_missing_unreadable_or_binary_file(tmp_path):
    for path in (tmp_path / "nope.csv", tmp_path):
        with pytest.raises(TrajectoryError) as info:
            Trajectory.read_csv(path)
        assert info.value.field == "trajectory.file"
    binary = tmp_path / "bin.csv"
    binary.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(TrajectoryError) as info:
        Trajectory.read_csv(binary)
    assert info.value.field == "trajectory.file"


def test_write_csv_to_missing_directory(tmp_path):
    with pytest.raises(TrajectoryError) as info:
        line_trajectory([0.0, 0.0]).write_csv(tmp_path / "no" / "t.csv")
    assert info.value.field == "trajectory.file"


def test_error_message_format_and_value_lengths():
    err = TrajectoryError("flight.length_m", "x" * 500, "a finite number > 0 [m]")
    assert (err.field, err.value, err.allowed) == ("flight.length_m", "x" * 500, "a finite number > 0 [m]")
    assert isinstance(err, ValueError)
    assert str(TrajectoryError("a.b", -1.0, "> 0")) == "invalid a.b = -1.0: expected > 0"
    assert str(err) == f"invalid flight.length_m = {'x' * 500!r}: expected a finite number > 0 [m]"  # a string whole
    head = str(TrajectoryError("flight.length_m", "x" * 5000, "> 0")).split(": expected")[0]
    assert len(head) <= len("invalid flight.length_m = ") + 1000  # … up to 1000 characters
    head = str(TrajectoryError("a.b", list(range(500)), "> 0")).split(": expected")[0]
    assert len(head) <= len("invalid a.b = ") + 80  # anything else at most 80


# ---------------------------------------------------------------- flight lines


def test_default_speed_is_200_kmh():
    line = FlightLine(0.0, 0.0, 0.0, 1000.0, 500.0)
    assert line.speed_mps * 3.6 == pytest.approx(200.0, rel=1e-15)
    assert line.duration_s == pytest.approx(18.0, rel=1e-15)
    assert line.end_gps_time == pytest.approx(450_000_018.0, abs=1e-7)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.0, 360.0, exclude_max=True),
    st.floats(10.0, 20_000.0),
    st.floats(20.0, 120.0),
    st.floats(-30.0, 3000.0),
)
def test_flight_line_geometry(heading_deg, length_m, speed_mps, ground):
    line = FlightLine(512_345.6, 3_412_345.6, heading_deg, length_m, 800.0, speed_mps=speed_mps, line_id=4)
    traj = line.trajectory(ground, sample_interval_s=0.5)
    h = math.radians(heading_deg)
    end = np.array([512_345.6 + length_m * math.sin(h), 3_412_345.6 + length_m * math.cos(h)])
    np.testing.assert_allclose(traj.position[-1, :2], end, rtol=0, atol=1e-5)
    np.testing.assert_allclose([line.end_easting, line.end_northing], end, rtol=0, atol=1e-6)
    np.testing.assert_allclose(traj.position[0, :2], [512_345.6, 3_412_345.6], rtol=0, atol=1e-9)
    assert traj.end_time == line.end_gps_time and traj.start_time == line.start_gps_time
    elapsed = traj.gps_time - traj.start_time
    np.testing.assert_allclose(np.diff(elapsed[:-1]), 0.5, atol=1e-6)
    assert 0.0 < elapsed[-1] - elapsed[-2] <= 0.5 + 1e-6
    travelled = np.hypot(*(traj.position[:, :2] - traj.position[0, :2]).T)
    np.testing.assert_allclose(travelled, speed_mps * elapsed, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(traj.position[:, 2], ground + 800.0)
    np.testing.assert_allclose(traj.attitude, np.tile([0.0, 0.0, h], (len(traj.gps_time), 1)), atol=1e-15)
    assert traj.line_id == 4


def test_trajectory_samples_count_and_exact_end():
    line = FlightLine(0.0, 0.0, 45.0, 100.0, 500.0, speed_mps=10.0, start_gps_time=1000.0)
    traj = line.trajectory(0.0, sample_interval_s=1.0)
    np.testing.assert_array_equal(traj.gps_time, 1000.0 + np.arange(11.0))
    line = FlightLine(0.0, 0.0, 45.0, 105.0, 500.0, speed_mps=10.0, start_gps_time=1000.0)
    np.testing.assert_array_equal(line.trajectory(0.0, 1.0).gps_time, 1000.0 + np.append(np.arange(11.0), 10.5))


def test_no_sample_squeezed_just_before_the_end():
    line = FlightLine(0.0, 0.0, 0.0, 100.0 + 1e-9, 500.0, speed_mps=10.0)  # 1e-10 s past a whole sample
    times = line.trajectory(0.0, sample_interval_s=1.0).gps_time
    assert len(times) == 11
    assert times[-1] - times[-2] == pytest.approx(1.0, abs=1e-6)


def test_centred_line_midpoint():
    line = FlightLine.centred(1000.0, 2000.0, 30.0, 600.0, 700.0, line_id=2)
    mid = [(line.start_easting + line.end_easting) / 2, (line.start_northing + line.end_northing) / 2]
    np.testing.assert_allclose(mid, [1000.0, 2000.0], atol=1e-9)
    assert line.start_easting == pytest.approx(1000.0 - 300.0 * math.sin(30 * DEG))
    assert line.line_id == 2 and line.heading_deg == 30.0


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(length_m=0.0), "flight.length_m"),
        (dict(length_m=math.inf), "flight.length_m"),
        (dict(altitude_m=-1.0), "flight.altitude_m"),
        (dict(altitude_m=math.nan), "flight.altitude_m"),
        (dict(speed_mps=0.0), "flight.speed_kmh"),
        (dict(speed_mps="fast"), "flight.speed_kmh"),
        (dict(roll_deg=30.0), "flight.roll_deg"),
        (dict(pitch_deg=-45.0), "flight.pitch_deg"),
        (dict(heading_deg=math.nan), "flight.heading_deg"),
        (dict(start_easting=math.inf), "flight.start_easting"),
        (dict(line_id=-1), "flight.line_id"),
        (dict(length_m=-5.0, field_prefix="lines[2]"), "lines[2].length_m"),
    ],
)
def test_flight_line_validation(kwargs, field):
    args = dict(start_easting=0.0, start_northing=0.0, heading_deg=0.0, length_m=1000.0, altitude_m=500.0)
    args.update(kwargs)
    with pytest.raises(TrajectoryError) as info:
        FlightLine(**args)
    assert info.value.field == field


def test_speed_error_reports_kmh():
    with pytest.raises(TrajectoryError) as info:
        FlightLine(0.0, 0.0, 0.0, 1000.0, 500.0, speed_mps=-10.0)
    assert info.value.value == pytest.approx(-36.0)


def test_trajectory_sample_interval_validation():
    line = FlightLine(0.0, 0.0, 0.0, 1000.0, 500.0)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(TrajectoryError) as info:
            line.trajectory(0.0, sample_interval_s=bad)
        assert info.value.field == "flight.sample_interval_s"
    with pytest.raises(TrajectoryError) as info:
        line.trajectory(math.nan)
    assert info.value.field == "flight.ground_height_m"


def midpoint(line):
    return (line.start_easting + line.end_easting) / 2, (line.start_northing + line.end_northing) / 2


def test_parallel_lines_heading_north():
    lines = plan_parallel_lines(1000.0, 5000.0, 0.0, 2000.0, 600.0, 3, 400.0, turn_time_s=60.0, speed_mps=50.0)
    assert [line.line_id for line in lines] == [1, 2, 3]
    assert [line.heading_deg for line in lines] == [0.0, 180.0, 0.0]
    mids = [midpoint(line) for line in lines]
    np.testing.assert_allclose(mids, [(600.0, 5000.0), (1000.0, 5000.0), (1400.0, 5000.0)], atol=1e-9)
    assert lines[0].start_northing == pytest.approx(4000.0) and lines[0].end_northing == pytest.approx(6000.0)
    assert lines[1].start_northing == pytest.approx(6000.0) and lines[1].end_northing == pytest.approx(4000.0)
    assert lines[0].start_gps_time == 450_000_000.0
    for before, after in zip(lines, lines[1:]):
        assert after.start_gps_time == pytest.approx(before.start_gps_time + 40.0 + 60.0, abs=1e-6)
    assert all(line.speed_mps == 50.0 for line in lines)


def test_parallel_lines_heading_east_offsets_to_the_south_and_are_symmetric():
    lines = plan_parallel_lines(0.0, 0.0, 90.0, 1000.0, 600.0, 4, 100.0, start_gps_time=10.0)
    mids = np.array([midpoint(line) for line in lines])
    np.testing.assert_allclose(mids[:, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(mids[:, 1], [150.0, 50.0, -50.0, -150.0], atol=1e-9)
    assert [line.heading_deg for line in lines] == [90.0, 270.0, 90.0, 270.0]
    assert lines[0].start_gps_time == 10.0


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(n_lines=0), "flight.n_lines"),
        (dict(n_lines=2.0), "flight.n_lines"),
        (dict(spacing_m=0.0), "flight.spacing_m"),
        (dict(turn_time_s=-1.0), "flight.turn_time_s"),
        (dict(length_m=-1.0), "flight.length_m"),
    ],
)
def test_parallel_lines_validation(kwargs, field):
    args = dict(centre_easting=0.0, centre_northing=0.0, heading_deg=0.0, length_m=1000.0, altitude_m=500.0)
    args.update(n_lines=2, spacing_m=100.0)
    args.update(kwargs)
    with pytest.raises(TrajectoryError) as info:
        plan_parallel_lines(**args)
    assert info.value.field == field


# ---------------------------------------------------------------- pulse timing and prism phase


def exact_angle(rotation_hz, prf_hz, t_start, k):
    """2π·frac(f_rot·(t_start + k/PRF)), the fraction computed exactly."""
    turns = Fraction(rotation_hz) * (Fraction(t_start) + Fraction(k) / Fraction(prf_hz))
    return 2 * math.pi * float(turns - math.floor(turns))


HOUR_OF_PULSES = 3600 * 5000


def test_prism_phase_exact_over_one_hour_at_gps_450e6():
    timing = PulseTiming()
    t_start = 450e6 + 0.1234567
    rng = np.random.default_rng(5)
    edges = [0, 1, 249, 250, HOUR_OF_PULSES - 1, HOUR_OF_PULSES]
    k = np.concatenate([edges, rng.integers(0, HOUR_OF_PULSES, 3000)])
    angles = timing.prism_angles(t_start, k)
    exact = np.array([exact_angle(20.0, 5000.0, t_start, int(i)) for i in k])
    error = np.abs(angle_difference(angles, exact))
    assert error.max() < 1e-6
    assert np.all((angles >= 0) & (angles < 2 * math.pi))
    naive = np.mod(2 * math.pi * 20.0 * timing.pulse_times(t_start, k), 2 * math.pi)
    assert np.abs(angle_difference(naive, exact)).max() > 1e-6  # the float64 product is not good enough


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, 1e9),
    st.integers(0, HOUR_OF_PULSES),
    st.sampled_from([20.0, 17.3, 50.0, -20.0]),
    st.sampled_from([5000.0, 3000.0, 20_000.0]),
)
def test_prism_phase_matches_fraction(t_start, k, rotation_hz, prf_hz):
    timing = PulseTiming(prf_hz=prf_hz, rotation_hz=rotation_hz)
    angle = float(timing.prism_angles(t_start, k))
    assert abs(angle_difference(angle, exact_angle(rotation_hz, prf_hz, t_start, k))) < 1e-6


def test_phase_repeats_after_whole_turns():
    timing = PulseTiming()
    t0 = 450e6 + 0.123
    t1 = t0 + 3600.0  # 72000 turns at 20 Hz
    assert Fraction(t1) - Fraction(t0) == 3600  # the shift is exact in float64
    assert timing.phase_cycles_at(t1) == timing.phase_cycles_at(t0)
    assert 0.0 <= timing.phase_cycles_at(t0) < 1.0
    turn = timing.prism_angles(t0, [0, 250, 250 * 72_000])  # 250 pulses per turn
    assert np.abs(angle_difference(turn, turn[0])).max() < 1e-9


def test_phase_cycles_with_phase0_and_edge_values():
    assert PulseTiming(phase0_rad=math.pi / 2).phase_cycles_at(0.0) == pytest.approx(0.25, abs=1e-16)
    assert PulseTiming(phase0_rad=-math.pi / 2).phase_cycles_at(0.0) == pytest.approx(0.75, abs=1e-16)
    assert PulseTiming(phase0_rad=-1e-20).phase_cycles_at(0.0) == 0.0  # frac(−1e-20) would round to 1.0
    assert PulseTiming(rotation_hz=20.0).phase_cycles_at(0.025) == pytest.approx(0.5, abs=1e-15)
    # exact: 20 · (450e6 + 0.0125) = 9e9 + 0.25 turns; 0.0125 is not a float64, so compare with Fraction
    t = 450e6 + 0.0125
    turns = Fraction(20) * Fraction(t)
    assert PulseTiming().phase_cycles_at(t) == float(turns - math.floor(turns))
    assert PulseTiming(phase0_rad=-1e-20).prism_angles(0.0, 0) == 0.0


def test_pulse_times_and_counts_at_boundaries():
    timing = PulseTiming()
    assert timing.pulse_period_s == 2e-4 and timing.cycles_per_pulse == 20.0 / 5000.0
    np.testing.assert_array_equal(timing.pulse_times(2.0, [0, 1, 5000]), [2.0, 2.0 + 1 / 5000, 3.0])
    assert timing.pulse_count(0.0, 1.0) == 5001  # both ends inclusive
    assert timing.pulse_count(0.0, 0.0) == 1
    assert timing.pulse_count(0.0, -1e-9) == 0
    assert timing.pulse_count(0.0, 0.99999) == 5000
    assert timing.pulse_count(0.0, math.nextafter(1.0, 0.0)) == 5000
    t0 = 450e6
    assert timing.pulse_count(t0, t0 + 1.0) == 5001
    assert timing.pulse_count(t0, math.nextafter(t0 + 1.0, 0.0)) == 5000
    assert timing.pulse_count(t0, t0 + 3600.0) == HOUR_OF_PULSES + 1
    assert PulseTiming(prf_hz=3.0).pulse_count(0.0, 1.0) == 4  # 3/3 = 1 exactly


@pytest.mark.parametrize("t_start", [0.0, 0.1, 450e6, 450e6 + 0.1234567, -3.3e8, 1e9 - 0.3])
@pytest.mark.parametrize("prf_hz", [5000.0, 3.0, 7777.7])
def test_pulse_count_when_the_end_is_exactly_a_pulse_time(t_start, prf_hz):
    timing = PulseTiming(prf_hz=prf_hz)
    for k in [0, 1, 2, 3, 7, 10, 999, 4999, 5000, 12345, 18_000_000]:
        t_end = float(timing.pulse_times(t_start, k))
        assert timing.pulse_count(t_start, t_end) == k + 1
        # just before it: pulse k is out, unless float64 rounding put pulse k−1 at the same time
        before = math.nextafter(t_end, -math.inf)
        expected = k if k == 0 or timing.pulse_times(t_start, k - 1) <= before else k - 1
        assert timing.pulse_count(t_start, before) == expected


@settings(max_examples=200, deadline=None)
@given(st.floats(-1e9, 1e9), st.floats(0.0, 100.0), st.sampled_from([5000.0, 3.0, 7777.7]))
def test_pulse_count_brackets_the_end(t_start, span, prf_hz):
    timing = PulseTiming(prf_hz=prf_hz)
    t_end = t_start + span
    count = timing.pulse_count(t_start, t_end)
    assert count >= 1
    assert timing.pulse_times(t_start, count - 1) <= t_end
    assert timing.pulse_times(t_start, count) > t_end
    assert abs(count - (span * prf_hz + 1)) <= 1 + 1e-6 * span * prf_hz


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(prf_hz=0.0), "scan.prf_hz"),
        (dict(prf_hz=-5.0), "scan.prf_hz"),
        (dict(rotation_hz=math.nan), "scan.rotation_hz"),
        (dict(phase0_rad=math.inf), "scan.phase0_rad"),
        (dict(prf_hz=0.0, field_prefix="instrument"), "instrument.prf_hz"),
    ],
)
def test_pulse_timing_validation(kwargs, field):
    with pytest.raises(TrajectoryError) as info:
        PulseTiming(**kwargs)
    assert info.value.field == field


def test_quaternions_primed_together_are_each_trajectorys_own_bit_for_bit():
    """prime_quaternions over trajectories at random attitudes (headings across ±180°, so the signs flip within
    some lines): the quaternions each trajectory works out alone, to the bit, sign continuity per line."""
    from trajectories import prime_quaternions

    rng = np.random.default_rng(3)
    lines = []
    for k in range(300):
        n = int(rng.integers(2, 30))
        attitude = np.column_stack([rng.normal(0.0, 0.4, n), rng.normal(0.0, 0.4, n), rng.uniform(-4.0, 4.0, n)])
        lines.append((1.0e8 + np.cumsum(rng.uniform(0.01, 1.0, n)), rng.normal(0.0, 100.0, (n, 3)), attitude, k))
    primed, alone = [Trajectory(*line) for line in lines], [Trajectory(*line) for line in lines]
    prime_quaternions(primed)
    assert all("_quaternions" in t.__dict__ for t in primed) and not any("_quaternions" in t.__dict__ for t in alone)
    flips = 0
    for a, b in zip(primed, alone):
        assert np.array_equal(a.quaternions(), b.quaternions())
        flips += int(np.any(np.einsum("ij,ij->i", a.quaternions()[1:], a.quaternions()[:-1]) < 0.0))
    assert flips == 0 and sum(np.any(np.diff(np.sign(t.quaternions()[:, 3])) != 0) for t in alone) > 10


def _lines_of_three(count: int, seed: int = 4):
    rng = np.random.default_rng(seed)
    times = 1.0e8 + np.cumsum(rng.uniform(0.01, 1.0, (count, 3)), axis=1)
    return times, rng.normal(0.0, 100.0, (count, 3, 3)), rng.uniform(-3.0, 3.0, (count, 3, 3)), np.arange(count) * 7


def test_trajectories_made_together_are_each_made_alone():
    """Trajectory.many: each trajectory's arrays, line id, poses and quaternions those it has made alone, its arrays
    read-only float64 copies (the caller's arrays changed afterwards change nothing)."""
    times, position, attitude, ids = _lines_of_three(40)
    together = Trajectory.many(times, position, attitude, ids)
    alone = [Trajectory(times[i], position[i], attitude[i], int(ids[i])) for i in range(len(ids))]
    times += 1.0
    position[:] = 0.0
    for a, b in zip(together, alone):
        for name in ("gps_time", "position", "attitude"):
            assert np.array_equal(getattr(a, name), getattr(b, name)) and getattr(a, name).dtype == np.float64
            assert not getattr(a, name).flags.writeable
        assert a.line_id == b.line_id and type(a.line_id) is int
        assert np.array_equal(a.quaternions(), b.quaternions())
        middle = 0.5 * (b.gps_time[0] + b.gps_time[2])
        for x, y in zip(a.interpolate(middle), b.interpolate(middle)):
            assert np.array_equal(x, y)


@pytest.mark.parametrize("spoil", ["time", "position", "attitude", "line_id"])
def test_trajectories_made_together_refuse_the_first_bad_one_as_it_alone_is_refused(spoil):
    times, position, attitude, ids = _lines_of_three(30)
    if spoil == "time":
        times[12, 2] = times[12, 1]
    elif spoil == "position":
        position[9, 1, 2] = np.nan
    elif spoil == "attitude":
        attitude[17, 0, 0] = np.inf
    else:
        ids = ids.copy()
        ids[21] = 65536  # one past the largest LAS point_source_id
    bad = {"time": 12, "position": 9, "attitude": 17, "line_id": 21}[spoil]
    with pytest.raises(TrajectoryError) as alone:
        Trajectory(times[bad], position[bad], attitude[bad], int(ids[bad]))
    with pytest.raises(TrajectoryError) as together:
        Trajectory.many(times, position, attitude, ids)
    assert str(together.value) == str(alone.value) and together.value.field == alone.value.field
