"""A stand's crowns as leaf area density voxels, from the exact fraction of each voxel inside each crown.

The grid is cubic, of side ``cell_m``, aligned with the local origin (voxel faces at whole multiples of the cell)
and just large enough to hold every crown. Voxel (i, j, k) spans ``lower + (i, j, k)·cell`` to
``lower + (i + 1, j + 1, k + 1)·cell``, indexed east, north, up; its leaf area density [m²/m³] is

    LAD(i, j, k) = Σ over crowns of crown LAD × (volume of the voxel inside the crown) / cell³.

The volume of a voxel inside a crown (a solid of revolution, radius r(z) about its axis) is ∫ A(r(z)) dz over
the voxel's height, where A(r) is the area of the voxel's square column inside the crown's disc of radius r, in
closed form (the disc's signed area over the rectangle between the axis and each corner of the square, added
with alternating signs). A(r(z)) is smooth between breakpoints: the voxel's floor and ceiling, the crown's ends,
and the heights where r(z) equals the distance from the axis to a side or a corner of the square (the disc starts
to cross it there). Every piece between breakpoints is integrated by Gauss–Legendre after the substitution
z = a + (b − a)(1 − cos πt)/2, which tames the (r − d)^{3/2} behaviour at a piece's ends: with GAUSS_NODES = 8
each fraction is good to about 1e-8 of the voxel (4 nodes: 3e-4, 6: 1e-6; tested to 1e-7 against nested
adaptive quadrature), a cylinder's (A constant in z) to rounding.
"""
from __future__ import annotations

import collections
import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.forest import Trees, box_cells, crown_radius_at

MAX_VOXELS = 500_000_000  # 2 GB of float32 leaf area density
GAUSS_NODES = 8
_COLUMNS_PER_CHUNK = 512  # crown columns integrated at once: few enough for their pieces to stay in the caches
_THREADS = 8  # threads integrating chunks at once (16 were no faster than 8 on a 16-core host)
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(GAUSS_NODES)
_T = 0.5 * (_NODES + 1.0)  # on [0, 1]
_SUB = 0.5 * (1.0 - np.cos(math.pi * _T))  # z = a + (b − a)·_SUB
_JAC = 0.5 * _WEIGHTS * 0.5 * math.pi * np.sin(math.pi * _T)  # weight × dz/dt / (b − a)


def voxel_grid(trees: Trees, cell_m: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Lower corner (3,) local [m] and shape (nx, ny, nz) of the smallest grid of ``cell_m`` cells aligned with
    the origin that holds every crown (one voxel at the stand's centre on the ground when there is none).
    InputError naming scene.forest_voxel_m when it would exceed MAX_VOXELS."""
    if len(trees) == 0:
        return np.zeros(3), (1, 1, 1)
    r = trees.crown_radius
    lo = np.array([(trees.x - r).min(), (trees.y - r).min(), trees.crown_bottom_z().min()])
    hi = np.array([(trees.x + r).max(), (trees.y + r).max(), trees.top_z().max()])
    first, last = np.floor(lo / cell_m), np.ceil(hi / cell_m)
    shape = tuple(int(n) for n in np.maximum(last - first, 1))
    if math.prod(shape) > MAX_VOXELS:
        raise InputError("scene.forest_voxel_m", cell_m, f"a voxel large enough for at most {MAX_VOXELS:.0e} voxels "
                                                         f"(this stand needs {shape[0]}×{shape[1]}×{shape[2]})")
    return first * cell_m, shape


def stand_voxels(trees: Trees, cell_m: float = 1.0, device: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stand's leaf area density: ``(lad, lower, cell)``: lad float32 (nx, ny, nz) [m²/m³] indexed east,
    north, up; lower (3,) float64 local corner of voxel (0, 0, 0) [m]; cell (3,) float64 voxel sides [m].
    ``device``: None integrates on the host (NumPy, in threads); a Warp device ("cpu", "cuda:0", …) in
    :mod:`kernels.crown_voxels`, the same integrals (a few float64 ulps apart, see there)."""
    cell = float(cell_m)
    if not (math.isfinite(cell) and cell > 0.0):
        raise InputError("scene.forest_voxel_m", cell_m, "a voxel side > 0 m")
    lower, shape = voxel_grid(trees, cell)
    if device is not None and len(trees):
        return device_lad(trees, lower, shape, cell, device), lower, np.full(3, cell)
    lad = (crown_volumes(trees, lower, shape, cell) * (trees.lad / cell ** 3)).reshape(shape).astype(np.float32)
    return lad, lower, np.full(3, cell)


def device_lad(trees: Trees, lower: np.ndarray, shape: tuple[int, int, int], cell: float, device: str) -> np.ndarray:
    """The leaf area density (nx, ny, nz) float32 [m²/m³] of the grid (``lower``, ``shape``, cubic ``cell`` [m]),
    integrated on the Warp ``device``: a thread per voxel column that some crown's box covers (the columns and
    their trees listed here)."""
    import warp as wp

    from flightsim.core.warp_runtime import resolve_device
    from kernels import crown_voxels as kc

    d = resolve_device(device)
    columns, first, members = column_trees(trees, lower, shape, cell)
    lad = wp.zeros(math.prod(shape), dtype=wp.float32, device=d)

    def f64(values) -> wp.array:
        return wp.array(np.ascontiguousarray(values, dtype=np.float64), dtype=wp.float64, device=d)

    def i32(values) -> wp.array:
        return wp.array(np.ascontiguousarray(values, dtype=np.int32), dtype=wp.int32, device=d)

    code = {"cone": kc.CONE, "ellipsoid": kc.ELLIPSOID, "cylinder": kc.CYLINDER}[trees.shape]
    wp.launch(kc.column_lad, len(columns),
              inputs=[i32(columns), i32(first), i32(members), f64(trees.x), f64(trees.y), f64(trees.crown_bottom_z()),
                      f64(trees.top_z()), f64(trees.crown_length), f64(trees.crown_radius), code,
                      wp.vec3d(*lower), wp.float64(cell), shape[1], shape[2], f64(_SUB), f64(_JAC),
                      wp.float64(trees.lad / cell ** 3)], outputs=[lad], device=d)
    return lad.numpy().reshape(shape)


def column_trees(trees: Trees, lower: np.ndarray, shape: tuple[int, int, int], cell: float
                 ) -> tuple[np.ndarray, ...]:
    """(columns, first, members): the flat index i·ny + j of every voxel column some crown's bounding box covers,
    ascending, and its trees ``members[first[c]:first[c + 1]]``, ascending."""
    owner, i, j = box_cells(*_box(trees, lower, cell))
    column = i * shape[1] + j
    order = np.argsort(column, kind="stable")
    columns, first = np.unique(column[order], return_index=True)
    return columns, np.append(first, len(order)), owner[order]


def crown_volumes(trees: Trees, lower: np.ndarray, shape: tuple[int, int, int], cell: float) -> np.ndarray:
    """Volume [m³] of each voxel of the grid (``lower``, ``shape``, cubic ``cell`` [m]) inside the crowns, summed
    over them: float64, flat in C order."""
    volume = np.zeros(math.prod(shape))
    for flat, inside in _in_threads(lambda chunk: _crown_volumes(trees, chunk, lower, shape, cell),
                                    _chunks(trees, lower, cell)):
        cells, where = np.unique(flat, return_inverse=True)
        volume[cells] += np.bincount(where, weights=inside, minlength=len(cells))
    return volume


def threads() -> int:
    """Threads that integrate a stand's crowns on this machine: _THREADS or the cores this process may use."""
    return min(_THREADS, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def _in_threads(work, items: list):
    """``work(item)`` of each item, yielded in the items' order (so the volumes add up in the same order, to the same
    bits, whatever the threads) and computed by up to _THREADS threads (NumPy releases the GIL in its array
    arithmetic), at most two items per thread ahead of the one yielded."""
    count = threads()
    if count <= 1 or len(items) <= 1:
        yield from map(work, items)
        return
    with ThreadPoolExecutor(count, thread_name_prefix="crowns") as pool:
        pending = collections.deque(pool.submit(work, item) for item in items[:2 * count])
        for item in items[2 * count:] + [None] * len(pending):
            done = pending.popleft().result()
            if item is not None:
                pending.append(pool.submit(work, item))
            yield done


def lai_map(lad: np.ndarray, cell) -> np.ndarray:
    """Leaf area index of each voxel column, (nx, ny) float64 [m²/m²]: Σ over the column of LAD × voxel height."""
    return np.asarray(lad, dtype=np.float64).sum(axis=2) * float(np.asarray(cell, dtype=np.float64).reshape(-1)[-1])


def _box(trees: Trees, lower: np.ndarray, cell: float) -> tuple[np.ndarray, ...]:
    """First column and columns across of each crown's bounding box: i0, nx, j0, ny."""
    r = trees.crown_radius
    i0 = np.floor((trees.x - r - lower[0]) / cell).astype(np.int64)
    j0 = np.floor((trees.y - r - lower[1]) / cell).astype(np.int64)
    nx = np.ceil((trees.x + r - lower[0]) / cell).astype(np.int64) - i0
    ny = np.ceil((trees.y + r - lower[1]) / cell).astype(np.int64) - j0
    return i0, np.maximum(nx, 1), j0, np.maximum(ny, 1)


def _chunks(trees: Trees, lower: np.ndarray, cell: float) -> list[np.ndarray]:
    """Tree indices in groups of about _COLUMNS_PER_CHUNK crown columns."""
    _, nx, _, ny = _box(trees, lower, cell)
    group = np.cumsum(nx * ny) // _COLUMNS_PER_CHUNK
    return [np.flatnonzero(group == g) for g in np.unique(group)]


def _columns(trees: Trees, chunk: np.ndarray, lower: np.ndarray, cell: float) -> dict[str, np.ndarray]:
    """Every voxel column of the crowns' bounding boxes that the crown's widest disc reaches: its tree, its
    indices (i, j) and its square's sides relative to the crown's axis (x0, x1, y0, y1) [m]."""
    owner, i, j = box_cells(*(a[chunk] for a in _box(trees, lower, cell)))
    tree = chunk[owner]
    x0, y0 = lower[0] + i * cell - trees.x[tree], lower[1] + j * cell - trees.y[tree]
    near = np.hypot(np.maximum(np.maximum(x0, -x0 - cell), 0.0),
                    np.maximum(np.maximum(y0, -y0 - cell), 0.0)) < trees.crown_radius[tree]
    cols = {"tree": tree, "i": i, "j": j, "x0": x0, "x1": x0 + cell, "y0": y0, "y1": y0 + cell}
    return {key: value[near] for key, value in cols.items()}


def _breakpoints(trees: Trees, cols: dict[str, np.ndarray], lower_z: float, cell: float) -> np.ndarray:
    """(C, B) sorted heights [m] that split each column's crown into smooth pieces (repeats give empty pieces)."""
    tree = cols["tree"]
    bottom, top, radius = trees.crown_bottom_z()[tree], trees.top_z()[tree], trees.crown_radius[tree]
    k0 = np.floor((bottom - lower_z) / cell)
    layers = int(np.max(np.ceil((top - lower_z) / cell) - k0))
    planes = lower_z + (k0[:, None] + 1 + np.arange(max(layers - 1, 0))) * cell
    sides = [np.abs(cols[key]) for key in ("x0", "x1", "y0", "y1")]
    corners = [np.hypot(cols[a], cols[b]) for a in ("x0", "x1") for b in ("y0", "y1")]
    q = np.stack(sides + corners, axis=1) / radius[:, None]
    length = (top - bottom)[:, None]
    if trees.shape == "cone":
        critical = [bottom[:, None] + length * (1.0 - q)]
    elif trees.shape == "ellipsoid":
        half = 0.5 * np.sqrt(np.maximum(1.0 - q * q, 0.0))
        critical = [bottom[:, None] + length * (0.5 - half), bottom[:, None] + length * (0.5 + half)]
    else:
        critical = []
    inner = np.concatenate([planes] + [np.where(q < 1.0, c, top[:, None]) for c in critical], axis=1)
    inner = np.clip(inner, bottom[:, None], top[:, None])
    return np.sort(np.concatenate([bottom[:, None], top[:, None], inner], axis=1), axis=1)


def _crown_volumes(trees: Trees, chunk: np.ndarray, lower: np.ndarray, shape, cell: float):
    """(flat voxel index, volume inside the crown [m³]) of every piece of the ``chunk`` crowns."""
    cols = _columns(trees, chunk, lower, cell)
    edges = _breakpoints(trees, cols, lower[2], cell)
    a, b = edges[:, :-1], edges[:, 1:]
    column, _ = np.nonzero(b > a)
    a, b = a[b > a], b[b > a]
    tree = cols["tree"][column]
    bottom, length = trees.crown_bottom_z()[tree], trees.crown_length[tree]
    z = a[:, None] + (b - a)[:, None] * _SUB
    r = trees.crown_radius[tree][:, None] * crown_radius_at(trees.shape, (z - bottom[:, None]) / length[:, None])
    area = disc_square_area(r, *(cols[key][column][:, None] for key in ("x0", "x1", "y0", "y1")))
    area = np.clip(area, 0.0, cell * cell)  # rounding: a corner barely touched must not give −1e-16
    inside = (area @ _JAC) * (b - a)
    k = np.clip(np.floor((0.5 * (a + b) - lower[2]) / cell).astype(np.int64), 0, shape[2] - 1)
    flat = (cols["i"][column] * shape[1] + cols["j"][column]) * shape[2] + k
    return flat, inside


def disc_square_area(r, x0, x1, y0, y1) -> np.ndarray:
    """Area [m²] of the disc of radius ``r`` centred on (0, 0) inside the rectangle [x0, x1] × [y0, y1] [m]
    (arrays broadcast together): the signed areas of the disc inside the rectangles between (0, 0) and each corner
    (u, v), added with alternating signs. With a = min(|u|, r), b = min(|v|, r) and c = min(√(r² − b²), a), such an
    area is c·b plus the area under the circle from c to a (the circle's primitive S(x) = (x√(r² − x²) +
    r² asin(x/r)) / 2). a and S(a) depend on the corner's u alone, √(r² − b²) on its v alone: each is taken once
    for the two corners that share it."""
    r2 = r * r
    scale = np.where(r > 0.0, r, 1.0)

    def primitive(x):
        return 0.5 * (x * np.sqrt(np.maximum(r2 - x * x, 0.0)) + r2 * np.arcsin(np.minimum(x / scale, 1.0)))

    a = [np.minimum(np.abs(u), r) for u in (x0, x1)]
    s_a = [primitive(x) for x in a]
    b = [np.minimum(np.abs(v), r) for v in (y0, y1)]
    w = [np.sqrt(np.maximum(r2 - y * y, 0.0)) for y in b]

    def corner(i: int, j: int, u, v) -> np.ndarray:
        c = np.minimum(w[j], a[i])
        return np.sign(u) * np.sign(v) * (c * b[j] + s_a[i] - primitive(c))

    return corner(1, 1, x1, y1) - corner(0, 1, x0, y1) - corner(1, 0, x1, y0) + corner(0, 0, x0, y0)
