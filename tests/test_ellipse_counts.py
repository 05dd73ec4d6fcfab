"""ATL08's density filter counts, by columns sorted by height (flightsim.outputs.atl08.ellipse_counts), against
SciPy's KD-tree (`cKDTree.query_ball_point(r=1, return_length=True)`), the count the filter was written with: equal for
every point, ties at distance exactly 1, coordinates an ulp across a column edge and a long pass's large keys
included; on one thread and shared out over several (bands of columns sorted and walked side by side)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from flightsim.outputs import atl08
from flightsim.outputs.atl08 import ellipse_counts


def _kd(u, v) -> np.ndarray:
    points = np.column_stack([u, v])
    return cKDTree(points).query_ball_point(points, r=1.0, return_length=True)


@pytest.mark.parametrize("threads", [1, 2, 5])
def test_clustered_photons_like_a_pass(threads):
    """A noise cloud, a dense ground line and a canopy band."""
    rng = np.random.default_rng(11)
    n = 20_000
    u = np.concatenate([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.uniform(10, 20, n // 4)])
    v = np.concatenate([rng.uniform(-300, 900, n), rng.normal(0.0, 0.2, n) + 0.05 * u[n:2 * n],
                        rng.uniform(1, 12, n // 4)])
    np.testing.assert_array_equal(ellipse_counts(u, v, threads), _kd(u, v))


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("step", [0.5, 0.25, 1.0, 0.6])
def test_lattices_with_pairs_at_distance_exactly_one(step, threads):
    """Points on a lattice: many pairs exactly 1 apart (and, for 0.6, sums of squares that round either way)."""
    g = np.arange(-8, 9) * step
    u, v = (a.ravel() for a in np.meshgrid(g, g + 1e3))
    np.testing.assert_array_equal(ellipse_counts(u, v, threads), _kd(u, v))


def test_coordinates_an_ulp_across_a_cell_boundary():
    """2 − 0.9999999999999999 rounds to 1: the pair is counted though its points' floors are two apart."""
    below = np.nextafter(1.0, 0.0)
    u = np.array([2.0, below, 0.0, np.nextafter(2.0, 3.0), 3.0 - 1e-12, -1.0, np.nextafter(-1.0, 0.0)])
    v = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
    assert (u[0] - u[1]) ** 2 <= 1.0 and np.floor(u[0]) - np.floor(u[1]) == 2
    np.testing.assert_array_equal(ellipse_counts(u, v), _kd(u, v))


@pytest.mark.parametrize("threads", [1, 4])
def test_a_long_pass_keys_of_a_billion(threads):
    """Columns up to 8e5 and heights over 3,000 half axes (sort keys ~2.4e9, their ulp 5e-7): pairs exactly 1 apart in
    height, in one column and across two, at the bottom and the top of the height range, and points just beyond."""
    rng = np.random.default_rng(5)
    base_u = rng.uniform(0.0, 8e5, 3_000)
    base_v = np.where(rng.random(3_000) < 0.5, rng.uniform(-1500.0, -1490.0, 3_000), rng.uniform(1490.0, 1500.0, 3_000))
    du = rng.choice([0.0, 0.3, 0.9999, np.nextafter(1.0, 0.0)], 3_000)
    u = np.concatenate([base_u, base_u + du, base_u + du, base_u])
    v = np.concatenate([base_v, base_v + 1.0, base_v - np.sqrt(1.0 - du * du), np.nextafter(base_v - 1.0, -2e3)])
    edge = np.floor(rng.uniform(1.0, 8e5, 3_000)) * atl08.CELL  # pairs across a column edge, just under 1 in height
    lift = np.where(rng.random(3_000) < 0.5, -1.0, 1.0) * (1.0 - 1e-12)
    u = np.concatenate([u, edge - 1e-7, edge + 1e-7])
    v = np.concatenate([v, base_v, base_v + lift])
    counts = ellipse_counts(u, v, threads)
    np.testing.assert_array_equal(counts, _kd(u, v))
    assert (counts[:3_000][du == 0.0] >= 3).all()  # itself and its partners exactly 1 above and 1 below
    assert (counts[-6_000:] >= 2).all()  # each across the edge finds its partner


@pytest.mark.parametrize("threads", [1, 8])
def test_nothing_one_point_and_far_apart_points(threads):
    """(More threads than columns too.)"""
    assert ellipse_counts(np.zeros(0), np.zeros(0), threads).shape == (0,)
    np.testing.assert_array_equal(ellipse_counts(np.array([5.0]), np.array([-7.0]), threads), [1])
    u, v = np.array([0.0, 1e6, 0.5, -3e5]), np.array([0.0, 0.0, 1e4, 2e4])
    np.testing.assert_array_equal(ellipse_counts(u, v, threads), [1, 1, 1, 1])
