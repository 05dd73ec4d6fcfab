"""Point-to-truth distances against a scene's mesh, on the device (kernels/distance.py)."""
from __future__ import annotations

import numpy as np
import warp as wp

from kernels.distance import surface_distance


def signed_distances(scene, points_local: np.ndarray, device: str = "cpu", max_distance: float = 1.0e4) -> np.ndarray:
    """Signed distance [m] of each local point (n, 3) to the scene's surface (positive on the side the
    faces' normals point to, up for ground); NaN beyond ``max_distance``."""
    mesh = wp.Mesh(points=wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3f, device=device),
                   indices=wp.array(scene.triangles.ravel().astype(np.int32), dtype=wp.int32, device=device))
    points = wp.array(np.ascontiguousarray(points_local, dtype=np.float32), dtype=wp.vec3f, device=device)
    out = wp.empty(len(points_local), dtype=wp.float32, device=device)
    wp.launch(surface_distance, len(points_local), inputs=[mesh.id, points, float(max_distance)], outputs=[out],
              device=device)
    return out.numpy().astype(np.float64)
