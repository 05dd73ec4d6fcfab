"""An HDF5 product written the way every flightsim file is: under a temporary name (core.atomic), datasets
grown row by row as chunks arrive, renamed into place when complete or removed on failure."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from flightsim.core.version import __version__
from flightsim.core.atomic import temporary_name

ROWS_PER_CHUNK = 1 << 16  # largest HDF5 chunk of a 1-D dataset [rows]
MIN_ROWS_PER_CHUNK = 1 << 10  # smallest: a one-shot product stays small (a chunk is stored whole)


class H5Product:
    """``path`` open for writing under its temporary name, the file's attributes set (``flightsim`` too)."""

    def __init__(self, path: Path, **attrs):
        self.path, self.part = Path(path), temporary_name(Path(path))
        self.file = h5py.File(self.part, "w")
        self.file.attrs.update(flightsim=__version__, **attrs)

    def append(self, group: str, columns: dict, compress: bool = False) -> int:
        """Append rows to the datasets ``group/name`` (created on first use from the values' dtype and row
        shape; gzip with ``compress``); returns the rows the group held before."""
        g = self.file.require_group(group)
        before = None
        for name, values in columns.items():
            values = np.asarray(values)
            if name not in g:
                rows = min(ROWS_PER_CHUNK, max(MIN_ROWS_PER_CHUNK, len(values)))  # the first rows' count: a hint
                chunks = (rows,) if values.ndim == 1 else True
                g.create_dataset(name, shape=(0,) + values.shape[1:], maxshape=(None,) + values.shape[1:],
                                 dtype=values.dtype, chunks=chunks,
                                 **({"compression": "gzip", "shuffle": True} if compress else {}))
            n = g[name].shape[0]
            before = n if before is None else before
            g[name].resize((n + len(values),) + values.shape[1:])
            g[name][n:] = values
        return before or 0

    def close(self) -> str:
        """Rename the finished file into place; its name."""
        self.file.close()
        os.replace(self.part, self.path)
        return self.path.name

    def abort(self) -> None:
        self.file.close()
        self.part.unlink(missing_ok=True)
