"""astropy's Earth orientation table (IERS-A with IERS-B, as ``IERS_Auto`` reads them without downloading), parsed
once per machine and kept in the scene cache folder (:func:`flightsim.scenes.cache.cache_folder`); and the GCRS → ITRS
rotations astropy works out from it, kept there per set of times (:func:`cached_rotations`).

astropy reads the bundled IERS files (two fixed-width text tables of ~20,000 days) the first time a process turns
GCRS into ITRS: 0.4-0.6 s of every Earth-orbit run. :func:`use_cached_table` hands astropy the same table from an
HDF5 entry written by astropy's own table writer (units and metadata kept: ``serialize_meta``) the first time,
keyed on astropy's version, the IERS data package's and the bundled files' paths, sizes and modification times.
The rotations are the same bits as with the table parsed afresh (``tests/test_orbit.py``). An entry that is
missing, stale or unreadable is ignored (astropy parses the files as usual and the entry is written again); a folder
that cannot be written only costs the saving. Entries are written to a temporary name and renamed. A run with
``run.scene_cache = false`` neither reads nor writes the entry (:data:`USE_CACHE`).

The rotations of a pass (astropy's transform graph, its import and its time scales: 1.1-2.2 s of an Earth-orbit
run's plan on the 2-core CPU, ~0.3 s on a GPU host, before its first ray) are the same for every run of the same
epochs: :func:`cached_rotations` keeps them in an ``.npy`` entry keyed on the times' bytes and on what shapes
astropy's answer (the versions of astropy, pyerfa and the IERS data package, and the bundled IERS and leap-second
files' paths, sizes and times), so a run of a pass flown before reads astropy's own bits without importing astropy.
"""
from __future__ import annotations

import contextvars
import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import numpy as np

from flightsim.scenes.cache import cache_folder

_TABLE_PATH = "iers"  # the table's path inside the HDF5 entry
_KEY = "flightsim_key"  # the entry's key, among the table's metadata
USE_CACHE = contextvars.ContextVar("earth_orientation_cache", default=True)
"""Whether :func:`use_cached_table` and :func:`cached_rotations` may read and write their entries (a run sets it from
``run.scene_cache``)."""


def use_cached_table(folder: Path | None = None) -> None:
    """Give astropy's ``IERS_Auto`` the bundled table from the cache, or parse it and store it there; nothing
    when this process has the table already. ``folder``: the cache folder (:func:`cache_folder` by default)."""
    from astropy.utils import iers

    if iers.IERS_Auto.iers_table is not None or not USE_CACHE.get():
        return
    key = _sources()
    entry = _entry(folder, "iers", key, ".h5")
    table = _read(entry, key, iers)
    if table is not None:
        iers.IERS_Auto.iers_table = table
        return
    _write(entry, key, iers.IERS_Auto.open())


def cached_rotations(times: np.ndarray, rotations: Callable[[np.ndarray], np.ndarray],
                     folder: Path | None = None) -> np.ndarray:
    """``rotations(times)`` (astropy's (n, 3, 3) GCRS → ITRS rotations at ``times``, float64) from the scene cache
    (``folder``, :func:`cache_folder` by default), or worked out and stored there for the next run of the same
    times; an entry missing, of another key or unreadable is worked out again."""
    times = np.ascontiguousarray(times, dtype=np.float64)
    if not USE_CACHE.get():
        return rotations(times)
    key = json.dumps({"times": hashlib.sha256(times.tobytes()).hexdigest(), "shape": times.shape,
                      "sources": _sources()}, sort_keys=True)
    entry = _entry(folder, "rotations", key, ".npy")
    try:
        with open(entry, "rb") as f:
            if f.readline().decode("utf-8").rstrip("\n") == key:
                found = np.load(f)
                if found.dtype == np.float64 and found.shape == times.shape + (3, 3):
                    return found
    except (OSError, ValueError, UnicodeDecodeError):  # missing, cut short or foreign: worked out again
        pass
    found = np.asarray(rotations(times), dtype=np.float64)

    def write(path: str) -> None:
        with open(path, "wb") as f:
            f.write(key.encode("utf-8") + b"\n")
            np.save(f, found)

    _store(entry, write)
    return found


def _entry(folder: Path | None, kind: str, key: str, suffix: str) -> Path:
    digest = hashlib.sha256(key.encode("utf-8")).hexdigest()[:24]
    return (cache_folder() if folder is None else Path(folder)) / f"{kind}-{digest}{suffix}"


def _sources() -> str:
    """What shapes astropy's Earth orientation, read without importing astropy, as canonical JSON: the versions of
    astropy, pyerfa and the IERS data package and the bundled IERS-A, IERS-B and leap-second files' stamps."""
    try:
        import astropy_iers_data
        bundled = (astropy_iers_data.IERS_A_FILE, astropy_iers_data.IERS_B_FILE, astropy_iers_data.IERS_LEAP_SECOND_FILE)
    except ImportError:  # an astropy that bundles its tables itself: its version keys them
        bundled = ()
    versions = {}
    for name in ("astropy", "pyerfa", "astropy-iers-data"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    files = {}
    for name in bundled:
        try:
            stat = os.stat(name)
            files[str(name)] = [stat.st_size, stat.st_mtime_ns]
        except OSError:
            files[str(name)] = None
    return json.dumps({"versions": versions, "files": files}, sort_keys=True)


def _store(entry: Path, write: Callable[[str], None]) -> None:
    """``write(path)`` of a temporary file then renamed to ``entry``; a failure only costs the saving."""
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=entry.parent, prefix=f".{entry.stem}-", suffix=entry.suffix)
        os.close(handle)
        try:
            write(temporary)
            os.replace(temporary, entry)
        finally:
            if os.path.exists(temporary):
                os.remove(temporary)
    except Exception:  # noqa: BLE001 (h5py's, astropy's and the file system's errors; the run goes on without)
        return


def _read(entry: Path, key: str, iers):
    """The IERS_Auto table of the entry when it holds ``key``; None otherwise."""
    from astropy.table import QTable

    if not entry.is_file():
        return None
    try:
        table = QTable.read(entry, path=_TABLE_PATH)
    except Exception:  # a truncated or foreign file: h5py's, astropy's errors
        return None
    if table.meta.pop(_KEY, None) != key:
        return None
    return iers.IERS_Auto(table)


def _write(entry: Path, key: str, table) -> None:
    """Store ``table`` (astropy's, left as it is) under ``entry`` with ``key``; a failure only costs the saving."""
    stored = table.copy(copy_data=False)
    stored.meta[_KEY] = key
    _store(entry, lambda path: stored.write(path, path=_TABLE_PATH, format="hdf5", serialize_meta=True, overwrite=True))
