"""Properties of the device optics over random prisms, fans and prism angles (hypothesis), and of
the terrain clearance the flight plan relies on.

System under test: ``flightsim.instrument.fan.trace_fan`` (the Warp optics of kernels/optics.py). Each property
is checked against a law, not against stored output: refracted directions are unit vectors,
coplanar with the incident ray and the face normal and obey Snell's law at each face; tracing the
exit ray backwards (a Warp kernel here, built from ``kernels.optics.refract``) recovers the
incident direction; the fan repeats every 2π of prism angle; the rigid-array model is exact for
the on-axis beam.
"""
import math

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import reference_optics as ref
from flightsim.instrument.risley_model import trace_fan
from flightsim.scenes.scene import CLASS_GROUND, Scene, parse_crs, plane_info
from kernels.optics import back_face_normal, refract

Z = np.array([0.0, 0.0, 1.0])
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def prisms(draw):
    """(n, spacing [rad], n_glass, apex [rad], φ values [rad]) with the on-axis beam short of TIR."""
    n_glass = draw(st.floats(1.3, 2.4))
    critical = math.asin(1.0 / n_glass)
    apex = draw(st.floats(0.02, 0.97)) * critical
    n = draw(st.integers(1, 9))
    spacing = draw(st.floats(0.0, 0.03))
    phis = draw(st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=1, max_size=6))
    return n, spacing, n_glass, apex, np.array(phis)


def sin_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.cross(a, b), axis=-1)


@FAST
@given(prisms())
def test_refraction_keeps_unit_length_coplanarity_and_snell_at_each_face(case):
    n, spacing, n_glass, apex, phis = case
    fan = trace_fan(phis, n, spacing, n_glass, apex, precision="float64")
    s1 = np.broadcast_to(ref.fan_directions(n, spacing), fan.directions.shape)
    s2 = fan.exit_points / np.linalg.norm(fan.exit_points, axis=-1, keepdims=True)  # the ray inside the glass
    s3 = fan.directions
    n2 = np.stack([ref.back_normal(p, apex) for p in phis])[:, None, :]
    ok = fan.ok
    assert np.isfinite(s3).all() and np.isfinite(fan.exit_points).all()
    assert np.abs(np.linalg.norm(s3[ok], axis=-1) - 1.0).max(initial=0.0) < 1e-12
    # Σ1 (normal ẑ): sin θ1 = n sin θ2, and s1, ẑ, s2 in one plane
    assert np.abs(sin_angle(s1, Z) - n_glass * sin_angle(s2, Z)).max() < 1e-12
    assert np.abs(np.einsum("...i,...i", np.cross(s1, Z), s2)).max() < 1e-12
    # Σ2 (normal N2): n sin θ2' = sin θ3 where the beam exits, and s2, N2, s3 in one plane
    n2 = np.broadcast_to(n2, s3.shape)
    assert np.abs(n_glass * sin_angle(s2, n2) - sin_angle(s3, n2))[ok].max(initial=0.0) < 1e-12
    assert np.abs(np.einsum("...i,...i", np.cross(s2, n2), s3))[ok].max(initial=0.0) < 1e-12
    # a beam is dropped exactly when Snell has no solution at Σ2 (n sin θ2' > 1)
    margin = n_glass * sin_angle(s2, n2) - 1.0
    decided = np.abs(margin) > 1e-12
    assert np.array_equal(~ok[decided], (margin > 0)[decided])


@wp.kernel
def _trace_back(
    exit_directions: wp.array2d(dtype=wp.vec3d),  # S3 [sensor frame]
    phis: wp.array(dtype=wp.float64),  # [rad]
    n_glass: wp.float64,
    apex: wp.float64,
    incident: wp.array2d(dtype=wp.vec3d),  # out: the recovered S1
):
    """Reverse ray: −S3 enters the glass through Σ2 (normal −N2 along propagation, μ = 1/n), then
    leaves through Σ1 (normal −ẑ, μ = n); the incident direction is minus what comes out."""
    k, beam = wp.tid()
    one = wp.float64(1.0)
    inside, ok_back = refract(-exit_directions[k, beam], -back_face_normal(phis[k], apex), one / n_glass)
    out, ok_front = refract(inside, wp.vec3d(0.0, 0.0, -1.0), n_glass)
    incident[k, beam] = -out


@FAST
@given(prisms())
def test_tracing_the_exit_ray_back_recovers_the_incident_direction(case):
    n, spacing, n_glass, apex, phis = case
    fan = trace_fan(phis, n, spacing, n_glass, apex)  # the production precision: float32
    shape = fan.directions.shape[:2]
    back = wp.empty(shape, dtype=wp.vec3d)
    wp.launch(_trace_back, shape, inputs=[wp.array(fan.directions, dtype=wp.vec3d), wp.array(phis, dtype=wp.float64),
                                          n_glass, apex], outputs=[back])
    s1 = np.broadcast_to(ref.fan_directions(n, spacing), fan.directions.shape)
    # float32 forward trace, float64 return trip: the angle between them stays within 1 µrad
    # (amplified near grazing exit, so the beams within 2° of the critical angle are left out)
    s2 = fan.exit_points / np.linalg.norm(fan.exit_points, axis=-1, keepdims=True)
    n2 = np.stack([ref.back_normal(p, apex) for p in phis])[:, None, :]
    clear = fan.ok & (n_glass * sin_angle(s2, np.broadcast_to(n2, s2.shape)) < math.sin(math.radians(88.0)))
    assert ref.angle_between(back.numpy()[clear], s1[clear]).max(initial=0.0) < 1e-6


@FAST
@given(prisms(), st.integers(-3, 3).filter(lambda k: k != 0))
def test_fan_repeats_every_full_turn_of_the_prism(case, turns):
    n, spacing, n_glass, apex, phis = case
    a = trace_fan(phis, n, spacing, n_glass, apex, precision="float64")
    b = trace_fan(phis + 2 * np.pi * turns, n, spacing, n_glass, apex, precision="float64")
    assert np.array_equal(a.ok, b.ok)
    assert np.abs(a.directions - b.directions)[a.ok].max(initial=0.0) < 1e-12
    assert np.abs(a.exit_points - b.exit_points).max() < 1e-15


@FAST
@given(prisms())
def test_rigid_array_model_is_exact_for_the_on_axis_beam(case):
    n, spacing, n_glass, apex, phis = case
    n = n | 1  # odd arrays have a beam on the axis
    for precision, tolerance in (("float64", 1e-12), ("float32", 1e-6)):
        fan = trace_fan(phis, n, spacing, n_glass, apex, precision=precision)
        centre = n * n // 2
        assert fan.ok[:, centre].all()
        assert ref.angle_between(fan.nominal[:, centre], fan.directions[:, centre]).max() < tolerance
        # and equals the float64 reference exit direction of ẑ
        s3, _, _ = zip(*(ref.prism_exit(Z[None], p, n_glass, apex, 0.01) for p in phis))
        assert ref.angle_between(fan.directions[:, centre], np.concatenate(s3)).max() < tolerance


# ---------------------------------------------------------------------------------------------
# terrain clearance: the highest point of a mesh over a rectangle


def clipped_top(triangle: np.ndarray, xmin, ymin, xmax, ymax) -> float:
    """Highest z of a triangle clipped to the prism over a rectangle (Sutherland–Hodgman in 3-D)."""
    polygon = [p for p in triangle]
    for axis, bound, keep_above in ((0, xmin, True), (0, xmax, False), (1, ymin, True), (1, ymax, False)):
        inside = (lambda p: p[axis] >= bound) if keep_above else (lambda p: p[axis] <= bound)
        out = []
        for k, p in enumerate(polygon):
            q = polygon[k - 1]
            if inside(p) != inside(q):
                s = (bound - q[axis]) / (p[axis] - q[axis])
                crossing = q + s * (p - q)
                crossing[axis] = bound  # exactly on the clipping plane, whatever the rounding
                out.append(crossing)
            if inside(p):
                out.append(p)
        polygon = out
        if not polygon:
            return -math.inf
    return max(p[2] for p in polygon)


# eighths of a metre: exact in binary, so rectangles often pass exactly through vertices and edges
coordinate = st.integers(-400, 400).map(lambda v: v / 8)
length = st.integers(0, 320).map(lambda v: v / 8)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(*[coordinate] * 9), min_size=1, max_size=6),
       st.tuples(coordinate, coordinate), st.tuples(length, length), st.booleans())
def test_terrain_top_is_the_highest_point_of_the_surface_over_the_rectangle(triangles, corner, size, vertical):
    corners = np.array(triangles, dtype=np.float64).reshape(-1, 3, 3)
    if vertical:  # walls: the triangle's xy projection is a segment
        corners[:, 2, :2] = corners[:, 0, :2] + 0.3 * (corners[:, 1, :2] - corners[:, 0, :2])
    scene = Scene(name="t", crs=parse_crs("EPSG:32648"), origin=(0.0, 0.0, 0.0), vertices=corners.reshape(-1, 3),
                  triangles=np.arange(3 * len(corners)).reshape(-1, 3), plane_id=np.zeros(len(corners), dtype=np.int32),
                  classification=np.full(len(corners), CLASS_GROUND, dtype=np.uint8),
                  planes=[plane_info(0, "ground", CLASS_GROUND, (0, 0, 1), (0, 0, 0))], ground_z=0.0)
    rect = (corner[0], corner[1], corner[0] + size[0], corner[1] + size[1])
    expected = max(clipped_top(t, *rect) for t in corners)
    got = scene.terrain_top(*rect)
    if expected == -math.inf:
        assert got == -math.inf or got <= corners[:, :, 2].max()  # touching within rounding only
    else:
        assert got == pytest.approx(expected, abs=1e-6)
