"""A synthetic terrain for tests and benchmarks, so that neither needs a download.

    python3 -m flightsim.scenes.testdem --out DIR [--size-m 3000] [--cell-m 1] [--seed 0] [--crs EPSG:32648]

writes into DIR, on a square of ``size_m`` centred on (409000, 3393000) in ``crs``:
- ``dem.tif``: float32 heights [m] at ``cell_m`` pixels: a fractal relief (spectral synthesis, Hurst
  0.9, rolled off below 50 m wavelengths, RMS 40 m) around 450 m, cut by a meandering river valley
  (Gaussian, 60 m deep, half-width a tenth of the side) that falls gently to the east, its river 1 m
  below the valley floor;
- ``landcover.tif``: uint8 ASPRS codes on the same grid (:mod:`flightsim.scenes.landcover`): 9 water
  in the river, 5 high vegetation on slopes steeper than 0.35, 6 under the buildings, 2 elsewhere;
- ``buildings.obj``: a town of closed box buildings (flat or gable roofs, 10–22 m long, eaves 4–14 m
  above the highest ground under them, floors 1 m below the lowest) on a 30 m lot grid beside the
  river, in world coordinates, one OBJ group per face kind of each building.
The same seed gives the same files. :func:`terrain` gives the relief (no buildings) as a Scene of
about a requested number of triangles (1e4 … 5e7), for the scale benchmarks.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.dem import MAX_DEM_NODES, grid_scene
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, Scene, parse_crs

BASE_H = DEFAULT_ORIGIN[2]  # mean terrain height [m]
RELIEF_M, HURST, ROLLOFF_M = 40.0, 0.9, 50.0  # RMS [m], Hurst exponent, shortest wavelengths [m] of the relief
VALLEY_DEPTH_M, VALLEY_WIDTH, FALL = 60.0, 0.1, 0.002  # valley depth [m], half-width [side], eastward fall
RIVER_WIDTH = 0.01  # river half-width [side] (at least two cells)
TREE_SLOPE = 0.35  # land steeper than this (rise/run) is wooded
LOT_M, TOWN_HALF = 30.0, 0.08  # town lot spacing [m]; town half side [side], at most 240 m
CLASS_WATER, CLASS_TREES, CLASS_BUILDING, CLASS_GROUND = 9, 5, 6, 2


@dataclass
class Surface:
    """The relief on a square grid of nodes (rows from north to south)."""

    heights: np.ndarray  # (n, n) float32 world H [m]
    river_m: np.ndarray  # (n, n) float32 distance from the river's centre line [m]
    water: np.ndarray  # (n, n) bool: in the river
    cell_m: float
    size_m: float

    def local_axis(self) -> np.ndarray:
        """Local east (= −north) coordinate of each column (row) [m]."""
        return _axis(len(self.heights), self.cell_m)


def terrain(triangles: int, seed: int = 0, size_m: float = 3000.0, crs=DEFAULT_CRS) -> Scene:
    """The relief as a Scene of about ``triangles`` triangles (two per cell of a square grid)."""
    if not 2 <= triangles <= 2 * (math.isqrt(MAX_DEM_NODES) - 1) ** 2:
        raise InputError("triangles", triangles, f"2 to {2 * (math.isqrt(MAX_DEM_NODES) - 1) ** 2:,}")
    cells = max(1, round(math.sqrt(triangles / 2)))
    surface = relief(cells + 1, size_m / cells, seed)
    return grid_scene("testdem", surface.heights, np.array(DEFAULT_ORIGIN[:2]), (surface.cell_m, surface.cell_m),
                      parse_crs(crs), BASE_H)


def relief(nodes: int, cell_m: float, seed: int) -> Surface:
    """Heights of the fractal relief with its river valley on ``nodes`` × ``nodes`` nodes ``cell_m`` apart."""
    rng = np.random.default_rng([int(seed), 0x7E57])
    size = (nodes - 1) * cell_m
    axis = _axis(nodes, cell_m)
    x, y = axis[None, :], -axis[:, None]
    phase, offset = rng.uniform(0.0, 2.0 * math.pi), rng.uniform(-0.15, 0.15) * size
    wave = 2.0 * math.pi / (0.5 * size)
    centre = offset + 0.06 * size * np.sin(wave * x + phase)
    lean = 0.06 * size * wave * np.cos(wave * x + phase)
    river = np.abs(y - centre) / np.sqrt(1.0 + lean * lean)
    valley = np.exp(-(river / (VALLEY_WIDTH * size)) ** 2)
    heights = BASE_H + RELIEF_M * _fractal(rng, nodes, cell_m) * (1.0 - valley) - VALLEY_DEPTH_M * valley - FALL * x
    water = river < max(RIVER_WIDTH * size, 2.0 * cell_m)
    heights[water] = (BASE_H - VALLEY_DEPTH_M - 1.0 - FALL * np.broadcast_to(x, heights.shape))[water]
    return Surface(heights.astype(np.float32), river.astype(np.float32), water, cell_m, size)


def _axis(nodes: int, cell_m: float) -> np.ndarray:
    """(nodes,) float32 coordinates [m] of nodes ``cell_m`` apart, centred on the middle one."""
    return ((np.arange(nodes) - (nodes - 1) / 2) * cell_m).astype(np.float32)


def _fractal(rng: np.random.Generator, n: int, cell_m: float) -> np.ndarray:
    """(n, n) float32 fractional Brownian surface of unit RMS (spectral synthesis): amplitude
    ∝ k^−(H+1)·exp(−(k·ROLLOFF_M)²), k the spatial frequency [cycles/m], whatever the cell."""
    import scipy.fft

    ky = np.fft.fftfreq(n, cell_m).astype(np.float32)[:, None]
    kx = np.fft.rfftfreq(n, cell_m).astype(np.float32)[None, :]
    k0 = 1.0 / (n * cell_m)
    k2 = kx * kx + ky * ky
    amplitude = (k2 + k0 * k0) ** np.float32(-(HURST + 1.0) / 2.0) * np.exp(-k2 * np.float32(ROLLOFF_M ** 2))
    amplitude[0, 0] = 0.0
    shape = amplitude.shape
    coefficients = (rng.standard_normal(shape, np.float32) + 1j * rng.standard_normal(shape, np.float32)) * amplitude
    surface = scipy.fft.irfft2(coefficients.astype(np.complex64), s=(n, n), workers=-1)
    return surface / surface.std()


@dataclass
class Building:
    """A closed box building, axis-aligned: its sides local E, N [m]; floor, eave and ridge world H [m]."""

    west: float
    south: float
    east: float
    north: float
    floor: float
    eave: float
    ridge: float  # == eave for a flat roof
    ridge_along_x: bool

    def mesh(self) -> tuple[np.ndarray, list[tuple[str, tuple[int, ...]]]]:
        """(corners (k, 3): local E, N, world H [m]; faces (kind, corner indices) wound outwards)."""
        w, s, e, n = self.west, self.south, self.east, self.north
        foot = np.array([[w, s], [e, s], [e, n], [w, n]])  # SW, SE, NE, NW
        corners = [np.column_stack([foot, np.full(4, self.floor)]), np.column_stack([foot, np.full(4, self.eave)])]
        walls = [("wall", (0, 1, 5, 4)), ("wall", (1, 2, 6, 5)), ("wall", (2, 3, 7, 6)), ("wall", (3, 0, 4, 7))]
        floor = [("floor", (0, 3, 2, 1))]
        if self.ridge == self.eave:
            return np.concatenate(corners), [("roof", (4, 5, 6, 7))] + walls + floor
        if self.ridge_along_x:
            m = (s + n) / 2
            corners.append([[w, m, self.ridge], [e, m, self.ridge]])  # 8: west, 9: east ridge end
            faces = [("roof", (4, 5, 9, 8)), ("roof", (6, 7, 8, 9)), walls[0], walls[2],
                     ("wall", (3, 0, 4, 8, 7)), ("wall", (1, 2, 6, 9, 5))]
        else:
            m = (w + e) / 2
            corners.append([[m, s, self.ridge], [m, n, self.ridge]])  # 8: south, 9: north ridge end
            faces = [("roof", (5, 6, 9, 8)), ("roof", (7, 4, 8, 9)), walls[1], walls[3],
                     ("wall", (0, 1, 5, 8, 4)), ("wall", (2, 3, 7, 9, 6))]
        return np.concatenate(corners), faces + floor


def town(surface: Surface, seed: int) -> list[Building]:
    """The buildings of the town: one per 30 m lot of a square beside the river, away from the valley floor."""
    rng = np.random.default_rng([int(seed), 0x70E])
    size, axis = surface.size_m, surface.local_axis()
    half = min(TOWN_HALF * size, 240.0)
    lots = max(1, int(2 * half // LOT_M))
    column = int(np.argmin(np.abs(axis - rng.uniform(-0.2, 0.2) * size)))
    river_row = int(np.argmin(surface.river_m[:, column]))
    side = rng.choice([-1.0, 1.0])
    cx, cy = float(axis[column]), float(-axis[river_row] + side * 0.25 * size)
    buildings = []
    for i in range(lots):
        for j in range(lots):
            x, y = cx - half + (i + 0.5) * LOT_M, cy - half + (j + 0.5) * LOT_M
            length, width = rng.uniform(10.0, 22.0), rng.uniform(8.0, 14.0)
            along_x, gable = bool(rng.integers(2)), bool(rng.integers(2))
            height, pitch = rng.uniform(4.0, 14.0), math.radians(rng.uniform(20.0, 40.0))
            hx, hy = (length / 2, width / 2) if along_x else (width / 2, length / 2)
            ground = _ground_range(surface, x - hx, y - hy, x + hx, y + hy)
            if ground is None or _near_river(surface, x, y):
                continue
            eave = ground[1] + height
            ridge = eave + ((hy if along_x else hx) * math.tan(pitch) if gable else 0.0)  # half span across the ridge
            buildings.append(Building(x - hx, y - hy, x + hx, y + hy, ground[0] - 1.0, eave, ridge, along_x))
    return buildings


def _ground_range(surface: Surface, west: float, south: float, east: float, north: float):
    """(lowest, highest) node height [m] over the cells under a rectangle (local [m]); None if it is not
    inside the grid with a cell to spare."""
    n, cell = len(surface.heights), surface.cell_m
    j0, j1 = math.floor(west / cell + (n - 1) / 2), math.ceil(east / cell + (n - 1) / 2)
    i0, i1 = math.floor((n - 1) / 2 - north / cell), math.ceil((n - 1) / 2 - south / cell)
    if min(i0, j0) < 1 or max(i1, j1) > n - 2:
        return None
    patch = surface.heights[i0:i1 + 1, j0:j1 + 1]
    return float(patch.min()), float(patch.max())


def _near_river(surface: Surface, x: float, y: float) -> bool:
    n, cell = len(surface.heights), surface.cell_m
    i, j = round((n - 1) / 2 - y / cell), round(x / cell + (n - 1) / 2)
    return bool(surface.river_m[i, j] < VALLEY_WIDTH * surface.size_m)


def landcover(surface: Surface, buildings: list[Building]) -> np.ndarray:
    """(n, n) uint8 ASPRS codes at the nodes (pixel centres): water, trees on slopes, buildings, ground."""
    n, cell = len(surface.heights), surface.cell_m
    north_grad, east_grad = np.gradient(surface.heights, cell)
    codes = np.full((n, n), CLASS_GROUND, dtype=np.uint8)
    codes[np.hypot(north_grad, east_grad) > TREE_SLOPE] = CLASS_TREES
    codes[surface.water] = CLASS_WATER
    axis = surface.local_axis()
    for b in buildings:
        cols = (axis >= b.west) & (axis <= b.east)
        rows = (-axis >= b.south) & (-axis <= b.north)
        codes[np.ix_(rows, cols)] = CLASS_BUILDING
    return codes


def write(out_dir, size_m: float = 3000.0, cell_m: float = 1.0, seed: int = 0, crs=DEFAULT_CRS) -> dict[str, Path]:
    """Write dem.tif, landcover.tif and buildings.obj into ``out_dir``; return their paths by name."""
    crs = parse_crs(crs, "--crs")
    if not (math.isfinite(cell_m) and cell_m > 0.0):
        raise InputError("--cell-m", cell_m, "a pixel size > 0 m")
    cells = round(size_m / cell_m) if math.isfinite(size_m) and size_m > 0.0 else 0
    if not 2 <= cells + 1 <= math.isqrt(MAX_DEM_NODES):
        raise InputError("--size-m", size_m, f"a side of 2 to {math.isqrt(MAX_DEM_NODES) - 1} cells of {cell_m:g} m")
    surface = relief(cells + 1, cell_m, seed)
    buildings = town(surface, seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"dem": out / "dem.tif", "landcover": out / "landcover.tif", "buildings": out / "buildings.obj"}
    _write_tif(paths["dem"], surface, surface.heights, crs, nodata=-9999.0)
    _write_tif(paths["landcover"], surface, landcover(surface, buildings), crs, nodata=0)
    _write_obj(paths["buildings"], buildings)
    return paths


def _write_tif(path: Path, surface: Surface, values: np.ndarray, crs, nodata) -> None:
    """A single-band GeoTIFF whose pixel centres are the surface's nodes."""
    import rasterio
    from rasterio.transform import from_origin

    n, cell = len(values), surface.cell_m
    west = DEFAULT_ORIGIN[0] - (n - 1) / 2 * cell - cell / 2
    north = DEFAULT_ORIGIN[1] + (n - 1) / 2 * cell + cell / 2
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype=values.dtype.name,
                       crs=crs.to_wkt(), transform=from_origin(west, north, cell, cell), nodata=nodata,
                       compress="deflate", tiled=True) as dst:
        dst.write(values, 1)


def _write_obj(path: Path, buildings: list[Building]) -> None:
    """The buildings in world coordinates [m], one group per face kind of each ("building7_roof")."""
    lines, first = [], 1
    for k, b in enumerate(buildings):
        corners, faces = b.mesh()
        world = corners + np.array([DEFAULT_ORIGIN[0], DEFAULT_ORIGIN[1], 0.0])
        lines += [f"v {x:.3f} {y:.3f} {z:.3f}" for x, y, z in world]
        for kind in ("roof", "wall", "floor"):
            lines.append(f"g building{k}_{kind}")
            lines += ["f " + " ".join(str(first + c) for c in face) for name, face in faces if name == kind]
        first += len(corners)
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m flightsim.scenes.testdem", description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="folder to write dem.tif, landcover.tif, buildings.obj into")
    parser.add_argument("--size-m", type=float, default=3000.0, help="side of the square [m] (default 3000)")
    parser.add_argument("--cell-m", type=float, default=1.0, help="pixel size [m] (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--crs", default=DEFAULT_CRS, help=f"projected CRS (default {DEFAULT_CRS})")
    args = parser.parse_args(argv)
    try:
        paths = write(args.out, args.size_m, args.cell_m, args.seed, args.crs)
    except InputError as exc:
        print(f"flightsim: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
