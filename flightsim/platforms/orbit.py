"""A spacecraft on a circular orbit passing over the scene (``flight.platform = "orbit"``).

Orbit: two-body, circular, radius r = |the point flight.altitude_m above the scene origin| (so the pass is
at that altitude over the scene), inclination flight.inclination_deg, around ``flight.body``: the Earth
(WGS84 through pyproj, μ = 3.986004418e14 m³/s², rotating at 7.292115e-5 rad/s about its z axis — the
Earth rotation angle only: no precession, nutation or polar motion, the same in truth and processing) or
the Moon (a sphere of 1737.4 km, μ = 4.9048695e12 m³/s², one turn in 27.321661 d). The orbit's node and
phase put the ascending ground track over the scene origin at the middle of the run.

Frame: the scene is the tangent plane at its origin (east, north, up of the body's ellipsoid or sphere
there); world = scene origin + local, which matches a projected CRS near the origin to its scale factor
and meridian convergence (for UTM ≤ 4e-4 and a fraction of a degree; this frame is what the simulator and
its processing both use). The spacecraft points nadir: body z along the ellipsoid (sphere) normal at the
sub-spacecraft point, downward, body x along the ground track. Samples every ORBIT_STEP_S; between them
the simulator interpolates linearly (position error ≤ a·Δt²/8 = 1.1 mm at 8.7 m/s² and 0.05 s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.platforms.rotating_body import attitude_angles
from flightsim.scenes.scene import Scene
from trajectories import Trajectory

ORBIT_STEP_S = 0.05  # trajectory sample interval [s]


@dataclass(frozen=True)
class Body:
    """A central body: gravitational parameter μ [m³/s²], rotation rate [rad/s], equatorial radius and
    flattening of its reference surface."""

    name: str
    mu: float
    rotation_rad_s: float
    radius_m: float
    flattening: float


BODIES = {"earth": Body("earth", 3.986004418e14, 7.2921150e-5, 6378137.0, 1.0 / 298.257223563),
          "moon": Body("moon", 4.9048695e12, 2.0 * math.pi / (27.321661 * 86400.0), 1737400.0, 0.0)}


def ground_speed_mps(body: Body, altitude_m: float) -> float:
    """Speed of the sub-spacecraft point of a circular orbit at ``altitude_m`` over the equatorial radius,
    ignoring the body's rotation: √(μ/r)·R/r [m/s]."""
    r = body.radius_m + altitude_m
    return math.sqrt(body.mu / r) * body.radius_m / r


def geodetic_to_body_fixed(body: Body, lat_deg, lon_deg, h_m) -> np.ndarray:
    """(…, 3) body-fixed Cartesian [m] of geodetic latitude, longitude [deg] and height [m] (WGS84 via
    pyproj for the Earth; the sphere for the Moon)."""
    if body.name == "earth":
        to_ecef = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
        return np.stack(to_ecef.transform(lon_deg, lat_deg, h_m), axis=-1)
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    r = body.radius_m + np.asarray(h_m, dtype=np.float64)
    return np.stack([r * np.cos(lat) * np.cos(lon), r * np.cos(lat) * np.sin(lon), r * np.sin(lat)], axis=-1)


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """R_body-fixed→ENU at a geodetic latitude, longitude [deg] (rows: east, north, up)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    return np.array([[-math.sin(lon), math.cos(lon), 0.0],
                     [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
                     [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]])


def kepler_circular(body: Body, radius_m: float, inclination_rad: float, node_rad: float, u0_rad: float,
                    t_s: np.ndarray) -> np.ndarray:
    """(n, 3) inertial positions [m] at times ``t_s`` [s] after the epoch of a circular orbit: argument of
    latitude u = u0 + n t, n = √(μ/r³); r = R3(−Ω)·R1(−i)·(r cos u, r sin u, 0)."""
    u = u0_rad + math.sqrt(body.mu / radius_m ** 3) * np.asarray(t_s, dtype=np.float64)
    x, y = radius_m * np.cos(u), radius_m * np.sin(u)
    ci, si, co, so = math.cos(inclination_rad), math.sin(inclination_rad), math.cos(node_rad), math.sin(node_rad)
    return np.column_stack([co * x - so * ci * y, so * x + co * ci * y, si * y])


def body_fixed(body: Body, inertial: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Inertial positions turned into the body-fixed frame at times ``t_s`` after the epoch (the frames
    coincide at the epoch): R3(ω t)."""
    a = body.rotation_rad_s * np.asarray(t_s, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    x, y, z = inertial.T
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def pass_geometry(target: np.ndarray, inclination_deg: float) -> tuple[float, float]:
    """(node Ω, argument of latitude u0) [rad] of the circular orbit whose ascending pass goes through the
    body-fixed point ``target`` [m] at the epoch: sin φ = sin i sin u0 (φ: the point's geocentric latitude)."""
    i = math.radians(inclination_deg)
    phi = math.asin(target[2] / np.linalg.norm(target))
    if abs(math.sin(phi)) > abs(math.sin(i)) + 1e-12:
        raise InputError("flight.inclination_deg", inclination_deg,
                         f"an inclination whose track reaches the scene's latitude ({math.degrees(phi):.3f} deg)")
    u0 = math.asin(max(-1.0, min(1.0, math.sin(phi) / math.sin(i))))
    lam = math.atan2(target[1], target[0])
    node = lam - math.atan2(math.cos(i) * math.sin(u0), math.cos(u0))
    return node, u0


def orbit_trajectory(body_name: str, scene: Scene, altitude_m: float, inclination_deg: float, start_gps_time: float,
                     duration_s: float) -> Trajectory:
    """The nadir-pointing pass over the scene origin (mid-run: altitude_m above it along its normal), in
    the scene's tangent-plane world frame."""
    body = BODIES[body_name]
    lat0, lon0 = scene_geodetic(body, scene)
    centre = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2])
    above = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2] + altitude_m)
    node, u0 = pass_geometry(above, inclination_deg)
    steps = max(2, math.ceil(duration_s / ORBIT_STEP_S) + 1)
    t = np.linspace(0.0, duration_s, steps) - duration_s / 2.0  # from the epoch, mid-run
    fixed = body_fixed(body, kepler_circular(body, float(np.linalg.norm(above)), math.radians(inclination_deg),
                                             node, u0, t), t)
    to_enu = enu_rotation(lat0, lon0)
    local = (fixed - centre) @ to_enu.T
    nadir = -up_vectors(body, fixed) @ to_enu.T
    along = np.gradient(local, t, axis=0)
    return Trajectory(start_gps_time + t + duration_s / 2.0, local + scene.origin,
                      attitude_angles(_nadir_frames(nadir, along)), 1)


def _nadir_frames(nadir: np.ndarray, along: np.ndarray) -> np.ndarray:
    """(n, 3, 3) R_body→local: columns x (along track, level), y = z × x, z (nadir)."""
    x = along - np.sum(along * nadir, axis=1, keepdims=True) * nadir
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(nadir, x)
    return np.stack([x, y, nadir], axis=2)


def up_vectors(body: Body, p: np.ndarray) -> np.ndarray:
    """(n, 3) unit normals of the reference surface beneath body-fixed points ``p`` (n, 3) [m]."""
    if body.name == "earth":
        to_geodetic = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
        lon, lat, _ = (np.radians(a) for a in to_geodetic.transform(p[:, 0], p[:, 1], p[:, 2]))
        return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def scene_geodetic(body: Body, scene: Scene) -> tuple[float, float]:
    """Geodetic latitude, longitude [deg] of the scene origin: through its CRS on the Earth; on the Moon
    the scene's local frame is taken at latitude, longitude 0, 0."""
    if body.name != "earth":
        return 0.0, 0.0
    to_geodetic = pyproj.Transformer.from_crs(scene.crs, "EPSG:4326", always_xy=True)
    lon, lat = to_geodetic.transform(scene.origin[0], scene.origin[1])
    return float(lat), float(lon)


def local_to_geodetic(cfg, scene: Scene, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(latitude, longitude [deg], height [m]) of local points (n, 3): through the tangent plane and the
    body for the orbit platform (heights above the WGS84 ellipsoid or the Moon's sphere), else through
    the scene's projected CRS (world = origin + local; heights as the scene's)."""
    local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    if cfg.flight.platform != "orbit":
        world = scene.local_to_world(local)
        lon, lat = pyproj.Transformer.from_crs(scene.crs, "EPSG:4326", always_xy=True).transform(world[:, 0],
                                                                                                  world[:, 1])
        return np.asarray(lat), np.asarray(lon), world[:, 2]
    body = BODIES[cfg.flight.body]
    lat0, lon0 = scene_geodetic(body, scene)
    fixed = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2]) + local @ enu_rotation(lat0, lon0)
    if body.name == "earth":
        to_geodetic = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
        lon, lat, h = to_geodetic.transform(fixed[:, 0], fixed[:, 1], fixed[:, 2])
        return np.asarray(lat), np.asarray(lon), np.asarray(h)
    r = np.linalg.norm(fixed, axis=1)
    return (np.degrees(np.arcsin(fixed[:, 2] / r)), np.degrees(np.arctan2(fixed[:, 1], fixed[:, 0])),
            r - body.radius_m)
