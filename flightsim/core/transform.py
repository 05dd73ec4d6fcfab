"""pyproj transforms of many points on every core: pyproj lets go of Python's lock while PROJ works, so the points
cut into parts are transformed side by side on threads. Each point is transformed by itself, so the values are those
of one call.

A pair of CRSs gets one :func:`transformer` for the process: making one parses both CRSs against PROJ's database
under Python's lock (0.4 ms on the 2-core CPU, several ms on a GPU host, where an ATLAS pass made one for every beam
and part, ~1.7 s of the lock in a 30 s pass), and pyproj (≥ 3.1) gives each thread that uses a transformer a PROJ
object of its own, made at the thread's first use: the parts go to one pool of threads kept for the process, so
that happens once a thread. Every transform runs there, a single part too (the calling thread waits for it): a thread
made for a moment (a pool a chunk) would make a PROJ object of its own (several ms of the lock on a GPU host) for a
handful of points."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyproj

from flightsim.core.process_map import MAX_THREADS, thread_count

PART_POINTS = 1 << 18  # the fewest points a thread transforms
_TRANSFORMERS: dict[tuple[str, str], pyproj.Transformer] = {}
_LOCK = threading.Lock()
_POOL: list[ThreadPoolExecutor] = []  # the transforms' threads, made at the first transform in parts


def transformer(source, target) -> pyproj.Transformer:
    """``pyproj.Transformer.from_crs(source, target, always_xy=True)`` (CRSs as pyproj takes them), one for each pair
    of CRSs by their definitions (a :class:`pyproj.CRS`'s ``srs``), shared by every thread."""
    key = (_definition(source), _definition(target))
    with _LOCK:
        made = _TRANSFORMERS.get(key)
        if made is None:
            made = _TRANSFORMERS[key] = pyproj.Transformer.from_crs(source, target, always_xy=True)
    return made


def transform(source, target, *coordinates: np.ndarray) -> tuple[np.ndarray, ...]:
    """``transformer(source, target).transform(*coordinates)`` as float64 arrays of the coordinates' (broadcast) shape,
    on the kept threads: over several from 2 · PART_POINTS points."""
    shaped = np.broadcast_arrays(*(np.asarray(c, dtype=np.float64) for c in coordinates))
    coordinates = tuple(np.ascontiguousarray(c).reshape(-1) for c in shaped)
    n = len(coordinates[0]) if coordinates else 0
    threads = thread_count(n // PART_POINTS)
    if threads < 2:
        values = _pool().submit(_transform, source, target, coordinates).result()
        return tuple(v.reshape(shaped[0].shape) for v in values)
    bounds = np.linspace(0, n, threads + 1).astype(np.int64)
    parts = [tuple(c[a:b] for c in coordinates) for a, b in zip(bounds[:-1], bounds[1:])]
    done = list(_pool().map(lambda part: _transform(source, target, part), parts))
    return tuple(np.concatenate([part[k] for part in done]).reshape(shaped[0].shape) for k in range(len(coordinates)))


def _transform(source, target, coordinates: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    values = transformer(source, target).transform(*coordinates)
    return tuple(np.asarray(v, dtype=np.float64) for v in values)


def _definition(crs) -> str:
    return crs if isinstance(crs, str) else pyproj.CRS.from_user_input(crs).srs


def _pool() -> ThreadPoolExecutor:
    with _LOCK:
        if not _POOL:
            _POOL.append(ThreadPoolExecutor(MAX_THREADS, thread_name_prefix="pyproj"))
        return _POOL[0]
