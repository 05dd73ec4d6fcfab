"""`flightsim forest`: the truth of a procedural forest stand (the ``forest`` scene,
:mod:`flightsim.scenes.forest_scene`), the reference for what a lidar retrieves from it.

Written into the output directory, each file atomically, the same bytes for the same settings and seed:

- ``chm.tif``: canopy height model, float32 GeoTIFF in the scene's CRS, north-up, cells of ``chm_cell_m``
  covering the stand square (its lower-left corner at the stand's, world = local + scene origin). A cell holds the
  highest point of any crown's top surface over the closed cell, above that tree's ground: exact, since every
  crown's top falls monotonically away from its axis, so the highest point over a cell is where the cell comes
  nearest the axis. 0 where no crown reaches (flat ground: the heights above the ground; on a slope each crown's
  height is above the ground at its stem).
- ``trees.csv``: tree_id, x_m, y_m (world E, N of the stem), ground_z_m (world H at the stem), height_m,
  crown_radius_m, crown_base_height_m, dbh_m.
- ``canopy.npz``: the leaf area density voxels of :func:`~flightsim.scenes.forest_voxels.stand_voxels` (through
  the scene cache with ``run.scene_cache``, as a forest run's): ``lad``
  float32 (nx, ny, nz) [m²/m³] indexed east, north, up; ``lower_world`` (3,) world E, N, H of voxel (0, 0, 0)'s
  lower corner [m]; ``cell`` (3,) [m]; ``crs`` the CRS as WKT; the leaves' ``leaf_angles``, ``leaf_reflectance``
  and ``leaf_transmittance``: the format of :mod:`flightsim.scenes.canopy_io`, so ``scene.canopy = ".../canopy.npz"``
  lays the stand's leaves over any scene.
- ``forest.json``: the ``[scene]`` settings and seed, the stem count and density, the target and achieved
  stand LAI (voxel leaf area / stand area), the crowns' leaf area density and the canopy cover (fraction of the
  stand square under a crown's vertical projection: the union of the crown discs, integrated over COVER_ROWS
  rows of exact interval unions).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from flightsim.core.atomic import write_atomic
from flightsim.core.errors import InputError
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.outputs.grid_products import write_geotiff
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import write_canopy_npz
from flightsim.scenes.forest import Trees, box_cells, crown_top
from flightsim.scenes.forest_scene import crown_voxels, stand, voxel_device
from flightsim.scenes.scene import parse_crs

FILES = ("chm.tif", "trees.csv", "canopy.npz", "forest.json")
COVER_ROWS = 4096
MAX_CHM_CELLS = 100_000_000
_CELLS_PER_CHUNK = 1 << 20


def forest_config(items=(), seed: int | None = None) -> RunConfig:
    """The default instrument's config over the forest scene, with ``items`` ((key, value) pairs such as
    ("scene.forest_lai", "4")) and ``seed`` set; validated."""
    cfg = preset_config("risley")
    set_value(cfg, "scene.name", "forest")
    for key, value in items:
        set_value(cfg, key, value)
    if seed is not None:
        set_value(cfg, "run.seed", seed)
    return validate(cfg)


def canopy_height_model(trees: Trees, cell_m: float) -> tuple[np.ndarray, float, float]:
    """Highest crown top above the ground [m] per cell of the stand square: ``(heights, west, north)``,
    heights (rows, columns) float64 north-up (row 0 the northernmost), 0 where no crown; (west, north) the local
    upper-left corner [m]. InputError naming --chm-cell-m for a cell that is not > 0 or too small."""
    if not (math.isfinite(cell_m) and 0.0 < cell_m <= 100.0):
        raise InputError("--chm-cell-m", cell_m, "a cell side in (0, 100] m")
    half, n = trees.size_m / 2.0, int(math.ceil(trees.size_m / cell_m - 1e-9))
    if n * n > MAX_CHM_CELLS:
        raise InputError("--chm-cell-m", cell_m, f"a cell of at least {trees.size_m / math.sqrt(MAX_CHM_CELLS):.3g} m "
                                                 f"(at most {MAX_CHM_CELLS:.0e} cells)")
    top = np.zeros(n * n)  # row r counts northwards: flat index r·n + c
    r = trees.crown_radius
    first = [np.clip(np.floor((v - r + half) / cell_m), 0, n - 1).astype(np.int64) for v in (trees.x, trees.y)]
    last = [np.clip(np.floor((v + r + half) / cell_m), 0, n - 1).astype(np.int64) for v in (trees.x, trees.y)]
    count = (last[0] - first[0] + 1) * (last[1] - first[1] + 1)
    for chunk in np.array_split(np.arange(len(trees)), max(1, int(count.sum() // _CELLS_PER_CHUNK) + 1)):
        owner, col, row = box_cells(first[0][chunk], (last[0] - first[0] + 1)[chunk],
                                    first[1][chunk], (last[1] - first[1] + 1)[chunk])
        tree = chunk[owner]
        west, south = -half + col * cell_m, -half + row * cell_m
        dx = np.maximum(np.maximum(west - trees.x[tree], trees.x[tree] - west - cell_m), 0.0)
        dy = np.maximum(np.maximum(south - trees.y[tree], trees.y[tree] - south - cell_m), 0.0)
        height = crown_top(trees.shape, trees.crown_base[tree], trees.crown_length[tree], r[tree], np.hypot(dx, dy))
        np.maximum.at(top, row * n + col, height)
    return top.reshape(n, n)[::-1].copy(), -half, -half + n * cell_m


def canopy_cover(trees: Trees, rows: int = COVER_ROWS) -> float:
    """Fraction of the stand square under the union of the crowns' discs: the covered length of each of ``rows``
    rows (midpoint rule in y) from the exact union of the discs' chords."""
    if len(trees) == 0:
        return 0.0
    half, step = trees.size_m / 2.0, trees.size_m / rows
    ys = -half + (np.arange(rows) + 0.5) * step
    order = np.argsort(trees.y, kind="stable")
    x, y, r = trees.x[order], trees.y[order], trees.crown_radius[order]
    lo = np.searchsorted(y, ys - r.max(), side="left")
    hi = np.searchsorted(y, ys + r.max(), side="right")
    covered = 0.0
    for k in range(rows):
        w2 = r[lo[k]:hi[k]] ** 2 - (ys[k] - y[lo[k]:hi[k]]) ** 2
        near = w2 > 0.0
        w, centre = np.sqrt(w2[near]), x[lo[k]:hi[k]][near]
        covered += _union_length(np.clip(centre - w, -half, half), np.clip(centre + w, -half, half))
    return covered * step / trees.size_m ** 2


def _union_length(start: np.ndarray, end: np.ndarray) -> float:
    """Length of the union of the intervals [start, end]."""
    if len(start) == 0:
        return 0.0
    order = np.argsort(start, kind="stable")
    start, end = start[order], end[order]
    reached = np.concatenate([[-np.inf], np.maximum.accumulate(end)[:-1]])
    return float(np.maximum(end - np.maximum(start, reached), 0.0).sum())


def trees_csv(trees: Trees, origin) -> str:
    """trees.csv: one row per tree, world coordinates [m] (``origin``: the scene's world E, N, H of local 0)."""
    e, n, h = (np.asarray(origin, dtype=np.float64)[i] for i in range(3))
    rows = zip(trees.x + e, trees.y + n, trees.base_z + h, trees.height, trees.crown_radius, trees.crown_base,
               trees.dbh)
    lines = ["tree_id,x_m,y_m,ground_z_m,height_m,crown_radius_m,crown_base_height_m,dbh_m"]
    lines += [f"{i},{x:.4f},{y:.4f},{z:.4f},{ht:.4f},{cr:.4f},{cb:.4f},{d:.4f}"
              for i, (x, y, z, ht, cr, cb, d) in enumerate(rows)]
    return "\n".join(lines) + "\n"


def run_forest(out: Path, items=(), seed: int | None = None, chm_cell_m: float = 1.0, device: str = "cpu") -> dict:
    """Write the four truth files of the forest of ``items`` (``[scene]`` settings as (key, value) pairs) and
    ``seed`` into ``out``, its leaf voxels integrated for a run on ``device`` (:func:`voxel_device`); returns
    forest.json's content. Everything is computed before any file is written."""
    cfg = forest_config([*items, ("run.device", device)], seed)
    out = Path(out)
    s, crs = cfg.scene, parse_crs(cfg.scene.crs)
    origin = np.asarray(s.origin, dtype=np.float64)
    trees = stand(s, cfg.run.seed)
    lad, lower, cell = crown_voxels(trees, s, cfg.run.seed, cfg.run.scene_cache, voxel_device(cfg.run.device))
    heights, west, north = canopy_height_model(trees, chm_cell_m)
    area = trees.size_m ** 2
    summary = {
        "seed": cfg.run.seed, "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in s.values().items()},
        "stems": len(trees), "stems_per_ha": len(trees) / area * 1.0e4, "lai_target": s.forest_lai,
        "lai_achieved": float(lad.sum(dtype=np.float64) * np.prod(cell) / area),
        "leaf_area_density_m2_m3": trees.lad, "canopy_cover": canopy_cover(trees), "chm_cell_m": chm_cell_m,
        "voxels": list(lad.shape), "voxel_m": float(cell[0]), "files": list(FILES),
    }
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError("--out", str(out), f"a directory that can be made ({exc.strerror})") from None
    write_geotiff(out / "chm.tif", heights, (west + origin[0], north + origin[1]), chm_cell_m, crs)
    write_atomic(out / "trees.csv", trees_csv(trees, origin))
    write_canopy_npz(out / "canopy.npz", VoxelCanopy(lad, lower, cell, s.forest_leaf_angles, s.forest_leaf_reflectance,
                                                     s.forest_leaf_transmittance), crs, origin)
    write_atomic(out / "forest.json", json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return summary
