"""Read triangle meshes (OBJ, PLY) into a :class:`~flightsim.scenes.scene.Scene`, and write OBJ.

File coordinates + the user's ``origin`` are world coordinates in the user's CRS. The scene's
own origin is the centre of the world bounding box rounded to whole metres, so that local
coordinates stay small even when the file holds absolute UTM values.

Plane labels come from the file where it has them (PLY per-face ``plane_id`` and
``classification``; OBJ groups ``o``/``g``, whose names give the class: "ground" → 2,
"road" → 11, "roof"/"wall"/"building" → 6, else 1). A PLY ``plane_id`` is taken as it is.
Otherwise (``planes="auto"``) faces are grouped into planes by edge connectivity and
coplanarity (normal angle ≤ 1°, offset ≤ 0.05 m, every face against its plane's area-weighted
fit; :func:`~flightsim.scenes.mesh_planes.coplanar_planes`) without crossing a group (an OBJ
group, or a PLY classification): an OBJ group is split into its planar parts (a group holding a
whole house becomes one plane per face, a curved terrain many small planes) and its coplanar
parts that do not touch are merged again (a ground cut by roads stays one plane); an unlabelled
mesh is split by connectivity and geometry alone. With ``planes="none"`` (a terrain) the groups
are the labels and nothing is grouped.

The files are parsed by :mod:`.mesh_obj` and :mod:`.mesh_ply`, not by a mesh library. Measured on
the 2-million-triangle grid of ``tests/test_stress_meshes.py`` (best of 3 on the 2-core machine;
trimesh 5.2.0 with ``process=False, maintain_order=True``, meshio 5.3.5):

============================  ===========  ==================  ==============================
file                          this reader  trimesh             meshio
============================  ===========  ==================  ==============================
binary PLY (60 MB)            0.08 s       0.014 s (0.2x)      fails (a per-face property
                                                               after the list)
OBJ, two groups (64 MB)       1.71 s       1.57 s (0.9x)       3.98 s (2.3x)
ASCII PLY (70 MB)             1.59 s       4.33 s (2.7x)       7.53 s (4.7x)
============================  ===========  ==================  ==============================

Neither gives the same arrays for every file the tests read: trimesh loses the OBJ groups (or,
with ``split_groups``, re-indexes the vertices per group and joins a group's separate runs of
faces, so the faces are no longer in file order) and fans a quad as (0 1 2)(2 3 0) rather than
(0 1 2)(0 2 3); meshio drops the order of faces of mixed sizes (one block per size), keeps
negative (relative) OBJ indices as they are, and takes out-of-range indices and truncated PLY
bodies without a word. Neither names the file line of an error. Both would also be slower on
ASCII PLY than the limit of 1.2x, so the hand-written parser stays.

Every problem with the file raises ``InputError("scene.path", path, ...)`` saying what was wrong.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.mesh_format import MeshFormatError, class_from_name, kind_from_class
from flightsim.scenes.mesh_obj import read_obj
from flightsim.scenes.mesh_planes import coplanar_planes, degenerate, plane_infos, renumber, triangulate
from flightsim.scenes.mesh_ply import read_ply
from flightsim.scenes.scene import CLASS_BUILDING, CLASS_GROUND, PlaneInfo, Scene, parse_crs


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
    offset = _world_offset(origin)
    path = Path(path)
    try:
        raw = _read(path)
        coords = raw["vertices"]
        _check_mesh(coords, raw["corners"], raw["sizes"])
    except MeshFormatError as error:
        raise InputError("scene.path", str(path), f"a readable OBJ or PLY triangle mesh ({error})") from None

    world = coords + offset
    scene_origin = np.round(0.5 * (world.min(axis=0) + world.max(axis=0)))
    local = world - scene_origin
    triangles, source = triangulate(raw["corners"], raw["sizes"])
    keep = ~degenerate(local, triangles)
    if not np.any(keep):
        raise InputError("scene.path", str(path), "a readable OBJ or PLY triangle mesh (every face has zero area)")
    triangles, source = triangles[keep], source[keep]
    plane_of, classes = _plane_labels(raw, source, local, triangles, grouped)
    planes, plane_classes = plane_infos(local, triangles, plane_of, classes)
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



def _world_offset(origin) -> np.ndarray:
    """``origin`` as (3,) float64 world E, N, H [m]; InputError unless three finite numbers."""
    try:
        offset = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]") from None
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise InputError("scene.origin", origin, "three finite numbers (E, N, H) [m]")
    return offset


def _plane_labels(raw: dict, source: np.ndarray, local: np.ndarray, triangles: np.ndarray,
                  grouped: bool) -> tuple[np.ndarray, np.ndarray]:
    """Plane id (0..P-1) and file class of each triangle (``source``: its face in ``raw``, the
    :func:`_read` dict): the file's labels as they are, or its groups split into planes."""
    group = raw["group"][source]
    classes = raw["classification"][source]
    if raw["labels"] == "planes" or not grouped:
        return renumber(group), classes
    return coplanar_planes(local, triangles, group, merge_apart=raw["labels"] == "groups"), classes


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
    if plane.kind != "surface" and class_from_name(plane.kind) == plane.classification:
        return plane.kind
    return "building" if plane.classification == CLASS_BUILDING else kind_from_class(plane.classification)


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
        raise MeshFormatError(f"unknown extension {path.suffix!r}; expected .obj or .ply")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MeshFormatError("file not found") from None
    except OSError as error:
        raise MeshFormatError(f"cannot read the file: {error.strerror or error}") from None
    try:
        return read_obj(data) if suffix == ".obj" else read_ply(data)
    except MeshFormatError:
        raise
    except (ValueError, LookupError, OverflowError, TypeError, UnicodeDecodeError) as error:
        raise MeshFormatError(f"corrupt or truncated file: {error}") from None


def _check_mesh(coords: np.ndarray, flat: np.ndarray, sizes: np.ndarray) -> None:
    """Reject meshes without faces, with non-finite coordinates or out-of-range indices."""
    if len(sizes) == 0:
        raise MeshFormatError("no faces")
    if not np.all(np.isfinite(coords)):
        row = int(np.argwhere(~np.isfinite(coords))[0, 0])
        raise MeshFormatError(f"vertex {row} has a non-finite coordinate")
    if flat.min() < 0 or flat.max() >= len(coords):
        bad = int(flat[(flat < 0) | (flat >= len(coords))][0])
        raise MeshFormatError(f"vertex index {bad} out of range for {len(coords)} vertices")
