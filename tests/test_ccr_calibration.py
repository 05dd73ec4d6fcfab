"""Corner-cube (CCR) calibration of a spaceborne single-photon altimeter (flightsim.calibration)
against closed forms and injected truth.

Closed forms used:
- A nadir beam tilted by δ from altitude H moves its ground point by H·tan δ: 500 km and 1″
  give 500e3·tan(π/648000) = 2.4240684 m (the patent's "about 2.5 m").
- Two circles (c1, r1), (c2, r2) have their external common tangents through the external centre
  of similitude (r2·c1 − r1·c2)/(r2 − r1) and their internal ones through the internal centre
  (r2·c1 + r1·c2)/(r1 + r2); a tangent's point of tangency T_i has |T_i − c_i| = r_i with T_i − c_i
  perpendicular to the line. Equal circles r = 1 at (0, 0) and (4, 0): external tangents y = ±1,
  internal ones through (2, 0) at ±30° to the x axis (sin 30° = r/(D/2)).
- A CCR at distance d from the footprint centre line, passed at shot spacing Δ, is detected on shot
  k with p_k = 1 − exp(−N0·exp(−2(x_k² + d²)/w²)) (the synthetic pass's model), so its track holds
  on average Σ p_k shots: the expected count-based track length is Δ·Σ p_k.
- The background photons per shot in a CCR's height window of ±tol are B·2·(2·tol)/c.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from flightsim.calibration import (ARCSEC, Altimeter, Bias, CcrField, Track, calibrate_least_squares,
                                   calibrate_patent, common_tangents, design_field, geolocate, ground_shift_m,
                                   identify_ccr_tracks, measured_range, simulate_pass, theoretical_radius)
from flightsim.calibration import ccr, ccr_likelihood, ccr_lines, ccr_tracks
from flightsim.calibration.geolocation import footprint_centre, footprint_offset
from flightsim.core.errors import InputError

C = 299_792_458.0
H = 500e3
W = 6.5  # e⁻² footprint radius of the synthetic altimeter [m]
TRUTH = Bias(3.0, -2.0, 0.25)  # injected: 3″ along, −2″ across, 0.25 m ranging bias
SHIFT_1_ARCSEC = 2.4240684  # 500e3·tan(1″) [m]
TRACK = Track()
R_TH = theoretical_radius(H, Altimeter().divergence_rad(H))  # ρ·tan(θ/2) = w


def _field(min_triggered: int) -> CcrField:
    design = design_field(W, 2.0, H, min_triggered=min_triggered)
    return CcrField.from_track_frame(TRACK, 100.0 + design.along_m, design.across_m,
                                     np.resize([1.0, 1.5, 2.0], design.n_ccr))


@functools.lru_cache(maxsize=None)
def _pass(min_triggered: int, seed: int, background_hz: float = 1e6):
    field = _field(min_triggered)
    n_shots = int((200.0 + np.ptp(TRACK.to_track_frame(field.positions_m)[0])) / TRACK.spacing_m)
    return simulate_pass(TRACK, field, TRUTH, n_shots, seed=seed,
                         altimeter=Altimeter(background_rate_hz=background_hz))


@functools.lru_cache(maxsize=None)
def _calibrate(min_triggered: int, seed: int, background_hz: float = 1e6):
    p = _pass(min_triggered, seed, background_hz)
    patent = calibrate_patent(TRACK, p.shot, p.range_m, p.field, footprint_radius_m=R_TH)
    lsq = calibrate_least_squares(TRACK, p.shot, p.range_m, p.field, patent.identification,
                                  footprint_radius_m=R_TH, start=patent.coarse.solution.bias)
    return patent, lsq


def _errors(bias: Bias) -> np.ndarray:
    return bias.as_array() - TRUTH.as_array()


# --- 1. geolocation -----------------------------------------------------------------------------


def test_one_arcsecond_moves_the_ground_point_by_h_tan_one_arcsecond():
    assert ground_shift_m(H, 1.0) == pytest.approx(H * math.tan(math.radians(1.0 / 3600.0)), rel=1e-15)
    assert ground_shift_m(H, 1.0) == pytest.approx(SHIFT_1_ARCSEC, abs=1e-7)
    assert 2.42 <= SHIFT_1_ARCSEC <= 2.5  # the patent's "about 2.5 m"
    track = Track(azimuth_deg=30.0, origin_m=(100.0, -50.0))
    forward = np.array([math.sin(math.radians(30.0)), math.cos(math.radians(30.0))])
    right = np.array([forward[1], -forward[0]])
    nominal = footprint_centre(track, [10.0], 0.0)[0]
    along = footprint_centre(track, [10.0], 0.0, Bias(along_arcsec=1.0))[0] - nominal
    across = footprint_centre(track, [10.0], 0.0, Bias(across_arcsec=1.0))[0] - nominal
    np.testing.assert_allclose(along[:2], SHIFT_1_ARCSEC * forward, atol=1e-6)
    np.testing.assert_allclose(across[:2], SHIFT_1_ARCSEC * right, atol=1e-6)
    assert nominal[:2] == pytest.approx(track.origin_m + 7.0 * forward, abs=1e-9)  # shot 10 at 0.7 m


def test_geolocation_inverts_the_measured_range():
    bias = Bias(4.0, -7.0, 0.4)
    shots = np.array([0.0, 5.0, 123.5])
    target = footprint_centre(TRACK, shots, 12.0, bias)  # points on the biased beam axis
    rho = measured_range(TRACK, shots, target, bias)
    np.testing.assert_allclose(rho, np.linalg.norm(target - TRACK.position(shots), axis=1) + 0.4, rtol=0, atol=1e-9)
    np.testing.assert_allclose(geolocate(TRACK, shots, rho, bias), target, rtol=0, atol=1e-7)
    # the nominal model misplaces them by the pointing shift and the ranging bias
    off = geolocate(TRACK, shots, rho) - target
    np.testing.assert_allclose(off[:, 0], -ground_shift_m(H - 12.0, -7.0) / math.cos(4 * ARCSEC), rtol=1e-6)
    np.testing.assert_allclose(off[:, 1], -ground_shift_m(H - 12.0, 4.0), rtol=1e-6)
    np.testing.assert_allclose(off[:, 2], -0.4, atol=1e-3)


# --- 2. common tangents of two circles ----------------------------------------------------------


def _check_tangents(c1, r1, c2, r2, expected_count):
    t = common_tangents(c1, r1, c2, r2)
    assert len(t.kinds) == expected_count
    direction = np.column_stack([np.sin(np.radians(t.azimuth_deg)), np.cos(np.radians(t.azimuth_deg))])
    for p, c, r in ((t.point1_en, c1, r1), (t.point2_en, c2, r2)):
        np.testing.assert_allclose(np.linalg.norm(p - c, axis=1), r, atol=1e-9)
        np.testing.assert_allclose(np.sum((p - c) * direction, axis=1), 0.0, atol=1e-9)  # radius ⟂ line
    chord = t.point2_en - t.point1_en
    np.testing.assert_allclose(chord[:, 0] * direction[:, 1] - chord[:, 1] * direction[:, 0], 0.0, atol=1e-9)
    similitude = {"external": (r2 * np.asarray(c1) - r1 * np.asarray(c2)) / (r2 - r1) if r1 != r2 else None,
                  "internal": (r2 * np.asarray(c1) + r1 * np.asarray(c2)) / (r1 + r2)}
    for i, kind in enumerate(t.kinds):
        s = similitude[kind]
        if s is not None:
            v = s - t.point1_en[i]
            assert abs(v[0] * direction[i, 1] - v[1] * direction[i, 0]) < 1e-8  # the line passes through it
    return t


def test_common_tangents_of_two_equal_circles_closed_form():
    t = _check_tangents((0.0, 0.0), 1.0, (4.0, 0.0), 1.0, 4)
    assert t.kinds == ("external", "external", "internal", "internal")
    np.testing.assert_allclose(t.azimuth_deg[:2], 90.0, atol=1e-12)
    np.testing.assert_allclose(sorted(np.abs(t.point1_en[:2, 1])), [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(sorted(t.azimuth_deg[2:]), [60.0, 120.0], atol=1e-12)


@pytest.mark.parametrize("seed", range(20))
def test_common_tangents_against_independent_construction(seed):
    rng = np.random.default_rng(seed)
    c1, c2 = rng.uniform(-50, 50, 2), rng.uniform(-50, 50, 2)
    dist = float(np.linalg.norm(c2 - c1))
    r1, r2 = rng.uniform(0.01, 0.45 * dist, 2)
    _check_tangents(c1, r1, c2, r2, 4)  # apart
    _check_tangents(c1, r1, c2, dist - r1, 3)  # touching outside: the two internal tangents are one
    _check_tangents(c1, r1, c2, dist, 2)  # crossing: external tangents only
    _check_tangents(c1, dist + r2, c2, r2, 1)  # touching inside
    _check_tangents(c1, dist + r2 + 1.0, c2, r2, 0)  # one inside the other


def test_exact_chords_put_the_centroids_on_the_centre_line():
    line = ccr_lines.Line(np.array([10.0, -5.0]), 20.0)
    rng = np.random.default_rng(1)
    s, d = rng.uniform(-300, 300, 12), rng.uniform(-0.95, 0.95, 12) * W
    en = line.point_en + s[:, None] * line.direction + d[:, None] * line.normal
    field = CcrField(np.column_stack([en, np.ones(12)]), np.ones(12))
    x = np.arange(-W, W, 1e-4)  # brute-force chord: where a footprint of radius W centred on the line covers the CCR
    chords = [np.ptp(x[np.hypot(x, di) <= W]) for di in d]
    tracks = [ccr_tracks.CcrTrack(j, np.zeros(0, int), 0, 0, chords[j], 0.0, 1.0, 0.0) for j in range(12)]
    np.testing.assert_allclose(ccr.centroid_circle_radius(chords, W), np.abs(d), atol=0.02)
    centroids = ccr.footprint_centroids(field, tracks, W, line)
    np.testing.assert_allclose(line.signed_distance(centroids), 0.0, atol=0.02)
    np.testing.assert_allclose((centroids - line.point_en) @ line.direction, s, atol=1e-9)


def test_exact_control_points_give_the_exact_pointing():
    p = _pass(8, 0)
    ident = identify_ccr_tracks(TRACK, p.shot, p.range_m, p.field, footprint_radius_m=R_TH)
    mid = np.array([t.mid_shot for t in ident.tracks])
    up = p.field.positions_m[[t.ccr for t in ident.tracks], 2]
    exact = footprint_centre(TRACK, mid, up, TRUTH)[:, :2]
    solution = ccr.solve_bias(TRACK, p.shot, p.range_m, p.field, ident.tracks, exact)
    np.testing.assert_allclose(_errors(solution.bias)[:2], 0.0, atol=1e-6)
    assert abs(_errors(solution.bias)[2]) < 3 * solution.sigma[2] < 0.02


# --- 3. calibration of a synthetic pass ---------------------------------------------------------


def test_identification_finds_each_ccr_track():
    p = _pass(16, 0)
    ident = identify_ccr_tracks(TRACK, p.shot, p.range_m, p.field, footprint_radius_m=R_TH)
    ccr_photons = p.source >= 0
    assert len(ident.tracks) >= 16
    assert np.mean(ident.labels[ccr_photons] == p.source[ccr_photons]) > 0.9
    labelled = ident.labels >= 0
    assert np.mean(p.source[labelled] == ident.labels[labelled]) > 0.98
    for t in ident.tracks:
        assert t.height_above_ground_m == pytest.approx(p.field.heights_m[t.ccr], abs=0.1)


def test_candidates_are_the_closest_in_height_among_the_matching_ccrs():
    """Each photon's candidate, by the definition taken photon by photon over every CCR in reach."""
    p = _pass(16, 1)
    reach, tol, window = 30.0 + 1.5 * R_TH, 0.4, 150.0
    height = geolocate(TRACK, p.shot, p.range_m)[:, 2]
    labels, grounds, _ = ccr_tracks._candidates(TRACK, p.shot, height, p.field, reach, tol, window)
    along = p.shot * TRACK.spacing_m
    ccr_along, ccr_across = TRACK.to_track_frame(p.field.positions_m)
    expected, best = np.full(p.shot.size, -1), np.full(p.shot.size, np.inf)
    for j in np.flatnonzero(np.abs(ccr_across) <= reach):
        ground = ccr_tracks._ground_level(height[np.abs(along - ccr_along[j]) <= window])
        assert grounds[j] == ground
        for i in np.flatnonzero(np.abs(along - ccr_along[j]) <= reach):
            m = abs(height[i] - ground - p.field.heights_m[j])
            if m <= tol and m < best[i]:
                expected[i], best[i] = j, m
    assert np.count_nonzero(expected >= 0) > 100
    np.testing.assert_array_equal(labels, expected)


def test_photon_rate_recomputes_the_offsets_when_the_pointing_moves():
    """The likelihood's rate keeps footprint offsets per pointing: a sequence of parameters that
    returns to an earlier pointing with another radius gives, every time, the rate of its own x."""
    p = _pass(16, 0)
    shots = np.arange(0, 2000, 7)
    points = p.field.positions_m[np.arange(shots.size) % p.field.positions_m.shape[0]]
    rate = ccr_likelihood._PhotonRate(TRACK, shots, points)
    for x in ([0.0, 0.0, 6.5, 2.0, -4.0], [3.0, -2.0, 6.5, 2.0, -4.0], [3.0, -2.0, 7.0, 1.0, -3.0],
              [0.0, 0.0, 5.0, 2.5, -4.0], [3.0, -2.5, 6.5, 2.0, -4.0], [0.0, 0.0, 6.0, 2.0, -5.0]):
        r = footprint_offset(TRACK, shots, points, Bias(x[0], x[1]))
        expected = np.exp(x[3] - 2.0 * (r / x[2]) ** 2) + np.exp(x[4])
        np.testing.assert_array_equal(rate(np.array(x)), expected)


def test_track_length_against_the_footprint_chord():
    n0, spacing = Altimeter().ccr_photons_per_shot, TRACK.spacing_m
    shift_along = ground_shift_m(H, TRUTH.along_arcsec)
    shift_across = ground_shift_m(H, TRUTH.across_arcsec) / math.cos(TRUTH.along_arcsec * ARCSEC)
    differences = []
    for seed in range(3):
        p = _pass(16, seed, 0.0)
        ident = identify_ccr_tracks(TRACK, p.shot, p.range_m, p.field, footprint_radius_m=R_TH)
        along, across = TRACK.to_track_frame(p.field.positions_m)
        x = np.arange(p.shot.max() + 1) * spacing + shift_along
        for t in ident.tracks:
            d = across[t.ccr] - shift_across
            pk = 1.0 - np.exp(-n0 * np.exp(-2.0 * ((x - along[t.ccr]) ** 2 + d * d) / W**2))
            differences.append(t.length_m - spacing * pk.sum())
    assert len(differences) > 50
    assert abs(np.mean(differences)) < 0.5  # standard error ≈ 0.2 m
    assert np.sqrt(np.mean(np.square(differences))) < 2.0


@pytest.mark.parametrize("seed", range(3))
def test_both_methods_recover_the_injected_biases(seed):
    patent, lsq = _calibrate(16, seed)
    for bias in (patent.bias, lsq.bias):
        err = _errors(bias)
        assert np.all(np.abs(err[:2]) <= 0.2), err  # ≤ 0.2″ (0.48 m on the ground)
        assert abs(err[2]) <= 0.02, err  # ≤ 2 cm
    coarse = _errors(patent.coarse.solution.bias)
    assert np.all(np.abs(coarse[:2]) < R_TH / SHIFT_1_ARCSEC)  # within a footprint radius
    assert patent.coarse_line.azimuth_deg == pytest.approx(0.0, abs=1e-4) or \
        patent.coarse_line.azimuth_deg == pytest.approx(180.0, abs=1e-4)
    assert patent.radius.radii_m[1] - patent.radius.radii_m[0] == pytest.approx(0.1)
    assert lsq.footprint_radius_m == pytest.approx(W, rel=0.15)
    assert lsq.ccr_photons_per_shot == pytest.approx(math.e**2, rel=0.5)


def test_least_squares_uncertainties_match_the_scatter():
    n = 24
    z = [_errors(lsq.bias) / lsq.sigma for lsq in (_calibrate(8, seed)[1] for seed in range(n))]
    chi2 = np.mean(np.square(z), axis=0)  # χ²₂₄/24: 1 on average, in [0.41, 1.90] with 99% probability
    assert np.all((chi2 > 0.41) & (chi2 < 1.90)), chi2
    assert np.all(np.abs(np.mean(z, axis=0)) < 4.0 / math.sqrt(n)), np.mean(z, axis=0)  # no bias: 4 SE


# --- 4. accuracy against the number of CCRs and the background -----------------------------------


def _rms_pointing(min_triggered, background_hz, method):
    err = [_errors(_calibrate(min_triggered, seed, background_hz)[method].bias)[:2] for seed in range(8)]
    return float(np.sqrt(np.mean(np.square(err))))


def test_more_ccrs_give_smaller_errors():
    for method in (0, 1):  # patent, least squares
        few, many = _rms_pointing(2, 1e6, method), _rms_pointing(8, 1e6, method)
        assert many < 0.8 * few, (method, few, many)
    sigma_few = np.mean([_calibrate(2, s)[1].sigma[:2] for s in range(8)])
    sigma_many = np.mean([_calibrate(8, s)[1].sigma[:2] for s in range(8)])
    assert sigma_many < 0.8 * sigma_few


def test_background_rate():
    for rate in (1e6, 2e7):
        lsq = [_calibrate(8, s, rate)[1] for s in range(8)]
        expected = rate * 2.0 * (2.0 * 0.4) / C  # photons per shot in a ±0.4 m height window
        assert np.median([f.background_per_shot for f in lsq]) == pytest.approx(expected, rel=0.3)
        assert _rms_pointing(8, rate, 1) < 0.12
    # the patent's track lengths take in background photons: its error grows with the rate
    assert _rms_pointing(8, 2e7, 0) > _rms_pointing(8, 1e6, 0)


# --- field design ---------------------------------------------------------------------------------


@pytest.mark.parametrize("m", [2, 3, 5, 8])
def test_field_design_triggers_at_least_m_ccrs(m):
    design = design_field(W, 2.0, H, min_triggered=m)
    u = H * math.tan(3 * 2.0 * ARCSEC)
    assert design.across_spacing_m == pytest.approx(2 * 0.9 * W / (m + 1))
    assert design.along_spacing_m == pytest.approx(2 * (1.5 * W + u))
    for y in np.linspace(-u, u, 2001):  # wherever the centre line falls within 3σ
        assert np.sum(np.abs(design.across_m - y) < 0.9 * W) >= m


# --- 5. bad input -----------------------------------------------------------------------------------


def test_bad_input_names_the_argument():
    p = _pass(8, 0)
    ground_only = p.source < 0
    with pytest.raises(InputError, match="range_m"):
        identify_ccr_tracks(TRACK, p.shot[ground_only], p.range_m[ground_only], p.field, footprint_radius_m=R_TH)
    patent = _calibrate(8, 0)[0]
    with pytest.raises(InputError, match="tracks"):
        ccr.best_centre_line(p.field, patent.identification.tracks[:1], R_TH, TRACK.spacing_m, patent.coarse_line)
    with pytest.raises(InputError, match="radii_m"):
        calibrate_patent(TRACK, p.shot, p.range_m, p.field, footprint_radius_m=R_TH, radii_m=[])
    with pytest.raises(InputError, match="centre2"):
        common_tangents((1.0, 2.0), 1.0, (1.0, 2.0), 2.0)
    with pytest.raises(InputError, match="min_triggered"):
        design_field(W, 2.0, H, min_triggered=1)
