"""A stand as triangles: the ground under it, the trees' stems and, for discrete-return tests, opaque crowns.

Every tree's parts are one template (a unit shape, wound counter-clockwise seen from outside) scaled and moved
into place, so a stand of any size is built without a loop over trees. Each part is a closed polyhedron
inscribed in the analytic shape of :mod:`flightsim.scenes.forest` (its vertices lie on the surface, the tree top
is a vertex), with ``segments`` sides around:

- stem: a prism from below the ground (the lowest ground under the stem, less STEM_BURIAL_M, so no slope leaves a
  gap) to the crown base, diameter the tree's DBH, a lid on top (its buried bottom is left open);
- crown: a cone with its base disc, a cylinder with both discs, or an ellipsoid of ``segments`` // 2 − 1 rings
  of latitude between its two poles.

Labels: ``part`` 0 is the ground, 1 + i the stem of tree i, 1 + n + i its crown (n trees), so a return's plane id
names the tree it hit. ASPRS classes: 2 ground; 5 high vegetation for stems and crowns alike (the LAS
specification has no class for stems; classified ALS products put a tree's stem with its crown, and the part
ids tell them apart).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.scenes.forest import Trees

CLASS_GROUND = 2
CLASS_STEM = 5
CLASS_CROWN = 5
STEM_BURIAL_M = 0.1


@dataclass(frozen=True)
class StandMesh:
    """Triangles in the local frame: vertices (V, 3) float64 [m], triangles (T, 3) int32 (counter-clockwise
    seen from outside), classification (T,) uint8 ASPRS class, part (T,) int32 (see the module docstring)."""

    vertices: np.ndarray
    triangles: np.ndarray
    classification: np.ndarray
    part: np.ndarray


def _ring(segments: int) -> np.ndarray:
    """(segments, 2) unit circle points, counter-clockwise seen from above."""
    angle = 2.0 * math.pi * np.arange(segments) / segments
    return np.column_stack([np.cos(angle), np.sin(angle)])


def _band(lower: int, upper: int, segments: int) -> list[tuple[int, int, int]]:
    """Two triangles per side between the ring starting at vertex ``lower`` and the ring above at ``upper``."""
    out = []
    for k in range(segments):
        a, b = lower + k, lower + (k + 1) % segments
        c, d = upper + (k + 1) % segments, upper + k
        out += [(a, b, c), (a, c, d)]
    return out


def _lid(first: int, segments: int, up: bool) -> list[tuple[int, int, int]]:
    """A fan closing the ring starting at vertex ``first``, facing up or down."""
    return [(first, first + k, first + k + 1) if up else (first, first + k + 1, first + k)
            for k in range(1, segments - 1)]


def prism_template(segments: int, bottom: bool) -> tuple[np.ndarray, np.ndarray]:
    """Unit prism (radius 1, z from 0 to 1): vertices and triangles, the top lid always, the bottom one if asked."""
    ring = _ring(segments)
    vertices = np.vstack([np.column_stack([ring, np.zeros(segments)]), np.column_stack([ring, np.ones(segments)])])
    triangles = _band(0, segments, segments) + _lid(segments, segments, up=True)
    triangles += _lid(0, segments, up=False) if bottom else []
    return vertices, np.array(triangles)


def cone_template(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit cone: base disc of radius 1 at z = 0, apex at (0, 0, 1)."""
    ring = _ring(segments)
    vertices = np.vstack([np.column_stack([ring, np.zeros(segments)]), [[0.0, 0.0, 1.0]]])
    sides = [(k, (k + 1) % segments, segments) for k in range(segments)]
    return vertices, np.array(sides + _lid(0, segments, up=False))


def ellipsoid_template(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit spheroid: radius 1 at z = 0.5, poles at z = 1 (last but one vertex) and z = 0 (last)."""
    rings = max(segments // 2 - 1, 1)
    polar = math.pi * np.arange(1, rings + 1) / (rings + 1)  # from the top pole down
    ring = _ring(segments)
    vertices = [np.column_stack([np.sin(p) * ring, np.full(segments, 0.5 + 0.5 * math.cos(p))]) for p in polar]
    vertices = np.vstack(vertices + [[[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]])
    top, bottom = rings * segments, rings * segments + 1
    triangles = [(top, k, (k + 1) % segments) for k in range(segments)]
    for j in range(rings - 1):
        triangles += _band((j + 1) * segments, j * segments, segments)
    last = (rings - 1) * segments
    triangles += [(bottom, last + (k + 1) % segments, last + k) for k in range(segments)]
    return vertices, np.array(triangles)


def crown_template(shape: str, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit crown of ``shape`` (radius 1, z from 0 to 1)."""
    if shape == "cone":
        return cone_template(segments)
    if shape == "ellipsoid":
        return ellipsoid_template(segments)
    return prism_template(segments, bottom=True)


def _instances(template: tuple[np.ndarray, np.ndarray], scale: np.ndarray, offset: np.ndarray):
    """The template scaled by ``scale`` (n, 3) and moved by ``offset`` (n, 3): vertices (n·V, 3), triangles."""
    vertices, triangles = template
    placed = vertices[None, :, :] * scale[:, None, :] + offset[:, None, :]
    shifted = triangles[None, :, :] + (len(vertices) * np.arange(len(scale)))[:, None, None]
    return placed.reshape(-1, 3), shifted.reshape(-1, 3)


def stand_mesh(trees: Trees, segments: int = 12, crowns: bool = False, ground=None) -> StandMesh:
    """The stems of ``trees`` (and their crowns if ``crowns``) as triangles; ``ground`` (with ``lowest(x, y,
    radius)``, e.g. :class:`~flightsim.scenes.forest.PlaneGround`) sinks each stem's foot below the ground
    (default: the tree's ground height)."""
    n = len(trees)
    foot = trees.base_z if ground is None else ground.lowest(trees.x, trees.y, trees.dbh / 2.0)
    foot = foot - STEM_BURIAL_M
    radius = trees.dbh / 2.0
    stem_top = trees.base_z + trees.crown_base
    vertices, triangles = _instances(prism_template(segments, bottom=False),
                                     np.column_stack([radius, radius, stem_top - foot]),
                                     np.column_stack([trees.x, trees.y, foot]))
    part = np.repeat(1 + np.arange(n), len(triangles) // max(n, 1))
    classes = np.full(len(triangles), CLASS_STEM)
    mesh = StandMesh(vertices, triangles.astype(np.int32), classes.astype(np.uint8), part.astype(np.int32))
    if crowns:
        r = trees.crown_radius
        v, t = _instances(crown_template(trees.shape, segments), np.column_stack([r, r, trees.crown_length]),
                          np.column_stack([trees.x, trees.y, trees.crown_bottom_z()]))
        part = np.repeat(1 + n + np.arange(n), len(t) // max(n, 1))
        mesh = join(mesh, StandMesh(v, t.astype(np.int32), np.full(len(t), CLASS_CROWN, np.uint8),
                                    part.astype(np.int32)))
    return mesh


def ground_mesh(ground, half_m: float) -> StandMesh:
    """The square of half side ``half_m`` [m] centred on the local origin on ``ground`` (its ``height(x, y)`` at
    the four corners: exact for a plane), part 0, class 2."""
    xy = np.array([[-half_m, -half_m], [half_m, -half_m], [half_m, half_m], [-half_m, half_m]])
    vertices = np.column_stack([xy, ground.height(xy[:, 0], xy[:, 1])])
    return StandMesh(vertices, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32),
                     np.full(2, CLASS_GROUND, dtype=np.uint8), np.zeros(2, dtype=np.int32))


def join(*meshes: StandMesh) -> StandMesh:
    """One mesh of several (vertex indices shifted)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return StandMesh(np.vstack([m.vertices for m in meshes]),
                     np.vstack([m.triangles + o for m, o in zip(meshes, offsets)]).astype(np.int32),
                     np.concatenate([m.classification for m in meshes]).astype(np.uint8),
                     np.concatenate([m.part for m in meshes]).astype(np.int32))
