"""Read triangle meshes (OBJ, PLY) into a :class:`~flightsim.scenes.scene.Scene`, and write OBJ.

File coordinates + the user's ``origin`` are world coordinates in the user's CRS. The scene's
own origin is the centre of the world bounding box rounded to whole metres, so that local
coordinates stay small even when the file holds absolute UTM values.

Plane labels come from the file where it has them (PLY per-face ``plane_id`` and
``classification``; OBJ groups ``o``/``g``, whose names give the class: "ground" → 2,
"road" → 11, "roof"/"wall"/"building" → 6, else 1). A PLY ``plane_id`` is taken as it is.
Otherwise faces are grouped into planes by edge connectivity and coplanarity (normal angle
≤ 1°, offset ≤ 0.05 m) without crossing a group (an OBJ group, or a PLY classification): an
OBJ group is split into its planar parts (a group holding a whole house becomes one plane per
face) and its coplanar parts that do not touch are merged again (a ground cut by roads stays
one plane); an unlabelled mesh is split by connectivity and geometry alone.

Every problem with the file raises ``InputError("scene.path", path, ...)`` saying what was wrong.
"""
from __future__ import annotations

import math
from collections import deque
from pathlib import Path

import numpy as np

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


def load_mesh(path, crs, origin=(0.0, 0.0, 0.0), name: str | None = None) -> Scene:
    """Read an OBJ or PLY triangle mesh into a Scene.

    Args:
        path: the .obj or .ply file.
        crs: the CRS of the world coordinates (anything :func:`flightsim.scenes.scene.parse_crs` takes).
        origin: (3,) world E, N, H [m] added to the file coordinates.
        name: scene name; the file stem by default.

    Returns:
        A Scene with origin = world bounding-box centre rounded to whole metres, zero-area
        triangles dropped (counted in ``dropped_degenerate``) and ground_z = the lowest vertex
        height of the ground (class 2) triangles, or of all triangles when none is ground.
    """
    crs = parse_crs(crs, "scene.crs")
    try:
        offset = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]") from None
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]")
    path = Path(path)
    try:
        raw = _read(path)
        coords, faces = raw["vertices"], raw["faces"]
        _check_mesh(coords, faces)
    except _MeshFormatError as error:
        raise InputError("scene.path", str(path), f"a readable OBJ or PLY triangle mesh ({error})") from None

    world = coords + offset
    scene_origin = np.round(0.5 * (world.min(axis=0) + world.max(axis=0)))
    local = world - scene_origin
    triangles, source = _triangulate(faces)
    keep = ~_degenerate(local, triangles)
    if not np.any(keep):
        raise InputError("scene.path", str(path), "a readable OBJ or PLY triangle mesh (every face has zero area)")
    triangles, source = triangles[keep], source[keep]
    group = raw["group"][source]
    classes = raw["classification"][source]
    if raw["labels"] == "planes":
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

    Returns a dict: vertices (V, 3) float64; faces, an (F, k) array or a list of index arrays;
    per-face group (int) and classification (uint8); labels: "planes" (groups are plane ids),
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


def _check_mesh(coords: np.ndarray, faces) -> None:
    """Reject meshes without faces, with non-finite coordinates or out-of-range indices."""
    if len(faces) == 0:
        raise _MeshFormatError("no faces")
    if not np.all(np.isfinite(coords)):
        row = int(np.argwhere(~np.isfinite(coords))[0, 0])
        raise _MeshFormatError(f"vertex {row} has a non-finite coordinate")
    flat = faces.reshape(-1) if isinstance(faces, np.ndarray) else np.concatenate(faces)
    if flat.min() < 0 or flat.max() >= len(coords):
        bad = int(flat[(flat < 0) | (flat >= len(coords))][0])
        raise _MeshFormatError(f"vertex index {bad} out of range for {len(coords)} vertices")


def _read_obj(data: bytes) -> dict:
    if b"\x00" in data:
        raise _MeshFormatError("binary data in an OBJ file")
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
    names = sorted(groups, key=groups.get)
    group_class = np.array([_class_from_name(n) for n in names], dtype=np.uint8)
    group = np.asarray(face_group, dtype=np.int64)
    return {
        "vertices": np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
        "faces": faces,
        "group": group,
        "classification": group_class[group],
        "labels": "groups" if len(groups) > 1 or face_group[0] != 0 else "none",
    }


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
        if faces.shape[1] < 3:
            raise _MeshFormatError("a PLY face has fewer than 3 vertices")
    else:
        faces = [np.asarray(f, dtype=np.int64) for f in faces]
        if any(len(f) < 3 for f in faces):
            raise _MeshFormatError("a PLY face has fewer than 3 vertices")
    n = len(faces)
    coords = np.column_stack([np.asarray(vertex[a], dtype=np.float64) for a in "xyz"])
    classification = _ply_int_column(face, "classification", n, CLASS_UNCLASSIFIED)
    given = "plane_id" in face
    group = _ply_int_column(face, "plane_id", n, 0) if given else classification
    if np.any((classification < 0) | (classification > 255)):
        raise _MeshFormatError("a face classification is outside 0..255")
    return {
        "vertices": coords,
        "faces": faces,
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

def _triangulate(faces) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons, given as an (F, k) array or a list of index arrays.

    Returns (T, 3) vertex indices and the source face of each triangle.
    """
    if isinstance(faces, np.ndarray):
        k = faces.shape[1]
        triangles = np.concatenate([faces[:, [0, j, j + 1]] for j in range(1, k - 1)])
        return triangles.astype(np.int64), np.tile(np.arange(len(faces)), k - 2)
    triangles, source = [], []
    for k, f in enumerate(faces):
        for j in range(1, len(f) - 1):
            triangles.append((f[0], f[j], f[j + 1]))
            source.append(k)
    return np.asarray(triangles, dtype=np.int64), np.asarray(source, dtype=np.int64)


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
    """Plane id per triangle: region growing over shared edges within each group.

    Vertices at the same position are welded first, so a triangle soup groups like a mesh. A
    region starts at its largest remaining triangle; a neighbour joins when its normal is within
    COPLANAR_ANGLE_DEG of the region's area-weighted normal and its corners lie within
    COPLANAR_OFFSET_M of the region's plane. With ``merge_apart``, coplanar regions of one group
    that do not touch (a ground split by roads) are then merged into one plane.
    """
    normals, areas, corners = _triangle_geometry(vertices, triangles)
    _, weld = np.unique(np.round(vertices, 6), axis=0, return_inverse=True)
    start, neighbour = _edge_neighbours(weld.reshape(-1)[triangles])
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    # plain Python numbers: this loop visits every triangle, numpy calls on 3-vectors are slow
    start, neighbour, group_of = start.tolist(), neighbour.tolist(), group.tolist()
    normal_of, area_of = normals.tolist(), areas.tolist()
    corners_of = corners.reshape(-1, 9).tolist()
    plane = [-1] * len(triangles)
    n_planes = 0
    for seed in np.argsort(-areas, kind="stable").tolist():
        if plane[seed] >= 0:
            continue
        plane[seed] = n_planes
        w = area_of[seed]
        sx, sy, sz = (w * c for c in normal_of[seed])
        cs = corners_of[seed]
        cx, cy, cz = (w * (cs[k] + cs[k + 3] + cs[k + 6]) / 3.0 for k in range(3))
        area_sum = w
        queue = deque([seed])
        while queue:
            t = queue.popleft()
            for u in neighbour[start[t]:start[t + 1]]:
                if plane[u] >= 0 or group_of[u] != group_of[seed]:
                    continue
                length = math.sqrt(sx * sx + sy * sy + sz * sz)
                nx, ny, nz = sx / length, sy / length, sz / length
                un = normal_of[u]
                if un[0] * nx + un[1] * ny + un[2] * nz < cos_limit:
                    continue
                c = corners_of[u]
                px, py, pz = cx / area_sum, cy / area_sum, cz / area_sum
                offset = max(abs((c[k] - px) * nx + (c[k + 1] - py) * ny + (c[k + 2] - pz) * nz) for k in (0, 3, 6))
                if offset > COPLANAR_OFFSET_M:
                    continue
                plane[u] = n_planes
                w = area_of[u]
                sx, sy, sz = sx + w * un[0], sy + w * un[1], sz + w * un[2]
                cx += w * (c[0] + c[3] + c[6]) / 3.0
                cy += w * (c[1] + c[4] + c[7]) / 3.0
                cz += w * (c[2] + c[5] + c[8]) / 3.0
                area_sum += w
                queue.append(u)
        n_planes += 1
    plane = np.asarray(plane, dtype=np.int32)
    if merge_apart:
        plane = _merge_coplanar(plane, group, normals, areas, corners)
    return _first_appearance_order(plane)


def _merge_coplanar(plane, group, normals, areas, corners) -> np.ndarray:
    """Merge regions of one group whose planes agree (normal angle, offset of each centroid)."""
    n_regions = int(plane.max()) + 1
    area = np.bincount(plane, weights=areas, minlength=n_regions)
    normal = np.zeros((n_regions, 3))
    centroid = np.zeros((n_regions, 3))
    np.add.at(normal, plane, normals * areas[:, None])
    np.add.at(centroid, plane, corners.mean(axis=1) * areas[:, None])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    centroid /= area[:, None]
    region_group = np.zeros(n_regions, dtype=np.int64)
    region_group[plane] = group
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    target = np.arange(n_regions)
    for r in range(n_regions):
        if target[r] != r:
            continue
        rest = np.arange(r + 1, n_regions)
        rest = rest[(target[rest] == rest) & (region_group[rest] == region_group[r])]
        same = (
            (normal[rest] @ normal[r] >= cos_limit)
            & (np.abs((centroid[rest] - centroid[r]) @ normal[r]) <= COPLANAR_OFFSET_M)
            & (np.abs(np.sum((centroid[r] - centroid[rest]) * normal[rest], axis=1)) <= COPLANAR_OFFSET_M)
        )
        target[rest[same]] = r
    return target[plane].astype(np.int32)


def _first_appearance_order(plane: np.ndarray) -> np.ndarray:
    """Renumber plane labels 0..P-1 in the order of their first triangle (file order)."""
    _, first, inverse = np.unique(plane, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int32)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first), dtype=np.int32)
    return rank[inverse.reshape(-1)]


def _edge_neighbours(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles sharing an (undirected) edge, as CSR: neighbours of t are index[start[t]:start[t+1]]."""
    n = len(triangles)
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(n), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    new_edge = np.r_[True, np.any(edges[1:] != edges[:-1], axis=1)]
    starts = np.flatnonzero(new_edge)
    sizes = np.diff(np.r_[starts, len(edges)])
    pairs = [owner[starts[sizes == 2]], owner[starts[sizes == 2] + 1]]
    for s, size in zip(starts[sizes > 2], sizes[sizes > 2]):  # non-manifold edges: rare
        shared = owner[s:s + size]
        a, b = np.meshgrid(shared, shared)
        pairs[0] = np.r_[pairs[0], a[a < b]]
        pairs[1] = np.r_[pairs[1], b[a < b]]
    src = np.r_[pairs[0], pairs[1]]
    dst = np.r_[pairs[1], pairs[0]]
    order = np.lexsort((dst, src))
    src, dst = src[order], dst[order]
    start = np.searchsorted(src, np.arange(n + 1))
    return start, dst


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
