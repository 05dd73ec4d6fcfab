"""Float64 NumPy model of large-footprint waveforms summed from an ALS point cloud by the GEDI simulator's
method (Blair & Hofton 1999, GRL 26:2509; Hancock et al. 2019, Earth and Space Science 6:294; gediRat,
github.com/jhammer619/gedisimulator, ``waveFromPointCloud`` in gediIO.c). The reference that the device
version (:mod:`kernels.cloud_waveform`, :mod:`flightsim.engine.cloud_waveforms`) is tested against, and its
CPU stand-in in benchmarks; its neighbour search (SciPy's cKDTree) and its pulse sum (each point's Gaussian
evaluated at every sample within ``MODEL_PULSE_SIGMAS`` σ of it) are its own.

The method, for a footprint centred at (x, y) with a beam along the unit vector d (zenith angle θ, azimuth α
clockwise from grid north: d = (sin θ sin α, sin θ cos α, −cos θ)):
- The beam axis passes through C = (x, y, ``centre_z_m``); a point p lies t = (p − C)·d along it and
  ρ = |(p − C) − t d| from it. Its range, from the plane z = ``z_top``, is s = (z_top − centre_z)/cos θ + t
  (nadir: s = z_top − z, ρ the horizontal distance, exactly).
- Each point within ``cut_sigmas`` σ_f of the axis weighs w = ρ_class · exp(−ρ²/2σ_f²) (gediRat's Gaussian
  wavefront; it cuts where the normalised Gaussian drops below iThresh = 0.0006, i.e. at 3.10 σ_f for
  σ_f = 5.5 m). Cutting at k σ_f loses exp(−k²/2) of a uniform footprint's energy: 0.83 % at 3.10, 0.22 % at
  3.5 (the default), 0.04 % at 4. No intensity weighting (gediRat's "count" waveform).
- ρ_class: ``rho_ground`` for class 2, ``rho_canopy`` for every other class (vegetation, buildings,
  unclassified): gediRat splits its ground waveform (class 2) from the rest the same way. gediRat itself
  weighs every point alike (ρ_ground = ρ_canopy) and applies rhoG = 0.4, rhoC = 0.57 in gediMetric's
  cover; here they weigh the waveform, as a waveform from surfaces of those reflectances would be.
- ``normalise`` (gediRat's normCover, on by default there, ``-noNorm`` turns it off): each point's weight is
  divided by the number of last returns (return number = number of returns) in its 1.5 m cell, so that
  densely scanned patches (overlapping strips) do not outweigh the rest. gediRat lays its 1.5 m grid per
  footprint; here it is one grid for the whole cloud, from the lower-left corner of its bounding box.
- The waveform is the sum of the points' pulses, Gaussians of σ_r = c σ_p / 2 in range, sampled at
  r_i = window start + i c dt / 2; ``ground`` and ``canopy`` are the sums over class 2 and over the rest,
  ``rx`` = ground + canopy.
- Energy: every waveform of a footprint is divided by Σ w over the footprint's points, so that ∫ rx dr = 1
  [1/m] (gediRat's "normalise integral" in makeGediWaves, there over its bins): each sample is the relative
  energy per metre of range. A window that does not hold the whole echo shows it (its integral is below 1).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.pointcloud import CLASS_GROUND, PointCloud
from flightsim.scenes.scene import DEFAULT_ORIGIN, parse_crs

C = 299_792_458.0  # speed of light [m/s]
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
GEDI_PULSE_FWHM_S = 15e-9  # gediRat's pFWHM default [s]: σ_p = 6.37 ns, 0.955 m in range
GEDI_FOOTPRINT_SIGMA_M = 5.5  # gediRat's fSigma default [m]: 86 % of the energy within a 22 m diameter
NORMALISE_CELL_M = 1.5  # gediRat's gridRes for normCover [m]
COVER_SIGMAS = 3.0  # a footprint with no point within this many σ_f of its axis is outside the cloud
MODEL_PULSE_SIGMAS = 7.0  # the model sums each pulse over ±7 σ_r (the rest: 2.6e-12 of its energy)
MAX_SAMPLES = 65536


@dataclass(frozen=True)
class CloudBeam:
    """The large-footprint beam: footprint and pulse widths (GEDI's by default), direction and cut.

    Attributes:
        footprint_sigma_m: σ_f of the Gaussian footprint across the beam [m].
        pulse_sigma_s: σ of the Gaussian pulse in time [s] (two-way: σ_r = c σ / 2 in range).
        zenith_deg: incidence zenith angle θ of the beam [deg], in [0, 60].
        azimuth_deg: azimuth α of the beam's horizontal travel, clockwise from grid north [deg].
        centre_z_m: local height at which the beam axis passes through the footprint centres [m] (only
            off nadir does it matter; 0 = the lowest ground of a cloud read with its default origin).
        cut_sigmas: points farther than this many σ_f from the axis are left out.
    """

    footprint_sigma_m: float = GEDI_FOOTPRINT_SIGMA_M
    pulse_sigma_s: float = GEDI_PULSE_FWHM_S / FWHM_PER_SIGMA
    zenith_deg: float = 0.0
    azimuth_deg: float = 0.0
    centre_z_m: float = 0.0
    cut_sigmas: float = 3.5

    def check(self) -> None:
        """InputError naming the first field out of its range."""
        for name, lo, hi in (("footprint_sigma_m", 0.01, 1000.0), ("pulse_sigma_s", 1e-12, 1e-6),
                             ("zenith_deg", 0.0, 60.0), ("azimuth_deg", -360.0, 360.0),
                             ("centre_z_m", -1e5, 1e5), ("cut_sigmas", COVER_SIGMAS, 6.0)):
            value = getattr(self, name)
            if not (_real(value) and math.isfinite(value) and lo <= value <= hi):
                raise InputError(f"cloud_waveform.{name}", value, f"a finite number in [{lo:g}, {hi:g}]")

    def direction(self) -> np.ndarray:
        """(3,) unit vector d along the beam, pointing down."""
        theta, alpha = math.radians(self.zenith_deg), math.radians(self.azimuth_deg)
        return np.array([math.sin(theta) * math.sin(alpha), math.sin(theta) * math.cos(alpha), -math.cos(theta)])

    def range_sigma_m(self) -> float:
        """σ_r = c σ_p / 2 [m]."""
        return C * self.pulse_sigma_s / 2.0


def check_request(centres_xy, z_top: float, window_start_m, dt_s: float, samples: int,
                  beam: CloudBeam) -> tuple[np.ndarray, np.ndarray]:
    """(centres (F, 2) float64, window starts (F,) float64) of a valid request, else InputError."""
    beam.check()
    centres = np.asarray(centres_xy, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) == 0 or not np.isfinite(centres).all():
        raise InputError("cloud_waveform.centres_xy", f"an array of shape {centres.shape}",
                         "(F, 2) finite local x, y [m], F ≥ 1")
    starts = np.broadcast_to(np.asarray(window_start_m, dtype=np.float64), (len(centres),)).copy()
    if not np.isfinite(starts).all():
        raise InputError("cloud_waveform.window_start_m", window_start_m, "finite ranges [m], one or one per footprint")
    if not (_real(z_top) and math.isfinite(z_top)):
        raise InputError("cloud_waveform.z_top", z_top, "a finite local height [m]")
    if not (_real(dt_s) and math.isfinite(dt_s) and 1e-13 <= dt_s <= 1e-6):
        raise InputError("cloud_waveform.dt_s", dt_s, "a sample interval in [1e-13, 1e-6] s")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or not 1 <= samples <= MAX_SAMPLES:
        raise InputError("cloud_waveform.samples", samples, f"an integer in [1, {MAX_SAMPLES}]")
    return centres, starts


def _real(value) -> bool:
    """A real number (a NumPy scalar too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def point_weights(cloud: PointCloud, rho_ground: float, rho_canopy: float, normalise: bool) -> np.ndarray:
    """(N,) float64 weight of each point: its class's reflectance, divided by the last returns in its
    NORMALISE_CELL_M cell when ``normalise`` (a cell without one leaves its points' weights as they are)."""
    for name, rho in (("scene.rho_ground", rho_ground), ("scene.rho_canopy", rho_canopy)):
        if not (_real(rho) and 0.0 < rho <= 1.0):
            raise InputError(name, rho, "a reflectance in (0, 1]")
    weights = np.where(cloud.ground, float(rho_ground), float(rho_canopy))
    if normalise:
        lo = cloud.bounds()[0]
        ix = ((cloud.xyz[:, 0] - lo[0]) / NORMALISE_CELL_M).astype(np.int64)
        iy = ((cloud.xyz[:, 1] - lo[1]) / NORMALISE_CELL_M).astype(np.int64)
        cell = iy * (int(ix.max()) + 1) + ix
        last = np.bincount(cell, weights=cloud.return_number == cloud.number_of_returns)
        weights = weights / np.maximum(last[cell], 1.0)
    return weights


def model_waveforms(cloud: PointCloud, centres_xy, z_top: float, window_start_m, dt_s: float, samples: int,
                    beam: CloudBeam = CloudBeam(), rho_ground: float = 0.4, rho_canopy: float = 0.57,
                    normalise: bool = False) -> dict[str, np.ndarray]:
    """Waveforms of the footprints centred at ``centres_xy`` (F, 2) local [m], each sampled at ranges
    ``window_start_m`` (one, or (F,)) + i c ``dt_s`` / 2, i < ``samples``, from the plane z = ``z_top`` [m].

    Returns (float64): ``rx``, ``ground``, ``canopy`` (F, samples) [1/m] (see the module's notes) and
    ``near`` (F,) the points within COVER_SIGMAS σ_f of each axis (0: the footprint is outside the cloud).
    """
    from scipy.spatial import cKDTree

    centres, starts = check_request(centres_xy, z_top, window_start_m, dt_s, samples, beam)
    weights = point_weights(cloud, rho_ground, rho_canopy, normalise)
    tree = cKDTree(cloud.xyz[:, :2])
    shift, reach = _search_disc(cloud, beam)
    out = {name: np.zeros((len(centres), samples)) for name in ("rx", "ground", "canopy")}
    out["near"] = np.zeros(len(centres), dtype=np.int64)
    for f, centre in enumerate(centres):
        found = np.asarray(tree.query_ball_point(centre + shift, reach), dtype=np.int64)
        _footprint(cloud, weights, found, centre, z_top, starts[f], dt_s, beam, out, f)
    return out


def _search_disc(cloud: PointCloud, beam: CloudBeam) -> tuple[np.ndarray, float]:
    """(offset of the disc's centre from a footprint centre, its radius) [m]: a horizontal disc holding every
    point within cut_sigmas σ_f of a beam axis over the cloud's heights."""
    lo, hi = cloud.bounds()
    d = beam.direction()
    along = (beam.centre_z_m - np.array([lo[2], hi[2]])) / -d[2]  # t where the axis crosses the lowest, highest z
    ends = along[:, None] * d[None, :2]
    radius = beam.cut_sigmas * beam.footprint_sigma_m / -d[2]
    return ends.mean(axis=0), radius + 0.5 * float(np.hypot(*(ends[1] - ends[0]))) + 1e-9


def _footprint(cloud, weights, found, centre, z_top, start, dt_s, beam: CloudBeam, out, f) -> None:
    """Fill row ``f`` of ``out`` from the candidate points ``found`` of the footprint at ``centre``."""
    d = beam.direction()
    q = cloud.xyz[found] - np.array([centre[0], centre[1], beam.centre_z_m])
    t = q @ d
    rho2 = np.sum((q - t[:, None] * d) ** 2, axis=1)
    sigma_f = beam.footprint_sigma_m
    out["near"][f] = int(np.count_nonzero(rho2 < (COVER_SIGMAS * sigma_f) ** 2))
    keep = rho2 <= (beam.cut_sigmas * sigma_f) ** 2
    w = weights[found[keep]] * np.exp(-rho2[keep] / (2.0 * sigma_f ** 2))
    total = w.sum()
    if total <= 0.0:
        return
    s = (z_top - beam.centre_z_m) / -d[2] + t[keep]
    ground = cloud.classification[found[keep]] == CLASS_GROUND
    step, sigma_r = C * dt_s / 2.0, beam.range_sigma_m()
    out["ground"][f] = _pulse_sum(s[ground], w[ground], start, step, sigma_r, out["rx"].shape[1]) / total
    out["canopy"][f] = _pulse_sum(s[~ground], w[~ground], start, step, sigma_r, out["rx"].shape[1]) / total
    out["rx"][f] = out["ground"][f] + out["canopy"][f]


def _pulse_sum(s: np.ndarray, w: np.ndarray, start: float, step: float, sigma: float, samples: int) -> np.ndarray:
    """Σ_p w_p N(r_i; s_p, σ) [1/m] at r_i = start + i·step, each pulse over the samples within
    MODEL_PULSE_SIGMAS σ of it."""
    reach = int(math.ceil(MODEL_PULSE_SIGMAS * sigma / step))
    nearest = np.rint((s - start) / step).astype(np.int64)
    wave = np.zeros(samples)
    norm = 1.0 / (sigma * math.sqrt(2.0 * math.pi))
    for k in range(-reach, reach + 1):  # one pass per offset: memory stays O(points)
        i = nearest + k
        inside = (i >= 0) & (i < samples)
        u = (start + i[inside] * step - s[inside]) / sigma
        wave += np.bincount(i[inside], weights=w[inside] * norm * np.exp(-0.5 * u * u), minlength=samples)
    return wave


def sample_heights(z_top: float, window_start_m, dt_s: float, samples: int, beam: CloudBeam = CloudBeam()):
    """(F, samples) local heights [m] of the samples on the beam axis (nadir: z_top − range)."""
    ranges = np.asarray(window_start_m, dtype=np.float64).reshape(-1, 1) + np.arange(samples) * (C * dt_s / 2.0)
    return z_top + ranges * beam.direction()[2]


def waveform_metrics(rx: np.ndarray, ground: np.ndarray, heights: np.ndarray,
                     percentiles=(50.0, 98.0)) -> dict[str, np.ndarray]:
    """Ground elevation and relative heights of waveforms (F, S) over sample heights (F, S) or (S,) [m].

    ``ground_z``: the centroid height of the ground component. ``rh<p>``: the height at which the energy of
    ``rx`` accumulated from the lowest sample up reaches p % of the total, minus ``ground_z`` (GEDI's rh
    metrics with the true ground); each sample holds its energy evenly over its bin (between the midpoints to
    its neighbours), so the accumulated energy is linear within a bin. NaN where a waveform has no (ground)
    energy.
    """
    rx, ground = np.atleast_2d(rx).astype(np.float64), np.atleast_2d(ground).astype(np.float64)
    heights = np.broadcast_to(heights, rx.shape).astype(np.float64)
    order = np.argsort(heights, axis=1, kind="stable")
    h, energy = np.take_along_axis(heights, order, 1), np.take_along_axis(rx, order, 1)
    middle = (h[:, 1:] + h[:, :-1]) / 2.0
    edges = np.column_stack([2.0 * h[:, 0] - middle[:, 0], middle, 2.0 * h[:, -1] - middle[:, -1]])
    with np.errstate(invalid="ignore", divide="ignore"):
        ground_z = (ground * heights).sum(axis=1) / ground.sum(axis=1)
        cumulative = np.column_stack([np.zeros(len(rx)), np.cumsum(energy, axis=1)]) / energy.sum(1, keepdims=True)
    out = {"ground_z": ground_z}
    rows = np.arange(len(rx))
    for p in percentiles:
        level = p / 100.0
        above = np.maximum(np.argmax(cumulative >= level, axis=1), 1)  # the first edge the energy reaches it at
        c0, c1 = cumulative[rows, above - 1], cumulative[rows, above]
        fraction = np.where(c1 > c0, (level - c0) / np.where(c1 > c0, c1 - c0, 1.0), 1.0)
        height = edges[rows, above - 1] + fraction * (edges[rows, above] - edges[rows, above - 1])
        out[f"rh{p:g}"] = height - ground_z
    return out


def synthetic_forest(points: int = 100_000, density_m2: float = 15.0, seed: int = 0,
                     crs: str = "EPSG:32648") -> PointCloud:
    """About ``points`` ALS returns of a synthetic forest, ``density_m2`` returns per m² over a square centred
    on local (0, 0) (origin: the default scene origin), for tests and benchmarks.

    Ground: z = 0.03 x + 0.02 y + 0.8 sin(x / 17 m) cos(y / 23 m) [m]. Trees: 1 per 80 m², heights 8–35 m,
    paraboloid crowns of radius 0.2 h and depth 0.5 h. Each pulse (uniform in x, y) under a crown returns at
    the crown surface less up to 30 % of its depth (class 5), then with probability 0.4 at the ground (class 2);
    elsewhere at the ground, or 1 time in 10 at low vegetation 0.2–1.5 m above it (class 3).
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng([int(seed), 0xC10D])
    side = math.sqrt(points / density_m2)
    pulses = int(points / 1.25)
    xy = rng.uniform(-side / 2.0, side / 2.0, (pulses, 2))
    trees = rng.uniform(-side / 2.0, side / 2.0, (max(int(side * side / 80.0), 1), 2))
    height = rng.uniform(8.0, 35.0, len(trees))
    ground_z = 0.03 * xy[:, 0] + 0.02 * xy[:, 1] + 0.8 * np.sin(xy[:, 0] / 17.0) * np.cos(xy[:, 1] / 23.0)
    distance, index = cKDTree(trees).query(xy, k=min(4, len(trees)))
    distance, index = distance.reshape(pulses, -1), index.reshape(pulses, -1)
    radius = 0.2 * height[index]
    crown = np.where(distance < radius, height[index] * (1.0 - 0.5 * (distance / radius) ** 2), -np.inf).max(axis=1)
    in_crown = np.isfinite(crown)
    top = np.where(in_crown, ground_z + crown - rng.uniform(0.0, 0.15, pulses) * np.where(in_crown, crown, 0.0),
                   ground_z)
    low = ~in_crown & (rng.random(pulses) < 0.1)
    top[low] += rng.uniform(0.2, 1.5, int(low.sum()))
    second = in_crown & (rng.random(pulses) < 0.4)
    xyz = np.concatenate([np.column_stack([xy, top]), np.column_stack([xy[second], ground_z[second]])])
    classes = np.concatenate([np.where(in_crown, 5, np.where(low, 3, 2)), np.full(int(second.sum()), 2)])
    count = np.concatenate([np.where(second, 2, 1), np.full(int(second.sum()), 2)]).astype(np.uint8)
    number = np.concatenate([np.ones(pulses), np.full(int(second.sum()), 2)]).astype(np.uint8)
    return PointCloud(xyz, classes.astype(np.uint8), number, count, parse_crs(crs), np.array(DEFAULT_ORIGIN))
