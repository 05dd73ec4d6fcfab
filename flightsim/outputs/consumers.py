"""Consumers of simulated returns left on the device: per-plane and per-patch fit statistics (LAS tiles:
``device_las``)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.core.atomic import replaced_atomically
from flightsim.core.constants import MODELS
from flightsim.core.errors import InputError
from flightsim.scoring.planes import PlaneMoments, pooled_rms
from flightsim.scoring.reduction import SLOTS_PER_THREAD, reduce_models, replica_totals, symmetric
from kernels import statistics


AUTO_PATCH_M = 25.0
"""Side of the fit patches on a curved scene when ``scoring.patch_m`` is 0 [m]."""
MAX_PATCHES = 1 << 21
"""Patches a run may fit (each holds 2 × 80 bytes of sums per replica on the device)."""
MIN_PATCH_POINTS = 10
"""Returns a patch needs for its fit to be reported."""


class _DeviceMoments:
    """Per-group float64 moments of each model's points on the device (the statistics-mode reduction,
    :func:`kernels.statistics.reduce_records`), fed one chunk of codes at a time: the group of each slot."""

    def __init__(self, simulator, references: np.ndarray):
        """references: (G, 3) float64 reference point of each group [m, local]."""
        d = simulator.device
        self.device, self.models = d, simulator.models
        self.slots_per_thread = SLOTS_PER_THREAD[simulator.device_kind]
        self.reference_points = np.asarray(references, dtype=np.float64)
        self.references = wp.array(self.reference_points, dtype=wp.vec3d, device=d)
        shape = (simulator.sum_replicas(len(references)), 2, len(references))
        self.sums = [wp.zeros(shape, dtype=wp.int64, device=d), wp.zeros(shape, dtype=wp.vec3d, device=d),
                     wp.zeros(shape, dtype=statistics.vec6d, device=d), wp.zeros(3, dtype=wp.int32, device=d)]
        self.codes: wp.array | None = None

    def kernels_needed(self, simulator) -> list:
        return [statistics.reduce_records]  # the codes' kernels share its module

    def codes_for(self, n_slots: int) -> wp.array:
        """The device array of at least ``n_slots`` codes to fill for :meth:`add`."""
        if self.codes is None or self.codes.shape[0] < n_slots:
            self.codes = wp.empty(n_slots, dtype=wp.int32, device=self.device)
        return self.codes

    def add(self, returns) -> None:
        """Reduce the chunk's points by the codes just written into :meth:`codes_for`'s array."""
        b, n, spt = returns.buffers, returns.n_slots, self.slots_per_thread
        reduce_models(self.codes, [b.model_points[m] for m in MODELS], self.models, n, spt, self.references,
                      self.sums, self.device)

    def moments(self) -> dict[str, PlaneMoments]:
        """Each model's moments, the replicas added (one device → host copy)."""
        count, first, second = replica_totals(self.sums[:3])
        out = {}
        for k, model in enumerate(MODELS):
            if model in self.models:
                out[model] = PlaneMoments(self.reference_points)
                out[model].add_sums(count[k], first[k], symmetric(second[k]))
        return out


class PlaneStatistics:
    """Per-plane float64 moments of each model's points, accumulated on the device chunk by chunk from the
    points kernel's slots (the statistics-mode reduction).

    Returns whose true hit lies within ``edge_buffer_m`` of a plane boundary are left out, the same rule
    statistics mode applies.
    """

    def __init__(self, simulator, edge_buffer_m: float = 0.0):
        scene = simulator.scene
        self.edge_buffer_m = edge_buffer_m if simulator.features.edges else 0.0
        self.face_plane = wp.array(scene.plane_id.astype(np.int32), dtype=wp.int32, device=simulator.device)
        self.sums = _DeviceMoments(simulator, np.array([plane.point for plane in scene.planes], dtype=np.float64))

    def __call__(self, returns) -> None:
        b, n = returns.buffers, returns.n_slots
        wp.launch(statistics.plane_codes, n, inputs=[b.status, b.faces, b.edge_distance, self.face_plane,
                                                self.edge_buffer_m], outputs=[self.sums.codes_for(n)],
                  device=self.sums.device)
        self.sums.add(returns)

    def kernels_needed(self, simulator) -> list:
        return self.sums.kernels_needed(simulator)

    def rms_m(self) -> dict[str, float | None]:
        """Pooled plane-fit RMS of each model over all planes [m]."""
        return {model: _finite_or_none(pooled_rms(m.fits())) for model, m in self.sums.moments().items()}


@dataclass(frozen=True)
class PatchGrid:
    """Square patches over a scene's (x, y) extent, row-major from the lower-left corner ``low``."""

    low: tuple[float, float]  # local (x, y) of the lower-left corner [m]
    patch_m: float  # side of a patch [m]
    nx: int
    ny: int

    def centres(self) -> np.ndarray:
        """(nx·ny, 2) local (x, y) of every patch centre [m], row-major."""
        y, x = np.mgrid[0:self.ny, 0:self.nx]
        return np.stack([self.low[0] + (x.ravel() + 0.5) * self.patch_m,
                         self.low[1] + (y.ravel() + 0.5) * self.patch_m], axis=-1)


def patch_grid(scene, patch_m: float) -> PatchGrid | None:
    """The fit patches of a LAS run over ``scene`` for ``scoring.patch_m`` (0: :data:`AUTO_PATCH_M` on a
    curved scene, widened to stay within :data:`MAX_PATCHES`, none on a planar one).

    Raises:
        InputError: a set ``patch_m`` that would cut the scene into more than :data:`MAX_PATCHES`.
    """
    low, high = scene.bounds()
    width, height = max(high[0] - low[0], 1e-9), max(high[1] - low[1], 1e-9)
    if patch_m <= 0.0:
        if scene.planar:
            return None
        patch_m = max(AUTO_PATCH_M, math.ceil(math.sqrt(width * height / MAX_PATCHES) * 1.01))
    nx, ny = math.ceil(width / patch_m), math.ceil(height / patch_m)
    if nx * ny > MAX_PATCHES:
        least = math.sqrt(width * height / MAX_PATCHES)
        raise InputError("scoring.patch_m", f"{patch_m:g}",
                         f"≥ {math.ceil(least * 1.01):g} m for this {width:.0f} m × {height:.0f} m scene "
                         f"(at most {MAX_PATCHES} patches)")
    return PatchGrid((float(low[0]), float(low[1])), float(patch_m), nx, ny)


class PatchStatistics:
    """Plane fits over square patches of the ground: what a LAS run over curved ground (a DEM, a lunar or
    small-body surface) scores instead of whole planes, whose fits would measure the terrain's curvature.

    Each return counts in the patch holding its exact-model (x, y) (the nominal one without the exact
    model); both models' points of a return go to the same patch. A patch's RMS holds the curvature of
    the ground within it too: the exact model's RMS is that floor, and the nominal model's excess over
    it is the error of the nominal geolocation.
    """

    def __init__(self, simulator, grid: PatchGrid, edge_buffer_m: float = 0.0):
        self.grid = grid
        self.edge_buffer_m = edge_buffer_m if simulator.features.edges else 0.0
        self.selector = "exact" if "exact" in simulator.models else "nominal"
        self.sums = _DeviceMoments(simulator, self._references(simulator.scene, grid))

    @staticmethod
    def _references(scene, grid: PatchGrid) -> np.ndarray:
        """(nx·ny, 3) reference point of each patch: its centre at the mean height of the scene's vertices
        in it (the scene's ground height where it holds none), so the moment sums stay well conditioned."""
        xy = scene.vertices[:, :2]
        i = np.clip(np.floor((xy[:, 0] - grid.low[0]) / grid.patch_m), 0, grid.nx - 1).astype(np.int64)
        j = np.clip(np.floor((xy[:, 1] - grid.low[1]) / grid.patch_m), 0, grid.ny - 1).astype(np.int64)
        patch = j * grid.nx + i
        size = grid.nx * grid.ny
        count = np.bincount(patch, minlength=size)
        z = np.bincount(patch, weights=scene.vertices[:, 2], minlength=size) / np.maximum(count, 1)
        z[count == 0] = scene.ground_z
        return np.column_stack([grid.centres(), z])

    def __call__(self, returns) -> None:
        b, n, g = returns.buffers, returns.n_slots, self.grid
        wp.launch(statistics.patch_codes, n,
                  inputs=[b.status, b.model_points[self.selector], b.edge_distance, self.edge_buffer_m,
                          wp.vec2d(*g.low), g.patch_m, g.nx, g.ny],
                  outputs=[self.sums.codes_for(n)], device=self.sums.device)
        self.sums.add(returns)

    def kernels_needed(self, simulator) -> list:
        return self.sums.kernels_needed(simulator)

    def rms_grids(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Each model's (ny, nx) patch RMS [m] (NaN where fewer than :data:`MIN_PATCH_POINTS` returns) and
        the (ny, nx) returns per patch, row 0 the southernmost."""
        moments = self.sums.moments()
        shape = (self.grid.ny, self.grid.nx)
        rms = {model: m.rms_all(MIN_PATCH_POINTS).reshape(shape) for model, m in moments.items()}
        return rms, next(iter(moments.values())).count.reshape(shape)

    def summary(self, rms: dict[str, np.ndarray], count: np.ndarray) -> dict:
        """The run summary's ``patches`` entry: patch side, patches fitted, and each model's pooled
        (√(Σ n·rms² / Σ n)) and median patch RMS [m]."""
        fitted = np.isfinite(next(iter(rms.values())))
        weights = count[fitted]
        pooled = {m: _finite_or_none(float(np.sqrt(np.sum(weights * r[fitted] ** 2) / np.sum(weights))))
                  if fitted.any() else None for m, r in rms.items()}
        median = {m: float(np.median(r[fitted])) if fitted.any() else None for m, r in rms.items()}
        return {"patch_m": self.grid.patch_m, "patches": int(fitted.sum()), "min_points": MIN_PATCH_POINTS,
                "rms_m": pooled, "median_rms_m": median}

    def write(self, path: Path, scene) -> dict:
        """Write the patch raster (:func:`write_patch_raster`) to ``path``; return the summary entry."""
        rms, count = self.rms_grids()
        write_patch_raster(path, self.grid, scene, rms, count)
        return {**self.summary(rms, count), "raster": Path(path).name}


def write_patch_raster(path: Path, grid: PatchGrid, scene, rms: dict[str, np.ndarray], count: np.ndarray) -> None:
    """Write the patch grids as a north-up GeoTIFF (rasterio), atomically, on the patch grid in the scene's
    CRS: one float32 band per model (patch RMS [m], NaN = too few returns), then the returns per patch."""
    import rasterio
    from rasterio.transform import from_origin

    west = scene.origin[0] + grid.low[0]
    north = scene.origin[1] + grid.low[1] + grid.ny * grid.patch_m
    bands = [(f"{m} plane-fit RMS [m]", r) for m, r in rms.items()] + [("returns", count.astype(np.float64))]
    profile = dict(driver="GTiff", width=grid.nx, height=grid.ny, count=len(bands), dtype="float32",
                   crs=scene.crs.to_wkt(), transform=from_origin(west, north, grid.patch_m, grid.patch_m),
                   nodata=float("nan"), compress="deflate")
    with replaced_atomically(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        for k, (name, values) in enumerate(bands, start=1):
            dst.write(values[::-1].astype(np.float32), k)  # row 0 of a GeoTIFF is the northernmost
            dst.set_band_description(k, name)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None
