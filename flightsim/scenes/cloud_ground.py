"""The ground under an ALS point cloud, as a scene mesh: a grid of the ground points' heights, or a DEM given
beside the cloud.

Grid (:func:`ground_grid`): cells of ``cell_m`` over the cloud's horizontal bounding box (all points, so the
mesh reaches under every point), each node at its cell's centre holding the mean height of the ground points
(class 2) in the cell. Cells without a ground point (under buildings and dense crowns, past the edge of the
ground returns) are filled by linear interpolation (a Delaunay triangulation) between the filled cells that
border a hole, and by the nearest filled cell where a hole lies outside their hull; so a filled surface passes
through every cell mean, is linear across each hole and flat beyond the last ground returns. The grid becomes a
mesh of two triangles per cell (:func:`flightsim.scenes.dem.grid_scene`), one "surface" face label, class 2,
not planar, in the cloud's local frame.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.core.process_map import by_pieces
from flightsim.scenes.dem import MAX_DEM_NODES, dem_scene, grid_scene
from flightsim.scenes.lunar import surface_scene
from flightsim.scenes.scene import Scene

if TYPE_CHECKING:  # pointcloud imports this module to build its scene
    from flightsim.scenes.pointcloud import PointCloud


def lowest_per_cell(xyz: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the lowest point (least z) of each occupied ``cell_m`` [m] cell of the points ``xyz`` (N, 3)."""
    columns = _cells(xyz[:, 0], xyz[:, 1], cell_m, xyz[:, 0].min(), xyz[:, 1].min())
    order = np.lexsort((xyz[:, 2], columns))
    first = np.r_[True, columns[order][1:] != columns[order][:-1]]
    return order[first]


def ground_grid(cloud: PointCloud, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(heights (rows, cols) local z [m], rows from north to south; local (x, y) [m] of the centre of the
    south-west cell) of the cloud's ground, holes filled (see the module's notes)."""
    lo, hi = cloud.bounds()
    cols, rows = (max(int(np.ceil((hi[a] - lo[a]) / cell_m)), 2) for a in (0, 1))
    if rows * cols > MAX_DEM_NODES:
        smallest = float(np.sqrt((hi[0] - lo[0]) * (hi[1] - lo[1]) / MAX_DEM_NODES))
        raise InputError("scene.cloud_cell_m", cell_m, f"a ground cell of at least {smallest:.3g} m for this "
                                                       f"cloud's {hi[0] - lo[0]:.0f} × {hi[1] - lo[1]:.0f} m")
    cell, z = _ground_cells(cloud, lo, cell_m, rows, cols)
    counts = np.bincount(cell, minlength=rows * cols).reshape(rows, cols)
    sums = np.bincount(cell, weights=z, minlength=rows * cols).reshape(rows, cols)
    heights = np.divide(sums, counts, out=np.full((rows, cols), np.nan), where=counts > 0)
    return fill_holes(heights), lo[:2] + cell_m / 2.0


def _ground_cells(cloud: PointCloud, lo: np.ndarray, cell_m: float, rows: int, cols: int):
    """(cell (G,) int64 row-major from the north-west, local z (G,) [m]) of the cloud's G ground points in their
    order, worked out in pieces of the points on threads (each piece's ground points written after those of the
    pieces before it), not over gathered copies of all of them."""
    def counted(points: slice) -> tuple[int, int]:
        return points.start, int(np.count_nonzero(cloud.ground_of(points)))

    counts = by_pieces(len(cloud), counted)
    starts = dict(zip((start for start, _ in counts), np.cumsum([0] + [n for _, n in counts]).tolist()))
    total = sum(n for _, n in counts)
    cell, z = np.empty(total, dtype=np.int64), np.empty(total)

    def piece(points: slice) -> None:
        ground = cloud.xyz[points][cloud.ground_of(points)]
        at = slice(starts[points.start], starts[points.start] + len(ground))
        ix = np.minimum(((ground[:, 0] - lo[0]) / cell_m).astype(np.int64), cols - 1)
        iy = np.minimum(((ground[:, 1] - lo[1]) / cell_m).astype(np.int64), rows - 1)
        cell[at] = (rows - 1 - iy) * cols + ix  # rows from north to south
        z[at] = ground[:, 2]

    by_pieces(len(cloud), piece)
    return cell, z


def fill_holes(heights: np.ndarray) -> np.ndarray:
    """``heights`` with its NaN cells filled: linear between the filled cells bordering the holes, nearest
    filled cell outside their hull (at least one cell must be filled)."""
    from scipy import ndimage
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import QhullError

    holes = np.isnan(heights)
    if not holes.any():
        return heights
    rim = ~holes & ndimage.binary_dilation(holes, structure=np.ones((3, 3), dtype=bool))
    filled = heights.copy()
    try:
        interpolate = LinearNDInterpolator(np.argwhere(rim), heights[rim])
        filled[holes] = interpolate(np.argwhere(holes))
    except (QhullError, ValueError):  # fewer than 3 rim cells, or all in a line: nearest only
        pass
    still = np.isnan(filled)
    if still.any():
        nearest = ndimage.distance_transform_edt(holes, return_distances=False, return_indices=True)
        filled[still] = heights[nearest[0][still], nearest[1][still]]
    return filled


def ground_scene(cloud: PointCloud, name: str, cell_m: float, dem_path: str = "") -> Scene:
    """The Scene of ``cloud``: its ground mesh (the ground grid of ``cell_m`` [m], or the GeoTIFF DEM at
    ``dem_path``, which must be in the cloud's CRS) in the cloud's local frame, with ``cloud`` attached."""
    if dem_path:
        scene = dem_scene(dem_path, cloud.crs, cloud.origin, cell_m)
        if not _same_crs(scene.crs, cloud.crs):
            raise InputError("scene.cloud_dem", dem_path, f"a GeoTIFF DEM in the cloud's CRS ({cloud.crs.name}; "
                                                          f"this one is in {scene.crs.name})")
    else:
        heights, south_west = ground_grid(cloud, cell_m)
        rows, cols = heights.shape
        middle = south_west + np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) * cell_m
        scene = grid_scene(name, heights + cloud.origin[2], middle + cloud.origin[:2], (cell_m, cell_m), cloud.crs,
                           float(cloud.origin[2]))
    moved = _moved(scene, cloud.origin, name)
    moved.cloud = cloud
    return moved


def _moved(scene: Scene, origin: np.ndarray, name: str) -> Scene:
    """``scene`` (one surface face label) re-expressed in the local frame of ``origin`` (world E, N, H [m])."""
    shift = scene.origin - origin
    return surface_scene(name, scene.crs, origin, scene.vertices + shift, scene.triangles,
                         scene.ground_z + float(shift[2]))


def _cells(x: np.ndarray, y: np.ndarray, cell_m: float, x0: float, y0: float) -> np.ndarray:
    """One int64 id per point of the ``cell_m`` cell holding it (cells counted from (x0, y0))."""
    ix = ((x - x0) / cell_m).astype(np.int64)
    iy = ((y - y0) / cell_m).astype(np.int64)
    return iy * (int(ix.max()) + 1) + ix


def _same_crs(a: pyproj.CRS, b: pyproj.CRS) -> bool:
    return a == b or a.equals(b, ignore_axis_order=True) or (a.to_epsg() is not None and a.to_epsg() == b.to_epsg())
