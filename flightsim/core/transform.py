"""pyproj transforms of many points on every core: pyproj lets go of Python's lock while PROJ works, so the points
cut into parts are transformed side by side on threads, each with a transformer of its own (a transformer is not
to be shared between threads). Each point is transformed by itself, so the values are those of one call."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyproj

from flightsim.core.process_map import thread_count

PART_POINTS = 1 << 18  # the fewest points a thread transforms


def transform(source, target, *coordinates: np.ndarray) -> tuple[np.ndarray, ...]:
    """``pyproj.Transformer.from_crs(source, target, always_xy=True).transform(*coordinates)`` as float64 arrays,
    over threads from 2 · PART_POINTS points."""
    coordinates = tuple(np.ascontiguousarray(c, dtype=np.float64) for c in coordinates)
    n = len(coordinates[0]) if coordinates else 0
    threads = thread_count(n // PART_POINTS)
    if threads < 2:
        return _transform(source, target, coordinates)
    bounds = np.linspace(0, n, threads + 1).astype(np.int64)
    parts = [tuple(c[a:b] for c in coordinates) for a, b in zip(bounds[:-1], bounds[1:])]
    with ThreadPoolExecutor(threads, thread_name_prefix="pyproj") as pool:
        done = list(pool.map(lambda part: _transform(source, target, part), parts))
    return tuple(np.concatenate([part[k] for part in done]) for k in range(len(coordinates)))


def _transform(source, target, coordinates: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    values = pyproj.Transformer.from_crs(source, target, always_xy=True).transform(*coordinates)
    return tuple(np.asarray(v, dtype=np.float64) for v in values)
