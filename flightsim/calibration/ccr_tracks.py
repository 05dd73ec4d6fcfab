"""Step 1 of the CCR calibration (:mod:`flightsim.calibration.ccr`): which CCR each CCR photon track
belongs to (patent ¶5, claim 2)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.calibration.ccr_field import CcrField
from flightsim.calibration.geolocation import Track, geolocate
from flightsim.core.errors import InputError
from flightsim.core.poisson import at_least


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
    return bool(at_least(n_run, rate * run_shots) < false_alarm)


def _near_along(along_sorted, order, centre_m: float, half_m: float) -> np.ndarray:
    """Indices (ascending) of the photons whose along-track position may lie within half_m of centre_m:
    a superset (1 m wider) cut from the sorted positions, which the caller tests exactly."""
    lo, hi = np.searchsorted(along_sorted, [centre_m - half_m - 1.0, centre_m + half_m + 1.0])
    return np.sort(order[lo:hi])


def _candidates(track, shot, height, field, reach, height_tol_m, ground_window_m):
    """Each photon's candidate CCR (closest in height among those matching), each CCR's local
    ground level and searched shot window."""
    along = shot * track.spacing_m
    order = np.argsort(along, kind="stable")
    along_sorted = along[order]
    ccr_along, ccr_across = track.to_track_frame(field.positions_m)
    labels, mismatch = np.full(shot.size, -1), np.full(shot.size, np.inf)
    grounds, windows = {}, {}
    for j in np.flatnonzero(np.abs(ccr_across) <= reach):
        idx = _near_along(along_sorted, order, ccr_along[j], max(ground_window_m, reach))
        distance = np.abs(along[idx] - ccr_along[j])
        near = distance <= ground_window_m
        if not near.any():
            continue
        grounds[int(j)] = _ground_level(height[idx[near]])
        windows[int(j)] = (math.ceil((ccr_along[j] - reach) / track.spacing_m),
                           math.floor((ccr_along[j] + reach) / track.spacing_m))
        m = np.abs(height[idx] - grounds[j] - field.heights_m[j])
        hit = (distance <= reach) & (m <= height_tol_m) & (m < mismatch[idx])
        labels[idx[hit]], mismatch[idx[hit]] = j, m[hit]
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
