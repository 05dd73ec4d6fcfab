"""astropy's Earth orientation table (IERS-A with IERS-B, as ``IERS_Auto`` reads them without downloading), parsed
once per machine and kept in the scene cache folder (:func:`flightsim.scenes.cache.cache_folder`).

astropy reads the bundled IERS files (two fixed-width text tables of ~20,000 days) the first time a process turns
GCRS into ITRS: 0.4-0.6 s of every Earth-orbit run. :func:`use_cached_table` hands astropy the same table from an
HDF5 entry written by astropy's own table writer (units and metadata kept: ``serialize_meta``) the first time,
keyed on astropy's version, the IERS data package's and the bundled files' paths, sizes and modification times.
The rotations are the same bits as with the table parsed afresh (``tests/test_orbit.py``). An entry that is
missing, stale or unreadable is ignored (astropy parses the files as usual and the entry is written again); a folder
that cannot be written only costs the saving. Entries are written to a temporary name and renamed. A run with
``run.scene_cache = false`` neither reads nor writes the entry (:data:`USE_CACHE`).
"""
from __future__ import annotations

import contextvars
import hashlib
import json
import os
import tempfile
from pathlib import Path

from flightsim.scenes.cache import cache_folder

_TABLE_PATH = "iers"  # the table's path inside the HDF5 entry
_KEY = "flightsim_key"  # the entry's key, among the table's metadata
USE_CACHE = contextvars.ContextVar("earth_orientation_cache", default=True)
"""Whether :func:`use_cached_table` may read and write the entry (a run sets it from ``run.scene_cache``)."""


def use_cached_table(folder: Path | None = None) -> None:
    """Give astropy's ``IERS_Auto`` the bundled table from the cache, or parse it and store it there; nothing
    when this process has the table already. ``folder``: the cache folder (:func:`cache_folder` by default)."""
    from astropy.utils import iers

    if iers.IERS_Auto.iers_table is not None or not USE_CACHE.get():
        return
    key = _key(iers)
    digest = hashlib.sha256(key.encode("utf-8")).hexdigest()[:24]
    entry = (cache_folder() if folder is None else Path(folder)) / f"iers-{digest}.h5"
    table = _read(entry, key, iers)
    if table is not None:
        iers.IERS_Auto.iers_table = table
        return
    _write(entry, key, iers.IERS_Auto.open())


def _key(iers) -> str:
    """The bundled files' stamps and the versions that read them, as canonical JSON."""
    import astropy

    try:
        import astropy_iers_data
        data = astropy_iers_data.__version__
    except ImportError:
        data = ""
    files = {}
    for name in (iers.IERS_A_FILE, iers.IERS_B_FILE):
        try:
            stat = os.stat(name)
            files[str(name)] = [stat.st_size, stat.st_mtime_ns]
        except OSError:
            files[str(name)] = None
    return json.dumps({"astropy": astropy.__version__, "iers_data": data, "files": files}, sort_keys=True)


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
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=entry.parent, prefix=".iers-", suffix=".h5")
        os.close(handle)
        try:
            stored.write(temporary, path=_TABLE_PATH, format="hdf5", serialize_meta=True, overwrite=True)
            os.replace(temporary, entry)
        finally:
            if os.path.exists(temporary):
                os.remove(temporary)
    except Exception:  # noqa: BLE001 (h5py's and astropy's writers raise their own; the run goes on without)
        return
