"""The CCR field of :mod:`flightsim.calibration.ccr`: the known corner cubes (reflecting points in the
local east-north-up frame of :mod:`.geolocation` [m] and their heights above the ground [m]), and the
design of a field for a footprint and a pointing uncertainty."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.calibration.geolocation import ARCSEC, Track
from flightsim.core.errors import InputError


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
