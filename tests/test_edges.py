"""Plane boundaries (flightsim.scenes.edges) against a plain-Python count of every edge per plane."""
from collections import Counter

import numpy as np
import pytest

from flightsim.scenes import edges
from flightsim.scenes.edges import boundary_segments
from test_scene_scale import grid_mesh
from flightsim.scenes.scene import DEFAULT_CRS, PlaneInfo, Scene


def split_terrain(seed: int) -> Scene:
    """A rough 9×9-node terrain, its triangles in three planes (by x), every vertex duplicated (the copies
    used by alternate triangles), a few degenerate triangles added."""
    rng = np.random.default_rng(seed)
    vertices, triangles = grid_mesh(rng.normal(0.0, 1.0, (9, 9)), 1.5)
    copies = np.arange(len(triangles)) % 2 == 1
    triangles = np.where(copies[:, None], triangles + len(vertices), triangles)
    vertices = np.concatenate([vertices, vertices])
    triangles = np.concatenate([triangles, [[0, 0, 1], [2, len(vertices) // 2 + 2, 3]]])
    centre_x = vertices[triangles][:, :, 0].mean(axis=1)
    plane_id = np.digitize(centre_x, [4.0, 8.0]).astype(np.int32)
    planes = [PlaneInfo(id=k, kind="ground", classification=2, normal=np.array([0.0, 0.0, 1.0]),
                        point=np.zeros(3), pitch_deg=0.0, azimuth_deg=float("nan")) for k in range(3)]
    return Scene(name="split", crs=DEFAULT_CRS, origin=np.zeros(3), vertices=vertices, triangles=triangles,
                 plane_id=plane_id, classification=np.full(len(triangles), 2, dtype=np.uint8), planes=planes,
                 ground_z=0.0)


def brute_force_boundaries(scene: Scene) -> Counter:
    """How many planes each edge bounds: the (plane, edge) pairs used by exactly one triangle of the plane, edges as sorted pairs of vertex
    positions (rounded to 1 µm), degenerate edges left out."""
    key = [tuple(np.round(v / 1e-6).astype(np.int64)) for v in scene.vertices]
    uses = Counter()
    for triangle, plane in zip(scene.triangles, scene.plane_id):
        for a, b in ((0, 1), (1, 2), (2, 0)):
            ends = tuple(sorted((key[triangle[a]], key[triangle[b]])))
            if ends[0] != ends[1]:
                uses[(int(plane), ends)] += 1
    return Counter(edge for (plane, edge), n in uses.items() if n == 1)


def as_edges(segments: np.ndarray) -> Counter:
    return Counter(tuple(sorted(tuple(np.round(p / 1e-6).astype(np.int64)) for p in s)) for s in segments)


@pytest.mark.parametrize("path", ["packed", "colliding hashes", "rows"])
@pytest.mark.parametrize("seed", [0, 1])
def test_boundary_edges_are_those_one_triangle_of_a_plane_uses(seed, path, monkeypatch):
    """Duplicated vertices make no false boundaries and the planes' shared borders count for both planes;
    so do a hash that puts every row in one bucket (forcing the exact fallback sort) and edge keys too
    wide to pack into an int64 (grouped row by row)."""
    if path == "colliding hashes":
        monkeypatch.setattr(edges, "_HASH_MULTIPLIERS", np.zeros(3, dtype=np.uint64))
    if path == "rows":
        monkeypatch.setattr(edges, "_PACKED_KEYS", 0)
    scene = split_terrain(seed)
    segments = boundary_segments(scene)
    want = brute_force_boundaries(scene)
    assert max(want.values()) == 2  # the inner borders bound two planes
    assert as_edges(segments) == want
    assert np.array_equal(segments, in_triangle_order(scene))


def in_triangle_order(scene: Scene) -> np.ndarray:
    """The bounding edges as the triangles draw them: every triangle's edge 0→1, then 1→2, then 2→0
    (LAS bytes hold distances to them in float32, which depend on each segment's direction)."""
    key = [tuple(np.round(v / 1e-6).astype(np.int64)) for v in scene.vertices]
    records = [(int(plane), tuple(sorted((key[t[a]], key[t[b]]))), (t[a], t[b]))
               for a, b in ((0, 1), (1, 2), (2, 0)) for t, plane in zip(scene.triangles, scene.plane_id)]
    uses = Counter((plane, ends) for plane, ends, _ in records if ends[0] != ends[1])
    return np.array([[scene.vertices[i], scene.vertices[j]] for plane, ends, (i, j) in records
                     if ends[0] != ends[1] and uses[(plane, ends)] == 1])


def test_prefetched_boundaries_are_the_same_and_found_once(monkeypatch):
    """Scene.prefetch_boundary_segments finds them in a thread; Scene.boundary_segments then hands over that
    result (the same segments as a direct call, computed once); an error in the thread is raised there."""
    calls = []
    real = edges.boundary_segments
    monkeypatch.setattr(edges, "boundary_segments", lambda scene: calls.append(1) or real(scene))
    scene = split_terrain(0)
    scene.prefetch_boundary_segments()
    scene.prefetch_boundary_segments()
    assert np.array_equal(scene.boundary_segments(), in_triangle_order(scene))
    assert np.array_equal(scene.boundary_segments(), in_triangle_order(scene))
    assert calls == [1]

    def fail(scene):
        raise MemoryError("no room for the edge keys")

    monkeypatch.setattr(edges, "boundary_segments", fail)
    broken = split_terrain(1)
    broken.prefetch_boundary_segments()
    with pytest.raises(MemoryError, match="edge keys"):
        broken.boundary_segments()
