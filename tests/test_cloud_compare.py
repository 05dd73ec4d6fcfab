"""The TLS-reference study's pieces against closed forms: the rigid fit recovers a known transform and its error
from noisy control points matches the first-order expectation; C2C and local-plane distances between parallel
planes match their analytic distributions; the total station's noise is what its class says."""
from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.polynomial.hermite_e import hermegauss
from scipy import special, stats
from scipy.spatial.transform import Rotation

from flightsim.studies import cloud_compare as cc

CONTROLS = np.array([[-5.5, -5.5, 0.1], [5.5, -5.5, -0.2], [5.5, 5.5, 0.3], [-5.5, 5.5, 0.0]])


def _transform(seed=1):
    rot = Rotation.from_euler("zyx", [33.0, -4.0, 7.0], degrees=True).as_matrix()
    return rot, np.array([12.0, -3.0, 100.0])


def test_rigid_fit_recovers_an_exact_transform():
    rot, t = _transform()
    r, tr = cc.rigid_fit(CONTROLS, CONTROLS @ rot.T + t)
    assert np.abs(r - rot).max() < 1e-13 and np.abs(tr - t).max() < 1e-12


def test_rigid_fit_error_matches_the_closed_form():
    """Noise σ on the target points, 4000 fits: the mean squared error at a point 100 m off (the lever of a
    registration through the lidar's markers) within 5 standard errors of the first-order expectation."""
    rot, t = _transform()
    rng = np.random.default_rng(7)
    sigma, x = 0.002, np.array([1.0, 2.0, 100.0])
    target = CONTROLS @ rot.T + t
    errors = []
    for _ in range(4000):
        r, tr = cc.rigid_fit(CONTROLS, target + rng.normal(0.0, sigma, target.shape))
        errors.append(np.sum((r @ x + tr - (rot @ x + t)) ** 2))
    errors = np.asarray(errors)
    expected = cc.rigid_fit_error(CONTROLS, sigma, x)  # the error at x, in the source frame's geometry
    assert abs(errors.mean() - expected) < 5.0 * errors.std() / math.sqrt(len(errors))
    assert expected > 10 * 3 * sigma ** 2 / 4  # the rotation's lever dominates: the test can tell it from 3σ²/n


def _poisson_plane(rng, density, half=5.0):
    n = rng.poisson(density * (2 * half) ** 2)
    return np.column_stack([rng.uniform(-half, half, (n, 2)), np.zeros(n)])


def test_c2c_between_parallel_planes_matches_the_nearest_neighbour_law():
    """Reference: Poisson points of density λ on z = 0; points at z ~ N(d, σ). Given z, D² − z² is exponential
    with rate λπ, so E[D | z] = |z| + erfcx(√(λπ)|z|) / (2√λ) and E[D²] = d² + σ² + 1/(λπ)."""
    rng = np.random.default_rng(3)
    lam, d, sigma = 2000.0, 0.01, 0.005
    reference = _poisson_plane(rng, lam)
    n = 20000
    points = np.column_stack([rng.uniform(-4.0, 4.0, (n, 2)), rng.normal(d, sigma, n)])
    dist = cc.c2c_distances(points, reference)
    nodes, weights = hermegauss(80)
    z = np.abs(d + sigma * nodes)
    mean = np.sum(weights * (z + special.erfcx(math.sqrt(lam * math.pi) * z) / (2 * math.sqrt(lam)))) / math.sqrt(2 * math.pi)
    assert abs(dist.mean() - mean) < 5.0 * dist.std() / math.sqrt(n)
    second = d ** 2 + sigma ** 2 + 1.0 / (lam * math.pi)
    assert abs(np.mean(dist ** 2) - second) < 5.0 * np.std(dist ** 2) / math.sqrt(n)


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0])
def test_plane_distance_between_parallel_planes_is_the_offset_plus_noise(tilt_deg):
    """A noise-free reference plane (tilted or not): the signed distance along the fitted normal has mean d and
    standard deviation σ (chi-square bounds), whatever the reference's spacing."""
    rng = np.random.default_rng(5)
    d, sigma, n = 0.02, 0.004, 20000
    reference = _poisson_plane(rng, 400.0)
    points = np.column_stack([rng.uniform(-4.0, 4.0, (n, 2)), rng.normal(d, sigma, n)])
    turn = Rotation.from_euler("y", tilt_deg, degrees=True).as_matrix()
    dist = cc.plane_distances(points @ turn.T, reference @ turn.T)
    assert abs(dist.mean() - d) < 5.0 * sigma / math.sqrt(n)
    chi = (n - 1) * dist.var(ddof=1) / sigma ** 2
    assert stats.chi2.ppf(1e-6, n - 1) < chi < stats.chi2.ppf(1 - 1e-6, n - 1)


def test_total_station_noise_follows_its_class():
    rng = np.random.default_rng(9)
    station = np.array([0.0, 0.0, 1.6])
    n, reach = 20000, 100.0
    target = np.tile([reach * 0.6, reach * 0.8, 1.6], (n, 1))
    measured = cc.total_station(target, station, rng, mm=2.0, ppm=2.0, arcsec=2.0)
    v = measured - station
    r = np.linalg.norm(v, axis=1)
    sigma_r = math.hypot(2e-3, 2e-6 * reach)
    chi = (n - 1) * r.var(ddof=1) / sigma_r ** 2
    assert stats.chi2.ppf(1e-6, n - 1) < chi < stats.chi2.ppf(1 - 1e-6, n - 1)
    across = v[:, 2]  # the zenith angle's noise moves the point vertically by reach · δζ
    sigma_z = reach * 2.0 * cc.ARCSEC
    chi = (n - 1) * across.var(ddof=1) / sigma_z ** 2
    assert stats.chi2.ppf(1e-6, n - 1) < chi < stats.chi2.ppf(1 - 1e-6, n - 1)


def test_registration_chain_is_the_identity_without_noise(monkeypatch):
    """TLS → total station → lidar → local with noise-free measurements puts the TLS cloud back where it was;
    with noise, the error at the sandbox is the markers' lever (checked against its closed form above)."""
    from flightsim.studies import spad_tls as st

    monkeypatch.setattr(st, "TS_CLASS", (0.0, 0.0, 0.0))
    monkeypatch.setattr(st, "TARGET_SIGMA_M", 0.0)
    tls_rot, tls_origin = _transform()
    lidar_rot = Rotation.from_euler("zyx", [-70.0, 3.0, 178.0], degrees=True).as_matrix()
    scan = st.TlsScan(np.zeros((1, 3)), np.zeros(1, np.int64), 1, tls_origin, tls_rot)
    rot, trans = st.registration(scan, np.array([0.5, -0.2, 99.0]), lidar_rot, CONTROLS, 0.0,
                                 np.random.default_rng(1), 0.5)
    assert np.abs(rot - np.eye(3)).max() < 1e-9 and np.abs(trans).max() < 1e-7
