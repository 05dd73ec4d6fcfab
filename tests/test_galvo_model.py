"""The float64 galvo model against the double-angle law in closed form, and the seed paper's numbers."""
from __future__ import annotations

import numpy as np
import pytest

from flightsim.core.constants import ARCSEC
from flightsim.instrument import galvo_model
from flightsim.instrument.galvo_model import GalvoGeometry

D = 100.0
# Mirrors meeting at one point (b = e = 0) and one channel on the axis: the beam leaves along
# (sin 2δ, cos 2δ sin 2γ, cos 2δ cos 2γ) from the origin, so every deviation has a closed form.
POINT = GalvoGeometry(b_m=0.0, e_m=0.0, channel_angles_rad=(0.0,), field_deg=(30.0, 30.0), strips=5, columns=7)
PAPER = GalvoGeometry()


def _direction(delta, gamma):
    return np.stack([np.sin(2 * delta), np.cos(2 * delta) * np.sin(2 * gamma), np.cos(2 * delta) * np.cos(2 * gamma)],
                    axis=-1)


def _closed_form(errors):
    """Processed − true point over the plane z = D: (D / d'_z)(d − d'), d the believed, d' the true direction."""
    e = {k: 0.0 for k in galvo_model.PARAMS} | errors
    delta, gamma, sign = galvo_model.raster_angles(POINT)
    true_delta = delta + e["b1"] * sign + e["b2"] / np.cos(gamma) + e["b3"] * np.tan(gamma)
    true_gamma = gamma + e["c1"]
    d, d_true = _direction(delta, gamma), _direction(true_delta, true_gamma)
    return (D / d_true[:, 2])[:, None] * (d - d_true) + e["range"] * d


def test_raster_covers_the_field_with_alternating_strips():
    delta, gamma, sign = galvo_model.raster_angles(POINT)
    assert np.degrees(2 * delta).min() == pytest.approx(-15.0) and np.degrees(2 * delta).max() == pytest.approx(15.0)
    assert np.degrees(2 * gamma).min() == pytest.approx(-15.0) and np.degrees(2 * gamma).max() == pytest.approx(15.0)
    strip_delta = delta.reshape(POINT.strips, POINT.columns)
    assert (np.diff(strip_delta[0]) > 0).all() and (np.diff(strip_delta[1]) < 0).all()
    assert (sign.reshape(POINT.strips, POINT.columns)[:, 0] == [1, -1, 1, -1, 1]).all()


def test_trace_obeys_the_double_angle_law():
    delta, gamma = np.radians([-7.5, -3.0, 0.0, 4.0, 7.5]), np.radians([7.5, -2.0, 0.0, 1.0, -7.5])
    exit_point, direction = galvo_model.trace(POINT, delta, gamma, np.zeros(5, dtype=int))
    assert np.abs(direction - _direction(delta, gamma)).max() < 1e-15
    assert np.abs(exit_point).max() < 1e-15


def test_exit_point_lies_on_mirror_two_and_beams_leave_unit():
    delta, gamma = np.meshgrid(np.radians(np.linspace(-7.5, 7.5, 9)), np.radians(np.linspace(-7.5, 7.5, 9)))
    channel = np.arange(PAPER.channels)[None, None, :]
    exit_point, direction = galvo_model.trace(PAPER, delta[..., None], gamma[..., None], channel)
    _, n2 = galvo_model.mirror_normals(delta, gamma)
    assert np.abs(np.sum(exit_point * n2[..., None, :], axis=-1)).max() < 1e-15
    assert np.abs(np.linalg.norm(direction, axis=-1) - 1.0).max() < 1e-15
    hits = galvo_model.mirror_hits(PAPER, delta[..., None], gamma[..., None], channel)
    assert hits.front.all()
    assert 0.0 < hits.off_pivot2.max() < 0.015


@pytest.mark.parametrize("errors", [{"b1": 42.9 * ARCSEC}, {"b2": 42.9 * ARCSEC}, {"b3": 42.9 * ARCSEC},
                                    {"c1": 94.5 * ARCSEC}, {"range": 0.05},
                                    {"b1": 1e-3, "b2": -2e-3, "b3": 3e-3, "c1": -1e-3, "range": -0.1}])
def test_deviation_matches_the_closed_form(errors):
    model = galvo_model.deviation(POINT, D, errors)[:, 0, :]
    assert np.abs(model - _closed_form(errors)).max() < 1e-11


def test_analytic_sigma_matches_the_closed_form_derivatives():
    delta, gamma, sign = galvo_model.raster_angles(POINT)
    d = _direction(delta, gamma)
    d_delta = np.stack([2 * np.cos(2 * delta), -2 * np.sin(2 * delta) * np.sin(2 * gamma),
                        -2 * np.sin(2 * delta) * np.cos(2 * gamma)], axis=-1)
    d_gamma = np.stack([np.zeros_like(delta), 2 * np.cos(2 * delta) * np.cos(2 * gamma),
                        -2 * np.cos(2 * delta) * np.sin(2 * gamma)], axis=-1)
    scale = (D / d[:, 2])[:, None]
    s = {"b1": 3e-4, "b2": 2e-4, "c1": 5e-4, "n_h": 1e-4, "range": 0.06}
    variance = ((scale * d_delta) ** 2 * (s["b1"] ** 2 + (s["b2"] / np.cos(gamma)[:, None]) ** 2 + s["n_h"] ** 2)
                + (scale * d_gamma) ** 2 * s["c1"] ** 2 + (d * s["range"]) ** 2)
    analytic = galvo_model.analytic_sigma(POINT, s, D)
    assert analytic == pytest.approx(np.sqrt(variance), rel=1e-7, abs=1e-12)


def test_allowed_errors_hold_the_binding_point_at_sigma_z():
    allowed = galvo_model.allowed_errors(PAPER, sigma_r_m=0.0604, distance_m=D)
    theta = allowed["sigma_theta_arcsec"] * ARCSEC
    sigma = galvo_model.analytic_sigma(PAPER, {"n_h": theta, "n_v": theta, "range": 0.0604}, D)
    assert sigma[:, 2].max() == pytest.approx(0.20 / 3.0, rel=1e-9)
    assert int(np.argmax(sigma[:, 2])) == allowed["binding_slot"]


def test_allowed_errors_reproduce_the_paper():
    """Seed paper §3.3: σ_r = 6.04 cm at 100 m gives σ_C1 = σθ = 94.5″ and σB = 42.9″."""
    allowed = galvo_model.allowed_errors(PAPER, sigma_r_m=0.0604, distance_m=D)
    assert allowed["sigma_theta_arcsec"] == pytest.approx(94.5, rel=0.10)
    assert allowed["sigma_b_arcsec"] == pytest.approx(42.9, rel=0.10)


# seed paper Table 1 [cm], (max, min) of |deviation|, each source alone at its allowed 1σ
TABLE1 = {"b2": {"X": (4.34, 4.17)}, "b3": {"X": (0.57, 0.0)}, "c1": {"X": (0.0, 0.0), "Y": (9.17, 9.17), "Z": (2.61, 0.0)}}
# the Y and Z columns of the horizontal-angle sources match the paper's for a 34° horizontal field
TABLE1_34 = {"b2": {"Y": (0.34, 0.0), "Z": (1.28, 0.0)}, "b3": {"Y": (0.04, 0.0), "Z": (0.17, 0.0)}}
VALUES = {"b2": 42.9 * ARCSEC, "b3": 42.9 * ARCSEC, "c1": 94.5 * ARCSEC}


@pytest.mark.parametrize("geometry, expected", [(PAPER, TABLE1),
                                                (GalvoGeometry(field_deg=(34.0, 30.0)), TABLE1_34)])
def test_table1_reproduces_the_paper(geometry, expected):
    table = galvo_model.table1(geometry, D, VALUES)
    for source, axes in expected.items():
        for axis, (high, low) in axes.items():
            got = [100 * v for v in table[source][axis]]
            assert got[0] == pytest.approx(high, rel=0.10, abs=0.01), (source, axis)
            assert got[1] == pytest.approx(low, rel=0.10, abs=0.01), (source, axis)
