"""Corner-cube (CCR) calibration of a spaceborne single-photon altimeter's pointing and ranging
(float64 NumPy/SciPy), after ``seeds/corner-cube-single-photon-calibration-patent.txt``.

The photons are plain arrays (shot index, measured range) and the CCRs known points in the local
frame of :mod:`.geolocation` (east, north, up [m]); every function geolocates with that module's
reduced eq. (1). The patent's method, one function per step, each returning what it found:

1. :func:`identify_ccr_tracks` — which CCR each CCR photon track belongs to (the ranges of the CCR
   photons against the ground photons' give their height above ground, matched to the CCRs' true
   heights; the flight direction orders the CCRs along track) [patent ¶5, claim 2];
2. :func:`coarse_calibration` — the CCR with the longest photon track is the best one; taking the
   footprint centre as passing over it gives a coarse calibration [¶4, claim 1];
3. :func:`coarse_centre_line` — the photons re-geolocated with it give the coarse footprint centre
   line, whose azimuth is taken as the true one [¶4, ¶7];
4. :func:`common_tangents`, :func:`best_centre_line` — a CCR whose photon track is L long lies
   d = √(R² − (L/2)²) from the footprint centre line (the chord of a footprint of radius R), so the
   line is tangent to the "CCR centroid circle" of radius d about the CCR; of the four common
   tangents of two CCRs' circles the one closest in azimuth to the coarse line is kept [¶6–7, ¶11];
   :func:`footprint_centroids` then puts each CCR's footprint centroid on it [¶12–16];
5. :func:`iterate_radius` — the radius R runs over a set around R = ρ·tan(θ/2) in 0.1 m steps
   (:func:`radius_set`); each radius's centroids are fitted with a line and the one closest in
   azimuth to the coarse line gives the fine centroids [¶8–9];
6. :func:`solve_bias` — the fine centroids are ground control points of eq. (1): the pointing
   (and ranging) correction is their least-squares solution [¶4, ¶17–19].

:func:`calibrate_patent` runs all six. :func:`calibrate_least_squares` is a generic estimator of
the same three parameters from the same photons (the maximum likelihood of every searched shot's
count of CCR photons, and of the CCR photons' ranges), with Fisher-information covariances.
:func:`design_field` sizes a CCR field.

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
from scipy.stats import poisson

from flightsim.calibration.geolocation import (ARCSEC, Bias, Track, footprint_centre, footprint_offset,
                                               geolocate)
from flightsim.core.errors import InputError

RADIUS_STEP_M = 0.1  # step of the footprint radius set [m] (patent ¶9)
_ROUND_OFF_M = 1e-9  # least residual scatter of a least-squares fit [m]
_TOUCH = 1e-12  # relative tolerance of two circles touching (one tangent where two meet)


@dataclass(frozen=True)
class CcrField:
    """Known CCRs: reflecting points (n, 3) ENU [m] and their heights above the ground [m]."""

    positions_m: np.ndarray
    heights_m: np.ndarray

    def __post_init__(self):
        positions = np.asarray(self.positions_m, dtype=np.float64)
        heights = np.asarray(self.heights_m, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3 or not np.all(np.isfinite(positions)):
            raise InputError("field.positions_m", f"shape {positions.shape}", "finite (n, 3) ENU points [m]")
        if heights.shape != (len(positions),) or not np.all(np.isfinite(heights) & (heights >= 0)):
            raise InputError("field.heights_m", heights.tolist(), f"{len(positions)} finite heights >= 0 [m]")
        object.__setattr__(self, "positions_m", positions)
        object.__setattr__(self, "heights_m", heights)

    def __len__(self) -> int:
        return len(self.positions_m)

    @classmethod
    def from_track_frame(cls, track: Track, along_m, across_m, heights_m, ground_height_m: float = 0.0):
        """CCRs at (along, across) track coordinates [m], ``heights_m`` above flat ground."""
        en = track.from_track_frame(along_m, across_m)
        heights = np.broadcast_to(np.asarray(heights_m, dtype=np.float64), en.shape[:1])
        return cls(np.column_stack([en, ground_height_m + heights]), heights.copy())


# --- lines in the (E, N) plane ------------------------------------------------------------------


def axial_difference_deg(a_deg, b_deg):
    """Difference of two line azimuths (defined modulo 180°), in [−90°, 90°) [deg]."""
    return (np.asarray(a_deg) - np.asarray(b_deg) + 90.0) % 180.0 - 90.0


@dataclass(frozen=True)
class Line:
    """A line in the (E, N) plane: a point on it [m] and its azimuth in [0°, 180°) [deg]."""

    point_en: np.ndarray
    azimuth_deg: float

    @property
    def direction(self) -> np.ndarray:
        """Unit vector along the line, (sin az, cos az)."""
        az = math.radians(self.azimuth_deg)
        return np.array([math.sin(az), math.cos(az)])

    @property
    def normal(self) -> np.ndarray:
        """Unit normal, to the right of :attr:`direction`."""
        d = self.direction
        return np.array([d[1], -d[0]])

    def signed_distance(self, points_en) -> np.ndarray:
        """Distance of points (n, 2) from the line, + on the side of :attr:`normal` [m]."""
        return (np.asarray(points_en, dtype=np.float64)[..., :2] - self.point_en) @ self.normal


def _line_from_direction(point_en, direction_en) -> Line:
    return Line(np.asarray(point_en, dtype=np.float64),
                float(math.degrees(math.atan2(direction_en[0], direction_en[1])) % 180.0))


def fit_line(points_en, weights=None) -> tuple[Line, float]:
    """Total-least-squares line through points (n ≥ 2, 2) [m], each weighted (default 1), and
    the weighted RMS distance of the points from it [m]."""
    p = np.asarray(points_en, dtype=np.float64)[:, :2]
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    centre = (w @ p) / w.sum()
    _, s, vt = np.linalg.svd((p - centre) * np.sqrt(w)[:, None], full_matrices=False)
    rms = s[1] / math.sqrt(w.sum()) if len(s) > 1 else 0.0
    return _line_from_direction(centre, vt[0]), float(rms)


# --- step 1: CCR track identification --------------------------------------------------------


@dataclass(frozen=True)
class CcrTrack:
    """The photon track of one triggered CCR."""

    ccr: int  # index into the field
    photons: np.ndarray  # indices of its photons into the photon arrays
    first_shot: int
    last_shot: int
    length_m: float  # along-track length: shots holding its photons × shot spacing [m]
    mid_shot: float  # mean shot of its photons: the footprint centre's closest approach to the CCR
    height_above_ground_m: float  # median height of its photons over the local ground [m]
    ground_height_m: float  # local ground level of the nominally geolocated photons [m]


@dataclass(frozen=True)
class Identification:
    """Step 1's result: the triggered CCRs' tracks in flight order, each photon's CCR (or −1),
    and what the search looked at (the generic estimator's input)."""

    tracks: tuple[CcrTrack, ...]
    labels: np.ndarray  # (n,) CCR of each photon in a track, or −1
    candidates: np.ndarray  # (n,) CCR whose height and shot window each photon matches, or −1
    windows: dict[int, tuple[int, int]]  # first and last shot searched for each reachable CCR


def _ground_level(heights: np.ndarray) -> float:
    """Mode of photon heights (0.5 m bins), refined by the median within ±1 m of it [m]."""
    edges = np.arange(heights.min(), heights.max() + 1.0, 0.5)
    counts, edges = np.histogram(heights, bins=edges)
    mode = edges[np.argmax(counts)] + 0.25
    return float(np.median(heights[np.abs(heights - mode) <= 1.0]))


def _largest_run(shots: np.ndarray, max_gap_shots: int) -> np.ndarray:
    """Mask of the photons in the run of shots (gaps of at most ``max_gap_shots``) with most photons."""
    order = np.argsort(shots, kind="stable")
    run = np.concatenate([[0], np.cumsum(np.diff(shots[order]) > max_gap_shots + 1)])
    best = np.argmax(np.bincount(run))
    mask = np.zeros(shots.size, dtype=bool)
    mask[order[run == best]] = True
    return mask


def _is_signal(n_run: int, run_shots: int, n_candidates: int, window_shots: int, false_alarm: float) -> bool:
    """Whether n_run photons over run_shots shots are unlikely (< false_alarm) to be background, its
    rate per shot taken from the window's other candidates (at least one)."""
    rate = max(n_candidates - n_run, 1) / max(window_shots - run_shots, 1)
    return bool(poisson.sf(n_run - 1, rate * run_shots) < false_alarm)


def _candidates(track, shot, height, field, reach, height_tol_m, ground_window_m):
    """Each photon's candidate CCR (closest in height among those matching), each CCR's local
    ground level and searched shot window."""
    along = shot * track.spacing_m
    ccr_along, ccr_across = track.to_track_frame(field.positions_m)
    labels, mismatch = np.full(shot.size, -1), np.full(shot.size, np.inf)
    grounds, windows = {}, {}
    for j in np.flatnonzero(np.abs(ccr_across) <= reach):
        near = np.abs(along - ccr_along[j]) <= ground_window_m
        if not near.any():
            continue
        grounds[int(j)] = _ground_level(height[near])
        windows[int(j)] = (math.ceil((ccr_along[j] - reach) / track.spacing_m),
                           math.floor((ccr_along[j] + reach) / track.spacing_m))
        m = np.abs(height - grounds[j] - field.heights_m[j])
        take = (np.abs(along - ccr_along[j]) <= reach) & (m <= height_tol_m) & (m < mismatch)
        labels[take], mismatch[take] = j, m[take]
    return labels, grounds, windows


def identify_ccr_tracks(track: Track, shot, range_m, field: CcrField, *, footprint_radius_m: float,
                        search_m: float = 30.0, height_tol_m: float = 0.4, max_gap_shots: int = 3,
                        min_photons: int = 5, false_alarm: float = 1e-6,
                        ground_window_m: float = 150.0) -> Identification:
    """Step 1: find each triggered CCR's photon track (patent ¶5, claim 2).

    Photons are geolocated with the nominal model; a CCR's candidates are the photons whose height
    over the local ground (the ground photons' mode within ``ground_window_m`` along track: a range
    difference, free of the ranging bias) is within ``height_tol_m`` of the CCR's true height, on
    shots whose nominal footprint passes within ``search_m`` + 1.5·R of it along the flight direction
    (``search_m``: the a priori bound on the footprint's displacement [m]). A photon matching several
    CCRs goes to the closest in height. Each CCR keeps its run of shots (gaps of at most
    ``max_gap_shots``) with the most photons, if it holds ``min_photons`` or more and background
    alone would give as many with probability below ``false_alarm``. The track's length is the
    number of shots holding its photons times the shot spacing.

    Raises:
        InputError: no CCR photon track found (argument ``range_m``).
    """
    shot, range_m = np.asarray(shot), np.asarray(range_m, dtype=np.float64)
    height = geolocate(track, shot, range_m)[:, 2]
    labels, grounds, windows = _candidates(track, shot, height, field, search_m + 1.5 * footprint_radius_m,
                                           height_tol_m, ground_window_m)
    candidates = labels.copy()
    tracks = []
    for j in sorted(windows, key=lambda j: windows[j][0]):
        idx = np.flatnonzero(candidates == j)
        keep = _largest_run(shot[idx], max_gap_shots) if idx.size else np.zeros(0, dtype=bool)
        labels[idx[~keep]] = -1
        idx = idx[keep]
        first, last = (int(shot[idx].min()), int(shot[idx].max())) if idx.size else (0, -1)
        k0, k1 = windows[j]
        n_candidates = int(np.sum(candidates == j))
        if idx.size < min_photons or not _is_signal(idx.size, last - first + 1, n_candidates, k1 - k0 + 1,
                                                    false_alarm):
            labels[idx] = -1
            continue
        tracks.append(CcrTrack(j, idx, first, last, np.unique(shot[idx]).size * track.spacing_m,
                               float(shot[idx].mean()), float(np.median(height[idx]) - grounds[j]),
                               grounds[j]))
    if not tracks:
        raise InputError("range_m", f"{shot.size} photons", "photons returned by at least one CCR of the field")
    return Identification(tuple(tracks), labels, candidates, windows)


# --- steps 2 and 6: ground control points in eq. (1) ---------------------------------------------


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
    mid = np.array([t.mid_shot for t in tracks])
    up = field.positions_m[[t.ccr for t in tracks], 2]
    photons = np.concatenate([t.photons for t in tracks])
    photon_up = np.concatenate([np.full(t.photons.size, field.positions_m[t.ccr, 2]) for t in tracks])
    axes = np.eye(2) if line is None else np.array([line.direction, line.normal]).T

    def residuals(x):
        bias = Bias.from_array(x)
        en = footprint_centre(track, mid, up, bias)[:, :2] - centroids_en
        vertical = geolocate(track, shot[photons], range_m[photons], bias)[:, 2] - photon_up
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


# --- step 3: coarse centre line ------------------------------------------------------------------


def coarse_centre_line(track: Track, shot, range_m, bias: Bias) -> Line:
    """Step 3: the footprint centre line, fitted to every photon re-geolocated with the coarse
    biases (patent ¶4); its azimuth stands for the true azimuth (¶7)."""
    return fit_line(geolocate(track, shot, range_m, bias)[:, :2])[0]


# --- step 4: common tangents of two CCR centroid circles ----------------------------------------


@dataclass(frozen=True)
class Tangents:
    """Common tangent lines of two circles: points of tangency on each and each line's azimuth."""

    point1_en: np.ndarray  # (k, 2) [m]
    point2_en: np.ndarray  # (k, 2) [m]
    normal_en: np.ndarray  # (k, 2) unit normals
    kinds: tuple[str, ...]  # "external" (both circles on one side) or "internal"

    @property
    def azimuth_deg(self) -> np.ndarray:
        """Azimuth of each line in [0°, 180°) [deg]."""
        return np.degrees(np.arctan2(self.normal_en[:, 1], -self.normal_en[:, 0])) % 180.0

    def line(self, i: int) -> Line:
        """Tangent i as a :class:`Line`."""
        n = self.normal_en[i]
        return _line_from_direction(self.point1_en[i], (n[1], -n[0]))


def common_tangents(centre1, radius1: float, centre2, radius2: float) -> Tangents:
    """The common tangents of two circles (patent ¶6): 4 when they are apart, 3 when touching
    outside, 2 when they cross, 1 when touching inside, 0 when one holds the other.

    A line n·x = p (|n| = 1) is tangent to circle i when n·c_i − p = σ_i r_i; with σ1 = 1,
    n·(c2 − c1) = σ2 r2 − r1 fixes n up to the side of the centre line (σ2 = +1: external
    tangents, −1: internal). The points of tangency are c_i − σ_i r_i n.
    """
    c1, c2 = np.asarray(centre1, dtype=np.float64), np.asarray(centre2, dtype=np.float64)
    if not (radius1 >= 0 and radius2 >= 0):
        raise InputError("radius", (radius1, radius2), "two radii >= 0 [m]")
    d = c2 - c1
    dist = math.hypot(*d)
    if dist == 0.0:
        raise InputError("centre2", c2.tolist(), "a centre different from centre1")
    e, e_perp = d / dist, np.array([-d[1], d[0]]) / dist
    p1, p2, normals, kinds = [], [], [], []
    for sigma2, kind in ((1.0, "external"), (-1.0, "internal")):
        cos_t = (sigma2 * radius2 - radius1) / dist
        if abs(cos_t) > 1.0 + _TOUCH:
            continue
        touching = abs(cos_t) >= 1.0 - _TOUCH
        sin_t = 0.0 if touching else math.sqrt(1.0 - cos_t * cos_t)
        for side in ((1.0,) if touching else (1.0, -1.0)):
            n = cos_t * e + side * sin_t * e_perp
            p1.append(c1 - radius1 * n)
            p2.append(c2 - sigma2 * radius2 * n)
            normals.append(n)
            kinds.append(kind)
    return Tangents(np.array(p1).reshape(-1, 2), np.array(p2).reshape(-1, 2),
                    np.array(normals).reshape(-1, 2), tuple(kinds))


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


# --- step 5: radius iteration ----------------------------------------------------------------


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


# --- the whole method ------------------------------------------------------------------------


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


# --- generic estimator: maximum likelihood of the CCR detections and ranges ---------------------


@dataclass(frozen=True)
class LeastSquaresCalibration:
    """The generic estimator's result."""

    bias: Bias
    covariance: np.ndarray  # (3, 3) of (δa [arcsec], δc [arcsec], b [m]), the inverse Fisher information
    footprint_radius_m: float  # fitted e⁻² radius w of the footprint's energy profile [m]
    ccr_photons_per_shot: float  # fitted CCR response N0 (mean photons at the footprint centre)
    background_per_shot: float  # fitted λ_b, background photons per shot in a CCR's height window
    range_sigma_m: float  # scatter of the CCR photons' ranges about the fit [m]
    n_trials: int  # (shot, CCR) photon counts in the likelihood
    n_photons: int  # CCR photon ranges in the likelihood

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations of (δa [arcsec], δc [arcsec], b [m])."""
        return np.sqrt(np.diag(self.covariance))


def _detection_trials(shot, identification: Identification):
    """Every searched (shot, CCR) pair of the pass and its count of candidate photons."""
    shots, ccr, counts = [], [], []
    for j, (k0, k1) in identification.windows.items():
        k = np.arange(max(k0, int(shot.min())), min(k1, int(shot.max())) + 1)
        if k.size == 0:
            continue
        shots.append(k)
        ccr.append(np.full(k.size, j))
        counts.append(np.bincount(shot[identification.candidates == j] - k[0], minlength=k.size)[: k.size])
    return np.concatenate(shots), np.concatenate(ccr), np.concatenate(counts)


def _photon_rate(track, shots, points, x):
    """Mean matching photons per shot λ = N0·exp(−2r²/w²) + λ_b, x = (δa, δc, w, ln N0, ln λ_b)."""
    r = footprint_offset(track, shots, points, Bias(x[0], x[1]))
    return np.exp(x[3] - 2.0 * (r / x[2]) ** 2) + np.exp(x[4])


def _deviance_residuals(lam, counts):
    """Signed √(2(y ln(y/λ) − (y − λ))) of Poisson counts y of mean λ: Σ r² = −2 ln L + const."""
    y_log = np.where(counts > 0, counts * np.log(np.maximum(counts, 1) / lam), 0.0)
    return np.sign(counts - lam) * np.sqrt(np.maximum(2.0 * (y_log - (counts - lam)), 0.0))


def _fisher(track, shots, points, x):
    """Fisher information of x from Poisson counts: Σ (∂λ/∂x)(∂λ/∂x)ᵀ / λ."""
    jac = np.empty((shots.size, x.size))
    for i in range(x.size):
        h = 1e-4 * max(1.0, abs(x[i]))
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        jac[:, i] = (_photon_rate(track, shots, points, up) - _photon_rate(track, shots, points, down)) / (2.0 * h)
    return jac.T @ (jac / _photon_rate(track, shots, points, x)[:, None])


def calibrate_least_squares(track: Track, shot, range_m, field: CcrField, identification: Identification,
                            *, footprint_radius_m: float, start: Bias = Bias()) -> LeastSquaresCalibration:
    """Generic estimator of the pointing and ranging biases from the CCR photons.

    Pointing: on every shot searched for every reachable CCR (``identification.windows``), the
    number of candidate photons (matching the CCR's height) is Poisson with mean λ = N0·exp(−2r²/w²)
    + λ_b, r the CCR's distance from the footprint centre that eq. (1) gives for (δa, δc) and λ_b
    the background in the CCR's height window (no dead time: a multi-channel detector, as ATLAS's
    16 channels per strong beam). (δa, δc, w, ln N0, ln λ_b) maximise the likelihood, as
    ``scipy.optimize.least_squares`` on the deviance residuals, started from ``start`` at the best
    of a grid of δc over ±1.5·R/H (``start``: e.g. the patent's coarse calibration, step 2).
    Triggered or not, every CCR in reach counts. Ranging: a CCR photon's range is |X_ccr − P_laser|
    + b whatever the pointing, so b is the mean range residual of the tracks' photons.
    Covariance: the inverse Fisher information, (JᵀJ)⁻¹ with J the Jacobian of (λ − y)/√λ for the
    pointing, and σ²/n for b (σ the ranges' scatter).
    """
    shot, range_m = np.asarray(shot), np.asarray(range_m, dtype=np.float64)
    shots, ccr, counts = _detection_trials(shot, identification)
    points = field.positions_m[ccr]

    def residuals(x):
        return _deviance_residuals(_photon_rate(track, shots, points, x), counts)

    half = 1.5 * footprint_radius_m / track.altitude_m / ARCSEC
    grid = [np.array([start.along_arcsec, c, footprint_radius_m, 2.0, math.log(0.01)])
            for c in start.across_arcsec + np.linspace(-half, half, 13)]
    x0 = min(grid, key=lambda x: float(np.sum(residuals(x) ** 2)))
    fit = least_squares(residuals, x0, bounds=([-np.inf, -np.inf, 0.1 * footprint_radius_m, -5.0, -20.0],
                                               [np.inf, np.inf, 10.0 * footprint_radius_m, 10.0, 2.0]))
    cov_pointing = np.linalg.inv(_fisher(track, shots, points, fit.x))[:2, :2]
    photons = np.flatnonzero(identification.labels >= 0)
    ccr_points = field.positions_m[identification.labels[photons]]
    dr = range_m[photons] - np.linalg.norm(ccr_points - track.position(shot[photons]), axis=-1)
    b, s = float(dr.mean()), float(dr.std(ddof=1))
    cov = np.zeros((3, 3))
    cov[:2, :2], cov[2, 2] = cov_pointing, s * s / dr.size
    return LeastSquaresCalibration(Bias(float(fit.x[0]), float(fit.x[1]), b), cov, float(fit.x[2]),
                                   float(math.exp(fit.x[3])), float(math.exp(fit.x[4])), s,
                                   int(shots.size), int(dr.size))


# --- CCR field design ------------------------------------------------------------------------


@dataclass(frozen=True)
class FieldDesign:
    """A CCR field in track coordinates relative to the nominal track (see :func:`design_field`)."""

    across_spacing_m: float  # s [m]
    along_spacing_m: float  # Δx [m]
    along_m: np.ndarray  # (n,) along-track positions from the first CCR [m]
    across_m: np.ndarray  # (n,) across-track offsets from the nominal track, + right [m]

    @property
    def n_ccr(self) -> int:
        return int(self.along_m.size)


def design_field(footprint_radius_m: float, pointing_sigma_arcsec: float, altitude_m: float, *,
                 min_triggered: int = 3, n_sigma: float = 3.0, usable_fraction: float = 0.9,
                 reach_factor: float = 1.5) -> FieldDesign:
    """Number, across-track spacing and along-track stagger of CCRs for a footprint of radius R
    and an a priori pointing uncertainty σ per axis.

    Rule: the footprint centre line lies within U = H·tan(n_sigma·σ) of the nominal track; a CCR
    at distance d from it gives a usable track when d < κR (κ = ``usable_fraction``: the track is
    then at least 2R√(1 − κ²) long). An open interval of length (m + 1)·s holds at least m points
    of a lattice of spacing s, so across-track spacing s = 2κR/(m + 1) triggers at least m =
    ``min_triggered`` CCRs wherever the line falls, if the lattice spans ±(U + κR):
    n = ⌈2(U + κR)/s⌉ + 1 CCRs. Each CCR's photons fall within ζR + U of its along-track position
    (ζ = ``reach_factor``: beyond r = 1.5w a CCR of N0 ≤ 10 returns < 0.11 photons per shot), so an
    along-track stagger Δx = 2(ζR + U) keeps every track in its own window and identification
    unambiguous. The CCRs run diagonally (across offset growing along track), so the triggered ones
    lie on both sides of the line in flight order, as step 5's azimuth criterion needs.
    """
    for name, value in (("footprint_radius_m", footprint_radius_m), ("altitude_m", altitude_m),
                        ("n_sigma", n_sigma), ("reach_factor", reach_factor)):
        if not (math.isfinite(value) and value > 0):
            raise InputError(name, value, "a finite number > 0")
    if not (math.isfinite(pointing_sigma_arcsec) and pointing_sigma_arcsec >= 0):
        raise InputError("pointing_sigma_arcsec", pointing_sigma_arcsec, "a finite number >= 0 [arcsec]")
    if not (isinstance(min_triggered, int) and min_triggered >= 2):
        raise InputError("min_triggered", min_triggered, "an integer >= 2 (step 4 needs two CCRs)")
    if not (0 < usable_fraction < 1):
        raise InputError("usable_fraction", usable_fraction, "a number in (0, 1)")
    reach = usable_fraction * footprint_radius_m
    u = altitude_m * math.tan(n_sigma * pointing_sigma_arcsec * ARCSEC)
    s = 2.0 * reach / (min_triggered + 1)
    n = int(math.ceil(2.0 * (u + reach) / s)) + 1
    dx = 2.0 * (reach_factor * footprint_radius_m + u)
    return FieldDesign(s, dx, dx * np.arange(n), -(u + reach) + s * np.arange(n))
