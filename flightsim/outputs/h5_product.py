"""An HDF5 product written the way every flightsim file is: under a temporary name (core.atomic), datasets
grown row by row as chunks arrive, renamed into place when complete or removed on failure."""
from __future__ import annotations

import os
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np
from h5py import h5s

from flightsim.core.version import __version__
from flightsim.core.atomic import temporary_name
from flightsim.core.process_map import thread_count

ROWS_PER_CHUNK = 1 << 16  # largest HDF5 chunk of a 1-D dataset [rows]; of wider rows, as many values
MIN_ROWS_PER_CHUNK = 1 << 10  # smallest (a one-shot product stays small: a chunk is stored whole); wider rows: as many
# values
GZIP_LEVEL = 4  # h5py's gzip level, which the datasets are made with
PARALLEL_CHUNKS = 4  # an append of this many chunks or more writes its whole chunks itself (compressed on threads)


class H5Product:
    """``path`` open for writing under its temporary name, the file's attributes set (``flightsim`` too)."""

    def __init__(self, path: Path, **attrs):
        self.path, self.part = Path(path), temporary_name(Path(path))
        self.file = h5py.File(self.part, "w")
        self.file.attrs.update(flightsim=__version__, **attrs)
        self.datasets: dict[str, tuple[h5py.Dataset, str | None]] = {}  # "group/name": (dataset, its chunks by hand)

    def append(self, group: str, columns: dict, compress: bool = False) -> int:
        """Append rows to the datasets ``group/name`` (created on first use from the values' dtype and row
        shape; gzip with ``compress``); returns the rows the group held before. The datasets are kept open between
        appends (h5py's lookups by name were half of a small append's time)."""
        before = None
        for name, values in columns.items():
            values = np.asarray(values)
            dataset, by_hand = self.datasets.get(f"{group}/{name}") or self._dataset(group, name, values, compress)
            n = dataset.id.shape[0]
            before = n if before is None else before
            dataset.id.set_extent((n + len(values),) + values.shape[1:])
            if by_hand and len(values) >= PARALLEL_CHUNKS * dataset.chunks[0]:
                _write_chunks(dataset, n, values, by_hand == "deflate")
            elif values.dtype == dataset.dtype and values.shape[1:] == dataset.shape[1:] and len(values):
                _write_rows(dataset, n, values)
            else:
                dataset[n:] = values
        return before or 0

    def _dataset(self, group: str, name: str, values: np.ndarray, compress: bool) -> tuple[h5py.Dataset, str | None]:
        """``group/name``, made from the first values' dtype and row shape where the file lacks it, and how its large
        appends' chunks may be written by hand (:func:`_chunks_by_hand`); kept for the next appends."""
        g = self.file.require_group(group)
        if name not in g:
            width = max(1, int(np.prod(values.shape[1:], dtype=np.int64)))  # values a row
            most, least = max(1, ROWS_PER_CHUNK // width), max(1, MIN_ROWS_PER_CHUNK // width)
            rows = min(most, max(least, len(values)))  # the first rows' count: a hint
            g.create_dataset(name, shape=(0,) + values.shape[1:], maxshape=(None,) + values.shape[1:],
                             dtype=values.dtype, chunks=(rows,) + values.shape[1:],
                             **({"compression": "gzip", "shuffle": True} if compress else {}))
        kept = self.datasets[f"{group}/{name}"] = (g[name], _chunks_by_hand(g[name]))
        return kept

    def close(self) -> str:
        """Rename the finished file into place; its name."""
        self.file.close()
        os.replace(self.part, self.path)
        return self.path.name

    def abort(self) -> None:
        self.file.close()
        self.part.unlink(missing_ok=True)


def _write_rows(dataset: h5py.Dataset, n: int, values: np.ndarray) -> None:
    """``dataset[n:n + len(values)] = values`` for values of the dataset's dtype and row shape, through h5py's
    low-level write: its high-level one builds selection objects every call (~0.1 ms of Python's lock an append, a few
    thousand appends a 30 s ATLAS pass)."""
    values = np.ascontiguousarray(values)
    space = dataset.id.get_space()
    space.select_hyperslab((n,) + (0,) * (values.ndim - 1), values.shape)
    dataset.id.write(h5s.create_simple(values.shape), space, values)


def _chunks_by_hand(dataset: h5py.Dataset) -> str | None:
    """How appends of PARALLEL_CHUNKS chunks of rows or more to ``dataset`` may write their whole chunks themselves:
    "deflate" (shuffled and deflated on threads) for a dataset chunked by whole rows with exactly the shuffle and gzip
    filters and the fill value 0, "plain" (as they are) for one of numbers or booleans without filters, of fill value
    0, in this machine's byte order (HDF5 would copy them through its chunk cache first); None otherwise."""
    if dataset.chunks is None or dataset.chunks[1:] != dataset.shape[1:] or dataset.fillvalue:
        return None
    if dataset.compression == "gzip" and dataset.shuffle and not dataset.fletcher32 and dataset.scaleoffset is None:
        return "deflate"
    if dataset.id.get_create_plist().get_nfilters() == 0 and dataset.dtype.kind in "biuf" and dataset.dtype.isnative:
        return "plain"
    return None


def _write_chunks(dataset: h5py.Dataset, n: int, values: np.ndarray, deflate: bool) -> None:
    """``dataset[n:n + len(values)] = values`` for a dataset of :func:`_chunks_by_hand`: the rows up to the first
    chunk boundary through HDF5, every chunk from there stored as it is, or shuffled and deflated on threads (zlib
    lets go of Python's lock, h5py holds it through HDF5's own filters) as HDF5's shuffle and gzip filters store it
    (a last partial chunk padded with the fill value 0, as HDF5 stores one). The values read back are the same either
    way."""
    rows, values = dataset.chunks[0], values.astype(dataset.dtype, copy=False)
    first = min(-(-n // rows) * rows, n + len(values))
    if first > n:
        _write_rows(dataset, n, values[:first - n])
    rest, across = values[first - n:], (0,) * (values.ndim - 1)
    starts = range(0, len(rest), rows)
    if not deflate:
        for start in starts:
            dataset.id.write_direct_chunk((first + start, *across), _padded(rest[start:start + rows], rows))
        return
    with ThreadPoolExecutor(thread_count(len(starts)), thread_name_prefix="deflate") as pool:
        deflated = pool.map(lambda start: _deflated(rest[start:start + rows], rows), starts)
        for start, chunk in zip(starts, deflated):
            dataset.id.write_direct_chunk((first + start, *across), chunk)


def _padded(values: np.ndarray, rows: int) -> np.ndarray:
    """One chunk of ``rows`` rows: ``values`` (contiguous), then zeros where they are fewer."""
    if len(values) == rows:
        return np.ascontiguousarray(values)
    chunk = np.zeros((rows,) + values.shape[1:], dtype=values.dtype)
    chunk[:len(values)] = values
    return chunk


def _deflated(values: np.ndarray, rows: int) -> bytes:
    """One chunk of ``rows`` rows (``values`` then zeros) as HDF5's shuffle and gzip filters store it."""
    chunk = _padded(values, rows)
    shuffled = np.ascontiguousarray(chunk.view(np.uint8).reshape(chunk.size, chunk.itemsize).T)  # byte k of each value
    return zlib.compress(shuffled.tobytes(), GZIP_LEVEL)
