"""A procedural forest stand: where the trees stand, how tall they are, their crowns and their stems.

All lengths in metres, in the scene's local frame (east, north, up; SPEC §2).

- **Positions**: a hard-core point process in the square stand of side ``size_m`` centred on the local origin.
  The number of stems is Poisson with mean ``stems_per_ha`` × area / 10⁴ m²; they are placed by simple
  sequential inhibition (Diggle 1983, *Statistical analysis of spatial point patterns*; the "Poisson-disc"
  dart throwing of graphics): uniform candidates, each kept when no kept stem lies within ``min_spacing_m``,
  until the count is reached. Candidates are drawn and tested in batches; the result is the sequential
  process's (a candidate is judged only against those before it).
- **Heights**: normal (``height_m``, ``height_sd_m``) truncated to [HEIGHT_MIN_M, HEIGHT_MAX_M] (inverse CDF).
- **Crowns**: solids of revolution about the stem's axis reaching the tree top, of radius
  ``crown_ratio_radius`` × height and length ``crown_length_ratio`` × height: ``cone`` (apex at the top,
  widest at the crown base), ``ellipsoid`` (a spheroid) or ``cylinder``. Leaf area density is uniform inside
  every crown and the same in all: LAD = ``lai`` × stand area / Σ crown volumes, so the stand's total leaf
  area (where crowns overlap their leaf areas add) over the stand's area is ``lai``.
- **Stems**: cylinders from the ground to the crown base, of diameter at breast height from the global
  allometry of Jucker et al. (2017), *Allometric equations for integrating remote sensing imagery into forest
  monitoring programmes*, Global Change Biology 23:177–190 (doi:10.1111/gcb.13388), fitted to ~108,000 trees:
  D [cm] = 0.557 × (H [m] × CD [m])^0.809 × exp(0.056²/2), CD the crown diameter.
- **Ground**: :class:`PlaneGround`, flat or sloped. Anything with the same two methods (``height``,
  ``lowest``) stands in for it: the hook for a DEM's ground.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError

CROWN_SHAPES = ("cone", "ellipsoid", "cylinder")
HEIGHT_MIN_M, HEIGHT_MAX_M = 2.0, 80.0
JUCKER_A, JUCKER_B, JUCKER_SIGMA = 0.557, 0.809, 0.056  # D [cm] = A (H CD)^B exp(σ²/2)
MAX_PACKING = 0.4  # stems × π (spacing/2)² / area at most: below the jamming limit 0.547 of sequential inhibition
STREAM = 0xF0E57  # the stand's random streams: [seed, STREAM, 0] positions, [seed, STREAM, 1] heights
_BATCH_MIN, _BATCH_MAX = 256, 1 << 18
_MAX_CANDIDATES_PER_STEM = 1000


@dataclass(frozen=True)
class StandSpec:
    """What a stand is drawn from (the ``forest_*`` settings of the scene, without the prefix)."""

    size_m: float
    stems_per_ha: float
    min_spacing_m: float
    height_m: float
    height_sd_m: float
    crown_shape: str
    crown_ratio_radius: float
    crown_length_ratio: float
    lai: float


@dataclass(frozen=True)
class PlaneGround:
    """Flat or uniformly sloped ground through the local origin: z = −slope·y [m] (descending towards grid north
    for slope > 0, as the plane scene's)."""

    slope: float = 0.0

    def height(self, x, y) -> np.ndarray:
        """Local ground height z [m] at local (x, y) [m]."""
        return np.zeros_like(np.asarray(x, dtype=np.float64)) - self.slope * np.asarray(y, dtype=np.float64)

    def lowest(self, x, y, radius) -> np.ndarray:
        """Lowest ground height [m] within ``radius`` [m] of local (x, y) [m]."""
        return self.height(x, y) - abs(self.slope) * np.asarray(radius, dtype=np.float64)


@dataclass(frozen=True)
class Trees:
    """A stand's trees (arrays of one value per tree, local frame [m]).

    Attributes:
        x, y: stem axis, local [m].
        base_z: local ground height at the stem axis [m]; every other height is above it.
        height: tree height above the ground [m] (the crown's top).
        crown_radius: largest horizontal radius of the crown [m].
        crown_base: height of the crown's bottom above the ground [m] (where the stem ends).
        dbh: stem diameter at breast height [m].
        shape: crown shape, one of CROWN_SHAPES (the same for every tree).
        lad: leaf area density inside every crown [m²/m³].
        size_m: side of the square stand [m], centred on the local origin.
    """

    x: np.ndarray
    y: np.ndarray
    base_z: np.ndarray
    height: np.ndarray
    crown_radius: np.ndarray
    crown_base: np.ndarray
    dbh: np.ndarray
    shape: str
    lad: float
    size_m: float

    def __len__(self) -> int:
        return len(self.x)

    @property
    def crown_length(self) -> np.ndarray:
        """Vertical extent of each crown [m]."""
        return self.height - self.crown_base

    def crown_volume(self) -> np.ndarray:
        """Analytic volume of each crown [m³]."""
        return crown_volume(self.shape, self.crown_radius, self.crown_length)

    def crown_bottom_z(self) -> np.ndarray:
        """Local z of each crown's bottom [m]."""
        return self.base_z + self.crown_base

    def top_z(self) -> np.ndarray:
        """Local z of each tree's top [m]."""
        return self.base_z + self.height


def crown_volume(shape: str, radius, length) -> np.ndarray:
    """Volume [m³] of crowns of ``shape`` with largest radius ``radius`` [m] and length ``length`` [m]."""
    factor = {"cone": 1.0 / 3.0, "ellipsoid": 2.0 / 3.0, "cylinder": 1.0}[shape]
    return factor * math.pi * np.asarray(radius, dtype=np.float64) ** 2 * np.asarray(length, dtype=np.float64)


def crown_radius_at(shape: str, t) -> np.ndarray:
    """Crown radius as a fraction of the largest at relative height ``t`` = (z − bottom) / length in [0, 1]."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    if shape == "cone":
        return 1.0 - t
    if shape == "ellipsoid":
        return 2.0 * np.sqrt(t * (1.0 - t))
    return np.ones_like(t)


def crown_top(shape: str, crown_base, length, radius, rho) -> np.ndarray:
    """Height above the ground [m] of the crown's top surface at horizontal distance ``rho`` [m] from the axis;
    −inf beyond the crown's radius. Each surface falls monotonically with ``rho``."""
    crown_base, length, radius, rho = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64)
                                                            for v in (crown_base, length, radius, rho)))
    q = np.minimum(rho / radius, 1.0)
    if shape == "cone":
        top = crown_base + length * (1.0 - q)
    elif shape == "ellipsoid":
        top = crown_base + 0.5 * length * (1.0 + np.sqrt(1.0 - q * q))
    else:
        top = crown_base + length
    return np.where(rho <= radius, top, -np.inf)


def box_cells(i0: np.ndarray, ni: np.ndarray, j0: np.ndarray, nj: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every cell (i, j) of the boxes i0 ≤ i < i0 + ni, j0 ≤ j < j0 + nj (one box per entry): the box's entry
    index, i and j, box after box, j fastest."""
    count = ni * nj
    owner = np.repeat(np.arange(len(count)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return owner, i0[owner] + local // nj[owner], j0[owner] + local % nj[owner]


def stem_dbh(height, crown_radius) -> np.ndarray:
    """Diameter at breast height [m] from height and crown radius [m] (Jucker et al. 2017, global model)."""
    h_cd = np.asarray(height, dtype=np.float64) * 2.0 * np.asarray(crown_radius, dtype=np.float64)
    return 0.01 * JUCKER_A * h_cd ** JUCKER_B * math.exp(JUCKER_SIGMA ** 2 / 2.0)


def truncated_normal(rng: np.random.Generator, count: int, mean: float, sd: float, lo: float, hi: float):
    """``count`` draws of a normal (``mean``, ``sd``) truncated to [lo, hi] (inverse CDF); ``mean`` if sd is 0."""
    if sd == 0.0:
        return np.full(count, float(mean))
    from scipy.special import ndtr, ndtri  # here, as the other SciPy imports: a run without a forest never loads it

    u = rng.uniform(ndtr((lo - mean) / sd), ndtr((hi - mean) / sd), count)
    return np.clip(mean + sd * ndtri(u), lo, hi)


def hard_core_positions(rng: np.random.Generator, count: int, size_m: float, min_spacing_m: float) -> np.ndarray:
    """(count, 2) local (x, y) [m] in the square of side ``size_m`` centred on the origin, no two closer than
    ``min_spacing_m``, by simple sequential inhibition. InputError when the square is too full to finish."""
    half = size_m / 2.0
    kept, tried, rate = np.empty((0, 2)), 0, 1.0
    while len(kept) < count:
        need = count - len(kept)
        batch = int(min(max(math.ceil(1.25 * need / max(rate, 1e-4)), _BATCH_MIN), _BATCH_MAX))
        candidates = rng.uniform(-half, half, (batch, 2))
        accepted = _inhibit(kept, candidates, min_spacing_m)
        kept = np.concatenate([kept, accepted[:need]])
        tried, rate = tried + batch, len(accepted) / batch
        if len(kept) < count and tried > _MAX_CANDIDATES_PER_STEM * count + 10 * _BATCH_MAX:
            raise InputError("scene.forest_min_spacing_m", min_spacing_m,
                             f"a spacing that leaves room for {count} stems in the stand (fewer stems or less spacing)")
    return kept


def _inhibit(kept: np.ndarray, candidates: np.ndarray, spacing: float) -> np.ndarray:
    """The candidates, in order, that lie ``spacing`` or more from every kept point and every earlier accepted
    candidate."""
    if spacing <= 0.0:
        return candidates
    from scipy.spatial import cKDTree

    ok = np.ones(len(candidates), dtype=bool)
    if len(kept):
        distance, _ = cKDTree(kept).query(candidates, distance_upper_bound=spacing)
        ok = ~(distance < spacing)
    pairs = cKDTree(candidates).query_pairs(spacing, output_type="ndarray")
    if len(pairs):
        gap = np.hypot(*(candidates[pairs[:, 0]] - candidates[pairs[:, 1]]).T)
        pairs = np.sort(pairs[gap < spacing], axis=1)
        pairs = pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]
        later, starts = np.unique(pairs[:, 1], return_index=True)
        ends = np.append(starts[1:], len(pairs))
        for j, lo, hi in zip(later.tolist(), starts.tolist(), ends.tolist()):
            if ok[j] and ok[pairs[lo:hi, 0]].any():  # an earlier candidate within the spacing was accepted
                ok[j] = False
    return candidates[ok]


def grow_stand(spec: StandSpec, seed: int, ground=None) -> Trees:
    """The stand of ``spec`` drawn from ``seed`` (the same seed, the same trees), on ``ground``
    (:class:`PlaneGround` or anything with its methods; default flat at z = 0)."""
    ground = PlaneGround() if ground is None else ground
    if spec.crown_shape not in CROWN_SHAPES:
        raise InputError("scene.forest_crown_shape", spec.crown_shape, "one of " + ", ".join(CROWN_SHAPES))
    area = spec.size_m ** 2
    positions = np.random.default_rng([int(seed), STREAM, 0])
    count = int(positions.poisson(spec.stems_per_ha * area / 1.0e4))
    xy = hard_core_positions(positions, count, spec.size_m, spec.min_spacing_m)
    height = truncated_normal(np.random.default_rng([int(seed), STREAM, 1]), count, spec.height_m,
                              spec.height_sd_m, HEIGHT_MIN_M, HEIGHT_MAX_M)
    radius = spec.crown_ratio_radius * height
    length = spec.crown_length_ratio * height
    volume = crown_volume(spec.crown_shape, radius, length).sum()
    return Trees(x=xy[:, 0].copy(), y=xy[:, 1].copy(), base_z=ground.height(xy[:, 0], xy[:, 1]), height=height,
                 crown_radius=radius, crown_base=height - length, dbh=stem_dbh(height, radius),
                 shape=spec.crown_shape, lad=float(spec.lai * area / volume) if count else 0.0,
                 size_m=float(spec.size_m))
