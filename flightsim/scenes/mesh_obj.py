"""OBJ mesh files: ``v``/``f``/``g``/``o`` records (others are skipped) into the arrays of
:func:`flightsim.scenes.meshio.load_mesh`'s reader.

The text is read with array operations over the whole file; a file with anything unusual (and every
file with an error, so that the message names the line) is read line by line.
"""
from __future__ import annotations

import warnings

import numpy as np

from flightsim.scenes.mesh_format import MeshFormatError, class_from_name


def read_obj(data: bytes) -> dict:
    """The dict of :func:`flightsim.scenes.meshio._read` for the bytes of an OBJ file: ``v``/``f``/``g``/``o``
    records (others are skipped), vectorised when every record is plain ASCII numbers, else (and for every
    error, so that its message names the line) line by line."""
    if b"\x00" in data:
        raise MeshFormatError("binary data in an OBJ file")
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
                raise MeshFormatError(f"line {number}: a vertex needs x y z")
            try:
                vertices.append((float(args[0]), float(args[1]), float(args[2])))
            except ValueError:
                raise MeshFormatError(f"line {number}: bad vertex {line.strip()!r}") from None
        elif keyword == "f":
            faces.append(_obj_face(args, len(vertices), number))
            face_group.append(current)
        elif keyword in ("g", "o"):
            current = groups.setdefault(" ".join(args), len(groups))
    if not faces:
        raise MeshFormatError("no faces")
    return _obj_mesh(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), np.concatenate(faces),
                     np.array([len(f) for f in faces]), np.asarray(face_group, dtype=np.int64), list(groups))


def _obj_mesh(vertices: np.ndarray, corners: np.ndarray, sizes: np.ndarray, group: np.ndarray,
              names: list[str]) -> dict:
    """The dict of :func:`flightsim.scenes.meshio._read` for an OBJ file: ``names`` are the groups in order of
    first use (id = index)."""
    group_class = np.array([class_from_name(n) for n in names], dtype=np.uint8)
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
        raise MeshFormatError(f"line {number}: a face needs at least 3 vertices")
    index = []
    for token in args:
        head = token.split("/", 1)[0]
        try:
            k = int(head)
        except ValueError:
            raise MeshFormatError(f"line {number}: bad face vertex {token!r}") from None
        if k == 0:
            raise MeshFormatError(f"line {number}: vertex index 0 (OBJ indices start at 1)")
        index.append(k - 1 if k > 0 else n_vertices + k)
        if not 0 <= index[-1] < n_vertices:
            raise MeshFormatError(f"line {number}: vertex index {k} out of range for {n_vertices} vertices")
    return np.asarray(index, dtype=np.int64)
