"""Photon geolocation of a spaceborne single-photon altimeter in a local metric frame: the seed
patent's eq. (1) reduced to what corner-cube (CCR) calibration needs (float64 NumPy only).

Eq. (1) of ``seeds/corner-cube-single-photon-calibration-patent.txt`` places a photon at

    P = X_gnss + R_icrf→itrf · R_body→icrf · (ΔX_laser − ΔX_gnss + (ρ + Δρ) · R_cal · u_laser)

with ρ the photon's range, Δρ the ranging correction, u_laser the pulse's unit vector and R_cal
the pointing calibration. Over a CCR field a few km long this module keeps:

- **Frame**: a local tangent plane, east, north, up [m] (flat Earth). To first order in the
  pointing angle δ a sphere moves the ground point by H·δ as the plane does (the Earth-centred
  angle H·δ/R_E times R_E), so the 1″ displacement H·tan(1″) of :func:`ground_shift_m` holds.
- **Laser position** (X_gnss with both lever arms, the two rotations applied): a straight,
  constant-velocity track at altitude H, known exactly; shot k fires at t = k / f and sits above
  ``origin_m + v·t`` along the azimuth of flight (:class:`Track`). From the orbit platform the track
  carries each shot's position and body axes in the local frame instead (``shot_positions``,
  ``shot_axes``): the simulator has already applied R_icrf→itrf (astropy's GCRS→ITRS at the shot's
  time, flightsim.platforms.orbit) and R_body→icrf, so eq. (1) needs no frame of its own here.
- **Body frame**: x along track (the flight direction, horizontal), y across track (to the right
  of the flight direction), z down (nadir); the nominal pulse vector u_laser is +z.
- **Pointing bias** (R_cal, :func:`pointing_rotation`): R_y(δ_along) · R_x(−δ_across), which turns
  +z into (sin δa cos δc, sin δc, cos δa cos δc): δ_along > 0 tilts the beam forward (the footprint
  moves H·tan δa in the flight direction), δ_across > 0 tilts it to the right (H·tan δc / cos δa).
- **Ranging bias** b [m]: the instrument measures ρ = |X − P_laser| + b; geolocation subtracts it
  (the patent's correction Δρ = −b).

The same two angles and b describe the truth that a synthetic pass injects and the correction
that calibration solves for (:class:`Bias`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError

ARCSEC = math.pi / (180.0 * 3600.0)  # one arcsecond [rad]


def ground_shift_m(altitude_m: float, angle_arcsec: float) -> float:
    """Ground displacement H·tan(δ) of a nadir beam tilted by δ [arcsec] from altitude H [m] [m]."""
    return altitude_m * math.tan(angle_arcsec * ARCSEC)


@dataclass(frozen=True)
class Bias:
    """Pointing bias (two angles [arcsec], see the module docstring) and ranging bias [m]."""

    along_arcsec: float = 0.0  # δa: rotation about the across-track axis, + moves the footprint forward
    across_arcsec: float = 0.0  # δc: rotation about the along-track axis, + moves it to the right
    range_m: float = 0.0  # b: measured range minus true range

    def as_array(self) -> np.ndarray:
        """(δa [arcsec], δc [arcsec], b [m])."""
        return np.array([self.along_arcsec, self.across_arcsec, self.range_m], dtype=np.float64)

    @classmethod
    def from_array(cls, values) -> "Bias":
        """Inverse of :meth:`as_array`."""
        a, c, b = (float(v) for v in values)
        return cls(a, c, b)


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise InputError(name, value, "a finite number > 0")


@dataclass(frozen=True)
class Track:
    """A straight, constant-velocity laser track at altitude H over the local frame.

    Defaults are ICESat-2-like: 500 km, 7 km/s ground speed, 10 kHz, so 0.7 m between shots.
    """

    altitude_m: float = 500e3  # H, laser above the frame's z = 0 [m]
    ground_speed_mps: float = 7000.0  # v, speed of the nadir point [m/s]
    rate_hz: float = 10e3  # f, pulse repetition frequency [Hz]
    azimuth_deg: float = 0.0  # flight direction, clockwise from north [deg]
    origin_m: tuple[float, float] = (0.0, 0.0)  # (E, N) of the nadir point at shot 0 [m]
    shot_positions: np.ndarray | None = None  # (n, 3) laser ENU of each shot: a known curved track [m]
    shot_axes: np.ndarray | None = None  # (n, 3, 3) body→ENU of each shot (columns along, right, down)

    def __post_init__(self):
        _positive("track.altitude_m", self.altitude_m)
        _positive("track.ground_speed_mps", self.ground_speed_mps)
        _positive("track.rate_hz", self.rate_hz)
        if not math.isfinite(self.azimuth_deg):
            raise InputError("track.azimuth_deg", self.azimuth_deg, "a finite angle [deg]")

    @property
    def spacing_m(self) -> float:
        """Along-track distance between consecutive shots v/f [m]."""
        return self.ground_speed_mps / self.rate_hz

    def axes(self) -> np.ndarray:
        """Body→ENU rotation: columns along-track x, right y, down z (unit vectors in ENU)."""
        az = math.radians(self.azimuth_deg)
        along = [math.sin(az), math.cos(az), 0.0]
        right = [math.cos(az), -math.sin(az), 0.0]
        return np.array([along, right, [0.0, 0.0, -1.0]], dtype=np.float64).T

    def position(self, shot) -> np.ndarray:
        """Laser positions (n, 3) ENU [m] of (possibly fractional) shot indices: on the straight track, or
        interpolated linearly between the known positions of a curved one."""
        if self.shot_positions is not None:
            k = np.asarray(shot, dtype=np.float64)
            index = np.arange(len(self.shot_positions))
            return np.stack([np.interp(k, index, self.shot_positions[:, i]) for i in range(3)], axis=-1)
        s = np.asarray(shot, dtype=np.float64) * self.spacing_m
        axes = self.axes()
        horizontal = np.asarray(self.origin_m, dtype=np.float64) + s[..., None] * axes[:2, 0]
        return np.concatenate([horizontal, np.full(s.shape + (1,), self.altitude_m)], axis=-1)

    def to_track_frame(self, en) -> tuple[np.ndarray, np.ndarray]:
        """(along [m] from shot 0's nadir, across [m], + right) of points given by their (E, N)."""
        d = np.asarray(en, dtype=np.float64)[..., :2] - np.asarray(self.origin_m, dtype=np.float64)
        axes = self.axes()
        return d @ axes[:2, 0], d @ axes[:2, 1]

    def from_track_frame(self, along_m, across_m) -> np.ndarray:
        """(E, N) [m] of points given by (along, across) track coordinates; inverse of the above."""
        axes = self.axes()
        along = np.asarray(along_m, dtype=np.float64)[..., None]
        across = np.asarray(across_m, dtype=np.float64)[..., None]
        return np.asarray(self.origin_m, dtype=np.float64) + along * axes[:2, 0] + across * axes[:2, 1]


def pointing_rotation(bias: Bias) -> np.ndarray:
    """R_cal of eq. (1) in the body frame: R_y(δ_along) · R_x(−δ_across)."""
    a, c = bias.along_arcsec * ARCSEC, bias.across_arcsec * ARCSEC
    ry = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(c), math.sin(c)], [0.0, -math.sin(c), math.cos(c)]])
    return ry @ rx


def _shot_axes(track: Track, shot) -> np.ndarray:
    """Body→ENU rotation of each shot: (3, 3) on a straight track or without shots, (n, 3, 3) the nearest
    known axes of a curved one."""
    if track.shot_axes is None or shot is None:
        return track.axes()
    k = np.clip(np.rint(np.asarray(shot, dtype=np.float64)).astype(np.int64), 0, len(track.shot_axes) - 1)
    return track.shot_axes[k]


def beam_direction(track: Track, bias: Bias = Bias(), shot=None) -> np.ndarray:
    """Unit pulse vector in ENU: the body-frame nadir +z turned by the pointing bias; (3,) on a straight
    track, (n, 3) for the given shots (nearest) of a curved one."""
    return _shot_axes(track, shot) @ _body_direction(bias)


def _body_direction(bias: Bias) -> np.ndarray:
    """The body-frame nadir +z turned by the pointing bias (3,)."""
    return pointing_rotation(bias) @ np.array([0.0, 0.0, 1.0])


class Shots:
    """Fixed shots of a track, their laser positions and body axes looked up once: eq. (1) for many
    biases on the same shots (a least-squares fit's residuals) without repeating the lookups. Each
    method gives the same bits as the module function of its name."""

    def __init__(self, track: Track, shot):
        self.shot = np.asarray(shot, dtype=np.float64)
        self.laser = track.position(self.shot)  # (n, 3) ENU [m]
        self.axes = _shot_axes(track, self.shot)

    def direction(self, bias: Bias) -> np.ndarray:
        """Unit pulse vectors in ENU, as :func:`beam_direction`."""
        return self.axes @ _body_direction(bias)

    def locate(self, range_m, bias: Bias) -> np.ndarray:
        """Ground positions (n, 3) ENU [m] of one photon per shot, as :func:`geolocate`."""
        return self.laser + (range_m - bias.range_m)[..., None] * self.direction(bias)

    def centre(self, height_m, bias: Bias) -> np.ndarray:
        """Footprint centres (n, 3) ENU [m] at the heights [m], as :func:`footprint_centre`."""
        u = self.direction(bias)
        t = (np.asarray(height_m, dtype=np.float64) - self.laser[..., 2]) / u[..., 2]
        return self.laser + t[..., None] * u

    def offset(self, points, bias: Bias) -> np.ndarray:
        """Horizontal distances [m] of points (n, 3) from the footprint centres, as :func:`footprint_offset`."""
        p = np.asarray(points, dtype=np.float64)
        d = p[..., :2] - self.centre(p[..., 2], bias)[..., :2]
        return np.hypot(d[..., 0], d[..., 1])


def photon_arrays(shot, range_m) -> tuple[np.ndarray, np.ndarray]:
    """Photons' (shot, range [m]) as float64 arrays of one shape, the ranges finite (else InputError)."""
    shot = np.asarray(shot, dtype=np.float64)
    range_m = np.asarray(range_m, dtype=np.float64)
    if shot.shape != range_m.shape:
        raise InputError("range_m", f"shape {range_m.shape}", f"the shape of shot, {shot.shape}")
    if not np.all(np.isfinite(range_m)):
        raise InputError("range_m", "non-finite values", "finite ranges [m]")
    return shot, range_m


def geolocate(track: Track, shot, range_m, bias: Bias = Bias()) -> np.ndarray:
    """Ground positions (n, 3) ENU [m] of photons, eq. (1): P_laser + (ρ − b) · R_cal u.

    Args:
        track: the laser track (known positions).
        shot: shot index of each photon (fractional allowed).
        range_m: measured range of each photon [m].
        bias: the pointing and ranging biases believed (zero: the nominal model).
    """
    shot, range_m = photon_arrays(shot, range_m)
    return Shots(track, shot).locate(range_m, bias)


def measured_range(track: Track, shot, points, bias: Bias = Bias()) -> np.ndarray:
    """Inverse of :func:`geolocate` for a point target: ranges |X − P_laser| + b [m] that a point
    X (n, 3) ENU (a CCR) returns on the given shots, when the footprint covers it."""
    p = np.asarray(points, dtype=np.float64)
    return np.linalg.norm(p - track.position(shot), axis=-1) + bias.range_m


def footprint_centre(track: Track, shot, height_m, bias: Bias = Bias()) -> np.ndarray:
    """Where the beam axis of each shot meets the horizontal plane z = height_m: (n, 3) ENU [m]."""
    return Shots(track, shot).centre(height_m, bias)


def footprint_offset(track: Track, shot, points, bias: Bias = Bias()) -> np.ndarray:
    """Horizontal distance [m] of points (n, 3) ENU from the footprint centre at their height."""
    return Shots(track, shot).offset(points, bias)


def theoretical_radius(range_m: float, divergence_rad: float) -> float:
    """The patent's theoretical footprint radius R = ρ·tan(θ/2), θ the full divergence [m]."""
    return range_m * math.tan(divergence_rad / 2.0)
