"""LAS tiles at the device's speed: records packed on the device, written by writer threads.

For each chunk the points kernel leaves on the device (:class:`~flightsim.engine.readouts.points.DeviceReturns`),
every georeferencing model's returns are packed into finished LAS records already grouped by tile
(:mod:`kernels.las_records`), copied once into a page-locked host buffer, and handed to that model's
writer thread, which appends each tile's records to its file (:meth:`TileWriter.write_records`) while
the device traces the next chunk. Host memory is bounded by ``BUFFERS_PER_MODEL`` chunk buffers per
model; the bytes are those the host writer makes from the same returns.
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
from flightsim.scenes.canopy import LEAF_CLASSES
from flightsim.scenes.scene import Scene
from kernels import las_records as kl

BUFFERS_PER_MODEL = 3  # host record buffers per model: one being filled, up to two queued or being written
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
                 edge_distance: bool) -> dict[str, TileWriter]:
    """One tile writer per georeferencing model of ``output`` (the [output] settings), ``directory/<model>/``; the
    tiles are dated by the GPS week of ``start_gps_time`` [s]."""
    extras = ("position_error",) * output.position_error + ("edge_distance",) * edge_distance
    date = gps_week_date(start_gps_time)
    return {model: TileWriter(Path(directory) / model, scene.crs, tile_size_m=output.tile_size_m,
                              compress=output.laz, extras=extras, creation_date=date,
                              software=f"flightsim {__version__}")
            for model in output.models}


@dataclass
class _Tiles:
    """A packed chunk of one model on the host: records grouped by tile and each tile's extent."""

    records: wp.array  # (capacity, words) uint32, host (page-locked on a GPU machine)
    keys: list[tuple[int, int]]  # tile indices of each group
    starts: np.ndarray  # first record of each group
    counts: np.ndarray  # records of each group
    bounds: np.ndarray  # (groups, 6): least X, Y, Z and greatest X, Y, Z stored [mm]


@register("output", "las")
class DeviceLasOutput:
    """Writes each model's points to its tile set from records packed on the device (``[output]`` of a
    discrete-return run).

    Call it with each chunk's ``DeviceReturns``; then :meth:`close` (finish the tiles) or :meth:`abort`
    (remove them). An error in a writer thread (a full disk) is raised by the next call or by close.
    """

    settings = LasOutputSettings

    def __init__(self, directory: Path, output, simulator, edge_distance: bool, start_gps_time: float,
                 plane_ids: np.ndarray | None = None):
        """output: the [output] settings; start_gps_time: the flight's [s] (dates the tiles); plane_ids: the plane
        id written for each triangle (default: the scene's own)."""
        scene = simulator.scene
        self.device = simulator.device
        self.models = simulator.models
        self.writers = tile_writers(directory, output, scene, start_gps_time, edge_distance)
        self.kernel = kl.pack_kernel(output.position_error, edge_distance, scene.canopy is not None)
        self.tables = _tables(output.tile_size_m, simulator, scene, plane_ids)
        self._none = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._device_arrays: dict[str, wp.array] = {}
        self._free = {m: queue.LifoQueue() for m in self.models}  # a released buffer is reused before a new one
        for m in self.models:
            for _ in range(BUFFERS_PER_MODEL):
                self._free[m].put(None)  # allocated on first use, sized to the chunk
        self._jobs = {m: queue.Queue(maxsize=BUFFERS_PER_MODEL) for m in self.models}
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
            tiles = self._pack(returns, model)
            self._jobs[model].put(tiles)

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

    def _pack(self, returns, model: str) -> _Tiles:
        """Pack one model's records on the device, grouped by tile, and copy them to a host buffer."""
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
        host = self._host_buffer(model, b.index.shape[0])
        wp.copy(host, records, count=n * self.kernel.words)
        key = to_host(tile_keys[:groups])  # waits for the copy above too (same stream)
        table = np.concatenate([to_host(starts[:groups]), to_host(lengths[:groups])])
        return _Tiles(host, [(ix0 + int(k) // rows, iy0 + int(k) % rows) for k in key], table[:groups],
                      table[groups:], to_host(bounds.flatten()[:groups * 6]).reshape(groups, 6))

    def _write_loop(self, model: str) -> None:
        """Writer thread of one model: append each queued chunk's tiles to their files."""
        writer, jobs = self.writers[model], self._jobs[model]
        while (tiles := jobs.get()) is not None:
            try:
                if not self._errors:
                    words = tiles.records.numpy()
                    for key, start, count, bound in zip(tiles.keys, tiles.starts, tiles.counts, tiles.bounds):
                        writer.write_records(key, words[start:start + count], bound[:3], bound[3:])
            except BaseException as exc:  # handed to the simulating thread
                self._errors.append(exc)
            finally:
                self._free[model].put(tiles.records)

    def _host_buffer(self, model: str, n: int) -> wp.array:
        """A free host buffer of at least ``n`` records (waits for a writer to release one). Asked for the
        chunk's slot count, not its return count, so that each buffer is allocated and page-locked (slow) once
        per run, not again whenever a chunk holds more returns than any before; and a buffer a writer has released
        is taken before a new one is made (last in, first out), so that a run whose writers keep up page-locks one
        buffer per model, not ``BUFFERS_PER_MODEL``."""
        buffer = self._free[model].get()
        self._raise_writer_error()
        if buffer is None or buffer.shape[0] < n:
            pinned = self.device != "cpu"
            buffer = wp.empty((n, self.kernel.words), dtype=wp.uint32, device="cpu", pinned=pinned)
        return buffer

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
    ids = scene.plane_id if plane_ids is None else plane_ids
    classes, ids = scene.classification.astype(np.int32), np.asarray(ids, dtype=np.int32)
    if scene.canopy is not None:  # leaf returns' faces follow the triangles (kernels.canopy_returns.leaf_face)
        classes, ids = np.concatenate([classes, LEAF_CLASSES]), np.concatenate([ids, [-1] * len(LEAF_CLASSES)])
    tables.face_class = wp.array(classes, dtype=wp.int32, device=d)
    tables.face_plane = wp.array(ids.astype(np.int32), dtype=wp.int32, device=d)
    tables.line_start = wp.array([t.start_time for t in simulator.trajectories], dtype=wp.float64, device=d)
    tables.line_source = wp.array([t.line_id for t in simulator.trajectories], dtype=wp.int32, device=d)
    return tables
