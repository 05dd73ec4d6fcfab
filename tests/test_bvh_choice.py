"""The automatic BVH (run.bvh = auto): the measured fastest constructor and leaf size per device kind, and any
constructor or leaf size giving the same hits."""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from flightsim.engine.meshes import GPU_LEAF_SIZE, bvh_choice
from flightsim.scenes.lunar import lunar_scene
from kernels.trace import cast_rays


def test_auto_is_sah_with_warps_leaves_on_a_cpu_and_cubql_with_small_leaves_on_a_gpu():
    assert bvh_choice("auto", 0, cpu=True) == ("sah", None)
    assert bvh_choice("auto", None, cpu=False) == ("cubql", GPU_LEAF_SIZE) == ("cubql", 2)
    assert bvh_choice("auto", 8, cpu=False) == ("cubql", 8)  # a leaf size given is kept
    assert bvh_choice("lbvh", 0, cpu=False) == ("lbvh", None)  # a constructor given: Warp's leaf size
    assert bvh_choice("median", 1, cpu=True) == ("median", 1)


@pytest.mark.parametrize("constructor,leaf", [("cubql", 2), ("cubql", 1), ("sah", 1), ("sah", 2)])
def test_every_bvh_casts_the_same_faces(constructor, leaf):
    scene = lunar_scene(20.0)
    rng = np.random.default_rng(5)
    n = 20000
    angles = rng.uniform(-0.3, 0.3, (n, 2))
    directions = np.column_stack([np.tan(angles), -np.ones(n)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = np.column_stack([rng.uniform(-3.0, 3.0, (n, 2)), np.full(n, 30.0)])
    s = wp.array(starts.astype(np.float32), dtype=wp.vec3f, device="cpu")
    d = wp.array(directions.astype(np.float32), dtype=wp.vec3f, device="cpu")
    points = wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3f, device="cpu")
    indices = wp.array(scene.triangles.astype(np.int32).ravel(), dtype=wp.int32, device="cpu")
    faces = {}
    for key in ((constructor, leaf), ("sah", None)):
        mesh = wp.Mesh(points=points, indices=indices, bvh_constructor=key[0], bvh_leaf_size=key[1])
        out = wp.empty(n, dtype=wp.int32, device="cpu")
        wp.launch(cast_rays, n, inputs=[mesh.id, s, d, 1000.0], outputs=[out], device="cpu")
        faces[key] = out.numpy()
    assert (faces[("sah", None)] >= 0).all()
    assert np.array_equal(faces[(constructor, leaf)], faces[("sah", None)])
