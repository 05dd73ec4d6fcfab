"""The orbit platform (``flight.platform = "orbit"``): a spacecraft on a Keplerian orbit passing over the scene.

Orbit: two-body, around ``flight.body``: the Earth (WGS84 through pyproj, μ = 3.986004418e14 m³/s²) or the
Moon (a sphere of 1737.4 km, μ = 4.9048695e12 m³/s², one turn in 27.321661 d). Elements in the inertial
frame: inclination flight.inclination_deg, eccentricity flight.eccentricity (0 ≤ e < 1), argument of
perigee flight.perigee_arg_deg (ω, from the ascending node); the node Ω and the phase (mean anomaly) are
not inputs: they put the ascending pass over the scene origin at the middle of the run, and
``flight.altitude_m`` is the altitude there (above the scene origin, along its normal) — for e > 0 the
semi-major axis follows, a = r_pass (1 + e cos ν_pass)/(1 − e²), ν_pass = u_pass − ω. Positions by
Kepler's equation M = E − e sin E, solved by Newton's method; e = 0 gives exactly the circle
r (cos u, sin u) with u = u_pass + n t.

Frames: for the Earth the inertial frame is GCRS (ICRF axes, geocentric) and the body-fixed frame ITRS,
both through astropy at the run's time (adjusted GPS time + 1e9 s, astropy ``Time(format="gps")``;
precession, nutation, Earth rotation and polar motion from astropy's bundled IERS tables — no download:
``iers.conf.auto_download = False``, and past the tables' end astropy warns and degrades to its
predictions). The rotation is taken from astropy at one epoch per ROTATION_STEP_S of the run and
interpolated between them (quaternion slerp; the Earth turns uniformly about a fixed axis over a minute to
≤ 1e-11 rad). For the Moon the body-fixed frame is a uniform rotation R3(ω t) about the inertial z axis,
the frames coinciding at mid-run: the Moon's mean-Earth/polar-axis frame and its librations are not
modelled.

Scene frame: the scene is the tangent plane at its origin (east, north, up of the body's ellipsoid or
sphere there); world = scene origin + local, which matches a projected CRS near the origin to its scale
factor and meridian convergence (for UTM ≤ 4e-4 and a fraction of a degree; this frame is what the
simulator and its processing both use). The spacecraft points nadir: body z along the ellipsoid (sphere)
normal at the sub-spacecraft point, downward, body x along the ground track. Samples every ORBIT_STEP_S;
between them the simulator interpolates linearly (position error ≤ a·Δt²/8 = 1.1 mm at 8.7 m/s² and
0.05 s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.core.transform import transform
from flightsim.platforms.earth_orientation import cached_rotations
from flightsim.platforms.flight import check_clearance
from flightsim.platforms.rotating_body import attitude_angles
from flightsim.scenes.scene import Scene
from trajectories import Trajectory

ORBIT_STEP_S = 0.05  # trajectory sample interval [s]
ROTATION_STEP_S = 60.0  # interval of the astropy GCRS→ITRS epochs that are interpolated [s]
ADJUSTED_GPS_OFFSET_S = 1.0e9  # standard GPS time − adjusted standard GPS time [s]
KEPLER_TOLERANCE_RAD = 1e-15  # Newton's method stops when its step is below this [rad]


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


@dataclass(frozen=True)
class Orbit:
    """Keplerian elements in the inertial frame: semi-major axis a [m], eccentricity e, inclination i,
    node Ω, argument of perigee ω and mean anomaly M0 at the epoch t = 0 [rad]."""

    a: float
    e: float
    inclination: float
    node: float
    perigee: float
    m0: float


def ground_speed_mps(body: Body, altitude_m: float, eccentricity: float = 0.0) -> float:
    """Upper bound of the speed of the sub-spacecraft point of an orbit at ``altitude_m`` over the equatorial
    radius, ignoring the body's rotation: the speed at perigee of an orbit of that perigee radius,
    √(μ (1 + e)/r)·R/r [m/s] (= √(μ/r)·R/r on a circle)."""
    r = body.radius_m + altitude_m
    return math.sqrt(body.mu * (1.0 + eccentricity) / r) * body.radius_m / r


def geodetic_to_body_fixed(body: Body, lat_deg, lon_deg, h_m) -> np.ndarray:
    """(…, 3) body-fixed Cartesian [m] of geodetic latitude, longitude [deg] and height [m] (WGS84 via
    pyproj for the Earth; the sphere for the Moon)."""
    if body.name == "earth":
        return np.stack(transform("EPSG:4979", "EPSG:4978", lon_deg, lat_deg, h_m), axis=-1)
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    r = body.radius_m + np.asarray(h_m, dtype=np.float64)
    return np.stack([r * np.cos(lat) * np.cos(lon), r * np.cos(lat) * np.sin(lon), r * np.sin(lat)], axis=-1)


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """R_body-fixed→ENU at a geodetic latitude, longitude [deg] (rows: east, north, up)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    return np.array([[-math.sin(lon), math.cos(lon), 0.0],
                     [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
                     [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]])


def eccentric_anomaly(mean_anomaly, e: float) -> np.ndarray:
    """E [rad] solving Kepler's equation M = E − e sin E for mean anomalies M [rad], 0 ≤ e < 1: Newton's
    method from Danby's start E0 = M + 0.85 e sign(sin M) (exact at once for e = 0)."""
    m = np.asarray(mean_anomaly, dtype=np.float64)
    anomaly = m + 0.85 * e * np.sign(np.sin(m))
    for _ in range(60):
        step = (anomaly - e * np.sin(anomaly) - m) / (1.0 - e * np.cos(anomaly))
        anomaly = anomaly - step
        if np.all(np.abs(step) <= KEPLER_TOLERANCE_RAD * np.maximum(1.0, np.abs(m))):
            break
    return anomaly


def kepler_state(body: Body, orbit: Orbit, t_s) -> tuple[np.ndarray, np.ndarray]:
    """(positions, velocities) (n, 3) in the inertial frame [m, m/s] at times ``t_s`` [s] after the epoch:
    M = M0 + n t, n = √(μ/a³); perifocal (a (cos E − e), b sin E), b = a √(1 − e²), and its time
    derivative with dE/dt = n / (1 − e cos E)."""
    t = np.asarray(t_s, dtype=np.float64)
    n = math.sqrt(body.mu / orbit.a ** 3)
    anomaly = eccentric_anomaly(orbit.m0 + n * t, orbit.e)
    cos_e, sin_e = np.cos(anomaly), np.sin(anomaly)
    b = orbit.a * math.sqrt(1.0 - orbit.e * orbit.e)
    rate = n / (1.0 - orbit.e * cos_e)
    return (_perifocal_to_inertial(orbit, orbit.a * (cos_e - orbit.e), b * sin_e),
            _perifocal_to_inertial(orbit, -orbit.a * sin_e * rate, b * cos_e * rate))


def _perifocal_to_inertial(orbit: Orbit, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, 3) inertial vectors of perifocal components (x to perigee, y 90° ahead in the orbit plane):
    R3(−Ω)·R1(−i)·R3(−ω)."""
    cw, sw = math.cos(orbit.perigee), math.sin(orbit.perigee)
    x, y = cw * x - sw * y, sw * x + cw * y  # node frame: x to the ascending node
    ci, si = math.cos(orbit.inclination), math.sin(orbit.inclination)
    co, so = math.cos(orbit.node), math.sin(orbit.node)
    return np.column_stack([co * x - so * ci * y, so * x + co * ci * y, si * y])


def pass_geometry(target: np.ndarray, inclination_deg: float) -> tuple[float, float]:
    """(node Ω, argument of latitude u) [rad] of the orbit whose ascending pass goes through the inertial
    point ``target`` [m]: sin φ = sin i sin u (φ: the point's geocentric latitude)."""
    i = math.radians(inclination_deg)
    phi = math.asin(target[2] / np.linalg.norm(target))
    if abs(math.sin(phi)) > abs(math.sin(i)) + 1e-12:
        raise InputError("flight.inclination_deg", inclination_deg,
                         f"an inclination whose track reaches the scene's latitude ({math.degrees(phi):.3f} deg)")
    u0 = math.asin(max(-1.0, min(1.0, math.sin(phi) / math.sin(i))))
    lam = math.atan2(target[1], target[0])
    node = lam - math.atan2(math.cos(i) * math.sin(u0), math.cos(u0))
    return node, u0


def pass_orbit(body: Body, target: np.ndarray, inclination_deg: float, eccentricity: float,
               perigee_arg_deg: float) -> Orbit:
    """The orbit whose ascending pass goes through the inertial point ``target`` [m] at the epoch: true
    anomaly there ν = u − ω, a = r (1 + e cos ν)/(1 − e²), E = ν − 2 atan(β sin ν / (1 + β cos ν)) with
    β = e / (1 + √(1 − e²)), M0 = E − e sin E."""
    if not 0.0 <= eccentricity < 1.0:
        raise InputError("flight.eccentricity", eccentricity, "a number in [0, 1) (a closed orbit)")
    node, u = pass_geometry(target, inclination_deg)
    e, perigee = eccentricity, math.radians(perigee_arg_deg)
    nu = u - perigee
    a = float(np.linalg.norm(target)) * (1.0 + e * math.cos(nu)) / (1.0 - e * e)
    _check_perigee(body, a * (1.0 - e), math.radians(inclination_deg), perigee, e)
    beta = e / (1.0 + math.sqrt(1.0 - e * e))
    anomaly = nu - 2.0 * math.atan(beta * math.sin(nu) / (1.0 + beta * math.cos(nu)))
    return Orbit(a, e, math.radians(inclination_deg), node, perigee, anomaly - e * math.sin(anomaly))


def _check_perigee(body: Body, perigee_m: float, inclination: float, perigee: float, e: float) -> None:
    """The perigee radius [m] is above the reference surface at the perigee's geocentric latitude
    (sin φ = sin i sin ω; the ellipsoid's radius b / √((1 − f)² cos² φ + sin² φ))."""
    phi = math.asin(math.sin(inclination) * math.sin(perigee))
    polar = body.radius_m * (1.0 - body.flattening)
    surface = polar / math.hypot((1.0 - body.flattening) * math.cos(phi), math.sin(phi))
    if perigee_m <= surface:
        raise InputError("flight.eccentricity", e,
                         f"an eccentricity whose perigee stays above the surface (perigee at "
                         f"{(perigee_m - surface) / 1e3:.1f} km from it with this altitude_m and perigee_arg_deg)")


def gcrs_to_itrs(gps_time) -> np.ndarray:
    """(n, 3, 3) rotations R_GCRS→ITRS at adjusted GPS times [s], from astropy (:func:`astropy_gcrs_to_itrs`), kept
    in the scene cache for the next run of the same times
    (:func:`flightsim.platforms.earth_orientation.cached_rotations`)."""
    return cached_rotations(np.asarray(gps_time, dtype=np.float64), astropy_gcrs_to_itrs)


def astropy_gcrs_to_itrs(gps_time) -> np.ndarray:
    """(n, 3, 3) rotations R_GCRS→ITRS at adjusted GPS times [s], from astropy (bundled IERS tables, no
    download; their parsed table kept in the scene cache: :mod:`flightsim.platforms.earth_orientation`): the
    columns are the ITRS images of the GCRS axes."""
    from astropy import units
    from astropy.coordinates import GCRS, ITRS, CartesianRepresentation
    from astropy.time import Time
    from astropy.utils import data, iers

    from flightsim.platforms.earth_orientation import use_cached_table

    with iers.conf.set_temp("auto_download", False), iers.conf.set_temp("iers_degraded_accuracy", "warn"), \
            data.conf.set_temp("allow_internet", False):
        use_cached_table()
        time = Time(np.asarray(gps_time, dtype=np.float64) + ADJUSTED_GPS_OFFSET_S, format="gps")
        axes = np.eye(3)[:, :, None] * np.ones(time.shape)  # (component, axis, epoch)
        gcrs = GCRS(CartesianRepresentation(axes * units.m), obstime=time)
        itrs = gcrs.transform_to(ITRS(obstime=time)).cartesian.xyz.to_value(units.m)
    return np.moveaxis(itrs, 2, 0)


def earth_rotation(gps_time) -> np.ndarray:
    """(n, 3, 3) R_GCRS→ITRS at adjusted GPS times [s]: astropy at epochs ≤ ROTATION_STEP_S apart over
    their span, quaternion slerp between them."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.asarray(gps_time, dtype=np.float64)
    lo, hi = float(t.min()), float(t.max())
    nodes = np.linspace(lo, max(hi, lo + 1.0), max(2, math.ceil((hi - lo) / ROTATION_STEP_S) + 1))
    return Slerp(nodes, Rotation.from_matrix(gcrs_to_itrs(nodes)))(t).as_matrix()


def inertial_to_body_fixed(body: Body, epoch_gps: float, inertial: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Inertial positions (n, 3) [m] at times ``t_s`` [s] after the epoch (adjusted GPS time ``epoch_gps``)
    in the body-fixed frame: ITRS for the Earth (:func:`earth_rotation`), R3(ω t) for the Moon."""
    t = np.asarray(t_s, dtype=np.float64)
    if body.name == "earth":
        return np.einsum("nij,nj->ni", earth_rotation(epoch_gps + t), inertial)
    c, s = np.cos(body.rotation_rad_s * t), np.sin(body.rotation_rad_s * t)
    x, y, z = inertial.T
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def body_fixed_to_inertial(body: Body, epoch_gps: float, point: np.ndarray) -> np.ndarray:
    """A body-fixed point (3,) [m] in the inertial frame at the epoch (the Moon's frames coincide there)."""
    if body.name == "earth":
        return earth_rotation(np.array([epoch_gps]))[0].T @ point
    return point


@dataclass
class OrbitSettings(Settings):
    """The orbit's central body and elements (the node and phase put the pass over the scene origin mid-run)."""

    body: str = setting("earth", "the central body: earth (WGS84) or moon (a 1737.4 km sphere)", choices=("earth", "moon"))
    inclination_deg: float = setting(92.0, "inclination", "deg", range=(0.0, 180.0))
    eccentricity: float = setting(0.0, "eccentricity, below 1 (flight.altitude_m is the altitude of the pass over "
                                  "the scene)", "", range=(0.0, 1.0))
    perigee_arg_deg: float = setting(0.0, "argument of perigee from the ascending node", "deg", range=(-360.0, 360.0))


@register("platform", "orbit")
class OrbitPlatform:
    """A pass of the ``[flight]`` section (common and orbit settings)."""

    settings = OrbitSettings

    def __init__(self, flight):
        self.f = flight

    def spans(self) -> tuple[float, float, float]:
        """(half the ground track's length, 0, 0): the track, as a line of heading 0, for sizing the scene."""
        f = self.f
        return ground_speed_mps(BODIES[f.body], f.altitude_m, f.eccentricity) * f.duration_s / 2.0, 0.0, 0.0

    def tilt_deg(self) -> float:
        return 0.0

    def trajectories(self, scene: Scene) -> list[Trajectory]:
        track = orbit_trajectory(self.f, scene)
        check_clearance(track, scene, self.f.altitude_m)
        return [track]


def orbit_trajectory(flight, scene: Scene) -> Trajectory:
    """The nadir-pointing pass of ``flight`` (the [flight] section: common and orbit settings) over the scene
    origin (mid-run: flight.altitude_m above it along its normal), in the scene's tangent-plane world frame."""
    body = BODIES[flight.body]
    lat0, lon0 = scene_geodetic(body, scene)
    centre = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2])
    above = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2] + flight.altitude_m)
    epoch = flight.start_gps_time + flight.duration_s / 2.0
    orbit = pass_orbit(body, body_fixed_to_inertial(body, epoch, above), flight.inclination_deg,
                       flight.eccentricity, flight.perigee_arg_deg)
    steps = max(2, math.ceil(flight.duration_s / ORBIT_STEP_S) + 1)
    t = np.linspace(0.0, flight.duration_s, steps) - flight.duration_s / 2.0  # from the epoch, mid-run
    fixed = inertial_to_body_fixed(body, epoch, kepler_state(body, orbit, t)[0], t)
    to_enu = enu_rotation(lat0, lon0)
    local = (fixed - centre) @ to_enu.T
    nadir = -up_vectors(body, fixed) @ to_enu.T
    along = np.gradient(local, t, axis=0)
    return Trajectory(flight.start_gps_time + t + flight.duration_s / 2.0, local + scene.origin,
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
        lon, lat, _ = (np.radians(a) for a in transform("EPSG:4978", "EPSG:4979", p[:, 0], p[:, 1], p[:, 2]))
        return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def scene_geodetic(body: Body, scene: Scene) -> tuple[float, float]:
    """Geodetic latitude, longitude [deg] of the scene origin: through its CRS on the Earth; on the Moon
    the scene's local frame is taken at latitude, longitude 0, 0."""
    if body.name != "earth":
        return 0.0, 0.0
    lon, lat = transform(scene.crs, "EPSG:4326", scene.origin[0], scene.origin[1])
    return float(lat), float(lon)


def local_to_geodetic(body_name: str | None, scene: Scene,
                      local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(latitude, longitude [deg], height [m]) of local points (n, 3): through the tangent plane and the
    body ``body_name`` orbited (heights above the WGS84 ellipsoid or the Moon's sphere), else (None: not from
    orbit) through the scene's projected CRS (world = origin + local; heights as the scene's)."""
    local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    if body_name is None:
        world = scene.local_to_world(local)
        lon, lat = transform(scene.crs, "EPSG:4326", world[:, 0], world[:, 1])
        return lat, lon, world[:, 2]
    body = BODIES[body_name]
    lat0, lon0 = scene_geodetic(body, scene)
    fixed = geodetic_to_body_fixed(body, lat0, lon0, scene.origin[2]) + local @ enu_rotation(lat0, lon0)
    if body.name == "earth":
        lon, lat, h = transform("EPSG:4978", "EPSG:4979", fixed[:, 0], fixed[:, 1], fixed[:, 2])
        return lat, lon, h
    r = np.linalg.norm(fixed, axis=1)
    return (np.degrees(np.arcsin(fixed[:, 2] / r)), np.degrees(np.arctan2(fixed[:, 1], fixed[:, 0])),
            r - body.radius_m)
