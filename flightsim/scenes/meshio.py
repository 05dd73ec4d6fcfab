"""Read triangle meshes (OBJ, PLY) into a :class:`~flightsim.scenes.scene.Scene`, and write OBJ.

File coordinates + the user's ``origin`` are world coordinates in the user's CRS. The scene's
own origin is the centre of the world bounding box rounded to whole metres, so that local
coordinates stay small even when the file holds absolute UTM values.

Plane labels come from the file where it has them (PLY per-face ``plane_id`` and
``classification``; OBJ groups ``o``/``g``, whose names give the class: "ground" → 2,
"road" → 11, "roof"/"wall"/"building" → 6, else 1). A PLY ``plane_id`` is taken as it is.
Otherwise (``planes="auto"``) faces are grouped into planes by edge connectivity and
coplanarity (normal angle ≤ 1°, offset ≤ 0.05 m, every face against its plane's area-weighted
fit; :func:`_coplanar_planes`) without crossing a group (an OBJ group, or a PLY
classification): an OBJ group is split into its planar parts (a group holding a whole house
becomes one plane per face, a curved terrain many small planes) and its coplanar parts that do
not touch are merged again (a ground cut by roads stays one plane); an unlabelled mesh is split
by connectivity and geometry alone. With ``planes="none"`` (a terrain) the groups are the
labels and nothing is grouped.

OBJ text is read with array operations over the whole file; a file with anything unusual
(and every file with an error, so that the message names the line) is read line by line.

Every problem with the file raises ``InputError("scene.path", path, ...)`` saying what was wrong.
"""
from __future__ import annotations

import itertools
import math
import warnings
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from flightsim.core.errors import InputError
from flightsim.scenes.scene import (
    CLASS_BUILDING, CLASS_GROUND, CLASS_ROAD, CLASS_UNCLASSIFIED, PlaneInfo, Scene, parse_crs,
    pitch_azimuth_deg, plane_info,
)

COPLANAR_ANGLE_DEG = 1.0
"""Largest angle [deg] between the normals of two faces of one plane."""

COPLANAR_OFFSET_M = 0.05
"""Largest distance [m] of a face's corners from the plane it joins."""

DEGENERATE_SINE = 1e-9
"""A triangle is dropped when 2·area < DEGENERATE_SINE · (longest edge)²."""

_NAME_CLASSES = (("ground", CLASS_GROUND), ("road", CLASS_ROAD), ("roof", CLASS_BUILDING),
                 ("wall", CLASS_BUILDING), ("building", CLASS_BUILDING))


class _MeshFormatError(Exception):
    """What is wrong with a mesh file; load_mesh turns it into an InputError."""


def load_mesh(path, crs, origin=(0.0, 0.0, 0.0), name: str | None = None, planes: str = "auto") -> Scene:
    """Read an OBJ or PLY triangle mesh into a Scene.

    Args:
        path: the .obj or .ply file.
        crs: the CRS of the world coordinates (anything :func:`flightsim.scenes.scene.parse_crs` takes).
        origin: (3,) world E, N, H [m] added to the file coordinates.
        name: scene name; the file stem by default.
        planes: "auto": faces grouped into planes (module docstring); "none": no grouping, one
            label per OBJ group or PLY classification (or the PLY's plane_id), and the scene is
            not ``planar`` (a terrain, whose plane fits would measure its curvature).

    Returns:
        A Scene with origin = world bounding-box centre rounded to whole metres, zero-area
        triangles dropped (counted in ``dropped_degenerate``) and ground_z = the lowest vertex
        height of the ground (class 2) triangles, or of all triangles when none is ground.
    """
    crs = parse_crs(crs, "scene.crs")
    if planes not in ("auto", "none"):
        raise InputError("scene.planes", planes, "one of auto, none")
    grouped = planes == "auto"
    try:
        offset = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]") from None
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]")
    path = Path(path)
    try:
        raw = _read(path)
        coords = raw["vertices"]
        _check_mesh(coords, raw["corners"], raw["sizes"])
    except _MeshFormatError as error:
        raise InputError("scene.path", str(path), f"a readable OBJ or PLY triangle mesh ({error})") from None

    world = coords + offset
    scene_origin = np.round(0.5 * (world.min(axis=0) + world.max(axis=0)))
    local = world - scene_origin
    triangles, source = _triangulate(raw["corners"], raw["sizes"])
    keep = ~_degenerate(local, triangles)
    if not np.any(keep):
        raise InputError("scene.path", str(path), "a readable OBJ or PLY triangle mesh (every face has zero area)")
    triangles, source = triangles[keep], source[keep]
    group = raw["group"][source]
    classes = raw["classification"][source]
    if raw["labels"] == "planes" or not grouped:
        plane_of = _renumber(group)
    else:
        plane_of = _coplanar_planes(local, triangles, group, merge_apart=raw["labels"] == "groups")
    planes, plane_classes = _plane_infos(local, triangles, plane_of, classes)
    ground = plane_classes[plane_of] == CLASS_GROUND
    ground_vertices = triangles[ground] if np.any(ground) else triangles
    return Scene(
        name=name if name is not None else path.stem,
        crs=crs,
        origin=scene_origin,
        vertices=local,
        triangles=triangles,
        plane_id=plane_of,
        classification=plane_classes[plane_of],
        planes=planes,
        ground_z=float(local[ground_vertices, 2].min()),
        dropped_degenerate=int(np.count_nonzero(~keep)),
        planar=grouped,
    )


def save_obj(scene: Scene, path) -> None:
    """Write a scene as OBJ in world coordinates [m] (local + origin), one group per plane.

    Group names are ``<label>_<plane id>``, where label is the plane's kind when the kind names
    its class ("ground", "road", "roof", "wall"), else the class ("building", "surface"), so
    that :func:`load_mesh` reads the same planes and classes back (for classes 1, 2, 6, 11).
    """
    world = scene.local_to_world(scene.vertices)
    lines = [f"# flightsim scene {scene.name}; CRS {scene.crs.to_string()}\n"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in world]
    order = np.argsort(scene.plane_id, kind="stable")
    bounds = np.searchsorted(scene.plane_id[order], np.arange(len(scene.planes) + 1))
    for plane in scene.planes:
        rows = order[bounds[plane.id]:bounds[plane.id + 1]]
        if len(rows) == 0:
            continue
        lines.append(f"g {_group_label(plane)}_{plane.id}\n")
        lines += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in scene.triangles[rows]]
    Path(path).write_text("".join(lines), encoding="utf-8")


def _group_label(plane: PlaneInfo) -> str:
    if plane.kind != "surface" and _class_from_name(plane.kind) == plane.classification:
        return plane.kind
    return "building" if plane.classification == CLASS_BUILDING else _kind_from_class(plane.classification)


def _kind_from_class(classification: int) -> str:
    return {CLASS_GROUND: "ground", CLASS_ROAD: "road"}.get(int(classification), "surface")


def _class_from_name(name: str) -> int:
    lowered = name.lower()
    for word, classification in _NAME_CLASSES:
        if word in lowered:
            return classification
    return CLASS_UNCLASSIFIED


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def _read(path: Path) -> dict:
    """Dispatch on the extension.

    Returns a dict: vertices (V, 3) float64; corners (the vertex indices of every face, one face
    after the other) and sizes (F,) (corners per face); per-face group (int) and classification
    (uint8); labels: "planes" (groups are plane ids),
    "groups" (named groups, each split into its planes) or "none" (faces of one group, e.g. of
    one class, are split into planes by geometry alone).
    """
    suffix = path.suffix.lower()
    if suffix not in (".obj", ".ply"):
        raise _MeshFormatError(f"unknown extension {path.suffix!r}; expected .obj or .ply")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise _MeshFormatError("file not found") from None
    except OSError as error:
        raise _MeshFormatError(f"cannot read the file: {error.strerror or error}") from None
    try:
        return _read_obj(data) if suffix == ".obj" else _read_ply(data)
    except _MeshFormatError:
        raise
    except (ValueError, LookupError, OverflowError, TypeError, UnicodeDecodeError) as error:
        raise _MeshFormatError(f"corrupt or truncated file: {error}") from None


def _check_mesh(coords: np.ndarray, flat: np.ndarray, sizes: np.ndarray) -> None:
    """Reject meshes without faces, with non-finite coordinates or out-of-range indices."""
    if len(sizes) == 0:
        raise _MeshFormatError("no faces")
    if not np.all(np.isfinite(coords)):
        row = int(np.argwhere(~np.isfinite(coords))[0, 0])
        raise _MeshFormatError(f"vertex {row} has a non-finite coordinate")
    if flat.min() < 0 or flat.max() >= len(coords):
        bad = int(flat[(flat < 0) | (flat >= len(coords))][0])
        raise _MeshFormatError(f"vertex index {bad} out of range for {len(coords)} vertices")


def _read_obj(data: bytes) -> dict:
    """OBJ ``v``/``f``/``g``/``o`` records (others are skipped): vectorised when every record is plain
    ASCII numbers, else (and for every error, so that its message names the line) line by line."""
    if b"\x00" in data:
        raise _MeshFormatError("binary data in an OBJ file")
    fast = _read_obj_vectorised(data)
    return fast if fast is not None else _read_obj_lines(data)


def _read_obj_lines(data: bytes) -> dict:
    text = data.decode("utf-8", errors="replace")  # a stray latin-1 comment is no reason to fail
    vertices: list[tuple[float, float, float]] = []
    faces: list[np.ndarray] = []
    face_group: list[int] = []
    groups: dict[str, int] = {}
    current = groups.setdefault("", 0)
    for number, line in enumerate(text.splitlines(), start=1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        keyword, args = parts[0], parts[1:]
        if keyword == "v":
            if len(args) < 3:
                raise _MeshFormatError(f"line {number}: a vertex needs x y z")
            try:
                vertices.append((float(args[0]), float(args[1]), float(args[2])))
            except ValueError:
                raise _MeshFormatError(f"line {number}: bad vertex {line.strip()!r}") from None
        elif keyword == "f":
            faces.append(_obj_face(args, len(vertices), number))
            face_group.append(current)
        elif keyword in ("g", "o"):
            current = groups.setdefault(" ".join(args), len(groups))
    if not faces:
        raise _MeshFormatError("no faces")
    return _obj_mesh(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), np.concatenate(faces),
                     np.array([len(f) for f in faces]), np.asarray(face_group, dtype=np.int64), list(groups))


def _obj_mesh(vertices: np.ndarray, corners: np.ndarray, sizes: np.ndarray, group: np.ndarray,
              names: list[str]) -> dict:
    """The :func:`_read` dict of an OBJ file: ``names`` are the groups in order of first use (id = index)."""
    group_class = np.array([_class_from_name(n) for n in names], dtype=np.uint8)
    return {
        "vertices": vertices,
        "corners": corners,
        "sizes": sizes,
        "group": group,
        "classification": group_class[group],
        "labels": "groups" if len(names) > 1 or group[0] != 0 else "none",
    }


_OBJ_ODD_BYTES = (b"\x0b", b"\x0c", b"\x1c", b"\x1d", b"\x1e", b"\x1f", b"\xc2\x85", b"\xe2\x80\xa8", b"\xe2\x80\xa9")
"""Whitespace and line breaks of Python's str.split / splitlines other than space, tab, CR, LF."""


def _read_obj_vectorised(data: bytes) -> dict | None:
    """:func:`_read_obj_lines`'s result computed on the whole byte buffer with numpy, or None when the
    file needs the line reader: an error to report, odd whitespace, non-ASCII keywords, numbers that
    are not plain decimals (``v`` coordinates) or integers (``f`` indices)."""
    if any(odd in data for odd in _OBJ_ODD_BYTES):
        return None
    buf = np.empty(len(data) + 1, dtype=np.uint8)
    buf[:-1] = np.frombuffer(data, dtype=np.uint8)
    buf[-1] = 10
    for byte, meaning in ((b"\r", 10), (b"\t", 32)):
        if byte in data:
            buf[buf == byte[0]] = meaning
    breaks = np.flatnonzero(buf == 10)
    if b"#" in data:
        _blank_comments(buf, breaks)
    sep = buf <= 32  # space or line break: the only bytes at or below 32 left
    edges = np.flatnonzero(np.diff(np.concatenate(([True], sep, [True])).view(np.int8)))
    starts, ends = edges[0::2], edges[1::2]  # tokens [start, end)
    line = np.searchsorted(breaks, starts)  # line number (0-based) of each token
    first = np.flatnonzero(np.r_[True, line[1:] != line[:-1]])  # each non-empty line's keyword
    count = np.diff(np.r_[first, len(starts)])  # tokens per non-empty line
    if not data.isascii():
        high = np.flatnonzero(buf >= 128)
        if np.isin(np.searchsorted(starts, high, side="right") - 1, first).any():
            return None
    keyword = np.where(ends[first] - starts[first] == 1, buf[starts[first]], 0)
    is_v, is_f = keyword == ord("v"), keyword == ord("f")
    if not is_f.any() or (count[is_v | is_f] < 4).any():
        return None
    coordinate = (first[is_v][:, None] + np.arange(1, 4)).reshape(-1)
    vertices = _parse_numbers(buf, starts[coordinate], ends[coordinate], np.float64, b"0123456789.eE+-")
    sizes = count[is_f] - 1
    token = np.repeat(first[is_f] + 1 - np.r_[0, np.cumsum(sizes)[:-1]], sizes) + np.arange(sizes.sum())
    slashes = np.flatnonzero(buf == ord("/"))
    head_end = ends[token]
    if slashes.size:
        next_slash = slashes[np.minimum(np.searchsorted(slashes, starts[token]), len(slashes) - 1)]
        head_end = np.where((next_slash > starts[token]) & (next_slash < head_end), next_slash, head_end)
    heads = _parse_numbers(buf, starts[token], head_end, np.int64, b"0123456789-")
    if vertices is None or heads is None:
        return None
    before = np.repeat((np.cumsum(is_v) - is_v)[is_f], sizes)  # vertices defined before each face
    corners = np.where(heads > 0, heads - 1, before + heads)
    if (heads == 0).any() or (corners < 0).any() or (corners >= before).any():
        return None
    group_line = np.flatnonzero((keyword == ord("g")) | (keyword == ord("o")))
    groups: dict[str, int] = {"": 0}
    group_of_line = np.zeros(len(first) + 1, dtype=np.int64)  # index -1: before any g/o record
    for k in group_line:
        n = line[first[k]]
        text = data[(breaks[n - 1] + 1 if n else 0):breaks[n]].decode("utf-8", errors="replace")
        group_of_line[k] = groups.setdefault(" ".join(text.split("#", 1)[0].split()[1:]), len(groups))
    latest = np.full(len(first), -1)
    latest[group_line] = group_line
    latest = np.maximum.accumulate(latest)
    return _obj_mesh(vertices.reshape(-1, 3), corners, sizes, group_of_line[latest[is_f]], list(groups))


def _blank_comments(buf: np.ndarray, breaks: np.ndarray) -> None:
    """Overwrite with spaces every byte from a line's first ``#`` to its end (``breaks``: line-break positions)."""
    hashes = np.flatnonzero(buf == ord("#"))
    line = np.searchsorted(breaks, hashes)
    first = np.r_[True, line[1:] != line[:-1]]
    marker = np.zeros(len(buf) + 1, dtype=np.int8)
    marker[hashes[first]] = 1
    marker[breaks[line[first]]] = -1
    buf[np.cumsum(marker[:-1], dtype=np.int8) > 0] = 32


def _parse_numbers(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, dtype, allowed: bytes) -> np.ndarray | None:
    """The numbers in byte ranges [starts, ends) of ``buf`` (disjoint, in order, each followed by a
    separator or a '/'), or None unless every range is a number made of ``allowed`` bytes alone."""
    if (ends <= starts).any():
        return None
    marker = np.zeros(len(buf) + 1, dtype=np.int8)
    marker[starts] = 1
    marker[ends] = -1
    text = np.where(np.cumsum(marker[:-1], dtype=np.int8) > 0, buf, np.uint8(32))
    table = np.zeros(256, dtype=bool)
    table[np.frombuffer(allowed + b" ", dtype=np.uint8)] = True
    if not table[text].all():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            values = np.fromstring(text.tobytes(), dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
    return values if len(values) == len(starts) else None


def _obj_face(args: list[str], n_vertices: int, number: int) -> np.ndarray:
    """0-based vertex indices of an OBJ face ``f v[/vt[/vn]] ...`` (negative = relative)."""
    if len(args) < 3:
        raise _MeshFormatError(f"line {number}: a face needs at least 3 vertices")
    index = []
    for token in args:
        head = token.split("/", 1)[0]
        try:
            k = int(head)
        except ValueError:
            raise _MeshFormatError(f"line {number}: bad face vertex {token!r}") from None
        if k == 0:
            raise _MeshFormatError(f"line {number}: vertex index 0 (OBJ indices start at 1)")
        index.append(k - 1 if k > 0 else n_vertices + k)
        if not 0 <= index[-1] < n_vertices:
            raise _MeshFormatError(f"line {number}: vertex index {k} out of range for {n_vertices} vertices")
    return np.asarray(index, dtype=np.int64)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_ply(data: bytes) -> dict:
    header, body = _ply_header(data)
    fmt = header["format"]
    elements = {}
    if fmt == "ascii":
        tokens = body.decode("ascii", errors="strict").split()
        cursor = 0
        for element in _ply_needed(header["elements"]):
            elements[element["name"]], cursor = _ply_ascii_element(element, tokens, cursor)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        cursor = 0
        for element in _ply_needed(header["elements"]):
            elements[element["name"]], cursor = _ply_binary_element(element, body, cursor, order)
    return _ply_mesh(elements)


def _ply_needed(elements: list[dict]) -> list[dict]:
    """The elements up to the last of "vertex" and "face" (later ones are not read)."""
    names = [e["name"] for e in elements]
    last = max((names.index(n) for n in ("vertex", "face") if n in names), default=len(names) - 1)
    return elements[:last + 1]


def _ply_header(data: bytes) -> tuple[dict, bytes]:
    if not data.startswith(b"ply"):
        raise _MeshFormatError("not a PLY file (no 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise _MeshFormatError("PLY header has no end_header")
    newline = data.find(b"\n", end)
    if newline < 0:
        raise _MeshFormatError("PLY header is not terminated by a newline")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    header = {"format": None, "elements": []}
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _MeshFormatError(f"unknown PLY format {line.strip()!r}")
            header["format"] = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise _MeshFormatError(f"bad PLY element line {line.strip()!r}")
            header["elements"].append({"name": parts[1], "count": int(parts[2]), "properties": []})
        elif parts[0] == "property":
            if not header["elements"]:
                raise _MeshFormatError("PLY property before any element")
            header["elements"][-1]["properties"].append(_ply_property(parts, line))
        else:
            raise _MeshFormatError(f"unknown PLY header line {line.strip()!r}")
    if header["format"] is None:
        raise _MeshFormatError("PLY header has no format line")
    return header, data[newline + 1:]


def _ply_property(parts: list[str], line: str) -> dict:
    if len(parts) == 3 and parts[1] in _PLY_TYPES:
        return {"name": parts[2], "type": _PLY_TYPES[parts[1]], "list": None}
    if len(parts) == 5 and parts[1] == "list" and parts[2] in _PLY_TYPES and parts[3] in _PLY_TYPES:
        return {"name": parts[4], "type": _PLY_TYPES[parts[3]], "list": _PLY_TYPES[parts[2]]}
    raise _MeshFormatError(f"bad PLY property line {line.strip()!r}")


def _ply_ascii_element(element: dict, tokens: list[str], cursor: int) -> tuple[dict, int]:
    """Parse ``count`` rows of an element from whitespace-separated tokens."""
    props, count = element["properties"], element["count"]
    if all(p["list"] is None for p in props):
        n = count * len(props)
        if cursor + n > len(tokens):
            raise _MeshFormatError(f"PLY element {element['name']!r} is truncated")
        table = np.array(tokens[cursor:cursor + n], dtype=np.float64).reshape(count, len(props))
        return {p["name"]: table[:, k] for k, p in enumerate(props)}, cursor + n
    fast = _ply_ascii_uniform_lists(element, tokens, cursor)
    if fast is not None:
        return fast
    columns: dict[str, list] = {p["name"]: [] for p in props}
    for _ in range(count):
        for p in props:
            if p["list"] is None:
                columns[p["name"]].append(float(_token(tokens, cursor, element)))
                cursor += 1
            else:
                length = int(_token(tokens, cursor, element))
                if length < 0 or cursor + 1 + length > len(tokens):
                    raise _MeshFormatError(f"PLY element {element['name']!r} is truncated")
                columns[p["name"]].append(np.array([int(t) for t in tokens[cursor + 1:cursor + 1 + length]]))
                cursor += 1 + length
    return {name: (v if _is_list(props, name) else np.asarray(v)) for name, v in columns.items()}, cursor


def _ply_ascii_uniform_lists(element: dict, tokens: list[str], cursor: int):
    """Fast path: every list of the element has the length found in its first row and holds
    integers. Returns (columns, new cursor), or None (the caller then parses row by row, and
    reports what is wrong)."""
    props, count = element["properties"], element["count"]
    columns, width = [], 0
    try:
        for p in props:
            columns.append((p, width))
            width += 1 if p["list"] is None else 1 + int(tokens[cursor + width])
        if count == 0 or cursor + count * width > len(tokens):
            return None
        table = np.array(tokens[cursor:cursor + count * width], dtype=np.float64).reshape(count, width)
    except (ValueError, IndexError):
        return None
    result = {}
    for (p, k), end in zip(columns, [k for _, k in columns[1:]] + [width]):
        if p["list"] is None:
            result[p["name"]] = table[:, k]
            continue
        values = table[:, k + 1:end]
        rows = slice(cursor, cursor + count * width, width)
        spelled = "".join("".join(tokens[rows.start + j:rows.stop:width]) for j in range(k + 1, end))
        integers = not any(c in spelled for c in ".eEnN") and np.all(np.abs(values) < 2.0**53)
        if end - k - 1 <= 0 or np.any(table[:, k] != end - k - 1) or not integers:
            return None
        result[p["name"]] = values.astype(np.int64)
    return result, cursor + count * width


def _is_list(props: list[dict], name: str) -> bool:
    """Whether the property ``name`` is a list property."""
    return any(p["name"] == name and p["list"] is not None for p in props)


def _token(tokens: list[str], cursor: int, element: dict) -> str:
    if cursor >= len(tokens):
        raise _MeshFormatError(f"PLY element {element['name']!r} is truncated")
    return tokens[cursor]


def _ply_binary_element(element: dict, body: bytes, cursor: int, order: str) -> tuple[dict, int]:
    """Parse ``count`` rows of a binary element starting at byte ``cursor``."""
    props, count = element["properties"], element["count"]
    truncated = _MeshFormatError(f"PLY element {element['name']!r} is truncated")
    if all(p["list"] is None for p in props):
        dtype = np.dtype([(f"p{k}", order + p["type"]) for k, p in enumerate(props)])
        if cursor + count * dtype.itemsize > len(body):
            raise truncated
        table = np.frombuffer(body, dtype=dtype, count=count, offset=cursor)
        return {p["name"]: table[f"p{k}"] for k, p in enumerate(props)}, cursor + count * dtype.itemsize
    fast = _ply_binary_uniform_lists(element, body, cursor, order)
    if fast is not None:
        return fast
    columns: dict[str, list] = {p["name"]: [] for p in props}
    for _ in range(count):
        for p in props:
            if p["list"] is None:
                dt = np.dtype(order + p["type"])
                if cursor + dt.itemsize > len(body):
                    raise truncated
                columns[p["name"]].append(np.frombuffer(body, dt, 1, cursor)[0])
                cursor += dt.itemsize
            else:
                ct, it = np.dtype(order + p["list"]), np.dtype(order + p["type"])
                if cursor + ct.itemsize > len(body):
                    raise truncated
                length = int(np.frombuffer(body, ct, 1, cursor)[0])
                cursor += ct.itemsize
                if length < 0 or cursor + length * it.itemsize > len(body):
                    raise truncated
                columns[p["name"]].append(np.frombuffer(body, it, length, cursor).astype(np.int64))
                cursor += length * it.itemsize
    return {name: (v if _is_list(props, name) else np.asarray(v)) for name, v in columns.items()}, cursor


def _ply_binary_uniform_lists(element: dict, body: bytes, cursor: int, order: str):
    """Fast path: every list of the element has the length found in its first row.

    Returns (columns, new cursor) or None when the rows differ (or the data is too short to
    tell), in which case the caller parses row by row.
    """
    props, count = element["properties"], element["count"]
    if count == 0:
        return {p["name"]: (np.zeros((0, 3), np.int64) if p["list"] else np.zeros(0)) for p in props}, cursor
    fields, lengths, at = [], {}, cursor
    for k, p in enumerate(props):
        if p["list"] is None:
            fields.append((f"p{k}", order + p["type"]))
            at += np.dtype(p["type"]).itemsize
            continue
        ct = np.dtype(order + p["list"])
        if at + ct.itemsize > len(body):
            return None
        length = int(np.frombuffer(body, ct, 1, at)[0])
        if length <= 0:
            return None
        lengths[k] = length
        fields.append((f"n{k}", ct))
        fields.append((f"p{k}", order + p["type"], (length,)))
        at += ct.itemsize + length * np.dtype(p["type"]).itemsize
    dtype = np.dtype(fields)
    if cursor + count * dtype.itemsize > len(body):
        return None
    table = np.frombuffer(body, dtype=dtype, count=count, offset=cursor)
    if any(np.any(table[f"n{k}"] != n) for k, n in lengths.items()):
        return None
    columns = {}
    for k, p in enumerate(props):
        if p["list"] is None:
            columns[p["name"]] = table[f"p{k}"]
        else:
            columns[p["name"]] = table[f"p{k}"].astype(np.int64).reshape(count, lengths[k])
    return columns, cursor + count * dtype.itemsize


def _ply_mesh(elements: dict) -> dict:
    vertex, face = elements.get("vertex"), elements.get("face")
    if vertex is None or not all(axis in vertex for axis in "xyz"):
        raise _MeshFormatError("PLY file has no vertex element with x, y, z")
    if face is None:
        raise _MeshFormatError("PLY file has no face element")
    key = "vertex_indices" if "vertex_indices" in face else "vertex_index" if "vertex_index" in face else None
    if key is None:
        raise _MeshFormatError("PLY face element has no vertex_indices list")
    faces = face[key]
    if isinstance(faces, np.ndarray):
        corners, sizes = faces.reshape(-1), np.full(len(faces), faces.shape[1])
    else:
        sizes = np.array([len(f) for f in faces], dtype=np.int64)
        corners = np.concatenate([np.asarray(f, dtype=np.int64) for f in faces] + [np.zeros(0, np.int64)])
    if len(sizes) and sizes.min() < 3:
        raise _MeshFormatError("a PLY face has fewer than 3 vertices")
    n = len(sizes)
    coords = np.column_stack([np.asarray(vertex[a], dtype=np.float64) for a in "xyz"])
    classification = _ply_int_column(face, "classification", n, CLASS_UNCLASSIFIED)
    given = "plane_id" in face
    group = _ply_int_column(face, "plane_id", n, 0) if given else classification
    if np.any((classification < 0) | (classification > 255)):
        raise _MeshFormatError("a face classification is outside 0..255")
    return {
        "vertices": coords,
        "corners": corners.astype(np.int64),
        "sizes": sizes,
        "group": group,
        "classification": classification.astype(np.uint8),
        "labels": "planes" if given else "none",
    }


def _ply_int_column(face: dict, name: str, n: int, default: int) -> np.ndarray:
    if name not in face:
        return np.full(n, default, dtype=np.int64)
    column = np.asarray(face[name], dtype=np.float64)
    if column.shape != (n,) or not np.all(np.isfinite(column)) or np.any(column != np.round(column)):
        raise _MeshFormatError(f"PLY face property {name} must be one integer per face")
    return column.astype(np.int64)


# --------------------------------------------------------------------------------------------
# Geometry: triangles, degeneracy, planes
# --------------------------------------------------------------------------------------------

def _triangulate(corners: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons: face f has corners[offset_f : offset_f + sizes[f]] (sizes ≥ 3).

    Returns (T, 3) vertex indices, the triangles of each face together in face order, and the
    source face of each triangle.
    """
    fan = sizes - 2
    source = np.repeat(np.arange(len(sizes)), fan)
    first = np.r_[0, np.cumsum(sizes)[:-1]][source]
    j = np.arange(len(source)) - np.r_[0, np.cumsum(fan)[:-1]][source] + 1
    triangles = np.column_stack([corners[first], corners[first + j], corners[first + j + 1]])
    return triangles.astype(np.int64), source


def _degenerate(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Mask of zero-area triangles (2·area < DEGENERATE_SINE · longest edge², or repeated corners)."""
    p0, p1, p2 = (vertices[triangles[:, k]] for k in range(3))
    e0, e1, e2 = p1 - p0, p2 - p1, p0 - p2
    longest = np.maximum(np.maximum(_norm_sq(e0), _norm_sq(e1)), _norm_sq(e2))
    twice_area_sq = _norm_sq(np.cross(e0, e2))
    return (twice_area_sq <= DEGENERATE_SINE**2 * longest * longest) | (longest == 0.0)


def _norm_sq(v: np.ndarray) -> np.ndarray:
    """Squared length of each row of (n, 3) ``v``."""
    return np.einsum("ij,ij->i", v, v)


def _renumber(labels: np.ndarray) -> np.ndarray:
    """Labels → 0..P-1, in increasing label order."""
    _, index = np.unique(labels, return_inverse=True)
    return index.astype(np.int32)


def _triangle_geometry(vertices: np.ndarray, triangles: np.ndarray):
    p = vertices[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    twice_area = np.linalg.norm(cross, axis=1)
    return cross / twice_area[:, None], 0.5 * twice_area, p


def _coplanar_planes(vertices: np.ndarray, triangles: np.ndarray, group: np.ndarray, merge_apart: bool) -> np.ndarray:
    """Plane id per triangle, in O(T log T) array operations.

    Vertices at the same position are welded first, so a triangle soup groups like a mesh. Two
    triangles of one group that share an edge are compatible when their normals are within
    COPLANAR_ANGLE_DEG and each one's corners lie within COPLANAR_OFFSET_M of the other's plane;
    the connected parts of compatible triangles are the first regions. A region is a plane when
    every triangle's normal is within COPLANAR_ANGLE_DEG of the region's area-weighted normal and
    every corner within COPLANAR_OFFSET_M of its plane through the area-weighted centroid; a region
    that is not (a curved surface) is cut in quarters at the mean of its triangles' centroids along
    its two axes of largest spread, and each quarter into its connected parts, until every region
    is a plane (every round handles only the regions that failed, so a mesh of T triangles takes
    about log₄ T rounds of O(T log T) work at most). With
    ``merge_apart``, planes of one group that do not touch (a ground split by roads) are merged
    when their normals and centroid offsets agree and their union is a plane.
    """
    normals, areas, corners = _triangle_geometry(vertices, triangles)
    _, weld = np.unique(np.round(vertices, 6), axis=0, return_inverse=True)
    a, b = _edge_pairs(weld.reshape(-1)[triangles])
    centroids = corners.mean(axis=1)
    keep = (group[a] == group[b]) & _same_plane(normals[a], centroids[a], normals[b], centroids[b], corners[a], corners[b])
    plane = _planar_regions(a[keep], b[keep], normals, areas, corners, centroids)
    if merge_apart:
        plane = _merge_coplanar(plane, group, normals, areas, corners, centroids)
    return _first_appearance_order(plane)


def _same_plane(n1, c1, n2, c2, corners1=None, corners2=None) -> np.ndarray:
    """Whether planes (unit normal n, point c) (m, 3) agree: normals within COPLANAR_ANGLE_DEG and each
    one's points (``corners`` (m, k, 3), else c) within COPLANAR_OFFSET_M of the other plane."""
    p1 = c1[:, None] if corners1 is None else corners1
    p2 = c2[:, None] if corners2 is None else corners2
    offset1 = np.abs(np.einsum("mkj,mj->mk", p1 - c2[:, None], n2)).max(axis=1)
    offset2 = np.abs(np.einsum("mkj,mj->mk", p2 - c1[:, None], n1)).max(axis=1)
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    return (np.einsum("mj,mj->m", n1, n2) >= cos_limit) & (offset1 <= COPLANAR_OFFSET_M) & (offset2 <= COPLANAR_OFFSET_M)


def _edge_pairs(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b), a < b, of triangles that share an (undirected) edge (every pair of a non-manifold edge)."""
    n_vertices = int(triangles.max()) + 1
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * n_vertices + edges[:, 1]
    order = np.argsort(key, kind="stable")
    owner = np.tile(np.arange(len(triangles)), 3)[order]
    starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    pairs = []
    for size in np.unique(sizes[sizes > 1]):  # 2 on a manifold mesh; more where several faces share an edge
        block = owner[starts[sizes == size][:, None] + np.arange(size)]
        i, j = np.triu_indices(size, 1)
        pairs.append(np.stack([block[:, i].reshape(-1), block[:, j].reshape(-1)]))
    a, b = np.concatenate(pairs, axis=1) if pairs else np.zeros((2, 0), dtype=np.int64)
    distinct = a != b
    return np.minimum(a, b)[distinct], np.maximum(a, b)[distinct]


def _connected(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Component label (0..C-1) of each of ``n`` nodes linked by edges (a, b)."""
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _area_weighted_planes(label, n_labels, normals, areas, centroids) -> tuple[np.ndarray, np.ndarray]:
    """Unit area-weighted normal (L, 3) and area-weighted centroid (L, 3) [m] of each label's
    triangles (zeros for a label without triangles)."""
    total = np.bincount(label, weights=areas, minlength=n_labels)
    normal = np.column_stack([np.bincount(label, weights=areas * normals[:, k], minlength=n_labels) for k in range(3)])
    centre = np.column_stack([np.bincount(label, weights=areas * centroids[:, k], minlength=n_labels) for k in range(3)])
    length = np.linalg.norm(normal, axis=1)
    return normal / np.where(length > 0.0, length, 1.0)[:, None], centre / np.where(total > 0.0, total, 1.0)[:, None]


def _planar(label, n_labels, normals, areas, corners, centroids) -> np.ndarray:
    """Per label: whether its triangles make a plane (module docstring's tolerances, against the
    label's area-weighted plane)."""
    normal, centre = _area_weighted_planes(label, n_labels, normals, areas, centroids)
    n = normal[label]
    height = np.einsum("tkj,tj->tk", corners, n) - np.einsum("lj,lj->l", normal, centre)[label][:, None]
    offset = np.maximum(np.maximum(np.abs(height[:, 0]), np.abs(height[:, 1])), np.abs(height[:, 2]))
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    fits = (np.einsum("tj,tj->t", normals, n) >= cos_limit) & (offset <= COPLANAR_OFFSET_M)
    return np.bincount(label, weights=~fits, minlength=n_labels) == 0


def _planar_regions(a, b, normals, areas, corners, centroids) -> np.ndarray:
    """Region label (0..R-1) per triangle: connected parts over edges (a, b), cut in quarters until
    planar (see :func:`_coplanar_planes`)."""
    label = _connected(len(normals), a, b)
    todo, local, n_local = np.arange(len(normals)), label.copy(), int(label.max()) + 1
    while True:
        planar = _planar(local, n_local, normals[todo], areas[todo], corners[todo], centroids[todo])
        failed = np.flatnonzero(~planar[local])
        if not len(failed):
            return np.unique(label, return_inverse=True)[1].reshape(-1)
        position = np.full(len(todo), -1)
        position[failed] = np.arange(len(failed))
        a, b = position[a], position[b]  # edges as positions in the failed triangles
        a, b = a[(a >= 0) & (b >= 0)], b[(a >= 0) & (b >= 0)]
        todo, local = todo[failed], local[failed]
        part = _quarters(local, n_local, centroids[todo])
        a, b = a[part[a] == part[b]], b[part[a] == part[b]]
        local = _connected(len(todo), a, b)
        n_local = int(local.max()) + 1
        label[todo] = label.max() + 1 + local


def _quarters(label: np.ndarray, n_labels: int, points: np.ndarray) -> np.ndarray:
    """Part 4·label + 0…3 of each point (m, 3): below or above its label's mean along the label's
    two axes of largest spread, so that every label of two or more points is cut into two to four
    non-empty parts (by position parity where the first cut would leave one side empty)."""
    count = np.maximum(np.bincount(label, minlength=n_labels), 1)
    mean = np.column_stack([np.bincount(label, weights=points[:, k], minlength=n_labels) for k in range(3)]) / count[:, None]
    spread = np.column_stack([np.bincount(label, weights=(points[:, k] - mean[label, k]) ** 2, minlength=n_labels)
                              for k in range(3)])
    axes = np.argsort(spread, axis=1)[label]
    part = 4 * label
    for rank, weight in ((-1, 2), (-2, 1)):
        axis = axes[:, rank]
        side = (points[np.arange(len(points)), axis] > mean[label, axis]).astype(np.int64)
        one_sided = np.bincount(label, weights=side, minlength=n_labels) % count == 0
        fallback = np.arange(len(points)) % 2 if rank == -1 else 0
        part += weight * np.where(one_sided[label], fallback, side)
    return part


def _merge_coplanar(plane, group, normals, areas, corners, centroids) -> np.ndarray:
    """Merge planes of one group that agree (:func:`_same_plane` on their area-weighted planes) and
    whose union is a plane; candidates are the first plane of each neighbouring cell of a grid over
    (normal, offset) with cells of the tolerances' size."""
    n_regions = int(plane.max()) + 1
    normal, centre = _area_weighted_planes(plane, n_regions, normals, areas, centroids)
    region_group = np.zeros(n_regions, dtype=np.int64)
    region_group[plane] = group
    group_rank = np.unique(region_group, return_inverse=True)[1].reshape(-1)
    offset = np.einsum("rj,rj->r", normal, centre)
    chord = 2.0 * math.sin(math.radians(COPLANAR_ANGLE_DEG) / 2.0)
    d_cell = max(COPLANAR_OFFSET_M, float(np.ptp(offset)) * (4.0 / chord) ** 3 * (group_rank.max() + 1) / 2.0**58)
    cell = np.floor(np.column_stack([normal / chord, offset / d_cell])).astype(np.int64)
    cell -= cell.min(axis=0) - 1  # ≥ 1, so that every neighbour cell has a non-negative index
    stride = np.cumprod(np.r_[1, cell.max(axis=0)[::-1][:-1] + 2])[::-1]
    code = group_rank * int(np.prod(cell.max(axis=0) + 2)) + cell @ stride
    order = np.argsort(code, kind="stable")
    sorted_code = code[order]
    pairs = []
    for step in itertools.product((-1, 0, 1), repeat=4):
        target = code + np.asarray(step) @ stride
        at = np.minimum(np.searchsorted(sorted_code, target), n_regions - 1)
        found = np.flatnonzero(sorted_code[at] == target)
        pairs.append(np.stack([found, order[at[found]]]))
    a, b = np.concatenate(pairs, axis=1)
    link = (a != b) & _same_plane(normal[a], centre[a], normal[b], centre[b])
    merged = _connected(n_regions, a[link], b[link])
    n_merged = int(merged.max()) + 1
    accepted = _planar(merged[plane], n_merged, normals, areas, corners, centroids)
    return np.where(accepted[merged[plane]], merged[plane], n_merged + plane)


def _first_appearance_order(plane: np.ndarray) -> np.ndarray:
    """Renumber plane labels 0..P-1 in the order of their first triangle (file order)."""
    _, first, inverse = np.unique(plane, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int32)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first), dtype=np.int32)
    return rank[inverse.reshape(-1)]


def _plane_infos(vertices, triangles, plane_of, classes) -> tuple[list[PlaneInfo], np.ndarray]:
    """PlaneInfo per plane (area-weighted normal and centroid, class covering most area)."""
    normals, areas, corners = _triangle_geometry(vertices, triangles)
    n_planes = int(plane_of.max()) + 1
    normal_sum = np.zeros((n_planes, 3))
    centroid_sum = np.zeros((n_planes, 3))
    np.add.at(normal_sum, plane_of, normals * areas[:, None])
    np.add.at(centroid_sum, plane_of, corners.mean(axis=1) * areas[:, None])
    area_sum = np.bincount(plane_of, weights=areas, minlength=n_planes)
    plane_classes = _majority(plane_of, classes.astype(np.int64), areas, n_planes).astype(np.uint8)
    largest = _majority(plane_of, np.arange(len(areas)), areas, n_planes)
    planes = []
    for k in range(n_planes):
        normal = normal_sum[k]
        if np.linalg.norm(normal) < 1e-9 * area_sum[k]:  # faces of opposite winding cancel
            normal = normals[largest[k]]
        if plane_classes[k] in (CLASS_GROUND, CLASS_ROAD) and normal[2] < 0.0:
            normal = -normal
        unit = normal / np.linalg.norm(normal)
        kind = _kind(int(plane_classes[k]), unit)
        planes.append(plane_info(k, kind, plane_classes[k], unit, centroid_sum[k] / area_sum[k]))
    return planes, plane_classes


def _majority(plane_of: np.ndarray, labels: np.ndarray, weights: np.ndarray, n_planes: int) -> np.ndarray:
    """Per plane, the label (≥ 0) with the largest summed weight (ties: the smallest label)."""
    span = int(labels.max()) + 1
    keys, inverse = np.unique(plane_of.astype(np.int64) * span + labels, return_inverse=True)
    totals = np.bincount(inverse.reshape(-1), weights=weights)
    plane, label = keys // span, keys % span
    order = np.lexsort((label, -totals, plane))
    first = np.r_[True, plane[order[1:]] != plane[order[:-1]]]
    best = np.empty(n_planes, dtype=np.int64)
    best[plane[order[first]]] = label[order[first]]
    return best


def _kind(classification: int, normal: np.ndarray) -> str:
    """Plane kind from its class and orientation: building faces steeper than 80° are walls."""
    if classification != CLASS_BUILDING:
        return _kind_from_class(classification)
    pitch, _ = pitch_azimuth_deg(normal)
    if pitch >= 80.0:
        return "wall"
    return "roof" if normal[2] > 0.0 else "surface"
