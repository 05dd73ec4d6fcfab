"""Scenes read from files (meshes, height grids), kept on disk as ``.npz`` so that the next run over
the same file starts in seconds.

An entry holds the scene's arrays (vertices, triangles, plane ids, classes, per-triangle reflectance:
empty when the scene has none), its height grid (:mod:`flightsim.scenes.height_grid`, built when the
entry is written: every flight plan reads it), its planes, origin, CRS (WKT), name and ground height, and the key it
was made for: the cache format, the flightsim version, the source file's resolved path, size and
modification time [ns], and every option that shapes the scene (with the size and modification
time of any file an option names). An entry is used only when its key equals the one asked for and
it reads back into a valid scene; anything else (missing, stale, truncated, corrupt, or of an older
format) is ignored and the scene is loaded afresh and written again. Entries are written to a
temporary name and renamed, so a reader never sees half an entry; entries whose source file is gone
are removed when a new one is written. A cache folder that cannot be written only costs the saving.

An entry is an ordinary ``.npz`` (``np.savez``: uncompressed members), read by mapping the file into memory
(copy-on-write) and viewing each member's bytes in place: no copy and no pass over the data until the
arrays are used (``np.load`` copies every member through 256 kB reads: 0.6 s for a 1e7-triangle scene).
The members' CRCs are not checked (that would be the pass over the data); an entry that is not a whole
zip of stored ``.npy`` members, or whose arrays do not make a valid scene, is ignored as above.

Arrays a scene computes from its settings alone (a procedural forest's leaf voxels) are kept the same way
(:func:`cached_arrays`): keyed on those settings, the seed and the source of the code that computes them, and never
removed as orphans (they name no source file).

The folder is ``$FLIGHTSIM_CACHE``, else ``~/.cache/flightsim/scenes``.
"""
from __future__ import annotations

import hashlib
import io
import json
import mmap
import os
import struct
import tempfile
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from flightsim.core.version import __version__
from flightsim.core.errors import InputError
from flightsim.scenes.scene import PlaneInfo, Scene, parse_crs

CACHE_FORMAT = 3
"""Bumped whenever the stored arrays or the way scenes are read change meaning (2: per-triangle reflectance,
3: the height grid)."""

_PLANE_FIELDS = ("kind", "classification", "normal", "point", "pitch_deg", "azimuth_deg", "building")
_GRID_FIELDS = ("origin_cell", "top", "start", "members")


def cache_folder() -> Path:
    """The folder of the scene cache: ``$FLIGHTSIM_CACHE`` or ``~/.cache/flightsim/scenes``."""
    return Path(os.environ.get("FLIGHTSIM_CACHE") or Path.home() / ".cache" / "flightsim" / "scenes")


def cached_scene(path, options: dict, load: Callable[[], Scene], folder: Path | None = None,
                 grid_device: str | None = None) -> Scene:
    """The scene of the file ``path`` from the cache, or ``load()`` (then stored for next time).

    Args:
        path: the source file (it must exist; ``load`` reports the errors of a bad one).
        options: JSON-serialisable settings that shape the scene (CRS, origin, plane grouping, …);
            a string naming an existing file also keys the entry on that file's size and time.
        load: reads the scene afresh.
        folder: the cache folder; :func:`cache_folder` by default.
        grid_device: the Warp device that builds the height grid of a scene read afresh (None: NumPy).
    """
    folder = cache_folder() if folder is None else Path(folder)
    key = _key(Path(path), options)
    if key is None:
        return load()
    digest = hashlib.sha256(key.encode("utf-8")).hexdigest()[:24]
    entry = folder / f"{Path(path).stem[:40]}-{digest}.npz"
    scene = _read_entry(entry, key)
    if scene is None:
        scene = load()
        if grid_device is not None:
            scene.build_height_grid(grid_device)
        _write_entry(folder, entry, key, scene)
    return scene


def cached_arrays(name: str, inputs: dict, code: tuple, compute: Callable[[], dict[str, np.ndarray]],
                  folder: Path | None = None) -> dict[str, np.ndarray]:
    """The arrays ``compute()`` makes, from the cache or computed (then stored for next time).

    Args:
        name: what they are (the entry's file name starts with it).
        inputs: JSON-serialisable values that are everything the arrays depend on besides the code.
        code: the modules whose source computes them: an entry is used only by the same source.
        compute: makes them afresh (a dict of arrays, none of them object arrays).
        folder: the cache folder; :func:`cache_folder` by default.
    """
    folder = cache_folder() if folder is None else Path(folder)
    source = hashlib.sha256(b"".join(Path(module.__file__).read_bytes() for module in code)).hexdigest()
    key = json.dumps({"format": CACHE_FORMAT, "flightsim": __version__, "numpy": np.__version__, "computed": name,
                      "code": source, "inputs": inputs}, sort_keys=True, default=str)
    entry = folder / f"{name}-{hashlib.sha256(key.encode('utf-8')).hexdigest()[:24]}.npz"
    try:
        stored = _stored_arrays(entry)
        if str(stored.pop("key")) == key:
            return stored
    except (OSError, EOFError, KeyError, ValueError, TypeError, zipfile.BadZipFile):
        pass
    arrays = compute()
    _store(folder, entry, {"key": np.array(key), **arrays})
    return arrays


def _key(path: Path, options: dict) -> str | None:
    """The entry's key as canonical JSON, None when the source cannot be stat'ed (``load`` then says why)."""
    try:
        source = path.resolve()
        files = {str(source): _stamp(source)}
        for value in options.values():
            if isinstance(value, str) and value and Path(value).is_file():
                files[str(Path(value).resolve())] = _stamp(Path(value))
    except OSError:
        return None
    key = {"format": CACHE_FORMAT, "flightsim": __version__, "source": str(source), "files": files,
           "options": options}
    return json.dumps(key, sort_keys=True, default=str)


def _stamp(path: Path) -> list[int]:
    """(size [B], modification time [ns]) of a file."""
    stat = path.stat()
    return [stat.st_size, stat.st_mtime_ns]


def _read_entry(entry: Path, key: str) -> Scene | None:
    """The scene stored at ``entry`` for ``key``; None if absent, made for another key, or unreadable."""
    try:
        data = _stored_arrays(entry)
        if str(data["key"]) != key:
            return None
        planes = [PlaneInfo(id=k, kind=str(kind), classification=int(c), normal=n, point=p,
                            pitch_deg=float(pitch), azimuth_deg=float(azimuth), building=int(b))
                  for k, (kind, c, n, p, pitch, azimuth, b)
                  in enumerate(zip(*(data[f"plane_{name}"] for name in _PLANE_FIELDS)))]
        reflectance = data["reflectance"]
        scene = Scene(name=str(data["name"]), crs=parse_crs(str(data["crs"])), origin=data["origin"],
                     vertices=data["vertices"], triangles=data["triangles"], plane_id=data["plane_id"],
                     classification=data["classification"], planes=planes, ground_z=float(data["ground_z"]),
                     dropped_degenerate=int(data["dropped_degenerate"]), planar=bool(data["planar"]),
                     reflectance=reflectance if reflectance.size else None)
        scene.adopt_height_grid({name: data[f"grid_{name}"] for name in _GRID_FIELDS})
        return scene
    except (OSError, EOFError, KeyError, ValueError, TypeError, IndexError, zipfile.BadZipFile, InputError):
        return None


def _write_entry(folder: Path, entry: Path, key: str, scene: Scene) -> None:
    """Store ``scene`` at ``entry`` (a temporary file renamed into place); drop entries of vanished sources."""
    arrays = {
        "key": np.array(key), "name": np.array(scene.name), "crs": np.array(scene.crs.to_wkt()),
        "origin": scene.origin, "vertices": scene.vertices, "triangles": scene.triangles,
        "plane_id": scene.plane_id, "classification": scene.classification,
        "reflectance": np.zeros(0, dtype=np.float32) if scene.reflectance is None else scene.reflectance,
        "ground_z": np.array(scene.ground_z), "dropped_degenerate": np.array(scene.dropped_degenerate),
        "planar": np.array(scene.planar),
        **{f"grid_{name}": array for name, array in scene.height_grid.arrays().items()},
        **{f"plane_{name}": np.array([getattr(p, name) for p in scene.planes]) for name in _PLANE_FIELDS},
    }
    try:
        _drop_orphans(folder)
    except OSError:
        pass
    _store(folder, entry, arrays)


def _store(folder: Path, entry: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``entry`` through a temporary file renamed into place; a folder that cannot be written
    only costs the saving."""
    temporary = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{entry.stem}.", suffix=".part", delete=False) as fh:
            temporary = Path(fh.name)
            np.savez(fh, **arrays)
        os.replace(temporary, entry)
    except OSError:
        if temporary is not None:
            temporary.unlink(missing_ok=True)


def _drop_orphans(folder: Path) -> None:
    """Remove the entries whose source file no longer exists, and unreadable ones (computed arrays name none)."""
    for entry in folder.glob("*.npz"):
        try:
            key = json.loads(str(_stored_arrays(entry)["key"]))
            source = "" if "computed" in key else key["source"]
        except (OSError, EOFError, KeyError, ValueError, TypeError, zipfile.BadZipFile):
            source = None
        if source is None or (source and not Path(source).exists()):
            entry.unlink(missing_ok=True)


def _stored_arrays(entry: Path) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``entry``, viewed in place in a copy-on-write mapping of the file.

    Raises ``zipfile.BadZipFile`` (not a whole zip file), ``ValueError`` (a compressed member, an object
    array, a bad ``.npy`` header) or ``TypeError`` (a member cut short) for a file that is not one
    ``np.savez`` wrote."""
    with open(entry, "rb") as file, zipfile.ZipFile(file) as archive:
        mapped = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_COPY)
        arrays = {}
        for member in archive.infolist():
            if member.compress_type != zipfile.ZIP_STORED or not member.filename.endswith(".npy"):
                raise ValueError(f"{member.filename}: not a stored .npy member")
            local = member.header_offset
            name_length, extra_length = struct.unpack("<HH", mapped[local + 26:local + 30])
            start = local + 30 + name_length + extra_length  # the member's bytes: a .npy file
            head = io.BytesIO(mapped[start:start + 65536])
            version = np.lib.format.read_magic(head)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(head)
            if dtype.hasobject:
                raise ValueError(f"{member.filename}: object array")
            arrays[member.filename[:-4]] = np.ndarray(shape, dtype=dtype, buffer=mapped, offset=start + head.tell(),
                                                      order="F" if fortran else "C")
    return arrays
