"""kernels.mesh_cast.closest_hit: the face and t of Warp's own mesh query bit for bit (the same traversal and
triangle test, the test's per-ray work hoisted), over rays that take every path of it: slanted and axis-parallel
directions (Warp's robust box test), rays through shared edges and vertices (ties between triangles), rays that end
before the surface, point away from it or miss the mesh; and t against the float64 closed form of a plane."""
import numpy as np
import pytest
import warp as wp

from kernels.mesh_cast import closest_hit


@wp.kernel(enable_backward=False)
def _both(mesh: wp.uint64, starts: wp.array(dtype=wp.vec3f), directions: wp.array(dtype=wp.vec3f),
          max_t: wp.array(dtype=wp.float32), faces: wp.array2d(dtype=wp.int32), ts: wp.array2d(dtype=wp.float32)):
    i = wp.tid()
    face, t = closest_hit(mesh, starts[i], directions[i], max_t[i])
    faces[i, 0] = face
    ts[i, 0] = t
    hit = wp.mesh_query_ray(mesh, starts[i], directions[i], max_t[i])
    faces[i, 1] = wp.where(hit.result, hit.face, -1)
    ts[i, 1] = wp.where(hit.result, hit.t, max_t[i])


def _terrain(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """An n × n grid of unit cells with random heights (two triangles a cell)."""
    x, y = np.meshgrid(np.arange(n + 1, dtype=np.float64), np.arange(n + 1, dtype=np.float64), indexing="ij")
    z = rng.normal(0.0, 0.3, x.shape)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    triangles = np.concatenate([np.column_stack([k, k + n + 1, k + 1]), np.column_stack([k + 1, k + n + 1, k + n + 2])])
    return vertices, triangles


def _rays(n_grid: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starts, directions and max_t of the rays the test casts (see the module docstring)."""
    m = 3000
    starts = np.column_stack([rng.uniform(-2.0, n_grid + 2.0, (m, 2)), rng.uniform(2.0, 30.0, m)])
    directions = np.column_stack([rng.normal(0.0, 0.4, (m, 2)), -np.ones(m)])
    nodes = rng.integers(1, n_grid, (400, 2)).astype(np.float64)  # straight down through grid vertices
    node_rays = np.column_stack([nodes, np.full(400, 10.0)]), np.tile([0.0, 0.0, -1.0], (400, 1))
    edges = np.column_stack([rng.integers(1, n_grid, 300) + 0.5, rng.integers(1, n_grid, 300)])  # through edges,
    edge_rays = np.column_stack([edges, np.full(300, 10.0)]), np.column_stack([np.zeros(300), rng.normal(0, 0.3, 300),
                                                                              -np.ones(300)])  # x held
    up = np.column_stack([rng.uniform(0.0, n_grid, (200, 2)), np.full(200, 10.0)]), np.tile([0.1, 0.2, 1.0], (200, 1))
    flat = np.column_stack([np.full(200, -5.0), rng.uniform(0.0, n_grid, 200), rng.uniform(-1.0, 1.0, 200)]), \
        np.tile([1.0, 0.0, 0.0], (200, 1))  # horizontal, through the relief
    s = np.concatenate([starts, node_rays[0], edge_rays[0], up[0], flat[0]])
    d = np.concatenate([directions, node_rays[1], edge_rays[1], up[1], flat[1]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    max_t = np.full(len(s), 1000.0)
    max_t[::7] = rng.uniform(0.5, 12.0, len(max_t[::7]))  # some rays end before the surface
    return s, d, max_t


def _cast(device, vertices, triangles, starts, directions, max_t):
    mesh = wp.Mesh(points=wp.array(vertices.astype(np.float32), dtype=wp.vec3f, device=device),
                   indices=wp.array(triangles.astype(np.int32).ravel(), dtype=wp.int32, device=device))
    faces = wp.empty((len(starts), 2), dtype=wp.int32, device=device)
    ts = wp.empty((len(starts), 2), dtype=wp.float32, device=device)
    wp.launch(_both, len(starts), inputs=[mesh.id, wp.array(starts.astype(np.float32), dtype=wp.vec3f, device=device),
                                          wp.array(directions.astype(np.float32), dtype=wp.vec3f, device=device),
                                          wp.array(max_t.astype(np.float32), dtype=wp.float32, device=device)],
              outputs=[faces, ts], device=device)
    return faces.numpy(), ts.numpy()


def test_closest_hit_is_warps_mesh_query_bit_for_bit(device):
    rng = np.random.default_rng(11)
    vertices, triangles = _terrain(40, rng)
    faces, ts = _cast(device, vertices, triangles, *_rays(40, rng))
    assert (faces[:, 0] >= 0).sum() > 2500 and (faces[:, 0] < 0).sum() > 300  # hits and misses both exercised
    np.testing.assert_array_equal(faces[:, 0], faces[:, 1])
    np.testing.assert_array_equal(ts[:, 0].view(np.int32), ts[:, 1].view(np.int32))


def test_closest_hit_t_is_the_plane_distance():
    """Over the plane z = 0 (two triangles), t = h / |d_z| in float64 to float32 rounding; no hit from below."""
    vertices = np.array([[-100.0, -100.0, 0.0], [100.0, -100.0, 0.0], [100.0, 100.0, 0.0], [-100.0, 100.0, 0.0]])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(5)
    starts = np.column_stack([rng.uniform(-20.0, 20.0, (500, 2)), rng.uniform(1.0, 50.0, 500)])
    d = np.column_stack([rng.normal(0.0, 0.5, (500, 2)), -np.ones(500)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    starts[:50, 2] *= -1.0  # below the plane, looking further down: no hit
    faces, ts = _cast("cpu", vertices, triangles, starts, d, np.full(500, 1e4))
    assert (faces[:50, 0] == -1).all() and (ts[:50, 0] == np.float32(1e4)).all()
    s32, d32 = starts.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    expected = s32[50:, 2] / -d32[50:, 2]
    assert (faces[50:, 0] >= 0).all()
    np.testing.assert_allclose(ts[50:, 0], expected, rtol=2e-6)


@pytest.mark.parametrize("max_t", [0.0, 5.0])
def test_closest_hit_stops_at_max_t(max_t):
    """A surface 10 m down is not hit by a ray allowed 0 or 5 m; t stays max_t."""
    vertices = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    faces, ts = _cast("cpu", vertices, np.array([[0, 1, 2]]), np.array([[0.0, 0.0, 10.0]]),
                      np.array([[0.0, 0.0, -1.0]]), np.array([max_t]))
    assert faces[0, 0] == -1 and ts[0, 0] == np.float32(max_t)
