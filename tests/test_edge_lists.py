"""The edge buffer's distance query (kernels/edges.py ``boundary_distance``, over the segments listed for a point's
list cell) against the minimum over every boundary segment in the same float32 arithmetic: the lists leave out no
segment that comes within the cap, so the two are the same numbers."""
import numpy as np
import pytest
import warp as wp

from flightsim.engine.meshes import SceneMeshes
from flightsim.scenes.calibration import calibration_scene
from flightsim.scenes.scene import DEFAULT_CRS
from kernels import edges


@wp.kernel
def _distances(grid: edges.EdgeGrid, a: wp.array(dtype=wp.vec3f), b: wp.array(dtype=wp.vec3f),
               points: wp.array(dtype=wp.vec3f), cap: wp.float32, listed: wp.array(dtype=wp.float32),
               every: wp.array(dtype=wp.float32)):
    i = wp.tid()
    p = points[i]
    listed[i] = edges.boundary_distance(grid, a, b, p, cap)
    best = cap
    for k in range(a.shape[0]):
        best = wp.min(best, edges._segment_distance(p, a[k], b[k]))
    every[i] = best


def _points(rng, a: np.ndarray, b: np.ndarray, cap: float, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Points along random segments moved up to 1.5 caps across and 1 along z (most within the cap), points over
    the whole scene, and points beyond the grid."""
    k = rng.integers(0, len(a), 20000)
    on = a[k] + rng.random((len(k), 1)) * (b[k] - a[k])
    near = on + rng.uniform(-1.5, 1.5, on.shape) * np.array([cap, cap, cap / 1.5])
    spread = rng.uniform(lower - 2 * cap, upper + 2 * cap, (5000, 3))
    beyond = np.array([[lower[0] - 50 * cap, lower[1], lower[2]], [upper[0] + 50 * cap, upper[1], upper[2]],
                       [lower[0], upper[1] + 1e6, lower[2]]])
    return np.concatenate([near, spread, beyond]).astype(np.float32)


def _listed_and_every(meshes: SceneMeshes, grid: edges.EdgeGrid, cap: float, seed: int):
    """(the query's distance over the listed segments, the minimum over every segment) of :func:`_points`."""
    a, b = meshes.boundary
    lower, upper = (np.asarray(v, dtype=np.float64) for v in meshes.scene.bounds())
    points = _points(np.random.default_rng(seed), a.numpy(), b.numpy(), cap, lower, upper)
    d = meshes.device
    listed, every = (wp.empty(len(points), dtype=wp.float32, device=d) for _ in range(2))
    wp.launch(_distances, len(points), inputs=[grid, a, b, wp.array(points, dtype=wp.vec3f, device=d), cap],
              outputs=[listed, every], device=d)
    return listed.numpy(), every.numpy()


@pytest.mark.parametrize("cap", [0.4, 1.2, 6.0])
def test_listed_distances_are_the_minimum_over_every_segment(device, cap):
    scene = calibration_scene(300.0, np.array([409000.0, 3393000.0, 450.0]), DEFAULT_CRS)
    meshes = SceneMeshes(scene, device)
    grid = meshes.edge_grid(cap)
    listed, every = _listed_and_every(meshes, grid, cap, 7)
    assert 0.3 < np.mean(every < np.float32(cap)) < 0.9  # both sides of the cap
    assert np.array_equal(listed, every)
    counts = np.diff(grid.offsets.numpy())
    assert counts[counts > 0].mean() < 8.0  # short lists: a few segments a cell on average


def test_a_point_that_is_not_a_number_is_the_cap_away(device):
    scene = calibration_scene(300.0, np.array([409000.0, 3393000.0, 450.0]), DEFAULT_CRS)
    meshes = SceneMeshes(scene, device)
    a, b = meshes.boundary
    grid = meshes.edge_grid(1.0)
    listed, every = (wp.empty(2, dtype=wp.float32, device=device) for _ in range(2))
    points = wp.array(np.array([[np.nan, 0.0, 0.0], [0.0, np.nan, 0.0]], dtype=np.float32), dtype=wp.vec3f,
                      device=device)
    wp.launch(_distances, 2, inputs=[grid, a, b, points, 1.0], outputs=[listed, every], device=device)
    assert listed.numpy().tolist() == [1.0, 1.0]


def test_a_grid_built_for_a_wider_cap_gives_the_same_distances(device):
    """A sweep's SceneMeshes serves a cap from a kept grid built for up to twice it: the returns it sends to the
    query are more, their distances (the query is given the run's own cap) the same."""
    scene = calibration_scene(300.0, np.array([409000.0, 3393000.0, 450.0]), DEFAULT_CRS)
    meshes = SceneMeshes(scene, device)
    wide = meshes.edge_grid(1.9)
    cap = 1.0
    assert meshes.edge_grid(cap) is wide
    listed, every = _listed_and_every(meshes, wide, cap, 11)
    assert 0.3 < np.mean(every < np.float32(cap)) < 0.9
    assert np.array_equal(listed, every)


def test_a_sweeps_caps_share_a_few_grids(monkeypatch):
    scene = calibration_scene(300.0, np.array([409000.0, 3393000.0, 450.0]), DEFAULT_CRS)
    meshes = SceneMeshes(scene, "cpu")
    built = []
    build = meshes._build_edge_grid
    monkeypatch.setattr(meshes, "_build_edge_grid", lambda cap: built.append(cap) or build(cap))
    first = meshes.edge_grid(0.3)  # a run's one cap: its own grid
    assert built == [0.3] and meshes.edge_grid(0.25) is first and meshes.edge_grid(0.15) is first
    meshes.edge_grid(0.31)  # above every kept grid: the power of two at or above it
    assert meshes.edge_grid(0.45) is meshes._grids[0.5]  # within half of that grid: shared
    meshes.edge_grid(0.14)  # below half of 0.3: a grid of its own
    assert built == [0.3, 0.5, 0.25]
    for k in range(10):  # at most 8 kept, the least recently used dropped first
        meshes.edge_grid(2.0 ** (k + 1))
    assert len(meshes._grids) == 8 and 0.3 not in meshes._grids and 2.0 ** 10 in meshes._grids
