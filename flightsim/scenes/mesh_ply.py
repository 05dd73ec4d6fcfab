"""PLY mesh files (ASCII, binary little- and big-endian) into the arrays of
:func:`flightsim.scenes.meshio.load_mesh`'s reader: vertex x, y, z; face vertex_indices (or
vertex_index) lists; per-face ``classification`` and ``plane_id`` where the file has them. Elements after
the last of vertex and face are not read. Lists of one length are read at once, others row by row.
"""
from __future__ import annotations

import numpy as np

from flightsim.scenes.mesh_format import MeshFormatError
from flightsim.scenes.scene import CLASS_UNCLASSIFIED

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply(data: bytes) -> dict:
    """The dict of :func:`flightsim.scenes.meshio._read` for the bytes of a PLY file."""
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
        raise MeshFormatError("not a PLY file (no 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise MeshFormatError("PLY header has no end_header")
    newline = data.find(b"\n", end)
    if newline < 0:
        raise MeshFormatError("PLY header is not terminated by a newline")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    header = {"format": None, "elements": []}
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise MeshFormatError(f"unknown PLY format {line.strip()!r}")
            header["format"] = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise MeshFormatError(f"bad PLY element line {line.strip()!r}")
            header["elements"].append({"name": parts[1], "count": int(parts[2]), "properties": []})
        elif parts[0] == "property":
            if not header["elements"]:
                raise MeshFormatError("PLY property before any element")
            header["elements"][-1]["properties"].append(_ply_property(parts, line))
        else:
            raise MeshFormatError(f"unknown PLY header line {line.strip()!r}")
    if header["format"] is None:
        raise MeshFormatError("PLY header has no format line")
    return header, data[newline + 1:]


def _ply_property(parts: list[str], line: str) -> dict:
    if len(parts) == 3 and parts[1] in _PLY_TYPES:
        return {"name": parts[2], "type": _PLY_TYPES[parts[1]], "list": None}
    if len(parts) == 5 and parts[1] == "list" and parts[2] in _PLY_TYPES and parts[3] in _PLY_TYPES:
        return {"name": parts[4], "type": _PLY_TYPES[parts[3]], "list": _PLY_TYPES[parts[2]]}
    raise MeshFormatError(f"bad PLY property line {line.strip()!r}")


def _ply_ascii_element(element: dict, tokens: list[str], cursor: int) -> tuple[dict, int]:
    """Parse ``count`` rows of an element from whitespace-separated tokens."""
    props, count = element["properties"], element["count"]
    if all(p["list"] is None for p in props):
        n = count * len(props)
        if cursor + n > len(tokens):
            raise MeshFormatError(f"PLY element {element['name']!r} is truncated")
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
                    raise MeshFormatError(f"PLY element {element['name']!r} is truncated")
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
        raise MeshFormatError(f"PLY element {element['name']!r} is truncated")
    return tokens[cursor]


def _ply_binary_element(element: dict, body: bytes, cursor: int, order: str) -> tuple[dict, int]:
    """Parse ``count`` rows of a binary element starting at byte ``cursor``."""
    props, count = element["properties"], element["count"]
    truncated = MeshFormatError(f"PLY element {element['name']!r} is truncated")
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
        raise MeshFormatError("PLY file has no vertex element with x, y, z")
    if face is None:
        raise MeshFormatError("PLY file has no face element")
    key = "vertex_indices" if "vertex_indices" in face else "vertex_index" if "vertex_index" in face else None
    if key is None:
        raise MeshFormatError("PLY face element has no vertex_indices list")
    faces = face[key]
    if isinstance(faces, np.ndarray):
        corners, sizes = faces.reshape(-1), np.full(len(faces), faces.shape[1])
    else:
        sizes = np.array([len(f) for f in faces], dtype=np.int64)
        corners = np.concatenate([np.asarray(f, dtype=np.int64) for f in faces] + [np.zeros(0, np.int64)])
    if len(sizes) and sizes.min() < 3:
        raise MeshFormatError("a PLY face has fewer than 3 vertices")
    n = len(sizes)
    coords = np.column_stack([np.asarray(vertex[a], dtype=np.float64) for a in "xyz"])
    classification = _ply_int_column(face, "classification", n, CLASS_UNCLASSIFIED)
    given = "plane_id" in face
    group = _ply_int_column(face, "plane_id", n, 0) if given else classification
    if np.any((classification < 0) | (classification > 255)):
        raise MeshFormatError("a face classification is outside 0..255")
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
        raise MeshFormatError(f"PLY face property {name} must be one integer per face")
    return column.astype(np.int64)
