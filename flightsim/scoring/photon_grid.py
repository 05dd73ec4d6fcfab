"""From photons to points: grid the photon events, histogram each cell's heights and keep the cell's
peak (seed: spad-fsm-small-body-lidar-paper.txt, Fig. 4a). Runs on the device (kernels/photon_grid.py):
a frame's photons never leave it, only its points do.

Per cell: the heights are binned at ``bin_m`` from the lowest photon; the fullest pair of adjacent bins
(the lowest on a tie) is the cell's surface when it holds at least ``min_count`` photons and 5σ above
the cell's background per pair of bins (noise spreads over the whole gate, the echo piles up in one
or two bins); the point is the mean of the cell's photons within ``window_m`` of that pair's middle,
then once more within ``window_m`` of that mean (so a window off the echo's centre does not clip it).

Cells are columns and rows given with the photons (:func:`xy_cells` for horizontal cells,
:func:`angle_cells` / :class:`PhotonFrame` for the beams' angle grid); a negative column or row, or a
non-finite position, leaves the photon out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import to_host
from kernels import photon_grid as k

REDUCE_THREADS = 1 << 16  # threads of the extent reduction (each strides over the photons)
MERGE_THREADS = 256  # threads merging their partials on the device (the host reads these few)


@dataclass
class GridPoints:
    """One point per accepted cell, in row-major cell order (local or world coordinates, as given) [m]."""

    points: np.ndarray  # (m, 3) float64
    cell: np.ndarray  # (m, 2) int32 column and row of each point's cell
    photons: np.ndarray  # (m,) int32 photons averaged into each point
    peak: np.ndarray  # (m,) int32 photons in the cell's fullest pair of bins
    cells: int  # cells holding any photon


def _empty(cells: int = 0) -> GridPoints:
    return GridPoints(np.zeros((0, 3)), np.zeros((0, 2), np.int32), np.zeros(0, np.int32), np.zeros(0, np.int32), cells)


def xy_cells(xyz: np.ndarray, cell_m: float) -> np.ndarray:
    """(n, 2) int64 column, row of each position's horizontal cell of side ``cell_m`` [m], from the lowest x, y."""
    xy = np.asarray(xyz, dtype=np.float64)[:, :2]
    return np.floor((xy - np.nanmin(xy, axis=0)) / cell_m).astype(np.int64)


def angle_cells(directions: np.ndarray, half_field_rad: float, cells: int, device: str = "cpu") -> np.ndarray:
    """(n, 2) int64 column, row of each downward beam direction (n, 3) in a ``cells`` × ``cells`` grid of
    angles from nadir over ±``half_field_rad`` (atan of the east and north direction over the depth);
    −1 outside the field. Every photon of a beam falls in its beam's cell whatever its range."""
    d = wp.array(np.asarray(directions, dtype=np.float32), dtype=wp.vec3f, device=device)
    out = wp.empty(len(d), dtype=wp.vec2i, device=device)
    wp.launch(k.angle_cells, len(d), inputs=[d, float(half_field_rad), int(cells)], outputs=[out], device=device)
    return out.numpy().astype(np.int64)


def grid_points(xyz, cells, bin_m: float, min_count: int, window_m: float, device: str = "cpu") -> GridPoints:
    """The surface points of photon positions ``xyz`` (n, 3) [m] gridded by ``cells`` (n, 2) column and row."""
    positions = wp.array(np.asarray(xyz, dtype=np.float64), dtype=wp.vec3d, device=device)
    ij = wp.array(np.asarray(cells).astype(np.int32), dtype=wp.vec2i, device=device)
    return _grid(positions, ij, len(positions), bin_m, min_count, window_m)


class PhotonFrame:
    """A frame's photon positions and beam angle cells, gathered on the device chunk by chunk, then gridded into
    points with ``grid``; ``reset`` starts the next frame in the same device and host memory.

    Filled either by the photons readout itself (``Photons(frame=...)``: its kernel writes every chunk's photons
    here, the frame's count kept on the device, :meth:`device_arrays`; then :meth:`settle` once the run is
    done, which reads the count and tells whether the arrays held them all) or by ``add`` (a consumer of
    :class:`~flightsim.engine.readouts.photons.DevicePhotons`). The points of ``grid`` are views of the frame's
    page-locked host buffers (the copy from the device runs at full bus speed and touches no fresh pages): they
    hold until the frame's next ``grid``.
    """

    def __init__(self, half_field_rad: float, cells: int, device: str, capacity: int = 1 << 20):
        self.half_field, self.cells, self.device = float(half_field_rad), int(cells), device
        self.xyz = wp.empty(capacity, dtype=wp.vec3d, device=device)
        self.cell = wp.empty(capacity, dtype=wp.vec2i, device=device)
        self._signal = wp.zeros(1024, dtype=wp.int64, device=device)
        self._total = wp.zeros(1, dtype=wp.int32, device=device)  # photons added, on the device
        self._host: dict[str, wp.array] = {}
        self._scratch: dict[str, wp.array] = {}  # the gridding's device arrays, kept frame after frame
        self.count = 0

    def reset(self) -> None:
        """Forget the photons added (keep the memory)."""
        self.count = 0
        self._total.zero_()
        self._signal.zero_()

    def device_arrays(self) -> tuple[wp.array, wp.array, wp.array, wp.array]:
        """(positions, angle cells, count [1], 1024 signal counters) for a kernel appending photons at ``count[0]``
        (writes past the arrays' length dropped, still counted)."""
        return self.xyz, self.cell, self._total, self._signal

    def settle(self) -> bool:
        """Read the count of the photons appended on the device; False when they overflowed the arrays (then
        grown to hold them: reset and fill the frame again), True when the frame holds them all."""
        self.count = int(to_host(self._total)[0])
        if self.count <= len(self.xyz):
            return True
        self.xyz = wp.empty(self.count, dtype=wp.vec3d, device=self.device)
        self.cell = wp.empty(self.count, dtype=wp.vec2i, device=self.device)
        return False

    def add(self, photons) -> None:
        """Append a chunk's photons (device arrays ``points``, ``directions``, ``signal``; ``count`` rows)."""
        n = photons.count
        if n == 0:
            return
        self._reserve(self.count + n)
        wp.launch(k.append_photons, n,
                  inputs=[photons.points, photons.directions, photons.signal, self.half_field, self.cells, self.count],
                  outputs=[self.xyz, self.cell, self._signal], device=self.device)
        self.count += n
        self._total.fill_(self.count)

    @property
    def signal_photons(self) -> int:
        """Photons flagged as signal (truth) among those added."""
        return int(to_host(self._signal).sum())

    def grid(self, bin_m: float, min_count: int, window_m: float) -> GridPoints:
        return _grid(self.xyz, self.cell, self.count, bin_m, min_count, window_m, self._host, self._scratch)

    def _reserve(self, n: int) -> None:
        if n <= len(self.xyz):
            return
        size = max(n, 2 * len(self.xyz))
        for name, dtype in (("xyz", wp.vec3d), ("cell", wp.vec2i)):
            grown = wp.empty(size, dtype=dtype, device=self.device)
            wp.copy(grown, getattr(self, name), count=self.count)
            setattr(self, name, grown)


def _take(scratch: dict[str, wp.array] | None, name: str, n: int, dtype, device) -> wp.array:
    """``n`` (≥ 1) elements of device memory for ``name``: the first of ``scratch[name]`` (grown when too small),
    so the next gridding reuses them rather than allocating afresh (a pool that gives memory back to the driver
    at each synchronisation makes each fresh gigabyte costly); a new array where ``scratch`` is None."""
    if scratch is None:
        return wp.empty(n, dtype=dtype, device=device)
    kept = scratch.get(name)
    if kept is None or len(kept) < n:
        kept = scratch[name] = wp.empty(max(n, 3 * len(kept) // 2 if kept is not None else n), dtype=dtype,
                                        device=device)
    return kept[:n]


def _extent(xyz: wp.array, cell: wp.array, n: int, scratch=None) -> tuple[float, float, int, int] | None:
    """(lowest, highest height [m], columns, rows) of the valid photons; None when there are none."""
    threads = min(n, REDUCE_THREADS)
    device = xyz.device
    zmin, zmax = (_take(scratch, name, threads, wp.float64, device) for name in ("zmin", "zmax"))
    top = _take(scratch, "top", threads, wp.vec2i, device)
    wp.launch(k.extent, threads, inputs=[xyz, cell, n, threads], outputs=[zmin, zmax, top], device=device)
    merged = min(threads, MERGE_THREADS)
    low, high = (_take(scratch, name, merged, wp.float64, device) for name in ("low", "high"))
    corner = _take(scratch, "corner", merged, wp.vec2i, device)
    wp.launch(k.merge_extent, merged, inputs=[zmin, zmax, top, threads, merged], outputs=[low, high, corner],
              device=device)
    lo, hi, top = to_host(low).min(), to_host(high).max(), to_host(corner).max(axis=0)
    if not np.isfinite(lo):
        return None
    return float(lo), float(hi), int(top[0]) + 1, int(top[1]) + 1


def _grid(xyz: wp.array, cell: wp.array, n: int, bin_m: float, min_count: int, window_m: float,
          host: dict[str, wp.array] | None = None, scratch: dict[str, wp.array] | None = None) -> GridPoints:
    """The points of the first ``n`` photons (device arrays), gridded on their device; copied into the
    page-locked ``host`` buffers when given (kept there for the next call), else into new arrays; the device
    arrays of the gridding taken from ``scratch`` when given (:func:`_take`).

    Launches: extent, keys, the radix sort, the cells' bounds, one thread per cell for its point, 2 × (flags, scan),
    compaction; host syncs: the extent (its merged partials), the occupied and the point counts, the points' copy."""
    extent = _extent(xyz, cell, n, scratch) if n else None
    if extent is None:
        return _empty()
    lo, hi, columns, rows = extent
    stride = int(np.floor((hi - lo) / bin_m)) + 2
    device, n_cells = xyz.device, columns * rows
    invalid = n_cells * stride
    keys, order = _take(scratch, "keys", 2 * n, wp.int64, device), _take(scratch, "order", 2 * n, wp.int32, device)
    wp.launch(k.bin_keys, n, inputs=[xyz, cell, lo, float(bin_m), stride, columns, invalid],
              outputs=[keys, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=invalid.bit_length())
    first, last = (_take(scratch, name, n_cells, wp.int32, device) for name in ("first", "last"))
    first.zero_()
    last.zero_()
    sorted_xyz = _take(scratch, "sorted_xyz", n, wp.vec3d, device)
    wp.launch(k.cell_bounds, n, inputs=[keys, order, xyz, n, stride, invalid], outputs=[first, last, sorted_xyz],
              device=device)
    totals, peak, count = (_take(scratch, name, n_cells, wp.int32, device) for name in ("totals", "peak", "count"))
    centre, sums = _take(scratch, "centre", n_cells, wp.float64, device), _take(scratch, "sums", n_cells, wp.vec3d, device)
    wp.launch(k.cell_points, n_cells, inputs=[sorted_xyz, keys, first, last, stride, lo, float(bin_m),
                                              int(min_count), float(window_m)],
              outputs=[totals, centre, peak, count, sums], device=device)
    return _compacted(centre, count, sums, peak, totals, columns, host, scratch)


def _compacted(centre: wp.array, count: wp.array, sums: wp.array, peak: wp.array, totals: wp.array,
               columns: int, host: dict[str, wp.array] | None, scratch=None) -> GridPoints:
    """The accepted cells' points, brought to the host."""
    device, n_cells = centre.device, len(centre)
    flags, offsets, held, held_offsets = (_take(scratch, name, n_cells, wp.int32, device)
                                          for name in ("flags", "offsets", "held", "held_offsets"))
    wp.launch(k.occupied, n_cells, inputs=[totals], outputs=[held], device=device)
    wp.utils.array_scan(held, held_offsets, inclusive=False)
    wp.launch(k.point_flags, n_cells, inputs=[centre, count], outputs=[flags], device=device)
    wp.utils.array_scan(flags, offsets, inclusive=False)
    last = _last_values(held_offsets, held, offsets, flags)  # one sync
    cells, m = last[0] + last[1], last[2] + last[3]
    if m == 0:
        return _empty(cells)
    out = {name: _take(scratch, "out_" + name, m, dtype, device) for name, dtype in OUTPUTS.items()}
    wp.launch(k.compact_points, n_cells, inputs=[flags, offsets, columns, count, sums, peak],
              outputs=list(out.values()), device=device)
    if host is None:
        found = {name: a.numpy() for name, a in out.items()}
    else:
        found = {name: _to_host(a, host, name) for name, a in out.items()}
        wp.synchronize_device(device)
    return GridPoints(found["points"], found["cell"], found["photons"], found["peak"], cells)


OUTPUTS = {"points": wp.vec3d, "cell": wp.vec2i, "photons": wp.int32, "peak": wp.int32}  # per point, in order


def _to_host(a: wp.array, host: dict[str, wp.array], name: str) -> np.ndarray:
    """A NumPy view of the page-locked buffer ``host[name]`` (grown when too small) into which ``a`` is
    being copied (valid once the device is synchronised)."""
    if name not in host or len(host[name]) < len(a):
        host[name] = wp.empty(max(len(a), 2 * len(host.get(name, ()))), dtype=a.dtype, device="cpu",
                              pinned=a.device.is_cuda)
    wp.copy(host[name], a, count=len(a))
    return host[name].numpy()[:len(a)]


_LAST: dict[tuple[str, type], wp.array] = {}  # page-locked landing places of _last_values, per device and type


def _last_values(*arrays: wp.array) -> list[int]:
    """The last element of each (integer) device array, copied to the host together: one sync for all."""
    landed = []
    for i, a in enumerate(arrays):
        key = (str(a.device), a.dtype)
        if key not in _LAST:
            _LAST[key] = wp.empty(8, dtype=a.dtype, device="cpu", pinned=a.device.is_cuda)
        wp.copy(_LAST[key], a, dest_offset=i, src_offset=len(a) - 1, count=1)
        landed.append((key, i))
    wp.synchronize_device(arrays[0].device)
    return [int(_LAST[key].numpy()[i]) for key, i in landed]
