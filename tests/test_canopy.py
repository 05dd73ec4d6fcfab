"""The turbid voxel canopy: the device walk against an independent NumPy walk, optical depth and first
interactions against closed forms and Monte Carlo, the leaf projection function G, the host grid's checks,
and the MacArthur–Horn inversion of simulated first returns."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from flightsim.core.errors import InputError
from flightsim.scenes import leaf_angles as la
from flightsim.scenes.canopy import VoxelCanopy, leaf_layers, no_canopy
from flightsim.scenes.macarthur_horn import lad_from_points, sampling_sigma
from kernels import canopy as kc
from tests import reference_canopy as ref

MAX_RECORDED = 128  # voxels recorded per ray


@wp.kernel
def _walks(c: kc.Canopy, starts: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d),
           t0: wp.array(dtype=wp.float64), t1: wp.array(dtype=wp.float64),
           index: wp.array2d(dtype=wp.vec3i), t_in: wp.array2d(dtype=wp.float64), t_out: wp.array2d(dtype=wp.float64),
           lad: wp.array2d(dtype=wp.float32), count: wp.array(dtype=wp.int32)):
    r = wp.tid()
    w = kc.walk_begin(c, starts[r], dirs[r], t0[r], t1[r])
    n = int(0)
    while w.done == 0:
        if n < index.shape[1]:
            index[r, n] = w.index
            t_in[r, n] = w.t_in
            t_out[r, n] = w.t_out
            lad[r, n] = w.lad
        n += 1
        w = kc.walk_next(c, w)
    count[r] = n


@wp.kernel
def _depths(c: kc.Canopy, starts: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d),
            t0: wp.array(dtype=wp.float64), t1: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    r = wp.tid()
    out[r] = kc.optical_depth(c, starts[r], dirs[r], t0[r], t1[r])


@wp.kernel
def _firsts(c: kc.Canopy, starts: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d),
            t0: wp.array(dtype=wp.float64), t1: wp.array(dtype=wp.float64), xi: wp.array(dtype=wp.float64),
            out: wp.array(dtype=wp.float64)):
    r = wp.tid()
    out[r] = kc.first_interaction(c, starts[r], dirs[r], t0[r], t1[r], xi[r])


@wp.kernel
def _g_values(c: kc.Canopy, dirs: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    r = wp.tid()
    out[r] = kc.g_of(c, dirs[r])


@wp.kernel
def _voxels(c: kc.Canopy, points: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3i),
            lad: wp.array(dtype=wp.float32)):
    r = wp.tid()
    out[r] = kc.voxel_of(c, points[r])
    lad[r] = kc.lad_at(c, points[r])


def _arrays(device, *columns, dtype=wp.float64):
    return [wp.array(np.ascontiguousarray(c), dtype=dtype, device=device) for c in columns]


def _run_walks(canopy: VoxelCanopy, device, starts, dirs, t0, t1, c=None):
    n = len(starts)
    c = canopy.to_device(device) if c is None else c
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    a0, a1 = _arrays(device, t0, t1)
    index = wp.zeros((n, MAX_RECORDED), dtype=wp.vec3i, device=device)
    t_in, t_out = (wp.zeros((n, MAX_RECORDED), dtype=wp.float64, device=device) for _ in range(2))
    lad = wp.zeros((n, MAX_RECORDED), dtype=wp.float32, device=device)
    count = wp.zeros(n, dtype=wp.int32, device=device)
    wp.launch(_walks, n, [c, s, d, a0, a1, index, t_in, t_out, lad, count], device=device)
    return index.numpy(), t_in.numpy(), t_out.numpy(), lad.numpy(), count.numpy()


def _run(kernel, device, canopy_struct, *arrays, n):
    out = wp.zeros(n, dtype=wp.float64, device=device)
    wp.launch(kernel, n, [canopy_struct, *arrays, out], device=device)
    return out.numpy()


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_grid(rng, dims, lower, cell) -> VoxelCanopy:
    lad = rng.uniform(0.0, 2.0, dims).astype(np.float32)
    lad[rng.random(dims) < 0.2] = 0.0  # some empty voxels
    return VoxelCanopy(lad, lower, cell)


def _ray_set(rng, canopy: VoxelCanopy, n: int):
    """Rays of every kind the walk must handle: random starts inside and outside the box, axis-parallel rays
    (on voxel faces and on the box's faces too), rays through grid vertices (edges and corners, the box's
    included), rays along diagonals through vertices (exact ties on a cubic grid), t0 == t1, very long segments."""
    lo, hi = canopy.bounds()
    dims, cell = np.asarray(canopy.dims), canopy.cell
    span = hi - lo
    starts, dirs, t0, t1 = [], [], [], []

    def add(s, d, a, b):
        starts.append(s), dirs.append(d), t0.append(a), t1.append(b)

    for _ in range(n):
        kind = rng.integers(7)
        if kind == 0:  # random start inside or around the box, random direction
            s = lo - 0.5 * span + 2.0 * span * rng.random(3)
            add(s, _unit(rng.normal(size=3)), rng.choice([0.0, -rng.uniform(0, 30)]), rng.choice([rng.uniform(0, 30), 1e7]))
        elif kind == 1:  # axis-parallel or in a coordinate plane; parallel coordinates on faces half the time
            d = rng.normal(size=3)
            zero = [[0], [1], [2], [0, 1], [0, 2], [1, 2]][rng.integers(6)]
            d[zero] = 0.0
            s = lo - 0.25 * span + 1.5 * span * rng.random(3)
            for a in zero:
                if rng.random() < 0.5:
                    s[a] = lo[a] + rng.integers(0, dims[a] + 1) * cell[a]  # on a voxel face or the box's
            add(s, _unit(d), 0.0, rng.choice([rng.uniform(0, 40), 1e7]))
        elif kind == 2:  # through a grid vertex (interior, or on the box's edges and corners)
            vertex = lo + rng.integers(0, dims + 1) * cell
            d = _unit(rng.normal(size=3))
            back = rng.uniform(0.5, 30.0)
            add(vertex - back * d, d, 0.0, back + rng.uniform(0.0, 30.0))
        elif kind == 3:  # starting exactly on a vertex, along a (face or space) diagonal of the cells
            vertex = lo + rng.integers(0, dims + 1) * cell
            d = rng.choice([-1.0, 0.0, 1.0], size=3) * cell
            if not d.any():
                d[2] = cell[2]
            add(vertex, _unit(d), 0.0, rng.choice([rng.uniform(0, 40), 1e7]))
        elif kind == 4:  # zero-length segment
            s = lo + span * rng.random(3)
            t = rng.uniform(-1, 1)
            add(s, _unit(rng.normal(size=3)), t, t)
        elif kind == 5:  # very long segment from far away
            s = lo + span * rng.random(3)
            d = _unit(rng.normal(size=3))
            add(s - 1e4 * d, d, -1e9, 1e9)
        else:  # start on a voxel face (inside), leaving it at once or going along
            s = lo + span * rng.random(3)
            a = rng.integers(3)
            s[a] = lo[a] + rng.integers(0, dims[a] + 1) * cell[a]
            add(s, _unit(rng.normal(size=3)), 0.0, rng.uniform(0, 40))
    return (np.array(starts), np.array(dirs), np.array(t0, dtype=np.float64), np.array(t1, dtype=np.float64))


def _significant(voxels, tol=1e-9):
    """The (index, t_in, t_out) of a walk without its slivers (voxels crossed for less than ``tol``)."""
    return [v for v in voxels if v[2] - v[1] > tol]


GRIDS = [
    ((7, 5, 4), (-3.25, 10.5, 2.0), (0.5, 1.25, 2.0)),  # non-cubic cells, planes exact in binary
    ((6, 6, 6), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),  # cubic: diagonal rays tie exactly at edges and corners
    ((9, 3, 11), (104.1, -7.3, 0.3), (0.7, 2.9, 0.45)),  # cells not exact in binary
]


@pytest.mark.parametrize("grid", range(len(GRIDS)))
def test_walk_matches_the_reference_walk(device, grid):
    rng = np.random.default_rng(7 + grid)
    dims, lower, cell = GRIDS[grid]
    canopy = _random_grid(rng, dims, lower, cell)
    starts, dirs, t0, t1 = _ray_set(rng, canopy, 2500)
    index, t_in, t_out, lad, count = _run_walks(canopy, device, starts, dirs, t0, t1)
    assert count.max() <= sum(dims)  # the step bound
    kinds_hit = 0
    for r in range(len(starts)):
        expected = ref.walk(lower, cell, dims, starts[r], dirs[r], t0[r], t1[r])
        n = count[r]
        got = [(tuple(int(i) for i in index[r, k]), t_in[r, k], t_out[r, k]) for k in range(n)]
        if t0[r] == t1[r]:
            assert n == 0 and not expected
        if n == 0 or not expected:  # no voxel, or a sliver where the ray grazes an edge or corner of the box
            assert sum(b - a for _, a, b in expected + got) <= 1e-9, (r, starts[r], dirs[r], t0[r], t1[r], got, expected)
            continue
        kinds_hit += 1
        # the walk is continuous and covers the clipped segment exactly
        assert np.all(t_in[r, 1:n] == t_out[r, :n - 1])
        assert np.all(t_out[r, :n] >= t_in[r, :n])
        ta, tb = ref.clip_to_box(lower, cell, dims, starts[r], dirs[r], t0[r], t1[r])
        assert abs(t_in[r, 0] - ta) <= 1e-9 and abs(t_out[r, n - 1] - tb) <= 1e-9
        assert abs((t_out[r, :n] - t_in[r, :n]).sum() - (tb - ta)) <= 1e-9
        # the same voxels for the same lengths
        a, b = _significant(got), _significant(expected)
        assert [v[0] for v in a] == [v[0] for v in b], (r, starts[r], dirs[r], t0[r], t1[r], a, b)
        assert np.allclose([v[2] - v[1] for v in a], [v[2] - v[1] for v in b], rtol=0, atol=1e-9)
        assert np.allclose([v[1] for v in a], [v[1] for v in b], rtol=0, atol=1e-9)
        # each voxel's leaf area density
        assert np.array_equal(lad[r, :n], canopy.lad[tuple(index[r, :n].T)])
    assert kinds_hit > 1000


def test_walk_takes_ties_together_and_no_sliver(device):
    """A ray through voxel corners along the cubic grid's space diagonal crosses three planes at once at every
    step: one voxel per step, each for the full diagonal length, none of zero length."""
    canopy = VoxelCanopy(np.ones((6, 6, 6), np.float32), [0, 0, 0], [1, 1, 1])
    d = _unit([1.0, 1.0, 1.0])
    index, t_in, t_out, _, count = _run_walks(canopy, device, np.zeros((1, 3)), d[None], np.zeros(1), np.full(1, 1e3))
    assert count[0] == 6
    assert [tuple(v) for v in index[0, :6]] == [(k, k, k) for k in range(6)]
    assert np.allclose(t_out[0, :6] - t_in[0, :6], math.sqrt(3.0), rtol=0, atol=1e-12)


def test_long_and_degenerate_segments(device):
    canopy = VoxelCanopy(np.ones((100, 100, 30), np.float32), [-50, -50, 0], [1, 1, 1])
    rng = np.random.default_rng(3)
    n = 4000
    dirs = _unit(rng.normal(size=(n, 3)))
    starts = rng.uniform(-60, 60, (n, 3))
    t0 = np.full(n, -1e15)
    t1 = np.full(n, 1e15)
    t1[:100] = t0[:100]  # zero length
    _, _, _, _, count = _run_walks(canopy, device, starts, dirs, t0, t1)
    assert count.max() <= 230
    assert np.all(count[:100] == 0)
    # a ray touching only a vertical edge of the box meets it for zero length; one along an edge of the box (the
    # box is closed) walks the outer voxels; one beside the box misses it
    grazing = np.array([[-60.0, -40.0, 10.0], [-50.0, -60.0, 0.0], [-51.0, 0.0, 0.0]])
    gdirs = _unit(np.array([[1.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]))
    index, t_in, t_out, _, count = _run_walks(canopy, device, grazing, gdirs, np.zeros(3), np.full(3, 1e3))
    assert count[0] == 0 and count[1] == 100 and count[2] == 0
    assert [tuple(v) for v in index[1, :3]] == [(0, 0, 0), (0, 1, 0), (0, 2, 0)]


@pytest.mark.parametrize("distribution", ["spherical", "planophile"])
def test_slab_optical_depth_is_g_lai_over_cos(device, distribution):
    """A homogeneous slab of leaf area index L = lad · h: depth G(μ) L / μ through it, G from the table."""
    h, lad = 12.0, 0.25  # L = 3, lad exact in float32
    canopy = VoxelCanopy(np.full((100, 100, 12), lad, np.float32), [-50, -50, 0], [1, 1, 1], leaf_angles=distribution)
    table = la.g_table(distribution)
    rng = np.random.default_rng(11)
    zenith = np.radians(np.r_[0.0, 20.0, 45.0, 60.0, rng.uniform(0, 70, 200)])
    azimuth = rng.uniform(0, 2 * np.pi, len(zenith))
    down = np.stack([np.sin(zenith) * np.sin(azimuth), np.sin(zenith) * np.cos(azimuth), -np.cos(zenith)], axis=1)
    starts = np.stack([rng.uniform(-2, 2, len(zenith)), rng.uniform(-2, 2, len(zenith)), np.full(len(zenith), 13.0)], 1)
    c = canopy.to_device(device)
    s, d = _arrays(device, starts, down, dtype=wp.vec3d)
    a0, a1 = _arrays(device, np.zeros(len(zenith)), np.full(len(zenith), 1e3))
    depth = _run(_depths, device, c, s, d, a0, a1, n=len(zenith))
    mu = np.cos(zenith)
    g = np.interp(mu, np.linspace(0, 1, len(table)), table)
    assert np.allclose(depth, g * lad * h / mu, rtol=0, atol=1e-9)
    assert np.allclose(g, la.g_function(distribution, mu), rtol=0, atol=1e-5)  # the table's own error
    # upward rays see the same depth
    s, d = _arrays(device, starts * [1, 1, -1] + [0, 0, 12], down * [1, 1, -1], dtype=wp.vec3d)  # from z = −1 up
    up = _run(_depths, device, c, s, d, a0, a1, n=len(zenith))
    assert np.allclose(up, depth, rtol=0, atol=1e-9)


def test_optical_depth_matches_the_reference(device):
    rng = np.random.default_rng(5)
    dims, lower, cell = GRIDS[2]
    canopy = _random_grid(rng, dims, lower, cell)
    starts, dirs, t0, t1 = _ray_set(rng, canopy, 1500)
    c = canopy.to_device(device)
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    a0, a1 = _arrays(device, t0, t1)
    depth = _run(_depths, device, c, s, d, a0, a1, n=len(starts))
    table = canopy.g_table()
    g = np.interp(np.abs(dirs[:, 2]), np.linspace(0, 1, len(table)), table)
    expected = [ref.optical_depth(canopy.lad, lower, cell, starts[r], dirs[r], t0[r], t1[r], g[r])
                for r in range(len(starts))]
    assert np.allclose(depth, expected, rtol=1e-12, atol=1e-9)


def test_g_of_interpolates_the_table(device):
    canopy = VoxelCanopy(np.ones((1, 1, 1), np.float32), [0, 0, 0], [1, 1, 1], leaf_angles="erectophile")
    rng = np.random.default_rng(2)
    dirs = _unit(rng.normal(size=(500, 3)))
    dirs[:3] = [[0, 0, 1], [0, 0, -1], [1, 0, 0]]
    g = np.zeros(len(dirs))
    out = wp.zeros(len(dirs), dtype=wp.float64, device=device)
    wp.launch(_g_values, len(dirs), [canopy.to_device(device), _arrays(device, dirs, dtype=wp.vec3d)[0], out],
              device=device)
    g = out.numpy()
    table = canopy.g_table()
    assert np.allclose(g, np.interp(np.abs(dirs[:, 2]), np.linspace(0, 1, len(table)), table), rtol=0, atol=1e-14)
    assert g[0] == g[1] == table[-1] and g[2] == table[0]


def test_first_interaction_inverts_the_depth(device):
    rng = np.random.default_rng(9)
    dims, lower, cell = GRIDS[0]
    canopy = _random_grid(rng, dims, lower, cell)
    starts, dirs, t0, t1 = _ray_set(rng, canopy, 3000)
    n = len(starts)
    xi = rng.random(n)
    xi[:50] = 0.0
    c = canopy.to_device(device)
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    a0, a1, x = _arrays(device, t0, t1, xi)
    t = _run(_firsts, device, c, s, d, a0, a1, x, n=n)
    total = _run(_depths, device, c, s, d, a0, a1, n=n)
    target = -np.log1p(-xi)
    hit = t <= t1
    assert np.all(np.isinf(t[~hit]))
    assert np.all(total[~hit] < target[~hit] + 1e-12)
    assert np.all(total[hit] >= target[hit] - 1e-9)
    assert np.all(t[hit] >= t0[hit])
    # the depth from t0 to the interaction is the target
    (a_hit,) = _arrays(device, np.where(hit, t, t1))
    upto = _run(_depths, device, c, s, d, a0, a_hit, n=n)
    assert np.allclose(upto[hit], target[hit], rtol=1e-10, atol=1e-10)
    # ξ = 0: the entry into the first voxel with leaves (depth 0 there, positive just after)
    assert np.all(upto[:50][hit[:50]] == 0.0)
    assert hit.sum() > 500 and (~hit).sum() > 500


@pytest.mark.parametrize("distribution", ["spherical", "planophile"])
@pytest.mark.parametrize("zenith_deg", [0.0, 20.0])
def test_monte_carlo_transmission_is_beer_lambert(device, distribution, zenith_deg):
    """10⁶ rays through a homogeneous layer: the fraction with no interaction is exp(−G L / cos θ)."""
    n = 1_000_000
    lai, h = 2.0, 8.0
    canopy = VoxelCanopy(np.full((20, 20, 8), lai / h, np.float32), [0, 0, 0], [1, 1, 1], leaf_angles=distribution)
    rng = np.random.default_rng(int(zenith_deg) + len(distribution))
    theta = math.radians(zenith_deg)
    azimuth = rng.uniform(0, 2 * np.pi, n)
    dirs = np.stack([math.sin(theta) * np.sin(azimuth), math.sin(theta) * np.cos(azimuth), np.full(n, -math.cos(theta))], 1)
    starts = np.stack([rng.uniform(6, 14, n), rng.uniform(6, 14, n), np.full(n, 9.0)], 1)
    c = canopy.to_device(device)
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    a0, a1, x = _arrays(device, np.zeros(n), np.full(n, 20.0), rng.random(n))
    t = _run(_firsts, device, c, s, d, a0, a1, x, n=n)
    escaped = np.mean(t > 20.0)
    g = float(la.g_function(distribution, np.array([math.cos(theta)]))[0])
    expected = math.exp(-g * lai / math.cos(theta))
    sigma = math.sqrt(expected * (1 - expected) / n)
    assert abs(escaped - expected) <= 0.01 * expected
    assert abs(escaped - expected) <= 4 * sigma
    # the interactions lie in the layer, exponentially distributed in depth
    z = 9.0 + t[t <= 20.0] * dirs[t <= 20.0, 2]
    assert z.min() >= 0.0 - 1e-9 and z.max() <= 8.0 + 1e-9


def test_no_canopy_returns_at_once(device):
    c = no_canopy(device)
    starts = np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 10.0]])
    dirs = _unit(np.array([[0.0, 0.0, -1.0], [0.1, 0.2, -1.0]]))
    canopy = VoxelCanopy(np.ones((1, 1, 1), np.float32), [0, 0, 0], [1, 1, 1])
    _, _, _, _, count = _run_walks(canopy, device, starts, dirs, np.zeros(2), np.full(2, 100.0), c=c)
    assert np.all(count == 0)
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    a0, a1, x = _arrays(device, np.zeros(2), np.full(2, 100.0), np.array([0.0, 0.999]))
    assert np.all(_run(_depths, device, c, s, d, a0, a1, n=2) == 0.0)
    assert np.all(np.isinf(_run(_firsts, device, c, s, d, a0, a1, x, n=2)))
    voxels = wp.zeros(2, dtype=wp.vec3i, device=device)
    lad = wp.zeros(2, dtype=wp.float32, device=device)
    wp.launch(_voxels, 2, [c, s, voxels, lad], device=device)
    assert np.all(voxels.numpy() == -1) and np.all(lad.numpy() == 0.0)


def test_voxel_of_and_lad_at(device):
    rng = np.random.default_rng(4)
    dims, lower, cell = GRIDS[0]
    canopy = _random_grid(rng, dims, lower, cell)
    lo, hi = canopy.bounds()
    points = lo - 1.0 + (hi - lo + 2.0) * rng.random((2000, 3))
    points[0] = [np.nan, 0, 0]
    points[1] = [1e300, 0, 0]
    voxels = wp.zeros(len(points), dtype=wp.vec3i, device=device)
    lad = wp.zeros(len(points), dtype=wp.float32, device=device)
    wp.launch(_voxels, len(points), [canopy.to_device(device), _arrays(device, points, dtype=wp.vec3d)[0], voxels, lad],
              device=device)
    expected = np.floor((points - lo) / cell)
    inside = np.all((expected >= 0) & (expected < dims), axis=1)
    got = voxels.numpy()
    assert np.array_equal(got[inside], expected[inside].astype(int))
    assert np.all(got[~inside] == -1)
    assert np.array_equal(lad.numpy()[inside], canopy.lad[tuple(got[inside].T)])
    assert np.all(lad.numpy()[~inside] == 0.0)


# --- leaf projection G -------------------------------------------------------------------------------------


MU = np.linspace(0.0, 1.0, 101)


def test_spherical_g_is_one_half_from_the_integral():
    g = la.projection_integral(la.DENSITIES["spherical"], MU)
    assert np.allclose(g, 0.5, rtol=0, atol=1e-13)


@pytest.mark.parametrize("distribution", la.DISTRIBUTIONS)
def test_g_integrates_to_one_half_over_mu(distribution):
    """∫₀¹ G(μ) dμ = ½ for every leaf angle distribution (Ross 1981)."""
    x, w = np.polynomial.legendre.leggauss(200)
    assert abs(0.5 * (w * la.g_function(distribution, 0.5 * (x + 1))).sum() - 0.5) < 1e-12


@pytest.mark.parametrize("distribution", la.DISTRIBUTIONS)
def test_leaf_densities_are_normalised_and_g_ends_are_the_cosine_moments(distribution):
    """At nadir ψ = cos θ_L, so G(1) = ∫ g cos θ_L; at the horizon ψ = (2/π) sin θ_L, so G(0) = (2/π) ∫ g sin θ_L."""
    x, w = np.polynomial.legendre.leggauss(200)
    t, w = np.pi / 4 * (x + 1), np.pi / 4 * w
    g = la.leaf_density(distribution, t)
    assert abs((w * g).sum() - 1.0) < 1e-13
    ends = la.g_function(distribution, np.array([1.0, 0.0]))
    assert abs(ends[0] - (w * g * np.cos(t)).sum()) < 1e-13
    assert abs(ends[1] - 2 / np.pi * (w * g * np.sin(t)).sum()) < 1e-13


def test_g_known_values():
    """Closed forms of the de Wit distributions' moments: planophile G(1) = 8/(3π), G(0) = 8/(3π²); erectophile
    G(1) = 4/(3π), G(0) = 16/(3π²); plagiophile G(1) = 32/(15π); extremophile G(1) = 28/(15π); uniform
    G(1) = 2/π, G(0) = 4/π²; and every G is near ½ at θ ≈ 57.3° (1 rad, Warren Wilson 1960, Ross 1981)."""
    known = {"planophile": (8 / (3 * np.pi), 8 / (3 * np.pi ** 2)), "erectophile": (4 / (3 * np.pi), 16 / (3 * np.pi ** 2)),
             "uniform": (2 / np.pi, 4 / np.pi ** 2)}
    for name, (g1, g0) in known.items():
        assert np.allclose(la.g_function(name, np.array([1.0, 0.0])), [g1, g0], rtol=0, atol=1e-13)
    assert abs(la.g_function("plagiophile", np.array([1.0]))[0] - 32 / (15 * np.pi)) < 1e-13
    assert abs(la.g_function("extremophile", np.array([1.0]))[0] - 28 / (15 * np.pi)) < 1e-13
    for name in la.DISTRIBUTIONS:
        assert abs(la.g_function(name, np.array([math.cos(1.0)]))[0] - 0.5) < 0.025


@pytest.mark.parametrize("x", [0.5, 2.0, 3.0])
def test_projection_integral_matches_campbells_ellipsoidal_closed_form(x):
    """Campbell (1986, 1990): leaves of the ellipsoidal distribution of axis ratio x have
    G(θ) = sqrt(x² cos²θ + sin²θ) / Λ(x), exactly; the quadrature of ψ must reproduce it."""
    if x < 1:
        e = math.sqrt(1 - x * x)
        lam = x + math.asin(e) / e
    else:
        e = math.sqrt(1 - x ** -2)
        lam = x + math.log((1 + e) / (1 - e)) / (2 * e * x)

    def density(t):
        return 2 * x ** 3 * np.sin(t) / (lam * (np.cos(t) ** 2 + x * x * np.sin(t) ** 2) ** 2)

    mu = np.linspace(0, 1, 51)
    closed = np.sqrt(x * x * mu ** 2 + 1 - mu ** 2) / lam
    assert np.allclose(la.projection_integral(density, mu), closed, rtol=0, atol=1e-12)


def test_psi_limits():
    """Horizontal leaves project as μ; vertical leaves as (2/π) sin θ."""
    mu = np.linspace(0, 1, 21)
    assert np.allclose(la.psi(mu, 0.0), mu, rtol=0, atol=1e-15)
    assert np.allclose(la.psi(mu, np.pi / 2), 2 / np.pi * np.sqrt(1 - mu ** 2), rtol=0, atol=1e-15)


def test_g_table_and_bad_distribution():
    table = la.g_table("planophile", 5)
    assert table.shape == (5,) and table.dtype == np.float64
    assert np.allclose(table, la.g_function("planophile", np.linspace(0, 1, 5)))
    with pytest.raises(InputError, match="scene.canopy.leaf_angles.*'conical'"):
        la.g_function("conical", MU)
    with pytest.raises(InputError, match="mu"):
        la.g_function("spherical", np.array([0.5, 1.5]))


# --- the host grid -----------------------------------------------------------------------------------------


def test_voxel_canopy_lai_bounds_and_device_struct(device):
    lad = np.zeros((3, 4, 5), np.float32)
    lad[1, 2, :] = 0.5
    canopy = VoxelCanopy(lad, [1.0, 2.0, 3.0], [2.0, 2.0, 0.5])
    lai = canopy.leaf_area_index()
    assert lai.shape == (3, 4) and lai[1, 2] == pytest.approx(1.25) and lai.sum() == pytest.approx(1.25)
    lo, hi = canopy.bounds()
    assert np.array_equal(lo, [1, 2, 3]) and np.array_equal(hi, [7, 10, 5.5])
    c = canopy.to_device(device)
    assert c is canopy.to_device(device)
    assert c.present == 1 and tuple(c.dims) == (3, 4, 5) and np.array_equal(c.lad.numpy(), lad)
    assert c.g_table.shape[0] == 257
    assert no_canopy(device).present == 0


def test_leaf_layers_bound_each_tiles_leaves():
    rng = np.random.default_rng(5)
    lad = np.zeros((11, 6, 9), np.float32)
    for _ in range(25):  # blobs of leaves at random heights; some columns and tiles stay empty
        i, j, k = rng.integers(0, 11), rng.integers(0, 6), rng.integers(0, 9)
        lad[i, j, k:k + rng.integers(1, 4)] = rng.uniform(0.1, 1.0)
    for tile in (1, 3, 4, 16):
        layers = leaf_layers(lad, tile)
        assert layers.dtype == np.int32 and layers.shape == (-(-11 // tile), -(-6 // tile), 2)
        for ti in range(layers.shape[0]):
            for tj in range(layers.shape[1]):
                block = lad[ti * tile:(ti + 1) * tile, tj * tile:(tj + 1) * tile]
                k = np.flatnonzero((block > 0).any(axis=(0, 1)))
                want = (k.min(), k.max() + 1) if len(k) else (9, 0)
                assert tuple(layers[ti, tj]) == want


@wp.kernel
def _leafy_depths(c: kc.Canopy, starts: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d),
                  t1: wp.array(dtype=wp.float64), clip: int, depth: wp.array(dtype=wp.float64),
                  leafy: wp.array(dtype=wp.int32)):
    """Σ lad · length over the leafy voxels of [0, t1] (and their count), walked whole or over its leaf_span."""
    r = wp.tid()
    s0 = wp.float64(0.0)
    s1 = t1[r]
    if clip != 0:
        span = kc.leaf_span(c, starts[r], dirs[r], t1[r])
        s0 = span[0]
        s1 = span[1]
    w = kc.walk_begin(c, starts[r], dirs[r], s0, s1)
    total = wp.float64(0.0)
    n = int(0)
    while w.done == 0:
        if w.lad > wp.float32(0.0):
            total += wp.float64(w.lad) * (w.t_out - w.t_in)
            n += 1
        w = kc.walk_next(c, w)
    depth[r] = total
    leafy[r] = n


def test_leaf_span_keeps_every_leafy_voxel_bit_for_bit(device):
    """The walk over a ray's leaf span crosses the same leafy voxels with the same parameters as the whole walk: crowns
    of leaves in a tall grid with empty columns, rays down from above it at ALS angles, slanted, upward, horizontal,
    and every kind of the walk's own test rays."""
    rng = np.random.default_rng(11)
    lad = np.zeros((40, 33, 30), np.float32)
    for _ in range(60):  # crowns: boxes of leaves between 5 and 25 layers up
        i, j, k = rng.integers(0, 40), rng.integers(0, 33), rng.integers(5, 20)
        lad[i:i + rng.integers(1, 5), j:j + rng.integers(1, 5), k:k + rng.integers(1, 6)] = rng.uniform(0.05, 1.5)
    canopy = VoxelCanopy(lad, (-20.3, 7.1, 0.4), (0.9, 1.1, 0.7))
    lo, hi = canopy.bounds()
    n = 3000
    top = lo + (hi - lo) * rng.random((n, 3))
    top[:, 2] = hi[2] + rng.uniform(0.0, 5.0, n)
    tilt = np.radians(rng.uniform(0.0, 25.0, n))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    down = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)], axis=1)
    reach = rng.uniform(0.0, 40.0, n)
    starts, dirs, t0, t1 = _ray_set(rng, canopy, 1500)
    others = t0 == 0.0
    starts = np.concatenate([top, starts[others], lo + (hi - lo) * rng.random((500, 3))])
    dirs = np.concatenate([down, dirs[others], _unit(rng.normal(size=(500, 3)) * [1.0, 1.0, 0.1])])
    t1 = np.concatenate([reach, t1[others], rng.uniform(0.0, 60.0, 500)])
    c = canopy.to_device(device)
    s, d = _arrays(device, starts, dirs, dtype=wp.vec3d)
    (a1,) = _arrays(device, t1)
    results = []
    for clip in (0, 1):
        depth = wp.zeros(len(t1), dtype=wp.float64, device=device)
        leafy = wp.zeros(len(t1), dtype=wp.int32, device=device)
        wp.launch(_leafy_depths, len(t1), [c, s, d, a1, clip, depth, leafy], device=device)
        results.append((depth.numpy(), leafy.numpy()))
    (whole, n_whole), (clipped, n_clipped) = results
    assert (n_whole > 0).sum() > 500 and (n_whole == 0).sum() > 500  # rays through leaves and rays past them
    assert np.array_equal(n_whole, n_clipped) and whole.tobytes() == clipped.tobytes()


@pytest.mark.parametrize("kwargs, field, value", [
    (dict(lad=np.array([[[0.1, np.nan]]])), "scene.canopy", r"nan at voxel \(0, 0, 1\)"),
    (dict(lad=np.array([[[0.1]], [[-0.5]]])), "scene.canopy", r"-0.5 at voxel \(1, 0, 0\)"),
    (dict(lad=np.array([[[np.inf]]])), "scene.canopy", r"inf at voxel \(0, 0, 0\)"),
    (dict(lad=np.array([[[1e39]]])), "scene.canopy", r"1e\+39 at voxel"),
    (dict(lad=np.zeros((0, 3, 2))), "scene.canopy", r"empty .*\(0, 3, 2\)"),
    (dict(lad=np.zeros((3, 2))), "scene.canopy", r"shape \(3, 2\)"),
    (dict(lad=np.array([[["a"]]])), "scene.canopy", "ndarray"),
    (dict(lad=np.broadcast_to(np.float32(0), (2048, 1024, 1025))), "scene.canopy", "2,149,580,800 voxels"),
    (dict(cell=[1.0, 0.0, 1.0]), "scene.canopy.cell", r"\(1.0, 0.0, 1.0\)"),
    (dict(cell=[1.0, -2.0, 1.0]), "scene.canopy.cell", "-2.0"),
    (dict(cell=[1.0, 1.0]), "scene.canopy.cell", r"\[1.0, 1.0\]"),
    (dict(lower=[0.0, np.nan, 0.0]), "scene.canopy.lower", "nan"),
    (dict(leaf_angles="conical"), "scene.canopy.leaf_angles", "conical"),
    (dict(leaf_reflectance=1.5), "scene.canopy.leaf_reflectance", "1.5"),
    (dict(leaf_reflectance=0.7, leaf_transmittance=0.5), "scene.canopy.leaf_transmittance", "0.5"),
])
def test_bad_canopy_names_the_field_and_value(kwargs, field, value):
    args = dict(lad=np.ones((2, 2, 2), np.float32), lower=[0.0, 0.0, 0.0], cell=[1.0, 1.0, 1.0])
    args.update(kwargs)
    with pytest.raises(InputError, match=rf"invalid {field} = .*{value}") as error:
        VoxelCanopy(**args)
    assert error.value.field == field


def test_first_bad_voxel_is_named():
    lad = np.ones((4, 4, 4))
    lad[2, 1, 3] = -1.0
    lad[3, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"-1.0 at voxel \(2, 1, 3\)"):
        VoxelCanopy(lad, [0, 0, 0], [1, 1, 1])


# --- MacArthur–Horn ----------------------------------------------------------------------------------------


def _simulate_first_returns(rng, profile, dz, columns, pulses, cell_xy, ground, g=0.5):
    """First returns of vertical pulses through a turbid canopy of layer densities ``profile`` (bottom up, from
    the local height ``ground`` of each column, its layers dz thick): each pulse's optical depth to its first
    interaction is exponential (Beer–Lambert); a pulse through the whole canopy returns from the ground."""
    nx, ny = columns
    tops = np.cumsum(np.asarray(profile)[::-1] * g * dz)  # optical depth at the bottom of each layer, top down
    xyz, is_ground = [], []
    for ix in range(nx):
        for iy in range(ny):
            n = pulses
            x = (ix + rng.random(n)) * cell_xy
            y = (iy + rng.random(n)) * cell_xy
            tau = rng.exponential(1.0, n)
            base = ground[ix, iy]
            top = base + len(profile) * dz
            layer = np.searchsorted(tops, tau)  # layers counted from the top
            hit = layer < len(profile)
            above = np.where(layer > 0, tops[np.maximum(layer - 1, 0)], 0.0)
            rate = np.asarray(profile)[::-1][np.minimum(layer, len(profile) - 1)] * g
            z = np.where(hit, top - layer * dz - (tau - above) / np.where(rate > 0, rate, 1.0), base)
            xyz.append(np.stack([x, y, z], 1))
            is_ground.append(~hit)
    return np.concatenate(xyz), np.concatenate(is_ground)


def test_macarthur_horn_recovers_a_known_profile():
    rng = np.random.default_rng(21)
    dz = 1.0
    profile = np.array([0.0, 0.0, 0.15, 0.4, 0.8, 1.0, 0.6, 0.3, 0.1, 0.0])  # bottom up [m²/m³]
    columns, pulses = (3, 3), 20000
    ground = np.zeros(columns)
    xyz, is_ground = _simulate_first_returns(rng, profile, dz, columns, pulses, 2.0, ground)
    canopy = lad_from_points(xyz, is_ground, 0.0, [0.0, 0.0, 0.0], [2.0, 2.0, dz], (3, 3, 10))
    assert canopy.lad.shape == (3, 3, 10)
    # pulses reaching each layer's top, in expectation: exp(−G Σ above)
    reach = pulses * np.exp(-0.5 * dz * np.cumsum(profile[::-1])[::-1] + 0.5 * dz * profile)
    sigma = sampling_sigma(profile, reach, 0.5, dz)
    for ix in range(3):
        for iy in range(3):
            error = canopy.lad[ix, iy].astype(np.float64) - profile
            assert np.all(np.abs(error) <= 4 * sigma + 1e-6), (error, sigma)
    # the errors scale as derived: about one σ each (not a generous bound)
    leafy = profile > 0
    z = (canopy.lad.reshape(9, 10)[:, leafy] - profile[leafy]) / sigma[leafy]
    assert 0.7 < z.std() < 1.3 and abs(z.mean()) < 0.5
    # the mean profile over the 9 columns, 3× tighter
    mean = canopy.lad.reshape(9, 10).mean(axis=0)
    assert np.all(np.abs(mean - profile) <= 4 * sigma / 3 + 1e-6)
    assert canopy.leaf_area_index().mean() == pytest.approx(profile.sum() * dz, rel=0.02)


def test_macarthur_horn_follows_the_ground_and_its_rules():
    rng = np.random.default_rng(5)
    dz = 0.5
    profile = np.array([0.0, 0.5, 1.0, 0.5])
    ground = np.array([[2.0, 2.5], [3.0, 2.0]])  # each column's ground, on the voxel planes
    xyz, is_ground = _simulate_first_returns(rng, profile, dz, (2, 2), 20000, 1.0, ground)
    canopy = lad_from_points(xyz, is_ground, ground, [0.0, 0.0, 0.0], [1.0, 1.0, dz], (2, 2, 12), min_height_m=0.0)
    for ix in range(2):
        for iy in range(2):
            k = int(ground[ix, iy] / dz)
            lad = canopy.lad[ix, iy]
            assert np.all(lad[:k] == 0.0)  # under the ground: no points, nothing below → unknown (0)
            assert np.allclose(lad[k:k + 4], profile, rtol=0, atol=0.1)
            assert np.all(lad[k + 4:] == 0.0)  # above the canopy: every pulse went through
    # the same with a callable ground and the low points taken as ground
    canopy2 = lad_from_points(xyz, is_ground, lambda x, y: ground[np.floor(x).astype(int), np.floor(y).astype(int)],
                              [0.0, 0.0, 0.0], [1.0, 1.0, dz], (2, 2, 12), min_height_m=0.0)
    assert np.array_equal(canopy.lad, canopy2.lad)
    # ... and with each point's ground height given, some points second returns (left out) and some off the grid
    numbers = rng.integers(1, 3, len(xyz))
    off = np.vstack([xyz, [[5.0, 0.5, 3.0], [-1.0, 0.5, 3.0]]])
    numbers, flags = np.r_[numbers, 1, 1], np.r_[is_ground, False, False]
    column = np.clip(np.floor(off[:, :2]).astype(int), 0, 1)
    per_point = np.r_[ground[column[:-2, 0], column[:-2, 1]], np.nan, np.nan]  # NaN: off the grid, never read
    by_point = lad_from_points(off, flags, per_point, [0.0, 0.0, 0.0], [1.0, 1.0, dz], (2, 2, 12), min_height_m=0.0,
                               return_number=numbers)
    by_grid = lad_from_points(off, flags, ground, [0.0, 0.0, 0.0], [1.0, 1.0, dz], (2, 2, 12), min_height_m=0.0,
                              return_number=numbers)
    assert np.array_equal(by_point.lad, by_grid.lad) and not np.array_equal(by_point.lad, canopy.lad)
    # P_gap = 0: a layer that stopped all n pulses reaching it takes half a pulse through: ln(2n) / (G dz)
    n = 100
    pts = np.column_stack([np.full(n, 0.5), np.full(n, 0.5), np.full(n, 3.5)])
    wall = lad_from_points(pts, np.zeros(n, bool), 0.0, [0, 0, 0], [1, 1, 1], (1, 1, 5))
    assert wall.lad[0, 0, 3] == pytest.approx(math.log(2 * n) / 0.5, rel=1e-6)
    assert np.all(wall.lad[0, 0, :3] == 0.0) and wall.lad[0, 0, 4] == 0.0
    capped = lad_from_points(pts, np.zeros(n, bool), 0.0, [0, 0, 0], [1, 1, 1], (1, 1, 5), max_lad=3.0)
    assert capped.lad[0, 0, 3] == 3.0
    # first returns only, when return numbers are given
    extra = np.vstack([pts, pts - [0, 0, 3.0]])
    numbers = np.r_[np.ones(n), np.full(n, 2)]
    only_first = lad_from_points(extra, np.zeros(2 * n, bool), 0.0, [0, 0, 0], [1, 1, 1], (1, 1, 5), return_number=numbers)
    assert np.array_equal(only_first.lad, wall.lad)


def test_macarthur_horn_bad_input():
    with pytest.raises(InputError, match="xyz_local"):
        lad_from_points(np.zeros((3, 2)), np.zeros(3, bool), 0.0, [0, 0, 0], [1, 1, 1])
    with pytest.raises(InputError, match="is_ground"):
        lad_from_points(np.zeros((3, 3)), np.zeros(2, bool), 0.0, [0, 0, 0], [1, 1, 1])
    with pytest.raises(InputError, match="scene.canopy.cell"):
        lad_from_points(np.zeros((3, 3)), np.zeros(3, bool), 0.0, [0, 0, 0], [1, 0, 1])
    with pytest.raises(InputError, match="ground_height"):
        lad_from_points(np.zeros((3, 3)), np.zeros(3, bool), np.zeros((4, 4)), [0, 0, 0], [1, 1, 1], (2, 2, 2))
    with pytest.raises(InputError, match=r"ground_height.*\(4,\) heights, one per point"):
        lad_from_points(np.zeros((4, 3)), np.zeros(4, bool), np.zeros(3), [0, 0, 0], [1, 1, 1], (2, 2, 2))
