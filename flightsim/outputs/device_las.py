"""LAS tiles at the device's speed: records packed on the device, written by writer threads.

For each chunk the points kernel leaves on the device (:class:`~flightsim.engine.readouts.points.DeviceReturns`),
every georeferencing model's returns are packed into finished LAS records already grouped by tile
(:mod:`kernels.las_records`) and copied, a slab at a time, into a small ring of page-locked host slabs, each handed
to that model's writer thread, which appends the slab's part of each tile to its file
(:meth:`TileWriter.write_records`) while the next slab is copied and the device traces the next chunk. Host memory
is bounded by ``SLABS_PER_MODEL`` slabs of ``SLAB_BYTES`` per model, whatever the chunk size (page-locking memory
costs about 0.5 s per GB, so a run page-locks little); the bytes are those the host writer makes from the same
returns.
"""
from __future__ import annotations

import queue
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.core.constants import MODELS
from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.core.version import __version__
from flightsim.core.warp_runtime import to_host
from flightsim.outputs.las_format import gps_week_date
from flightsim.outputs.las_tiles import TileWriter
from flightsim.scenes.scene import Scene
from kernels import las_records as kl

SLAB_BYTES = 32 << 20  # one page-locked host slab of records
SLABS_PER_MODEL = 4  # slabs per model: one being filled, the others queued or being written
INT32_MAX = np.iinfo(np.int32).max


@dataclass
class LasOutputSettings(Settings):
    """The discrete returns' LAS tiles: which georeferencing models, tile size and compression, extra fields; the
    canopy height model of a run over a canopy."""

    table = "output"

    models: tuple[str, ...] = setting(MODELS, "georeferencing models written, each to its own tile set: exact, "
                                      "nominal (the rigid-array model, risley only)")
    tile_size_m: int = setting(500, "side of a LAS tile", "m", range=(1, 100000))
    laz: bool = setting(False, "compress the tiles to LAZ")
    position_error: bool = setting(False, "add each point's true position error [m] as an extra field")
    copc: bool = setting(False, "also one COPC file per model, <model>.copc.laz, from its tiles")
    chm_m: float = setting(1.0, "over a scene with a canopy, the cell of chm.tif, the canopy height model of the "
                           "first model's points; 0 = none", "m", range=(0.0, 100.0))

    def check(self, context) -> None:
        models = tuple(self.models)
        if not models or any(m not in MODELS for m in models) or len(set(models)) != len(models):
            raise InputError("output.models", ",".join(map(str, models)), "a non-empty subset of exact,nominal")


def tile_writers(directory: Path, output, scene: Scene, start_gps_time: float,
                 edge_distance: bool, durable: bool = True) -> dict[str, TileWriter]:
    """One tile writer per georeferencing model of ``output`` (the [output] settings), ``directory/<model>/``; the
    tiles are dated by the GPS week of ``start_gps_time`` [s]; ``durable``: as :class:`TileWriter`'s."""
    extras = ("position_error",) * output.position_error + ("edge_distance",) * edge_distance
    date = gps_week_date(start_gps_time)
    return {model: TileWriter(Path(directory) / model, scene.crs, tile_size_m=output.tile_size_m,
                              compress=output.laz, extras=extras, creation_date=date,
                              software=f"flightsim {__version__}", durable=durable)
            for model in output.models}


@dataclass
class _Groups:
    """A packed chunk of one model: its records' tile groups (record order) and each group's extent."""

    keys: list[tuple[int, int]]  # tile indices of each group
    starts: np.ndarray  # first record of each group
    counts: np.ndarray  # records of each group
    bounds: np.ndarray  # (groups, 6): least X, Y, Z and greatest X, Y, Z stored [mm]


@dataclass
class _Slab:
    """Records first ≤ k < first + count of a packed chunk, in a host slab, and the chunk's groups."""

    records: wp.array  # (capacity, words) uint32, host (page-locked on a GPU machine)
    first: int
    count: int
    groups: _Groups


@register("output", "las")
class DeviceLasOutput:
    """Writes each model's points to its tile set from records packed on the device (``[output]`` of a
    discrete-return run).

    Call it with each chunk's ``DeviceReturns``; then :meth:`close` (finish the tiles) or :meth:`abort`
    (remove them). An error in a writer thread (a full disk) is raised by the next call or by close.
    """

    settings = LasOutputSettings

    def __init__(self, directory: Path, output, simulator, edge_distance: bool, start_gps_time: float,
                 plane_ids: np.ndarray | None = None, durable: bool = True):
        """output: the [output] settings; start_gps_time: the flight's [s] (dates the tiles); plane_ids: the plane
        id written for each triangle (default: the scene's own); durable: False for tiles read once and deleted
        (:class:`TileWriter`)."""
        scene = simulator.scene
        self.device = simulator.device
        self.models = simulator.models
        self.writers = tile_writers(directory, output, scene, start_gps_time, edge_distance, durable)
        self.kernel = kl.pack_kernel(output.position_error, edge_distance, scene.canopy is not None)
        self.tables = _tables(output.tile_size_m, simulator, scene, plane_ids)
        self._none = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._device_arrays: dict[str, wp.array] = {}
        self._free = {m: queue.LifoQueue() for m in self.models}  # a released slab is reused before a new one
        for m in self.models:
            for _ in range(SLABS_PER_MODEL):
                self._free[m].put(None)  # made on first use
        self._jobs = {m: queue.Queue(maxsize=SLABS_PER_MODEL) for m in self.models}
        self._errors: list[BaseException] = []
        self._threads = {m: threading.Thread(target=self._write_loop, args=(m,), daemon=True) for m in self.models}
        for thread in self._threads.values():
            thread.start()

    def __call__(self, returns) -> None:
        self._raise_writer_error()
        if returns.count == 0:
            return
        self._set_segments(returns.segments)
        for model in self.models:
            records, groups = self._pack(returns, model)
            self._hand_over(model, records, returns.count, groups)

    def kernels_needed(self, simulator) -> list:
        return [self.kernel, kl.tile_extent]  # the packing kernel; the tiles' kernels (one module)

    def close(self) -> dict[str, dict[str, int]]:
        """Finish every tile (atomic renames), the models' writers at once; return {model: {tile: points}}."""
        self._stop()
        self._raise_writer_error()
        with ThreadPoolExecutor(len(self.writers)) as pool:
            closed = {model: pool.submit(writer.close) for model, writer in self.writers.items()}
        return {model: future.result() for model, future in closed.items()}

    def abort(self) -> None:
        """Stop the writers and remove every unfinished tile."""
        self._stop()
        for writer in self.writers.values():
            writer.abort()

    # ------------------------------------------------------------------------------------------

    def _pack(self, returns, model: str) -> tuple[wp.array, _Groups]:
        """Pack one model's records on the device, grouped by tile: (the device records, their groups)."""
        b, n, d = returns.buffers, returns.count, self.device
        index, points = b.index, b.model_points[model]
        extent = self._array("extent", 4, wp.int32)
        extent.assign(np.array([INT32_MAX, -INT32_MAX, INT32_MAX, -INT32_MAX], dtype=np.int32))
        wp.launch(kl.tile_extent, n, inputs=[index, points, self.tables], outputs=[extent], device=d)
        ix0, ix1, iy0, iy1 = (int(v) for v in to_host(extent))
        rows = iy1 - iy0 + 1
        if (ix1 - ix0 + 1) * rows > INT32_MAX:
            raise ValueError(f"{model} points spread over more tiles than one chunk can key "
                             f"({ix1 - ix0 + 1} × {rows}); use larger output.tile_size_m")
        keys, order = self._array("keys", 2 * n, wp.int32), self._array("order", 2 * n, wp.int32)
        wp.launch(kl.tile_keys, n, inputs=[index, points, self.tables, ix0, iy0, rows], outputs=[keys, order],
                  device=d)
        wp.utils.radix_sort_pairs(keys, order, n, end_bit=max(1, ((ix1 - ix0 + 1) * rows - 1).bit_length()))
        tile_keys, lengths = self._array("tile_keys", n, wp.int32), self._array("lengths", n, wp.int32)
        runs = self._array("runs", 1, wp.int32)
        wp.utils.runlength_encode(keys, tile_keys, lengths, run_count=runs, value_count=n)
        groups = int(to_host(runs)[0])
        starts = self._array("starts", n, wp.int32)
        wp.utils.array_scan(lengths[:groups], starts[:groups], inclusive=False)
        bounds = self._array("bounds", (n, 6), wp.int32)
        wp.launch(kl.reset_bounds, (groups, 6), outputs=[bounds], device=d)
        records = self._array("records", (n, self.kernel.words), wp.uint32)
        wp.launch(self.kernel, n, inputs=[index, order, starts, tile_keys, groups, ix0, iy0, rows, b.pulses, b.ranges,
                                          b.faces, b.scan_angles, b.cos_incidence, b.edge_distance, b.true_points,
                                          points, self._none if b.returns is None else b.returns, self.tables],
                  outputs=[records, bounds], device=d)
        key = to_host(tile_keys[:groups])
        table = np.concatenate([to_host(starts[:groups]), to_host(lengths[:groups])])
        return records, _Groups([(ix0 + int(k) // rows, iy0 + int(k) % rows) for k in key], table[:groups],
                                table[groups:], to_host(bounds.flatten()[:groups * 6]).reshape(groups, 6))

    def _hand_over(self, model: str, records: wp.array, n: int, groups: _Groups) -> None:
        """Copy ``n`` packed device records to host slabs, one slab at a time, each queued for the model's writer
        as soon as it has arrived (the next copy waits only for a free slab)."""
        words = self.kernel.words
        per_slab = max(1, SLAB_BYTES // (4 * words))
        for first in range(0, n, per_slab):
            count = min(per_slab, n - first)
            slab = self._slab(model, per_slab)
            wp.copy(slab, records, src_offset=first * words, count=count * words)
            wp.synchronize_device(self.device)  # the slab holds its records before a writer reads it
            self._jobs[model].put(_Slab(slab, first, count, groups))

    def _write_loop(self, model: str) -> None:
        """Writer thread of one model: append each queued slab's part of every tile to its file."""
        writer, jobs = self.writers[model], self._jobs[model]
        while (slab := jobs.get()) is not None:
            try:
                if not self._errors:
                    _write_slab(writer, slab)
            except BaseException as exc:  # handed to the simulating thread
                self._errors.append(exc)
            finally:
                self._free[model].put(slab.records)

    def _slab(self, model: str, records: int) -> wp.array:
        """A free host slab of ``records`` records (waits for a writer to release one); made (page-locked on a GPU
        machine) only while fewer than ``SLABS_PER_MODEL`` exist and none is free."""
        slab = self._free[model].get()
        self._raise_writer_error()
        if slab is None:
            slab = wp.empty((records, self.kernel.words), dtype=wp.uint32, device="cpu", pinned=self.device != "cpu")
        return slab

    def _array(self, name: str, shape, dtype) -> wp.array:
        """A device scratch array kept between chunks, grown when a chunk needs more."""
        size = shape if isinstance(shape, tuple) else (shape,)
        array = self._device_arrays.get(name)
        if array is None or array.shape[0] < size[0]:
            array = self._device_arrays[name] = wp.empty(size, dtype=dtype, device=self.device)
        return array[:size[0]] if len(size) == 1 else array

    def _set_segments(self, segments) -> None:
        """The chunk's segment table (first pulse of each segment, and its line)."""
        starts = np.cumsum([0] + [s.count for s in segments]).astype(np.int32)
        self.tables.segment_start = wp.array(starts, dtype=wp.int32, device=self.device)
        self.tables.segment_line = wp.array([s.line for s in segments] + [segments[-1].line], dtype=wp.int32,
                                            device=self.device)
        self.tables.segments = len(segments)

    def _raise_writer_error(self) -> None:
        if self._errors:
            raise self._errors[0]

    def _stop(self) -> None:
        for model, thread in self._threads.items():
            if thread.is_alive():
                self._jobs[model].put(None)
                thread.join()


def _write_slab(writer: TileWriter, slab: _Slab) -> None:
    """Append the records of ``slab`` to their tiles: each group's part that lies in the slab (a group split between
    slabs is written in order, its extent given with each part: the header's bounds are the same)."""
    g = slab.groups
    words = slab.records.numpy()
    end = slab.first + slab.count
    ends = g.starts + g.counts
    for k in range(int(np.searchsorted(ends, slab.first, side="right")), len(g.keys)):
        start = int(g.starts[k])
        if start >= end:
            break
        a, b = max(start, slab.first), min(int(ends[k]), end)
        writer.write_records(g.keys[k], words[a - slab.first:b - slab.first], g.bounds[k, :3], g.bounds[k, 3:])


def _tables(tile_size_m: int, simulator, scene: Scene, plane_ids: np.ndarray | None) -> kl.RecordTables:
    """The per-run constants of the record kernels."""
    d = simulator.device
    tables = kl.RecordTables()
    tables.origin = wp.vec3d(*scene.origin)
    tables.tile_mm = tile_size_m * 1000
    tables.prf_hz = simulator.timing.prf_hz
    tables.beams_per_pulse = simulator.beams_per_pulse
    tables.returns_per_beam = simulator.returns_per_beam
    tables.beam_columns = simulator.instrument.emitter.beam_columns
    if plane_ids is None:  # the scene's own labels, kept on the device with its meshes
        tables.face_class, tables.face_plane = simulator.meshes.face_labels
    else:
        tables.face_class, tables.face_plane = (wp.array(a, dtype=wp.int32, device=d)
                                                for a in scene.face_labels(plane_ids))
    tables.line_start = wp.array([t.start_time for t in simulator.trajectories], dtype=wp.float64, device=d)
    tables.line_source = wp.array([t.line_id for t in simulator.trajectories], dtype=wp.int32, device=d)
    return tables
