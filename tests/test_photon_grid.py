"""Photons to points (per-cell height histograms) and point-to-truth distances, against synthetic
photons of known surfaces."""
from __future__ import annotations

import math

import numpy as np
import pytest

from flightsim.scoring.photon_grid import angle_cells, grid_points, xy_cells
from flightsim.scoring.surface import signed_distances
from flightsim.scenes.plane import plane_scene


def _photons(rng, cells=40, signal=8, noise=30, sigma=0.05, slope=0.1):
    """Signal photons on z = slope·x + N(0, σ) and uniform noise over ±50 m, in cells of 1 m."""
    x = rng.uniform(0, cells, (cells * cells * signal))
    y = rng.uniform(0, cells, x.size)
    z = slope * x + rng.normal(0, sigma, x.size)
    nx, ny = rng.uniform(0, cells, cells * cells * noise), rng.uniform(0, cells, cells * cells * noise)
    nz = rng.uniform(-50, 50, nx.size)
    return np.column_stack([np.concatenate([x, nx]), np.concatenate([y, ny]), np.concatenate([z, nz])])


def test_peak_of_each_cell_recovers_the_surface():
    rng = np.random.default_rng(0)
    sigma, slope = 0.05, 0.1
    xyz = _photons(rng, sigma=sigma, slope=slope)
    grid = grid_points(xyz, xy_cells(xyz, 1.0), bin_m=0.2, min_count=4, window_m=0.2)
    from scipy.stats import poisson

    found = poisson.sf(3, 8)  # a cell's 8 expected signal photons reach the 4 needed (noise only adds)
    assert len(grid.points) / 1600 > found - 4 * math.sqrt(found * (1 - found) / 1600)
    residual = grid.points[:, 2] - slope * grid.points[:, 0]
    wrong = np.abs(residual) > 0.2  # a background pile-up beat a weak echo
    assert wrong.mean() < 0.005
    residual = residual[~wrong]
    # each point averages ~8 signal photons (and ~0.1 noise photons in its 0.4 m window)
    assert abs(residual.mean()) < 4 * sigma / math.sqrt(len(residual) * 6)
    assert residual.std() < 1.5 * sigma / math.sqrt(6)
    assert (grid.photons >= 4).all()


def test_background_alone_is_rejected():
    rng = np.random.default_rng(1)
    noise = np.column_stack([rng.uniform(0, 40, 48000), rng.uniform(0, 40, 48000), rng.uniform(-50, 50, 48000)])
    grid = grid_points(noise, xy_cells(noise, 1.0), bin_m=0.2, min_count=4, window_m=0.2)
    # 30 photons over 500 bins per cell: P(a bin holds ≥ 4) ≈ 500 · P(Poisson(0.06) ≥ 4) ≈ 2e-3 per cell
    assert len(grid.points) <= 10
    assert grid.cells == 1600


def test_signed_distance_to_a_plane():
    scene = plane_scene(50.0)
    pts = np.array([[0.0, 0.0, 1.5], [10.0, -3.0, -0.25], [-20.0, 7.0, 0.0]])
    assert signed_distances(scene, pts) == pytest.approx([1.5, -0.25, 0.0], abs=1e-5)
    tilted = plane_scene(50.0, slope=0.5)  # z = −0.5·y
    d = signed_distances(tilted, np.array([[0.0, 0.0, 1.0]]))
    assert d[0] == pytest.approx(1.0 / math.sqrt(1.25), abs=1e-5)


def test_angle_cells_follow_the_beam_not_the_range():
    a = np.radians(np.array([[-3.0, 0.0], [0.0, 0.0], [3.2, -3.2], [3.3, 0.0]]))
    d = np.column_stack([np.tan(a[:, 0]), np.tan(a[:, 1]), -np.ones(4)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cells = angle_cells(np.concatenate([d, d * 7.0]), math.radians(3.25), 1100)  # any length along the beam
    assert (cells[:4] == cells[4:]).all()
    assert cells[1].tolist() == [550, 550]
    assert cells[0, 0] == math.floor((3.25 - 3.0) / 6.5 * 1100)
    assert (cells[3] == -1).all()  # outside the field


def _reference_grid(xyz, cells, bin_m, min_count, window_m):
    """Cell by cell in plain Python (float64): the rule of flightsim.scoring.photon_grid, written out."""
    ok = [i for i in range(len(xyz)) if np.isfinite(xyz[i]).all() and cells[i][0] >= 0 and cells[i][1] >= 0]
    lo = min(xyz[i][2] for i in ok)
    stride = math.floor((max(xyz[i][2] for i in ok) - lo) / bin_m) + 2
    by_cell = {}
    for i in ok:
        by_cell.setdefault((int(cells[i][1]), int(cells[i][0])), []).append(i)
    points = {}
    for (row, col), members in sorted(by_cell.items()):
        bins = {}
        for i in members:
            b = math.floor((xyz[i][2] - lo) / bin_m)
            bins[b] = bins.get(b, 0) + 1
        pairs = sorted(bins)
        window, low = max((bins[b] + bins.get(b + 1, 0), -b) for b in pairs)
        background = 2.0 * max(len(members) - window, 0) / max(stride - 1, 1)
        if window < max(min_count, background + 5.0 * math.sqrt(background)):
            continue
        centre = lo + (-low + 1) * bin_m
        for _ in range(2):
            near = [i for i in members if abs(xyz[i][2] - centre) <= window_m]
            if near:
                centre = sum(xyz[i][2] for i in near) / len(near)
        if near:
            points[(col, row)] = (np.mean(xyz[near], axis=0), len(near), window)
    return points, len(by_cell)


def test_device_gridding_matches_a_cell_by_cell_reference():
    rng = np.random.default_rng(7)
    n = 6000
    cells = rng.integers(0, 12, (n, 2))
    cells[rng.random(n) < 0.02] = -1  # outside the field
    z = np.where(rng.random(n) < 0.6, 0.3 * cells[:, 0] + rng.normal(0, 0.04, n), rng.uniform(-20, 20, n))
    xyz = np.column_stack([cells[:, 0] + rng.random(n), cells[:, 1] + rng.random(n), z])
    xyz[rng.random(n) < 0.01, 2] = np.nan
    # a tie: two pairs of bins of equal count in cell (11, 11); the lower one wins
    tie = np.column_stack([np.full(10, 11.5), np.full(10, 11.5), np.r_[np.full(5, 30.05), np.full(5, 35.05)]])
    xyz, cells = np.vstack([xyz, tie]), np.vstack([cells, np.full((10, 2), 11)])
    cells[(cells[:, 0] == 11) & (cells[:, 1] == 11) & (xyz[:, 2] < 30)] = 10
    expected, occupied = _reference_grid(xyz, cells, 0.1, 4, 0.12)
    grid = grid_points(xyz, cells, bin_m=0.1, min_count=4, window_m=0.12)
    assert grid.cells == occupied
    assert [tuple(c) for c in grid.cell] == sorted(expected, key=lambda c: (c[1], c[0]))
    for point, cell, photons, peak in zip(grid.points, grid.cell, grid.photons, grid.peak):
        mean, count, window = expected[tuple(cell)]
        assert (photons, peak) == (count, window)
        assert point == pytest.approx(mean, abs=1e-9)
    assert grid.points[-1][2] == pytest.approx(30.05, abs=1e-9)  # the tie: the lower pair
