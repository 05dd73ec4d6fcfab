"""Plane fits against closed forms: TLS normal, pitch, azimuth and RMS of known planes."""
import math

import numpy as np
import pytest

from flightsim.scoring.planes import PlaneMoments, fit_groups, fit_points, group_moments, pooled_rms, residuals

WORLD = np.array([409_000.0, 3_393_000.0, 450.0])  # UTM-sized offsets: precision must survive them


def plane_normal(slope: float, azimuth_deg: float) -> np.ndarray:
    """Unit upward normal of z = −slope·(x·sin a + y·cos a): descending towards azimuth a."""
    a = math.radians(azimuth_deg)
    n = np.array([slope * math.sin(a), slope * math.cos(a), 1.0])
    return n / np.linalg.norm(n)


def points_on_plane(normal: np.ndarray, n: int, half_side: float, rng, sigma: float = 0.0) -> np.ndarray:
    """n points uniform over a square patch of the plane through WORLD, plus N(0, σ²) along the normal."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    s, t = rng.uniform(-half_side, half_side, size=(2, n))
    offset = rng.normal(0.0, sigma, n) if sigma else np.zeros(n)
    return WORLD + np.outer(s, u) + np.outer(t, v) + np.outer(offset, normal)


def angle_rad(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (sign-free) [rad], accurate for tiny angles."""
    return math.atan2(np.linalg.norm(np.cross(a, b)), abs(float(a @ b)))


@pytest.mark.parametrize("azimuth_deg", [0.0, 37.0, 90.0, 133.0, 200.0, 315.0])
def test_noise_free_tilted_plane_is_recovered_to_1e_9_rad(azimuth_deg):
    rng = np.random.default_rng(1)
    truth = plane_normal(0.20, azimuth_deg)
    fit = fit_points(points_on_plane(truth, 500, 50.0, rng))
    assert angle_rad(fit.normal, truth) < 1e-9
    assert fit.normal[2] > 0.0
    assert fit.rms_m < 1e-9
    assert fit.pitch_deg == pytest.approx(math.degrees(math.atan(0.20)), abs=1e-7)  # 11.3099°
    assert (fit.azimuth_deg - azimuth_deg + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("sigma", [0.001, 0.05, 0.2])
@pytest.mark.parametrize("slope, azimuth_deg", [(0.0, 0.0), (0.20, 75.0), (1.0, 250.0)])
def test_gaussian_noise_gives_rms_sigma_and_the_right_normal(sigma, slope, azimuth_deg):
    rng = np.random.default_rng(7)
    n = 40_000  # relative standard error of the RMS: 1/sqrt(2n) = 0.35 %
    truth = plane_normal(slope, azimuth_deg)
    fit = fit_points(points_on_plane(truth, n, 30.0, rng, sigma))
    assert fit.rms_m == pytest.approx(sigma, rel=0.03)
    # normal error of a TLS fit: σ / (RMS in-plane extent · sqrt(n)), extent 30/sqrt(3) m; 6 standard errors
    assert angle_rad(fit.normal, truth) < 6.0 * sigma / (30.0 / math.sqrt(3.0) * math.sqrt(n))


def test_two_layers_at_plus_minus_d_give_rms_d():
    """Half the points at +d, half at −d along the normal: the TLS plane is the mid-plane, RMS = d."""
    rng = np.random.default_rng(3)
    truth = plane_normal(0.20, 120.0)
    base = points_on_plane(truth, 1000, 40.0, rng)
    d = 0.037
    layered = np.concatenate([base + d * truth, base - d * truth])  # each point twice: exactly symmetric
    fit = fit_points(layered)
    assert fit.rms_m == pytest.approx(d, rel=1e-6)
    assert angle_rad(fit.normal, truth) < 1e-6
    assert np.allclose(np.abs(residuals(layered, fit)), d, rtol=1e-5)


def test_plane_moments_fit_groups_and_fit_points_agree():
    rng = np.random.default_rng(11)
    clouds = [points_on_plane(plane_normal(s, a), 3000, 20.0, rng, sig)
              for s, a, sig in ((0.0, 0.0, 0.01), (0.2, 45.0, 0.05), (0.7, 300.0, 0.002))]
    xyz = np.concatenate(clouds)
    labels = np.repeat(np.arange(3), 3000)
    order = rng.permutation(len(xyz))
    xyz, labels = xyz[order], labels[order]

    moments = PlaneMoments(np.array([c[0] for c in clouds]))
    for chunk in np.array_split(np.arange(len(xyz)), 7):  # sums combine across chunks
        moments.add(xyz[chunk], labels[chunk])
    by_moments = moments.fits()
    by_groups = fit_groups(xyz, labels)
    for g, cloud in enumerate(clouds):
        direct = fit_points(cloud, plane_id=g)
        for other in (by_moments[g], by_groups[g]):
            assert other.plane_id == g and other.n == direct.n == 3000
            assert angle_rad(other.normal, direct.normal) < 1e-9
            assert other.rms_m == pytest.approx(direct.rms_m, rel=1e-6)
            assert np.allclose(other.centroid, direct.centroid, atol=5e-8, rtol=0)  # float64 sums: ~1e-15 of 3.4e6 m
    expected = math.sqrt(sum(fit_points(c).rms_m ** 2 for c in clouds) / 3)  # equal counts
    assert pooled_rms(by_groups) == pytest.approx(expected, rel=1e-12)


def test_fit_groups_skips_negative_labels_and_small_groups():
    rng = np.random.default_rng(5)
    xyz = points_on_plane(plane_normal(0.2, 10.0), 100, 5.0, rng, 0.01)
    labels = np.full(100, -1)
    labels[:50] = 4
    labels[50:52] = 1  # two points: too few for a plane
    fits = fit_groups(xyz, labels)
    assert [f.plane_id for f in fits] == [4]
    assert fits[0].n == 50
    assert fits[0].rms_m == pytest.approx(fit_points(xyz[:50]).rms_m, rel=1e-9)
    count, centroid, _ = group_moments(xyz, labels)
    assert list(count) == [0, 2, 0, 0, 50]
    assert np.allclose(centroid[4], xyz[:50].mean(axis=0), atol=1e-9, rtol=0)
    assert fit_groups(xyz, np.full(100, -1)) == []


def test_fit_points_needs_three_points():
    with pytest.raises(ValueError, match="at least 3"):
        fit_points(np.zeros((2, 3)))


def test_level_plane_has_no_azimuth_and_steep_plane_pitch():
    flat = fit_points(np.array([[0, 0, 5.0], [1, 0, 5.0], [0, 1, 5.0], [1, 1, 5.0]]))
    assert flat.pitch_deg == pytest.approx(0.0, abs=1e-12) and math.isnan(flat.azimuth_deg)
    wall = fit_points(np.array([[0, 0, 0.0], [0, 1, 0.0], [0, 0, 1.0], [0, 1, 1.0]]))  # the plane x = 0
    assert wall.pitch_deg == pytest.approx(90.0, abs=1e-9)
    assert wall.azimuth_deg % 180.0 == pytest.approx(90.0, abs=1e-9)  # faces east or west


def test_the_batched_fits_are_each_planes_own_fit_bit_for_bit():
    """PlaneMoments.fits decomposes every plane's covariance in one batched call: the numbers of fit(p), one plane
    at a time, to the last bit (a sweep's rows and the pins rest on them); planes under min_points left out."""
    rng = np.random.default_rng(5)
    slopes = rng.uniform(0.0, 1.5, 40)
    clouds = [points_on_plane(plane_normal(s, a), int(k), 30.0, rng, sig) for s, a, sig, k in
              zip(slopes, rng.uniform(0, 360, 40), rng.uniform(0.0, 0.1, 40), rng.integers(1, 400, 40))]
    moments = PlaneMoments(np.array([c[0] for c in clouds]) + rng.normal(0.0, 5.0, (40, 3)))
    moments.add(np.concatenate(clouds), np.repeat(np.arange(40), [len(c) for c in clouds]))
    batched = moments.fits(min_points=5)
    expected = [moments.fit(p) for p in range(40) if len(clouds[p]) >= 5]
    assert len(batched) == len(expected) < 40
    for a, b in zip(batched, expected):
        assert (a.plane_id, a.n, a.rms_m) == (b.plane_id, b.n, b.rms_m)
        assert np.array_equal(a.normal, b.normal) and np.array_equal(a.centroid, b.centroid)
    assert PlaneMoments(np.zeros((2, 3))).fits() == []
