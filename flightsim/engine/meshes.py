"""A scene's acceleration structures on one device: the triangle BVH, the padded-box BVH of the fallback cast, the
plane-boundary segments and edge grids of the edge buffer, and the per-triangle reflectance."""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import to_host
from flightsim.scenes.scene import Scene
from kernels import edges, mesh_hits

EDGE_GRID_CELLS = 4096  # the edge grid has at most this many cells along a side
EDGE_CELLS_PER_CAP = 4  # ... and cells of a quarter of the edge cap where that allows: a cell is marked out to the
# cap plus half its diagonal from its centre, so the returns sent to the boundary query lie within 1.35 caps of a
# boundary (cells of one cap: 2.41)
EDGE_GRIDS_KEPT = 8  # edge grids a SceneMeshes keeps (the paper's 250-configuration study needs 9 in all)
EDGE_GRID_SPAN = 2.0  # a grid built for a cap c serves the caps from c / EDGE_GRID_SPAN to c (SceneMeshes.edge_grid)
GPU_LEAF_SIZE = 2  # triangles per leaf of the automatic BVH on a GPU (cubql; an H100, bare casts against cubql's own
# default: the 720k-triangle sandbox 2.65 -> 3.31e9 rays/s, lunar 3.07 -> 3.28e9, DEMs of 1e6 / 8e6 triangles 1.39 ->
# 1.50e9 / 1.04 -> 1.19e9, the 546-triangle calibration field unchanged; profile-experiments.md section 32)


def bvh_choice(constructor: str, leaf_size: int | None, cpu: bool) -> tuple[str, int | None]:
    """(Warp's BVH constructor, triangles per leaf or None for Warp's default) of a run's ``run.bvh`` and
    ``run.bvh_leaf_size`` (0 or None: automatic) on a CPU or a GPU: auto is the measured fastest of each (README,
    run.bvh)."""
    if constructor != "auto":
        return constructor, leaf_size or None
    return ("sah", leaf_size or None) if cpu else ("cubql", leaf_size or GPU_LEAF_SIZE)


class SceneMeshes:
    """A scene's acceleration structures on one device, built once: the triangle BVH, a BVH of the
    plane-boundary segments for edge-buffer queries and the per-triangle reflectance (both on first use)."""

    def __init__(self, scene: Scene, device: str, bvh_constructor: str = "auto", leaf_size: int | None = None):
        """``bvh_constructor``: Warp's (sah, median, lbvh, cubql) or auto (sah on the CPU with Warp's leaf size, cubql
        on a GPU with GPU_LEAF_SIZE triangles a leaf); ``leaf_size``: triangles per leaf (None: as just said)."""
        self.scene = scene
        self.device = device
        bvh_constructor, leaf_size = bvh_choice(bvh_constructor, leaf_size, wp.get_device(device).is_cpu)
        points = scene.vertices.astype(np.float32)
        self.mesh = wp.Mesh(points=wp.array(points, dtype=wp.vec3f, device=device),
                            indices=wp.array(scene.triangles.astype(np.int32).ravel(), dtype=wp.int32, device=device),
                            bvh_constructor=bvh_constructor, bvh_leaf_size=leaf_size)
        self.vertices64 = wp.array(scene.vertices, dtype=wp.vec3d, device=device)
        self.indices = self.mesh.indices
        self.padded = self._padded_bvh(scene, device)
        self._boundary: tuple[wp.array, wp.array] | None = None
        self._reflectance: wp.array | None = None
        self._labels: tuple[wp.array, wp.array] | None = None
        self._grids: dict[float, edges.EdgeGrid] = {}

    def _padded_bvh(self, scene: Scene, device: str) -> wp.Bvh:
        """BVH of the triangles' boxes padded by 1e-6·(1 + the largest |coordinate| of a triangle corner)
        [m], for the fallback cast (:func:`kernels.mesh_hits.fallback_hit`); the boxes are made on the device."""
        n = len(scene.triangles)
        extent = wp.zeros(1, dtype=wp.float32, device=device)
        wp.launch(mesh_hits.corner_extent, n, inputs=[self.mesh.points, self.mesh.indices], outputs=[extent],
                  device=device)
        pad = np.float32(1e-6 * (1.0 + to_host(extent)[0]))
        self._padded_boxes = (wp.empty(n, dtype=wp.vec3f, device=device), wp.empty(n, dtype=wp.vec3f, device=device))
        wp.launch(mesh_hits.padded_boxes, n, inputs=[self.mesh.points, self.mesh.indices, pad],
                  outputs=list(self._padded_boxes), device=device)
        return wp.Bvh(*self._padded_boxes)

    @property
    def per_face(self) -> bool:
        """Whether the scene carries a Lambertian albedo per triangle (else the detectors take the run's value)."""
        return self.scene.reflectance is not None

    @property
    def reflectance(self) -> wp.array:
        """float32 Lambertian albedo of each triangle on the device (uploaded on first use); a one-element
        placeholder when the scene has none."""
        if self._reflectance is None:
            rho = self.scene.reflectance if self.per_face else np.ones(1, dtype=np.float32)
            self._reflectance = wp.array(rho, dtype=wp.float32, device=self.device)
        return self._reflectance

    @property
    def face_labels(self) -> tuple[wp.array, wp.array]:
        """(ASPRS class, plane id) int32 of each face a return can come from, on the device (uploaded on first use,
        like the BVH made once per scene, not per product): the triangles', then a canopy's leaf faces."""
        if self._labels is None:
            self._labels = tuple(wp.array(a, dtype=wp.int32, device=self.device)
                                 for a in self.scene.face_labels())
        return self._labels

    @property
    def boundary(self) -> tuple[wp.array, wp.array]:
        """(segment starts, segment ends) of the plane boundaries [m, local]."""
        if self._boundary is None:
            segments = self.scene.boundary_segments().astype(np.float32)
            if len(segments) == 0:  # a closed surface has no boundary: one far-away dummy segment
                segments = np.full((1, 2, 3), 1e9, dtype=np.float32)
            self._boundary = (wp.array(segments[:, 0], dtype=wp.vec3f, device=self.device),
                              wp.array(segments[:, 1], dtype=wp.vec3f, device=self.device))
        return self._boundary

    def edge_grid(self, cap_m: float) -> edges.EdgeGrid:
        """A grid of the cells a plane boundary may come within ``cap_m`` [m] of.

        A grid built for a cap c serves every cap from c / EDGE_GRID_SPAN to c: it marks a superset of the cells,
        so more returns take the exact boundary query, which is given the run's own cap (the distances, and every
        result, are the same). The first grid is built for ``cap_m`` itself (a run has one cap); a later one for
        the power of two at or above it, so that the many caps of a sweep (the paper's study: 140 between 0.24 and
        44 m) share a few grids (9) instead of building one each (~3 ms on an H100, 14 ms on two CPU cores). The
        last EDGE_GRIDS_KEPT used are kept."""
        fits = [c for c in self._grids if cap_m <= c <= EDGE_GRID_SPAN * cap_m]
        if fits:
            cap = min(fits)
            self._grids[cap] = self._grids.pop(cap)  # the most recently used last
            return self._grids[cap]
        cap = cap_m if not self._grids or cap_m <= 0.0 else 2.0 ** math.ceil(math.log2(cap_m))
        if len(self._grids) >= EDGE_GRIDS_KEPT:
            self._grids.pop(next(iter(self._grids)))
        self._grids[cap] = self._build_edge_grid(cap)
        return self._grids[cap]

    def _build_edge_grid(self, cap_m: float) -> edges.EdgeGrid:
        lower, upper = self.scene.bounds()
        extent = float(max(upper[0] - lower[0], upper[1] - lower[1])) + 2.0 * cap_m
        cell = max(cap_m / EDGE_CELLS_PER_CAP, extent / EDGE_GRID_CELLS, 1e-6)
        shape = tuple(int(math.ceil((upper[k] - lower[k] + 2.0 * cap_m) / cell)) + 1 for k in (0, 1))
        grid = edges.EdgeGrid()
        grid.near = wp.zeros(shape, dtype=wp.uint8, device=self.device)
        grid.origin = wp.vec2f(float(lower[0]) - cap_m, float(lower[1]) - cap_m)
        grid.inv_cell = 1.0 / cell
        a, b = self.boundary
        lists = tuple(-(-n // edges.LIST_CELLS) for n in shape)  # list cells of LIST_CELLS cells a side
        grid.list_shape = wp.vec2i(*lists)
        cells = lists[0] * lists[1]
        grid.offsets = wp.empty(cells + 1, dtype=wp.int32, device=self.device)
        grid.listed = wp.empty(1, dtype=wp.int32, device=self.device)
        filled = wp.zeros(cells + 1, dtype=wp.int32, device=self.device)
        for step in (edges.MARK, edges.COUNT, edges.WRITE):
            if step == edges.WRITE:  # the counts scanned into each list's start, the lists' room made
                wp.utils.array_scan(filled, grid.offsets, inclusive=False)
                grid.listed = wp.empty(max(1, int(to_host(grid.offsets[cells:])[0])), dtype=wp.int32,
                                       device=self.device)
                filled.zero_()
            wp.launch(edges.near_cells, a.shape[0], inputs=[a, b, cap_m, grid, step], outputs=[filled],
                      device=self.device)
        return grid

    def none_grid(self) -> edges.EdgeGrid:
        """An empty edge grid, for runs without an edge buffer."""
        grid = edges.EdgeGrid()
        grid.near = wp.zeros((1, 1), dtype=wp.uint8, device=self.device)
        grid.list_shape = wp.vec2i(0, 0)
        grid.offsets = wp.zeros(1, dtype=wp.int32, device=self.device)
        grid.listed = wp.zeros(1, dtype=wp.int32, device=self.device)
        return grid
