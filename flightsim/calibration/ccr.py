"""Corner-cube (CCR) calibration of a spaceborne single-photon altimeter's pointing and ranging
(float64 NumPy/SciPy), after ``seeds/corner-cube-single-photon-calibration-patent.txt``.

The photons are plain arrays (shot index, measured range) and the CCRs known points in the local
frame of :mod:`.geolocation` (east, north, up [m]); every function geolocates with that module's
reduced eq. (1). The patent's method, one function per step, each returning what it found:

1. :func:`.ccr_tracks.identify_ccr_tracks` — which CCR each CCR photon track belongs to (the ranges of the CCR
   photons against the ground photons' give their height above ground, matched to the CCRs' true
   heights; the flight direction orders the CCRs along track) [patent ¶5, claim 2];
2. :func:`coarse_calibration` — the CCR with the longest photon track is the best one; taking the
   footprint centre as passing over it gives a coarse calibration [¶4, claim 1];
3. :func:`coarse_centre_line` — the photons re-geolocated with it give the coarse footprint centre
   line, whose azimuth is taken as the true one [¶4, ¶7];
4. :func:`.ccr_lines.common_tangents`, :func:`best_centre_line` — a CCR whose photon track is L long lies
   d = √(R² − (L/2)²) from the footprint centre line (the chord of a footprint of radius R), so the
   line is tangent to the "CCR centroid circle" of radius d about the CCR; of the four common
   tangents of two CCRs' circles the one closest in azimuth to the coarse line is kept [¶6–7, ¶11];
   :func:`footprint_centroids` then puts each CCR's footprint centroid on it [¶12–16];
5. :func:`iterate_radius` — the radius R runs over a set around R = ρ·tan(θ/2) in 0.1 m steps
   (:func:`radius_set`); each radius's centroids are fitted with a line and the one closest in
   azimuth to the coarse line gives the fine centroids [¶8–9];
6. :func:`solve_bias` — the fine centroids are ground control points of eq. (1): the pointing
   (and ranging) correction is their least-squares solution [¶4, ¶17–19].

:func:`calibrate_patent` runs all six. :func:`.ccr_likelihood.calibrate_least_squares` is a generic
estimator of the same three parameters from the same photons (the maximum likelihood of every searched
shot's count of CCR photons, and of the CCR photons' ranges), with Fisher-information covariances.
:func:`.ccr_field.design_field` sizes a CCR field (:class:`.ccr_field.CcrField`).

The source text lost its formula images: the centroid formula (¶13) is reconstructed from the
definitions around it (the CCR moved by its centroid-circle radius d perpendicular to the line,
towards it), and the bounds of the radius set (¶9) are a parameter here (half-width 0.4·R).
Where the patent is silent, chosen here: a track's length counts the shots holding its photons
(its two ends are its noisiest part), its middle is its photons' mean shot, and steps 4–6 weight
each centroid by the precision its track length gives it (:func:`centroid_weights`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from flightsim.calibration.ccr_field import CcrField
from flightsim.calibration.ccr_lines import Line, Tangents, axial_difference_deg, common_tangents, fit_line
from flightsim.calibration.ccr_tracks import CcrTrack, Identification, identify_ccr_tracks
from flightsim.calibration.geolocation import Bias, Shots, Track, geolocate, photon_arrays
from flightsim.core.errors import InputError

RADIUS_STEP_M = 0.1  # step of the footprint radius set [m] (patent ¶9)
_ROUND_OFF_M = 1e-9  # least residual scatter of a least-squares fit [m]


# --- steps 2 and 6: ground control points in eq. (1) ----------------------------------------------


@dataclass(frozen=True)
class BiasSolution:
    """Least-squares pointing and ranging bias from ground control points (steps 2 and 6)."""

    bias: Bias
    covariance: np.ndarray  # (3, 3) of (δa [arcsec], δc [arcsec], b [m]); NaN where not estimable
    residual_en_m: np.ndarray  # (m, 2) footprint centre − control point, E N or along-across the line (weighted) [m]
    residual_up_m: np.ndarray  # (n,) CCR photons' heights minus their CCR's [m]

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations of (δa [arcsec], δc [arcsec], b [m])."""
        return np.sqrt(np.diag(self.covariance))


def _gcp_residuals(track, shot, range_m, field, tracks, centroids_en, line, weights):
    """The residual function x ↦ (horizontal (m, 2), vertical (n,)) of :func:`solve_bias`."""
    mid = Shots(track, [t.mid_shot for t in tracks])
    up = field.positions_m[[t.ccr for t in tracks], 2]
    photons = np.concatenate([t.photons for t in tracks])
    photon_shot, photon_range = photon_arrays(shot[photons], range_m[photons])
    photon_shots = Shots(track, photon_shot)
    photon_up = np.concatenate([np.full(t.photons.size, field.positions_m[t.ccr, 2]) for t in tracks])
    axes = np.eye(2) if line is None else np.array([line.direction, line.normal]).T

    def residuals(x):
        bias = Bias.from_array(x)
        en = mid.centre(up, bias)[:, :2] - centroids_en
        vertical = photon_shots.locate(photon_range, bias)[:, 2] - photon_up
        return (en @ axes) * weights, vertical

    return residuals


def _group_covariance(groups) -> np.ndarray:
    """(Σ_g J_gᵀJ_g / s_g²)⁻¹ over residual groups (r_g, J_g), s_g² = |r_g|²/(n_g − 1) each group's
    own variance (one parameter per group; at least (1 nm)², an exact fit's round-off); NaN if a
    group has no redundancy."""
    information = np.zeros((3, 3))
    for r, jac in groups:
        if r.size < 2:
            return np.full((3, 3), np.nan)
        information += jac.T @ jac / max(float(r @ r) / (r.size - 1), _ROUND_OFF_M**2)
    return np.linalg.inv(information)


def centroid_weights(tracks, radius_m: float, spacing_m: float) -> np.ndarray:
    """Relative weights 1/σ (m, 2) of the footprint centroids along and across the centre line.

    Along: the footprint's Gaussian edge makes a track's ends the softer the shorter the chord,
    σ ∝ 1/(L/2). Across: first-order propagation through d = √(R² − (L/2)²) of the errors of the
    half-length and of the radius, taken alike, σ_d ∝ √((L/2)² + R²)/d; near the line the first
    order fails (d = √(2R·ε) for a half-length ε short of R), so d is floored at √(2R·Δ), Δ the
    shot spacing. A CCR on the line says little across it.
    """
    half = 0.5 * np.array([t.length_m for t in tracks])
    d = np.maximum(centroid_circle_radius(2.0 * half, radius_m), math.sqrt(2.0 * radius_m * spacing_m))
    return np.column_stack([half / radius_m, d / np.hypot(half, radius_m)])


def solve_bias(track: Track, shot, range_m, field: CcrField, tracks, centroids_en,
               start: Bias = Bias(), line: Line | None = None, weights=None) -> BiasSolution:
    """Step 6 (and step 2): the biases whose eq. (1) puts each track's footprint centre, at its
    middle shot and the CCR's height, on its control point ``centroids_en`` (m, 2) [m], and the
    CCR photons at their CCR's height (patent ¶4, ¶17–19).

    With a centre ``line``, the horizontal residuals are taken along and across it, scaled by
    ``weights`` (m, 2) (:func:`centroid_weights`); else east and north, unweighted. The pointing
    comes from the horizontal residuals, the ranging from the vertical ones (their coupling is of
    order the pointing angle squared). Covariance: :func:`_group_covariance` of the three groups
    (horizontal components, vertical); NaN with one CCR, where nothing is redundant.
    """
    centroids_en = np.asarray(centroids_en, dtype=np.float64).reshape(-1, 2)
    if len(tracks) == 0 or len(centroids_en) != len(tracks):
        raise InputError("centroids_en", f"{len(centroids_en)} points", f"one per track ({len(tracks)})")
    weights = np.ones((len(tracks), 2)) if weights is None else np.asarray(weights, dtype=np.float64)
    residuals = _gcp_residuals(track, np.asarray(shot), np.asarray(range_m, dtype=np.float64),
                               field, tracks, centroids_en, line, weights)
    fit = least_squares(lambda x: np.concatenate([r.ravel() for r in residuals(x)]), start.as_array(),
                        x_scale=np.array([1.0, 1.0, 0.1]), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    r_en, r_up = residuals(fit.x)
    m = len(tracks)
    jac_en = fit.jac[: 2 * m].reshape(m, 2, 3)
    cov = _group_covariance([(r_en[:, 0], jac_en[:, 0]), (r_en[:, 1], jac_en[:, 1]), (r_up, fit.jac[2 * m:])])
    return BiasSolution(Bias.from_array(fit.x), cov, r_en, r_up)


@dataclass(frozen=True)
class CoarseCalibration:
    """Step 2's result: the best CCR's track and the coarse biases it gives."""

    best: CcrTrack
    solution: BiasSolution


def coarse_calibration(track: Track, shot, range_m, field: CcrField,
                       identification: Identification) -> CoarseCalibration:
    """Step 2: the CCR with the longest photon track is the best one; the footprint centre at its
    track's middle is taken to be the CCR itself (patent ¶4)."""
    best = max(identification.tracks, key=lambda t: t.length_m)
    solution = solve_bias(track, shot, range_m, field, [best], field.positions_m[best.ccr, :2])
    return CoarseCalibration(best, solution)


# --- step 3: coarse centre line -------------------------------------------------------------------


def coarse_centre_line(track: Track, shot, range_m, bias: Bias) -> Line:
    """Step 3: the footprint centre line, fitted to every photon re-geolocated with the coarse
    biases (patent ¶4); its azimuth stands for the true azimuth (¶7)."""
    return fit_line(geolocate(track, shot, range_m, bias)[:, :2])[0]


# --- step 4: the centre line, tangent to two CCR centroid circles ---------------------------------


def centroid_circle_radius(length_m, radius_m: float) -> np.ndarray:
    """Distance d = √(R² − (L/2)²) of a CCR from the centre line of footprints of radius R whose
    chord over it is the photon track length L (0 where L > 2R) [m]."""
    half = 0.5 * np.asarray(length_m, dtype=np.float64)
    return np.sqrt(np.maximum(radius_m**2 - half**2, 0.0))


def footprint_centroids(field: CcrField, tracks, radius_m: float, line: Line) -> np.ndarray:
    """Each track's footprint centroid (m, 2) [m]: its CCR moved by the centroid-circle radius d
    perpendicular to ``line``, towards it (patent ¶11–16)."""
    ccr = field.positions_m[[t.ccr for t in tracks], :2]
    d = centroid_circle_radius([t.length_m for t in tracks], radius_m)
    side = np.where(line.signed_distance(ccr) < 0.0, -1.0, 1.0)
    return ccr - (side * d)[:, None] * line.normal


@dataclass(frozen=True)
class CentreLineChoice:
    """Step 4's result."""

    pair: tuple[int, int]  # the two tracks (indices into the track list)
    radii_m: tuple[float, float]  # their centroid-circle radii [m]
    tangents: Tangents
    azimuth_difference_deg: np.ndarray  # of each tangent from the coarse line [deg]
    chosen: int
    line: Line


def _default_pair(field: CcrField, tracks, radius_m: float, spacing_m: float) -> tuple[int, int]:
    """The two tracks maximising D·wᵢ·wⱼ: D their CCRs' distance, w their :func:`centroid_weights`."""
    en = field.positions_m[[t.ccr for t in tracks], :2]
    w = centroid_weights(tracks, radius_m, spacing_m)[:, 1]
    score = np.linalg.norm(en[:, None] - en[None], axis=-1) * w[:, None] * w[None]
    i, j = np.unravel_index(np.argmax(score), score.shape)
    return (int(min(i, j)), int(max(i, j))) if i != j else (0, len(tracks) - 1)


def best_centre_line(field: CcrField, tracks, radius_m: float, spacing_m: float, coarse_line: Line,
                     pair: tuple[int, int] | None = None) -> CentreLineChoice:
    """Step 4: of the common tangents of two tracks' CCR centroid circles, the one whose azimuth
    is closest to the coarse centre line's (patent ¶4, ¶6–7). Any two triggered CCRs will do;
    ``pair`` defaults to the best conditioned (:func:`_default_pair`): far apart, and neither on
    the line (d ≈ 0, no information across it) nor with an over-long track.

    Raises:
        InputError: fewer than two tracks (``tracks``), or a bad ``pair``.
    """
    if len(tracks) < 2:
        raise InputError("tracks", f"{len(tracks)} CCR track(s)", "at least two triggered CCRs")
    i, j = _default_pair(field, tracks, radius_m, spacing_m) if pair is None else pair
    if not (0 <= i < len(tracks) and 0 <= j < len(tracks) and i != j):
        raise InputError("pair", pair, f"two different track indices in [0, {len(tracks)})")
    r = centroid_circle_radius([tracks[i].length_m, tracks[j].length_m], radius_m)
    tangents = common_tangents(field.positions_m[tracks[i].ccr, :2], r[0],
                               field.positions_m[tracks[j].ccr, :2], r[1])
    diff = axial_difference_deg(tangents.azimuth_deg, coarse_line.azimuth_deg)
    chosen = int(np.argmin(np.abs(diff)))
    return CentreLineChoice((i, j), (float(r[0]), float(r[1])), tangents, diff, chosen,
                            tangents.line(chosen))


# --- step 5: radius iteration ---------------------------------------------------------------------


def radius_set(radius_m: float, half_width_m: float) -> np.ndarray:
    """Radii R + k·0.1 m within ±half_width_m of the theoretical radius R, all > 0 [m] (patent ¶9)."""
    n = int(math.floor(half_width_m / RADIUS_STEP_M + 1e-9))
    radii = radius_m + RADIUS_STEP_M * np.arange(-n, n + 1)
    return radii[radii > 0]


@dataclass(frozen=True)
class RadiusIteration:
    """Step 5's result: per radius the fitted line's azimuth, its difference from the coarse
    line's and the centroids' RMS distance from it; the chosen radius and its centroids."""

    radii_m: np.ndarray
    azimuth_deg: np.ndarray
    azimuth_difference_deg: np.ndarray
    rms_m: np.ndarray
    chosen: int
    line: Line
    centroids_en: np.ndarray  # (m, 2) fine footprint centroids [m]

    @property
    def radius_m(self) -> float:
        """The chosen footprint radius [m]."""
        return float(self.radii_m[self.chosen])


def iterate_radius(field: CcrField, tracks, radii_m, spacing_m: float, coarse_line: Line,
                   centre_line: Line) -> RadiusIteration:
    """Step 5: for each radius of ``radii_m`` the footprint centroids (the sides of the CCRs from
    step 4's ``centre_line``) fitted with a line, each weighted by its :func:`centroid_weights`
    across the line; the radius whose line is closest in azimuth to the coarse line gives the
    fine centroids (patent ¶4, ¶8–9).

    Raises:
        InputError: ``radii_m`` empty or not all > 0, or fewer than two tracks.
    """
    radii = np.asarray(radii_m, dtype=np.float64).ravel()
    if radii.size == 0 or not np.all(np.isfinite(radii) & (radii > 0)):
        raise InputError("radii_m", radii.tolist(), "a non-empty set of finite footprint radii > 0 [m]")
    if len(tracks) < 2:
        raise InputError("tracks", f"{len(tracks)} CCR track(s)", "at least two triggered CCRs")
    fits = [fit_line(footprint_centroids(field, tracks, r, centre_line),
                     centroid_weights(tracks, r, spacing_m)[:, 1]) for r in radii]
    azimuth = np.array([f[0].azimuth_deg for f in fits])
    diff = axial_difference_deg(azimuth, coarse_line.azimuth_deg)
    chosen = int(np.argmin(np.abs(diff)))
    return RadiusIteration(radii, azimuth, diff, np.array([f[1] for f in fits]), chosen, fits[chosen][0],
                           footprint_centroids(field, tracks, radii[chosen], centre_line))


# --- the whole method -----------------------------------------------------------------------------


@dataclass(frozen=True)
class PatentCalibration:
    """Every step's result; ``fine.bias`` is the calibration."""

    identification: Identification
    coarse: CoarseCalibration
    coarse_line: Line
    centre_line: CentreLineChoice
    radius: RadiusIteration
    fine: BiasSolution

    @property
    def bias(self) -> Bias:
        return self.fine.bias


def calibrate_patent(track: Track, shot, range_m, field: CcrField, *, footprint_radius_m: float,
                     radii_m=None, pair: tuple[int, int] | None = None,
                     identification: Identification | None = None, **identify) -> PatentCalibration:
    """Steps 1–6 of the patent on one pass.

    Args:
        track: the laser track; shot, range_m: the photons (shot index, measured range [m]).
        field: the known CCRs.
        footprint_radius_m: theoretical radius R = ρ·tan(θ/2) [m] (:func:`.theoretical_radius`).
        radii_m: the radius set of step 5 (default :func:`radius_set` (R, 0.4·R)).
        pair: the two tracks of step 4 (default: see :func:`best_centre_line`).
        identification: step 1's result, if already run; else ``identify`` goes to
            :func:`identify_ccr_tracks`.
    """
    shot, range_m = np.asarray(shot), np.asarray(range_m, dtype=np.float64)
    ident = identification or identify_ccr_tracks(track, shot, range_m, field,
                                                  footprint_radius_m=footprint_radius_m, **identify)
    coarse = coarse_calibration(track, shot, range_m, field, ident)
    coarse_line = coarse_centre_line(track, shot, range_m, coarse.solution.bias)
    choice = best_centre_line(field, ident.tracks, footprint_radius_m, track.spacing_m, coarse_line, pair)
    radii = radius_set(footprint_radius_m, 0.4 * footprint_radius_m) if radii_m is None else radii_m
    radius = iterate_radius(field, ident.tracks, radii, track.spacing_m, coarse_line, choice.line)
    fine = solve_bias(track, shot, range_m, field, ident.tracks, radius.centroids_en, coarse.solution.bias,
                      radius.line, centroid_weights(ident.tracks, radius.radius_m, track.spacing_m))
    return PatentCalibration(ident, coarse, coarse_line, choice, radius, fine)
