"""Device optics (kernels/optics.py) against independent float64 math and closed forms."""
import math

import numpy as np
import pytest

import reference_optics as ref
from flightsim.instrument.risley_model import apex_for_cone
from flightsim.instrument.risley_model import trace_fan

N_BK7 = 1.5066
APEX = apex_for_cone(math.radians(15.0), N_BK7)
MICRORAD = 1e-6
PHIS = np.concatenate([np.linspace(0.0, 2 * np.pi, 73, endpoint=False), [np.pi / 4, 2 * np.pi - 1e-7]])


def reference_fan(phi, n, spacing, n_glass=N_BK7, apex=APEX, thickness=0.01):
    s1 = ref.fan_directions(n, spacing)
    out = [ref.prism_exit(s1, p, n_glass, apex, thickness) for p in phi]
    return (np.array([o[0] for o in out]), np.array([o[1] for o in out]), np.array([o[2] for o in out]))


@pytest.mark.parametrize("n, spacing_mrad", [(1, 2.314), (3, 2.314), (8, 5.0), (32, 10.0), (32, 0.5)])
def test_float32_exit_directions_within_one_microradian(device, n, spacing_mrad):
    spacing = spacing_mrad * 1e-3
    fan = trace_fan(PHIS, n, spacing, N_BK7, APEX, device=device)
    s3, points, tir = reference_fan(PHIS, n, spacing)
    assert not tir.any() and fan.ok.all()
    assert ref.angle_between(fan.directions, s3).max() <= MICRORAD
    assert np.abs(fan.exit_points - points).max() < 1e-8  # [m]


def test_float64_kernel_agrees_with_reference_to_rounding(device):
    fan = trace_fan(PHIS, 6, 4.628e-3, N_BK7, APEX, precision="float64", device=device)
    s3, points, _ = reference_fan(PHIS, 6, 4.628e-3)
    assert ref.angle_between(fan.directions, s3).max() < 1e-13
    assert np.abs(fan.exit_points - points).max() < 1e-15


@pytest.mark.parametrize("cone_deg, n_glass", [(15.0, N_BK7), (5.0, 1.45), (30.0, 1.8), (15.0, 3.4)])
def test_on_axis_beam_deviates_by_exactly_the_cone_angle(device, cone_deg, n_glass):
    apex = apex_for_cone(math.radians(cone_deg), n_glass)
    for precision, tol in (("float64", 1e-12), ("float32", MICRORAD)):
        fan = trace_fan(PHIS, 1, 0.0, n_glass, apex, precision=precision, device=device)
        deviation = ref.angle_between(fan.directions[:, 0], np.array([0.0, 0.0, 1.0]))
        assert np.abs(deviation - math.radians(cone_deg)).max() < tol, precision
        # and it swings round the axis with the prism: azimuth of the exit beam is φ + π
        azimuth = np.arctan2(fan.directions[:, 0, 1], fan.directions[:, 0, 0])
        assert np.abs(np.angle(np.exp(1j * (azimuth - PHIS - np.pi)))).max() < 1e-5


def test_snell_law_and_coplanarity_hold_at_each_face(device):
    n, spacing = 5, 8e-3
    fan = trace_fan(PHIS, n, spacing, N_BK7, APEX, precision="float64", device=device)
    s1 = ref.fan_directions(n, spacing)
    z = np.array([0.0, 0.0, 1.0])
    for k, phi in enumerate(PHIS):
        s2 = fan.exit_points[k] / np.linalg.norm(fan.exit_points[k], axis=1, keepdims=True)
        s3 = fan.directions[k]
        n2 = ref.back_normal(phi, APEX)
        # front face Σ1: sin θ1 = n sin θ2, incident ray, normal and refracted ray coplanar
        assert np.abs(np.sin(ref.angle_between(s1, z)) - N_BK7 * np.sin(ref.angle_between(s2, z))).max() < 1e-6
        assert np.abs(np.einsum("ij,ij->i", np.cross(s1, z), s2)).max() < 1e-9
        # back face Σ2: n sin θ2' = sin θ3
        assert np.abs(N_BK7 * np.sin(ref.angle_between(s2, n2)) - np.sin(ref.angle_between(s3, n2))).max() < 1e-6
        assert np.abs(np.einsum("ij,ij->i", np.cross(s2, n2), s3)).max() < 1e-9
        # the exit point lies on Σ2
        assert np.abs((fan.exit_points[k] - [0, 0, 0.01]) @ n2).max() < 1e-15


def test_total_internal_reflection_is_flagged_and_never_nan(device):
    # a steep wedge (on-axis beam just passes) and a wide fan: part of the fan reflects internally
    apex = math.asin(1.0 / N_BK7) - math.radians(2.0)
    n, spacing = 16, 20e-3
    fan = trace_fan(PHIS, n, spacing, N_BK7, apex, device=device)
    _, _, tir = reference_fan(PHIS, n, spacing, apex=apex)
    assert 0 < tir.sum() < tir.size
    # float32 may disagree only for rays within rounding of the critical angle
    s1 = ref.fan_directions(n, spacing)
    s2, _ = ref.refract_tangential(s1, np.array([0, 0, 1.0]), 1.0, N_BK7)
    margin = np.array([N_BK7 * np.sin(ref.angle_between(s2, ref.back_normal(p, apex))) - 1.0 for p in PHIS])
    decided = np.abs(margin) > 1e-5
    assert np.array_equal(~fan.ok[decided], tir[decided])
    assert np.isfinite(fan.directions).all() and np.isfinite(fan.exit_points).all()


def test_fan_at_phi_plus_pi_is_the_fan_turned_half_round_with_beams_mirrored(device):
    n = 4
    phi = np.linspace(0, np.pi, 19)
    a = trace_fan(phi, n, 3e-3, N_BK7, APEX, precision="float64", device=device)
    b = trace_fan(phi + np.pi, n, 3e-3, N_BK7, APEX, precision="float64", device=device)
    half_turn = np.diag([-1.0, -1.0, 1.0])
    mirrored = np.arange(n * n)[::-1]  # (i, j) -> (n-1-i, n-1-j) in row-major order
    assert np.abs(b.directions - a.directions[:, mirrored] @ half_turn.T).max() < 1e-14


def test_nominal_model_matches_reference_and_equals_exact_on_axis(device):
    n, spacing = 5, 2.314e-3
    fan = trace_fan(PHIS, n, spacing, N_BK7, APEX, precision="float64", device=device)
    for k, phi in enumerate(PHIS[::7]):
        expected = ref.nominal_directions(n, spacing, phi, N_BK7, APEX)
        assert ref.angle_between(fan.nominal[k * 7], expected).max() < 1e-13
    centre = n * n // 2
    assert ref.angle_between(fan.nominal[:, centre], fan.directions[:, centre]).max() < 1e-13
    # off-axis, the rigid-array model is wrong by a small but non-zero angle that varies with φ
    error = ref.angle_between(fan.nominal[:, 0], fan.directions[:, 0])
    assert 1e-5 < error.max() < 1e-2 and error.max() - error.min() > 1e-5
