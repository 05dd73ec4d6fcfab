"""LAS 1.4 point tiles: streamed, deterministic, atomic output of simulated returns (SPEC §8).

Points are cut into square tiles named by their lower-left corner (``409000_3392500.las``) and
streamed to their tile's file as they come, so memory does not grow with the length of a run: an uncompressed
tile's records straight after the header bytes laspy's writer makes (:mod:`.las_plain_tile`), a LAZ tile's through a
laspy writer of its own.

The format of every tile (LAS 1.4, point format 6, 1 mm, WKT1 CRS, extra bytes, fixed identity
fields) is :mod:`.las_format`'s; the points come as :class:`.las_points.PointBatch`.

A tile is written to ``.<name>.part`` in the output directory and renamed by :meth:`TileWriter.close` once every
tile is fsync'ed (together, on threads); :meth:`TileWriter.abort` deletes the temporaries.
"""
from __future__ import annotations

import copy
import datetime
import functools
import os
import threading
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pyproj

from flightsim.core.atomic import fsync_all, fsync_directory
from flightsim.core.version import __version__
from flightsim.core.errors import InputError
from flightsim.core.lazy import PARSING
from flightsim.outputs.las_format import (_EXTRA_DIMS, _MM_PER_M, OPTIONAL_DIMS, SCAN_ANGLE_UNIT_DEG, _quantized_mm,
                                          _check_header_fields, _tile_header_template, _tile_size_mm, _validated_crs)
from flightsim.outputs.las_plain_tile import PlainTile, header_bytes
from flightsim.outputs.las_points import PointBatch
from flightsim.outputs.laz_workers import LazWorkers

if TYPE_CHECKING:
    import laspy
    from laspy.lasappender import LasAppender


class TileRecords(NamedTuple):
    """Finished records of one tile, as :meth:`TileWriter.write_records` takes them."""
    key: tuple[int, int]  # tile indices
    records: np.ndarray  # the tile format's structured records, X and Y relative to the tile's corner [mm]
    lowest: np.ndarray  # (3,) least stored X, Y, Z [mm]
    highest: np.ndarray  # (3,) greatest stored X, Y, Z [mm]


class TileWriter:
    """Streams point batches into LAS 1.4 tiles of ``tile_size_m``, written atomically.

    Use as a context manager: a normal exit calls :meth:`close` (tiles appear under their final
    names), an exception calls :meth:`abort` (no tile appears, no temporary is left).

    A point belongs to the tile whose lower-left corner is ``floor(X / size)·size`` where X is its
    coordinate rounded to the 1 mm grid, so a stored coordinate always lies in ``[0, size)`` of
    its tile's offset and a point on a boundary goes to the upper/right tile.

    At most ``max_open_tiles`` tiles hold an open file (one descriptor each; for LAZ, one
    compressed chunk of up to 50 000 points in memory). When a new tile needs a slot, the least
    recently written tile is finished and closed; if it receives points again its temporary file is
    reopened and appended to (uncompressed: the result is byte-identical to never closing it).

    LAZ is compressed in ``processes`` worker processes (:mod:`flightsim.outputs.laz_workers`) when that
    is at least 1: this process then only hands each write's records over, and never holds the GIL
    while lazrs compresses. Each tile belongs to one worker, which runs an in-process ``TileWriter``
    with the same options for its tiles, compressing each write as it arrives (lazrs's sequential
    compressor); the bytes are those of writing in this process. Each worker keeps its own bound of
    ``max_open_tiles`` open files and holds one write in flight; this process holds no records. It renames
    the tiles once every worker has finished its files.

    Args:
        directory: output folder, created if missing.
        crs: CRS of the world coordinates (anything ``pyproj.CRS.from_user_input`` accepts); must be
            projected, in metres, and expressible as WKT1.
        tile_size_m: tile edge [m], a whole number of metres in [1, 1e6].
        compress: write LAZ (``.laz``, lazrs backend) instead of LAS.
        extras: optional extra-bytes fields to add, names from ``OPTIONAL_DIMS``
            (``position_error``, ``edge_distance``); batches must carry them.
        creation_date: header creation date (e.g. :func:`.las_format.gps_week_date` of the run's first pulse).
        software: header generating-software string (at most 32 ASCII characters).
        max_open_tiles: bound on simultaneously open tile files (>= 1), per worker process.
        processes: LAZ worker processes (>= 0; 0: compress in this process; ignored for LAS);
            None: :data:`LAZ_PROCESSES`.
        parallel_compression: compress LAZ in this process over every core (lazrs's parallel compressor,
            records held back in batches of :data:`LAZ_BATCH_POINTS`), or in the calling thread as each write
            arrives (each worker process does: the processes are the parallelism, and a compressor's threads
            in every one of them would only contend for the same cores). The bytes are the same.
        durable: have the disk take every tile's bytes as they are written and before its rename (write-back
            started per write, every file fsync'ed at close, then the folder); False for transient tiles, read once
            and deleted (a survey's part files), which then stay in the page cache. The bytes are the same.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        crs: pyproj.CRS,
        tile_size_m: float = 500.0,
        *,
        compress: bool = False,
        extras: Sequence[str] = (),
        creation_date: datetime.date,
        software: str = f"flightsim {__version__}",
        max_open_tiles: int = 64,
        processes: int | None = None,
        parallel_compression: bool = True,
        durable: bool = True,
    ) -> None:
        self._tile_mm = _tile_size_mm(tile_size_m)
        if not isinstance(max_open_tiles, int) or max_open_tiles < 1:
            raise InputError("max_open_tiles", max_open_tiles, "an integer >= 1")
        processes = LAZ_PROCESSES if processes is None else processes
        if not isinstance(processes, int) or processes < 0:
            raise InputError("processes", processes, "an integer >= 0")
        self._directory = Path(directory)
        self._directory.mkdir(parents=True, exist_ok=True)
        self._compress = bool(compress)
        self._parallel = bool(parallel_compression)
        self._durable = bool(durable)
        unknown = set(extras) - set(OPTIONAL_DIMS)
        if unknown:
            raise InputError("extras", sorted(unknown), f"names among {', '.join(OPTIONAL_DIMS)}")
        self._dims = _EXTRA_DIMS + tuple(OPTIONAL_DIMS[name] for name in OPTIONAL_DIMS if name in extras)
        crs = _validated_crs(crs)
        _check_header_fields(creation_date, software)
        self._header_fields = (crs, creation_date, software)
        self._max_open = max_open_tiles
        self._open: OrderedDict[tuple[int, int], _LazTile | PlainTile] = OrderedDict()
        self._counts: dict[tuple[int, int], int] = {}
        self._finished = False
        self._workers = None
        self._template_lock = threading.Lock()
        if self._compress and processes:
            self._workers = LazWorkers(processes, dict(
                directory=str(self._directory), crs=crs, tile_size_m=tile_size_m, compress=True, extras=tuple(extras),
                creation_date=creation_date, software=software, max_open_tiles=max_open_tiles, processes=0,
                parallel_compression=False, durable=durable))

    @functools.cached_property
    def _dtype(self) -> np.dtype:
        """The tiles' record dtype (made once should threads packing batches ask at once)."""
        with self._template_lock:
            return self._template.point_format.dtype()

    @functools.cached_property
    def _template(self) -> laspy.LasHeader:
        """The header every tile shares but for its offsets, made at the first write: laspy (and the HTTP stack its
        COPC reader imports) is loaded by the thread that writes, not before a run's first ray (under
        :data:`flightsim.core.lazy.PARSING`: laspy's import parses, as a kernels module's does)."""
        with PARSING:
            return _tile_header_template(*self._header_fields, self._dims)

    @functools.cached_property
    def _head(self) -> bytes:
        """An uncompressed tile's header and VLRs as laspy writes them (:func:`.las_plain_tile.header_bytes`)."""
        with self._template_lock:
            return header_bytes(self._template)

    def __enter__(self) -> TileWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write(self, batch: PointBatch) -> None:
        """Append the points of ``batch`` to their tiles, in batch order within each tile."""
        if self._finished:
            raise RuntimeError("TileWriter is closed")
        self.write_packed(self._packed(batch))

    def pack(self, batch: PointBatch) -> list[TileRecords]:
        """The records of ``batch`` tile by tile: ``write(batch)`` is ``write_packed(pack(batch))``. Reads only the
        writer's settings: batches may be packed on several threads at once, then written in their order on one."""
        return list(self._packed(batch))

    def write_packed(self, packed: Iterable[TileRecords]) -> None:
        """Append records packed by :meth:`pack` to their tiles."""
        for key, records, lowest, highest in packed:
            self.write_records(key, records, lowest, highest)

    def _packed(self, batch: PointBatch) -> Iterator[TileRecords]:
        """The records of ``batch`` tile after tile, made RECORDS_AT_ONCE points at a time."""
        missing = [field for _, field, _, _ in self._extra_dims() if getattr(batch, field) is None]
        if missing:
            raise ValueError(f"PointBatch fields written as LAS extra bytes are None: {missing}")
        if len(batch) == 0:
            return
        xq, yq, zq = (_quantized_mm(getattr(batch, axis), axis) for axis in "xyz")
        if np.abs(zq).max() > np.iinfo(np.int32).max:
            raise ValueError("z is out of the int32 range of a 1 mm LAS coordinate (|z| < 2147 km)")
        ix = np.floor_divide(xq, self._tile_mm)
        iy = np.floor_divide(yq, self._tile_mm)
        order, starts = _tile_order(ix, iy)
        for group in _tile_runs(starts, len(order)):  # several tiles' records made at once, tile after tile
            rows = order[group[0]:group[-1]]
            tx, ty = ix[rows], iy[rows]
            record = self._record(batch, rows)
            record["X"], record["Y"] = xq[rows] - tx * self._tile_mm, yq[rows] - ty * self._tile_mm
            record["Z"] = zq[rows]
            first = group[:-1] - group[0]
            lowest, highest = (np.column_stack([ufunc.reduceat(record[axis], first) for axis in "XYZ"])
                               for ufunc in (np.minimum, np.maximum))
            for k, (start, stop) in enumerate(zip(first, group[1:] - group[0])):
                yield TileRecords((int(tx[start]), int(ty[start])), record[start:stop], lowest[k], highest[k])

    def write_records(self, key: tuple[int, int], records: np.ndarray, lowest, highest) -> None:
        """Append finished point records to tile ``key`` (tile indices).

        ``records``: a structured array of the tile format's dtype, or a C-contiguous array of its bytes
        (e.g. words packed on the device); X and Y relative to the tile's lower-left corner and Z
        absolute, in mm. ``lowest``/``highest``: the least and greatest stored X, Y, Z of these records,
        which grow the header bounds exactly as laspy's own writer would.
        """
        if self._finished:
            raise RuntimeError("TileWriter is closed")
        dtype = self._dtype
        records = np.asarray(records)
        if records.dtype != dtype:
            records = records.reshape(-1).view(np.uint8).view(dtype)
        if len(records) == 0:
            return
        if self._workers is None:
            self._tile(key).write(records, lowest, highest)
            self._bound_held(dtype.itemsize)
        else:
            self._counts.setdefault(key, 0)  # registered first, so that abort() removes a half-made file
            self._workers.write(key, np.ascontiguousarray(records), lowest, highest)
        self._counts[key] += len(records)

    def _record(self, batch: PointBatch, rows: np.ndarray) -> np.ndarray:
        """Format-6 records (the tiles' dtype) of the points ``rows`` of ``batch``, every field but X, Y, Z filled in,
        written straight into the record array (one return of one: the return byte 0x11)."""
        angle = np.rint(batch.scan_angle_deg[rows].astype(np.float64) / SCAN_ANGLE_UNIT_DEG)
        if not np.all(np.abs(angle) <= 30000):
            raise ValueError("scan_angle_deg must be finite and within [-180, 180] deg")
        record = np.zeros(len(rows), self._dtype)
        record["bit_fields"] = ONE_RETURN
        record["scan_angle"] = angle.astype(np.int16)
        for name in ("intensity", "classification", "point_source_id", "gps_time"):
            record[name] = getattr(batch, name)[rows]
        for las_name, field, _, _ in self._extra_dims():
            record[las_name] = getattr(batch, field)[rows]
        return record

    def _bound_held(self, record_bytes: int) -> None:
        """Keep the LAZ records the open tiles hold back within :data:`LAZ_HELD_BYTES`: compress the
        fullest tile's while they exceed it."""
        while self._compress and self._open:
            held = sum(tile.held_points for tile in self._open.values())
            if held * record_bytes <= LAZ_HELD_BYTES:
                return
            max(self._open.values(), key=lambda tile: tile.held_points).flush()

    def close(self) -> dict[str, int]:
        """Finish every tile, sync them all together (a durable writer's), then rename each; {tile file: points}."""
        if self._finished:
            raise RuntimeError("TileWriter is closed")
        try:
            self._finish_files()
            if self._durable:
                fsync_all(self._temp_path(key) for key in self._counts)
            for key in sorted(self._counts):
                os.replace(self._temp_path(key), self._directory / self.tile_name(key))
            if self._durable:
                fsync_directory(self._directory)
        except BaseException:
            self.abort()
            raise
        self._finished = True
        return self.tile_counts

    def abort(self) -> None:
        """Drop all unfinished output: stop the workers, close open files and delete every temporary tile."""
        if self._workers is not None:
            self._workers.stop()
        for tile in self._open.values():
            tile.discard()
        self._open.clear()
        for key in self._counts:
            self._temp_path(key).unlink(missing_ok=True)
        self._finished = True

    @property
    def tile_counts(self) -> dict[str, int]:
        """{tile file name: points written so far}; after a ``with`` block, the final counts."""
        return {self.tile_name(key): self._counts[key] for key in sorted(self._counts)}

    def tile_name(self, key: tuple[int, int]) -> str:
        """File name of tile ``key`` (tile indices): its lower-left corner in whole metres."""
        size_m = self._tile_mm // _MM_PER_M
        suffix = ".laz" if self._compress else ".las"
        return f"{key[0] * size_m}_{key[1] * size_m}{suffix}"

    def _finish_files(self) -> None:
        """Finish every tile file under its temporary name (held records compressed, header and LAZ chunk
        table written, flushed to disk) and close it, in the workers if any."""
        if self._workers is not None:
            self._workers.finish()
        for key in sorted(self._open):
            self._open.pop(key).close()

    def _temp_path(self, key: tuple[int, int]) -> Path:
        return self._directory / f".{self.tile_name(key)}.part"

    def _extra_dims(self) -> tuple[tuple, ...]:
        return self._dims

    def _tile(self, key: tuple[int, int]) -> _LazTile | PlainTile:
        """The open file of tile ``key``, opening (or reopening) it within the open-file bound."""
        tile = self._open.get(key)
        if tile is not None:
            self._open.move_to_end(key)
            return tile
        if len(self._open) >= self._max_open:
            _, oldest = self._open.popitem(last=False)
            oldest.close()
        path = self._temp_path(key)
        if key in self._counts:
            if self._compress:
                tile = _LazTile.reopen(path, self._parallel, self._durable)
            else:
                tile = PlainTile.reopen(path, self._durable)
        else:
            offsets = np.array([key[0] * self._tile_mm / _MM_PER_M, key[1] * self._tile_mm / _MM_PER_M, 0.0])
            self._counts[key] = 0  # registered first, so that abort() removes a half-made file
            if self._compress:
                header = copy.copy(self._template)  # the offsets its own: laspy's LasWriter deep-copies the rest
                header.offsets = offsets
                tile = _LazTile.create(path, header, self._parallel, self._durable)
            else:
                tile = PlainTile.create(path, self._head, self._template.scales, offsets, self._durable)
        self._open[key] = tile
        return tile


LAZ_CHUNK_POINTS = 50_000
"""Points per LAZ chunk (laspy's and lazrs's default), the unit lazrs compresses on one core."""
LAZ_BATCH_POINTS = LAZ_CHUNK_POINTS * min(os.cpu_count() or 1, 16)
"""A LAZ tile holds its records until it has this many, then compresses them in one call: lazrs's parallel
compressor spreads the whole chunks of a call over every core (and holds the GIL while it does)."""
LAZ_HELD_BYTES = 256 << 20
"""Most record bytes the open LAZ tiles of a writer compressing in its own process hold back together (worker
processes hold none: they compress each write as it comes)."""
LAZ_PROCESSES = min(8, (os.cpu_count() or 1) // 2) if (os.cpu_count() or 1) >= 4 else 0
"""Worker processes a LAZ tile writer compresses in by default: one per 2 cores, at most 8 (16 cores and up);
none below 4 cores (compression in the writer's own process). lazrs holds the GIL of its process while it
compresses; in workers it leaves the threads that drive the device and pack records running, and several
tiles compress at once. A 100 km² survey (8.5e8 points, both models, 889 tiles) to LAZ on an H100 with 16
cores took 143 s in-process, 76 s with 2 workers per writer, 62 s with 4 and 55 s with 8 (LAS: ~60 s), each
worker then running lazrs's parallel compressor on held batches; compressing sequentially from shared memory,
the whole command now takes 57 s (``results/bench.md``, Survey). On 2 cores the workers gave nothing back
(the cores are all busy either way) for their start-up and memory (~90 MB each, plus the 64 MB ring each
shares with this process)."""


def _laz_backend(parallel: bool) -> laspy.LazBackend:
    """lazrs's compressor over every core (parallel) or in the calling thread."""
    import laspy
    return laspy.LazBackend.LazrsParallel if parallel else laspy.LazBackend.Lazrs


class _LazTile:
    """One LAZ tile's temporary file and the laspy writer (or appender) streaming into it (an uncompressed tile is a
    :class:`~flightsim.outputs.las_plain_tile.PlainTile`). A tile compressed over every core holds records back until
    :data:`LAZ_BATCH_POINTS`; one compressed in its writer's thread compresses each write as it comes (the bytes are
    the same either way: the compressor cuts chunks by point count). Compressed bytes are synced to disk as they are
    written, so that a run's output reaches the disk while it traces rather than in the final fsyncs of its tiles
    (``durable``; a transient tile is left to the page cache)."""

    def __init__(self, file, sink: laspy.LasWriter | LasAppender, parallel: bool, durable: bool) -> None:
        self._file = file
        self._sink = sink
        self._durable = durable
        self._batch = LAZ_BATCH_POINTS if parallel else 0
        self._held: list[np.ndarray] = []
        self.held_points = 0

    @classmethod
    def create(cls, path: Path, header: laspy.LasHeader, parallel: bool, durable: bool) -> _LazTile:
        import laspy
        file = open(path, "w+b")
        try:
            sink = laspy.LasWriter(file, header, do_compress=True, laz_backend=_laz_backend(parallel), closefd=False)
        except BaseException:
            file.close()
            raise
        return cls(file, sink, parallel, durable)

    @classmethod
    def reopen(cls, path: Path, parallel: bool, durable: bool) -> _LazTile:
        from laspy.lasappender import LasAppender
        file = open(path, "r+b")
        try:  # always lazrs's parallel appender: its sequential one (lazrs 0.8) fails on reopening a tile
            sink = LasAppender(file, laz_backend=_laz_backend(True), closefd=False)
        except BaseException:
            file.close()
            raise
        return cls(file, sink, parallel, durable)

    def write(self, records: np.ndarray, lowest, highest) -> None:
        """Append ``records`` (the tile format's structured array) whose stored X, Y, Z range over [lowest, highest]
        (ints, mm).

        The header is grown here as laspy's ``LasHeader.grow`` does (bounds = stored integer · scale +
        offset, counts by return number; every record is return 1 of 1, and no extra-bytes statistics
        are kept), without laspy's passes over the records: the bounds come from the caller.
        """
        if self._batch:
            self._held.append(records.copy())
            self.held_points += len(records)
            if self.held_points >= self._batch:
                self.flush()
        else:
            self._append(records)
            self._sync()
        header = self._sink.header
        header.maxs = np.maximum(header.maxs, np.asarray(highest, dtype=np.int64) * header.scales + header.offsets)
        header.mins = np.minimum(header.mins, np.asarray(lowest, dtype=np.int64) * header.scales + header.offsets)
        header.number_of_points_by_return[0] += len(records)
        header.point_count += len(records)

    def flush(self) -> None:
        """Compress and write the records held back, and wait until the disk has them: a run's compressed
        bytes reach the disk while it traces (batch by batch), not all in the final fsyncs of its tiles."""
        if self._held:
            self._append(np.concatenate(self._held))
            self._held, self.held_points = [], 0
            self._sync()

    def _sync(self) -> None:
        """Wait until the disk has every byte written so far (a durable tile's)."""
        self._file.flush()
        if self._durable:
            os.fdatasync(self._file.fileno())

    def _append(self, records: np.ndarray) -> None:
        import laspy
        record = laspy.PackedPointRecord(records, self._sink.header.point_format)
        if isinstance(self._sink, laspy.LasWriter):
            self._sink.point_writer.write_points(record)
        else:
            self._sink.points_appender.append_points(record)

    def close(self) -> None:
        """Finish the file (held records, header, LAZ chunk table) and close it (its writer's close syncs it)."""
        try:
            self.flush()
            self._sink.close()
            self._file.flush()
        finally:
            self._file.close()

    def discard(self) -> None:
        """Close the file without finishing it (its contents are to be deleted)."""
        self._file.close()


ONE_RETURN = 0x11  # format 6's return byte: return number 1 (bits 0-3) of 1 return (bits 4-7)
RECORDS_AT_ONCE = 1 << 20  # points whose records a write makes at once (whole tiles, at least one)


def _tile_runs(starts: np.ndarray, n: int) -> list[np.ndarray]:
    """The tiles of :func:`_tile_order` in runs of whole tiles holding at most RECORDS_AT_ONCE points (a larger tile
    alone): each run the positions in the order where its tiles start, and where its last one ends."""
    bounds = np.r_[starts, n]
    runs, first = [], 0
    while first < len(starts):
        last = max(int(np.searchsorted(bounds, bounds[first] + RECORDS_AT_ONCE, "right")) - 1, first + 1)
        runs.append(bounds[first:last + 1])
        first = last
    return runs


def _tile_order(ix: np.ndarray, iy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points' order tile after tile (by tile index pair; input order kept within a tile) and where each tile's
    points start in it. When the tiles' bounding box holds at most 2^16 tiles, the index pair is sorted as one 16-bit
    key (NumPy's stable sort of 16-bit keys is a radix sort), else by both indices."""
    x0, y0 = ix.min(), iy.min()
    width = int(iy.max() - y0) + 1
    if (int(ix.max() - x0) + 1) * width <= 1 << 16:
        key = ((ix - x0) * width + (iy - y0)).astype(np.uint16)
        order = np.argsort(key, kind="stable")
        key = key[order]
        return order, np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    order = np.lexsort((iy, ix))  # stable: input order is kept within a tile
    ix, iy = ix[order], iy[order]
    return order, np.flatnonzero(np.r_[True, (ix[1:] != ix[:-1]) | (iy[1:] != iy[:-1])])
