"""The procedural forest: stand statistics, leaf area voxels, crown meshes, the scene kind and `flightsim forest`'s
truth products, each against closed forms or float64 math of the test's own."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

from flightsim.core.errors import InputError
from flightsim.scenes.forest import PlaneGround, StandSpec, Trees, grow_stand
from flightsim.scenes.forest_mesh import crown_template, ground_mesh, prism_template, stand_mesh
from flightsim.scenes.forest_scene import ForestSettings, forest_scene, stand
from flightsim.scenes import forest_voxels
from flightsim.scenes.forest_voxels import lai_map, stand_voxels
from flightsim.studies.forest_truth import canopy_cover, canopy_height_model

ROOT = Path(__file__).resolve().parents[1]
SPEC = StandSpec(size_m=200.0, stems_per_ha=400.0, min_spacing_m=3.0, height_m=20.0, height_sd_m=4.0,
                 crown_shape="ellipsoid", crown_ratio_radius=0.15, crown_length_ratio=0.5, lai=3.0)
SHAPE_FACTOR = {"cone": 1.0 / 3.0, "ellipsoid": 2.0 / 3.0, "cylinder": 1.0}  # volume / (π R² L)


def one_tree(shape, x=0.37, y=-0.21, height=7.3, crown_base=3.1, radius=2.2, base_z=0.0, size=20.0):
    return Trees(x=np.array([x]), y=np.array([y]), base_z=np.array([base_z]), height=np.array([height]),
                 crown_radius=np.array([radius]), crown_base=np.array([crown_base]), dbh=np.array([0.2]),
                 shape=shape, lad=1.0, size_m=size)


def min_distance(xy):
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    return d[np.triu_indices(len(xy), 1)].min()


# ------------------------------------------------------------------------------------------------
# the stand


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stem_count_is_within_poisson_error_of_the_target(seed):
    trees = grow_stand(SPEC, seed)
    expected = 400.0 * 4.0  # stems/ha × 4 ha
    assert abs(len(trees) - expected) < 4.0 * math.sqrt(expected)
    assert np.all(np.abs(trees.x) <= 100.0) and np.all(np.abs(trees.y) <= 100.0)


def test_stem_counts_over_many_seeds_have_the_poisson_mean_and_variance():
    spec = dataclasses.replace(SPEC, size_m=50.0)  # 100 stems expected
    counts = np.array([len(grow_stand(spec, seed)) for seed in range(200)])
    assert abs(counts.mean() - 100.0) < 4.0 * math.sqrt(100.0 / 200)
    assert counts.var(ddof=1) == pytest.approx(100.0, rel=0.35)


@pytest.mark.parametrize("stems, spacing", [(400.0, 3.0), (1000.0, 2.1)])
def test_minimum_spacing_is_honoured(stems, spacing):
    trees = grow_stand(dataclasses.replace(SPEC, size_m=120.0, stems_per_ha=stems, min_spacing_m=spacing), 5)
    assert min_distance(np.column_stack([trees.x, trees.y])) >= spacing
    assert abs(len(trees) - stems * 1.44) < 4.0 * math.sqrt(stems * 1.44)


def test_too_little_room_for_the_stems_is_refused():
    with pytest.raises(InputError, match="forest_min_spacing_m"):
        stand(ForestSettings(forest_stems_per_ha=2000.0, forest_min_spacing_m=3.0), 0)


def truncated_moments(mean, sd, lo, hi):
    a, b = (lo - mean) / sd, (hi - mean) / sd
    z = norm.cdf(b) - norm.cdf(a)
    m = mean + sd * (norm.pdf(a) - norm.pdf(b)) / z
    var = sd ** 2 * (1.0 + (a * norm.pdf(a) - b * norm.pdf(b)) / z - ((norm.pdf(a) - norm.pdf(b)) / z) ** 2)
    return m, math.sqrt(var)


@pytest.mark.parametrize("mean, sd", [(20.0, 4.0), (4.0, 4.0)])
def test_heights_have_the_truncated_normal_mean_and_sd(mean, sd):
    trees = grow_stand(dataclasses.replace(SPEC, size_m=500.0, height_m=mean, height_sd_m=sd), 3)
    n = len(trees)
    m, s = truncated_moments(mean, sd, 2.0, 80.0)
    assert trees.height.min() >= 2.0 and trees.height.max() <= 80.0
    assert abs(trees.height.mean() - m) < 4.0 * s / math.sqrt(n)
    assert trees.height.std() == pytest.approx(s, rel=4.0 / math.sqrt(2 * n))


def test_crowns_stems_and_ground_follow_the_settings():
    trees = grow_stand(dataclasses.replace(SPEC, crown_ratio_radius=0.2, crown_length_ratio=0.6), 4,
                       PlaneGround(0.1))
    assert trees.crown_radius == pytest.approx(0.2 * trees.height)
    assert trees.crown_base == pytest.approx(0.4 * trees.height)
    assert trees.base_z == pytest.approx(-0.1 * trees.y)
    # Jucker et al. (2017): D [cm] = 0.557 (H CD)^0.809 exp(0.056²/2)
    dbh_cm = 0.557 * (trees.height * 2.0 * trees.crown_radius) ** 0.809 * math.exp(0.056 ** 2 / 2.0)
    assert trees.dbh == pytest.approx(dbh_cm / 100.0, rel=1e-12)


def test_the_same_seed_gives_the_same_stand_and_another_seed_another():
    a, b, c = grow_stand(SPEC, 9), grow_stand(SPEC, 9), grow_stand(SPEC, 10)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.height, b.height)
    assert len(a) != len(c) or not np.array_equal(a.x, c.x)


# ------------------------------------------------------------------------------------------------
# voxels


def reference_volume(shape, tree, x0, x1, y0, y1, z0, z1):
    """Volume of the crown inside the box, by nested adaptive quadrature of the chord length (float64)."""
    cx, cy, zb = tree.x[0], tree.y[0], tree.base_z[0] + tree.crown_base[0]
    length, radius = tree.crown_length[0], tree.crown_radius[0]

    def r(z):
        t = (z - zb) / length
        return {"cone": radius * (1 - t), "ellipsoid": 2 * radius * math.sqrt(max(t * (1 - t), 0.0)),
                "cylinder": radius}[shape]

    def chord(x, rr):
        h2 = rr * rr - (x - cx) ** 2
        return 0.0 if h2 <= 0 else max(0.0, min(y1, cy + math.sqrt(h2)) - max(y0, cy - math.sqrt(h2)))

    def area(z):
        rr = r(z)
        lo, hi = max(x0, cx - rr), min(x1, cx + rr)
        return quad(chord, lo, hi, args=(rr,), epsabs=1e-13, limit=200)[0] if hi > lo else 0.0

    lo, hi = max(z0, zb), min(z1, zb + length)
    return quad(area, lo, hi, epsabs=1e-13, limit=200)[0] if hi > lo else 0.0


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
@pytest.mark.parametrize("shape", ["cone", "ellipsoid", "cylinder"])
def test_voxel_fractions_match_nested_quadrature(shape, voxels_on):
    tree = one_tree(shape)
    cell = 0.5
    lad, lower, cells = stand_voxels(tree, cell, voxels_on)
    assert np.all(cells == cell) and np.allclose(lower / cell, np.round(lower / cell))
    partial = np.argwhere((lad > 1e-3) & (lad < 0.999))
    picks = partial[np.random.default_rng(0).choice(len(partial), 8, replace=False)]
    for i, j, k in picks:
        x0, y0, z0 = lower + np.array([i, j, k]) * cell
        expected = reference_volume(shape, tree, x0, x0 + cell, y0, y0 + cell, z0, z0 + cell) / cell ** 3
        assert lad[i, j, k] == pytest.approx(expected, abs=2e-7)


@pytest.mark.parametrize("shape", ["cone", "ellipsoid", "cylinder"])
def test_voxel_leaf_area_is_the_analytic_crown_volume_times_lad(shape, voxels_on):
    trees = grow_stand(dataclasses.replace(SPEC, size_m=100.0, crown_shape=shape), 11, PlaneGround(0.2))
    lad, lower, cell = stand_voxels(trees, 1.0, voxels_on)
    analytic = trees.lad * np.sum(SHAPE_FACTOR[shape] * math.pi * trees.crown_radius ** 2 * trees.crown_length)
    leaf_area = lad.sum(dtype=np.float64) * np.prod(cell)
    assert lad.min() >= 0.0
    assert leaf_area == pytest.approx(analytic, rel=1e-5)  # the brief asks 0.5 %
    assert leaf_area / 100.0 ** 2 == pytest.approx(3.0, rel=1e-5)  # the stand LAI, within 1 % asked
    assert lai_map(lad, cell).sum() * cell[0] * cell[1] == pytest.approx(leaf_area, rel=1e-9)
    assert lower[2] <= (trees.base_z + trees.crown_base).min() and lad.shape[2] * cell[2] + lower[2] >= (
        trees.base_z + trees.height).max()


@pytest.mark.parametrize("lai", [0.5, 3.0, 7.0])
def test_stand_lai_achieved_is_the_target(lai):
    trees = stand(ForestSettings(forest_size_m=80.0, forest_lai=lai, forest_crown_shape="cone"), 2)
    lad, _, cell = stand_voxels(trees, 0.5)
    assert lad.sum(dtype=np.float64) * np.prod(cell) / 80.0 ** 2 == pytest.approx(lai, rel=0.01)


def test_a_cylinder_crown_fills_whole_voxels_exactly(voxels_on):
    tree = one_tree("cylinder", x=0.5, y=0.5, height=8.0, crown_base=3.0, radius=3.0)
    lad, lower, cell = stand_voxels(tree, 1.0, voxels_on)
    k = int(round((5.0 - lower[2]) / cell[2]))  # the layer from 5 to 6 m: wholly inside the crown's height
    i, j = (int(round((v - lower[n]) / cell[n])) for n, v in enumerate((0.0, 0.0)))
    assert lad[i, j, k] == pytest.approx(1.0, abs=1e-7)  # [0, 1]² lies within 3 m of (0.5, 0.5)
    # the column (3, 0)-(4, 1): the disc of radius 3 about (0.5, 0.5) over x in [3, 3.5], y in [0, 1]
    expected = quad(lambda x: min(1.0, 0.5 + math.sqrt(max(9.0 - (x - 0.5) ** 2, 0.0)))
                    - max(0.0, 0.5 - math.sqrt(max(9.0 - (x - 0.5) ** 2, 0.0))), 3.0, 3.5, epsabs=1e-13)[0]
    assert lad[i + 3, j, k] == pytest.approx(expected, abs=1e-7)


def test_crown_volumes_in_threads_are_the_serial_ones_bit_for_bit(monkeypatch):
    """Crowns of different chunks share voxels, so their float64 volumes must add up in the chunks' order whatever
    the threads: a chunk per crown in eight threads against one thread."""
    dense = dataclasses.replace(SPEC, size_m=25.0, stems_per_ha=2000.0, min_spacing_m=1.0, crown_ratio_radius=0.3)
    trees = grow_stand(dense, 5, PlaneGround(0.1))  # crowns overlapping three and more deep
    lower, shape = forest_voxels.voxel_grid(trees, 0.5)
    monkeypatch.setattr(forest_voxels, "_COLUMNS_PER_CHUNK", 1)
    monkeypatch.setattr(forest_voxels, "_THREADS", 1)
    serial = forest_voxels.crown_volumes(trees, lower, shape, 0.5)
    monkeypatch.setattr(forest_voxels, "_THREADS", 8)
    monkeypatch.setattr(forest_voxels.os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    threaded = forest_voxels.crown_volumes(trees, lower, shape, 0.5)
    assert len(forest_voxels._chunks(trees, lower, 0.5)) == len(trees)
    assert threaded.tobytes() == serial.tobytes()


@pytest.mark.parametrize("shape", ["cone", "ellipsoid", "cylinder"])
def test_the_device_integrates_the_hosts_voxels_to_float64_rounding(shape, device):
    """Overlapping crowns on a slope: the kernel's pieces, nodes and sums are the host's, so the densities agree
    to the rounding of float64 (a crown barely touching a voxel leaves ~1e-16 m²/m³ of cancellation either way)
    and most voxels are the same float32; a piece lost or misplaced would be off by 1e-6 or more."""
    dense = dataclasses.replace(SPEC, size_m=25.0, stems_per_ha=2000.0, min_spacing_m=1.0, crown_ratio_radius=0.3,
                                crown_shape=shape)
    trees = grow_stand(dense, 5, PlaneGround(0.3))
    for cell in (1.0, 0.35):
        host, lower, _ = stand_voxels(trees, cell)
        kernel, kernel_lower, _ = stand_voxels(trees, cell, device)
        assert kernel.shape == host.shape and kernel.dtype == np.float32 and np.array_equal(kernel_lower, lower)
        assert np.abs(kernel.astype(np.float64) - host).max() <= 1e-12 * host.max()
        assert np.mean(kernel == host) > 0.95 and np.count_nonzero(host) > 1000


@pytest.mark.parametrize("shape", ["cone", "ellipsoid", "cylinder"])
@pytest.mark.parametrize("case", ["on_faces", "tiny_crown", "tiny_voxels", "huge_voxel", "high_and_thin"])
def test_the_device_voxels_hold_in_degenerate_geometry(shape, case, device):
    """Crowns whose axis, radius, base and top lie exactly on voxel faces (the disc reaching sides and corners at
    the crown's ends: zero-length pieces, q = 1), a crown far smaller than its voxel, voxels of 5 cm, one voxel of
    20 m holding the crown, a 60 m tree 0.4 m wide: no NaN or negative density, the host's numbers, and the
    crown's analytic volume."""
    tree = {"on_faces": dict(x=1.0, y=-2.0, height=8.0, crown_base=3.0, radius=2.0),
            "tiny_crown": dict(x=0.31, y=0.77, height=2.2, crown_base=2.0, radius=0.01),
            "tiny_voxels": dict(x=0.013, y=-0.027, height=2.0, crown_base=1.0, radius=0.35),
            "huge_voxel": dict(x=3.1, y=4.7, height=9.0, crown_base=4.0, radius=2.5),
            "high_and_thin": dict(x=-0.5, y=0.5, height=60.0, crown_base=1.0, radius=0.2)}[case]
    cell = {"tiny_voxels": 0.05, "huge_voxel": 20.0}.get(case, 1.0)
    trees = one_tree(shape, **tree)
    host, lower, _ = stand_voxels(trees, cell)
    kernel, _, _ = stand_voxels(trees, cell, device)
    assert np.isfinite(kernel).all() and kernel.min() >= 0.0
    assert np.abs(kernel.astype(np.float64) - host).max() <= 1e-12 * host.max()
    volume = kernel.sum(dtype=np.float64) * cell ** 3 / trees.lad
    analytic = SHAPE_FACTOR[shape] * math.pi * tree["radius"] ** 2 * (tree["height"] - tree["crown_base"])
    assert volume == pytest.approx(analytic, rel=1e-5)


def test_the_device_lists_each_column_with_its_crowns_in_order():
    trees = one_tree("cone", x=0.37, y=-0.21, radius=1.2)
    two = dataclasses.replace(trees, **{k: np.append(getattr(trees, k), getattr(trees, k) + d) for k, d in
                                        (("x", 1.0), ("y", 0.0), ("base_z", 0.0), ("height", 0.0),
                                         ("crown_radius", 0.0), ("crown_base", 0.0), ("dbh", 0.0))})
    lower, shape = forest_voxels.voxel_grid(two, 1.0)
    columns, first, members = forest_voxels.column_trees(two, lower, shape, 1.0)
    # tree 0's box: x in [-0.83, 1.57] → i 0..2 of the grid from x = -1; y in [-1.41, 0.99] → j 0..2; tree 1 x + 1
    boxes = {0: {(i, j) for i in range(3) for j in range(3)}, 1: {(i, j) for i in range(1, 4) for j in range(3)}}
    listed = {(int(c) // shape[1], int(c) % shape[1]): members[first[n]:first[n + 1]].tolist()
              for n, c in enumerate(columns)}
    assert listed == {ij: [t for t in (0, 1) if ij in boxes[t]] for ij in boxes[0] | boxes[1]}
    assert np.all(np.diff(columns) > 0) and lower[0] == -1.0 and lower[1] == -2.0


@pytest.mark.parametrize("r", [0.3, 1.0, 2.7])
def test_disc_square_area_has_the_closed_forms_of_discs_squares_and_segments(r):
    big = 4.0 * r
    cases = {(-big, big, -big, big): math.pi * r * r,  # the disc inside
             (0.0, big, 0.0, big): math.pi * r * r / 4.0,  # a quadrant
             (-big, big, 0.0, big): math.pi * r * r / 2.0,  # a half
             (-0.3 * r, 0.4 * r, -0.2 * r, 0.5 * r): 0.7 * r * 0.7 * r,  # a rectangle inside the disc
             (1.1 * r, big, -big, big): 0.0}  # beside it
    for d in (0.25, 0.6, 0.95):  # the circular segment beyond x = d·r: r² acos(d) − d·r · r√(1 − d²)
        cases[(d * r, big, -big, big)] = r * r * (math.acos(d) - d * math.sqrt(1.0 - d * d))
    for (x0, x1, y0, y1), expected in cases.items():
        got = forest_voxels.disc_square_area(np.array([r]), *(np.array([v]) for v in (x0, x1, y0, y1)))
        assert got[0] == pytest.approx(expected, rel=1e-13, abs=1e-15 * r * r), (x0, x1, y0, y1)


# ------------------------------------------------------------------------------------------------
# canopy height model and cover


def test_chm_is_the_tree_height_at_a_cone_apex_and_the_cone_beside_it():
    xs, ys, hs = np.array([-2.5, 3.5]), np.array([1.5, -3.5]), np.array([12.0, 17.0])
    trees = Trees(x=xs, y=ys, base_z=np.zeros(2), height=hs, crown_radius=np.array([2.0, 3.0]),
                  crown_base=hs / 2, dbh=np.full(2, 0.2), shape="cone", lad=1.0, size_m=12.0)
    heights, west, north = canopy_height_model(trees, 1.0)
    assert (west, north) == (-6.0, 6.0) and heights.shape == (12, 12)

    def at(x, y):
        return heights[int(north - y), int(x - west)]

    assert at(-2.5, 1.5) == 12.0 and at(3.5, -3.5) == 17.0
    # the cell east of the first apex: nearest point 0.5 m from the axis; cone top = base + L (1 − ρ/R)
    assert at(-1.5, 1.5) == pytest.approx(6.0 + 6.0 * (1 - 0.5 / 2.0))
    # diagonal neighbour: nearest point is the shared corner, √0.5 m away
    assert at(-1.5, 2.5) == pytest.approx(6.0 + 6.0 * (1 - math.sqrt(0.5) / 2.0))
    assert at(5.5, 5.5) == 0.0  # no crown reaches


@pytest.mark.parametrize("shape", ["ellipsoid", "cylinder", "cone"])
def test_chm_is_the_highest_crown_point_over_each_cell(shape):
    trees = grow_stand(dataclasses.replace(SPEC, size_m=30.0, crown_shape=shape), 6)
    heights, west, north = canopy_height_model(trees, 1.0)
    u = np.linspace(0.0, 1.0, 21)
    for row, col in np.random.default_rng(1).integers(0, 30, (25, 2)):
        x0, y0 = west + col, north - row - 1
        px, py = (g.ravel() for g in np.meshgrid(x0 + u, y0 + u))
        sampled, best = 0.0, 0.0
        for i in range(len(trees)):
            nearest = np.clip(trees.x[i], x0, x0 + 1.0), np.clip(trees.y[i], y0, y0 + 1.0)
            qx, qy = np.append(px, nearest[0]), np.append(py, nearest[1])
            rho = np.hypot(qx - trees.x[i], qy - trees.y[i])
            t = np.minimum(rho / trees.crown_radius[i], 1.0)
            top = {"cone": 1 - t, "ellipsoid": 0.5 + 0.5 * np.sqrt(1 - t * t), "cylinder": np.ones_like(t)}[shape]
            surface = np.where(rho <= trees.crown_radius[i], trees.crown_base[i] + trees.crown_length[i] * top, 0.0)
            sampled, best = max(sampled, surface[:-1].max()), max(best, surface.max())
        assert heights[row, col] >= sampled - 1e-9  # no sample of the cell is higher
        assert heights[row, col] == pytest.approx(best, abs=1e-9)  # the cell's point nearest an axis is the top


def test_canopy_cover_matches_a_monte_carlo_union_of_crown_discs():
    from scipy.spatial import cKDTree

    trees = grow_stand(dataclasses.replace(SPEC, size_m=100.0, stems_per_ha=250.0), 8)
    points = np.random.default_rng(42).uniform(-50.0, 50.0, (400_000, 2))
    covered = np.zeros(len(points), dtype=bool)
    for hits in cKDTree(points).query_ball_point(np.column_stack([trees.x, trees.y]), trees.crown_radius):
        covered[hits] = True
    mc = covered.mean()
    assert 0.3 < mc < 0.95
    assert canopy_cover(trees) == pytest.approx(mc, abs=4.0 * math.sqrt(mc * (1 - mc) / len(points)) + 1e-4)


# ------------------------------------------------------------------------------------------------
# meshes and the scene


def closed_and_outward(vertices, triangles):
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    forward = {tuple(e) for e in edges.tolist()}
    assert len(forward) == len(edges) and all((b, a) in forward for a, b in forward)  # each edge twice, opposed
    v = vertices[triangles]
    return np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0  # signed volume


@pytest.mark.parametrize("segments", [4, 12, 33])
def test_crown_templates_are_closed_outward_polyhedra_of_the_right_volume(segments):
    polygon = segments / (2 * math.pi) * math.sin(2 * math.pi / segments)  # inscribed polygon area / π
    assert closed_and_outward(*crown_template("cone", segments)) == pytest.approx(math.pi * polygon / 3.0)
    assert closed_and_outward(*crown_template("cylinder", segments)) == pytest.approx(math.pi * polygon)
    assert closed_and_outward(*prism_template(segments, bottom=True)) == pytest.approx(math.pi * polygon)
    # the spheroid's: frusta between rings of latitude (aligned regular polygons: planar sides), h/3 (A + B + √AB)
    polar = math.pi * np.arange(segments // 2 + 1) / (segments // 2)
    z, area = 0.5 + 0.5 * np.cos(polar), math.pi * polygon * np.sin(polar) ** 2
    frusta = np.sum((z[:-1] - z[1:]) / 3 * (area[:-1] + area[1:] + np.sqrt(area[:-1] * area[1:])))
    assert closed_and_outward(*crown_template("ellipsoid", segments)) == pytest.approx(frusta)


def test_stand_mesh_places_stems_and_crowns_and_labels_them_by_tree():
    trees = grow_stand(dataclasses.replace(SPEC, size_m=30.0, crown_shape="cone"), 1, PlaneGround(0.3))
    n = len(trees)
    mesh = stand_mesh(trees, 8, crowns=True, ground=PlaneGround(0.3))
    assert set(np.unique(mesh.part)) == set(range(1, 2 * n + 1)) and set(mesh.classification) == {5}
    for i in (0, n - 1):
        crown = mesh.vertices[np.unique(mesh.triangles[mesh.part == 1 + n + i])]
        assert crown[:, 2].max() == pytest.approx(trees.base_z[i] + trees.height[i])  # the apex
        assert np.hypot(crown[:, 0] - trees.x[i], crown[:, 1] - trees.y[i]).max() == pytest.approx(
            trees.crown_radius[i])
        stem = mesh.vertices[np.unique(mesh.triangles[mesh.part == 1 + i])]
        assert stem[:, 2].max() == pytest.approx(trees.base_z[i] + trees.crown_base[i])
        foot = stem[stem[:, 2] < trees.base_z[i]]
        assert len(foot) == 8 and np.all(foot[:, 2] < -0.3 * foot[:, 1])  # every foot vertex below the ground
    ground = ground_mesh(PlaneGround(0.3), 40.0)
    assert ground.vertices[:, 2] == pytest.approx(-0.3 * ground.vertices[:, 1])


class _Section:
    """A [scene] as the scene kind sees it: common and forest settings."""

    def __init__(self, **forest):
        self.__dict__.update(crs="EPSG:32648", origin=(409000.0, 3393000.0, 450.0), margin_m=50.0)
        self.__dict__.update(dataclasses.asdict(ForestSettings(**forest)))


def test_forest_scene_holds_ground_stems_and_mesh_crowns():
    s = _Section(forest_size_m=40.0, forest_crowns="mesh", forest_segments=6)
    scene = forest_scene(s, 30.0, 3)
    trees = stand(s, 3)
    n = len(trees)
    assert scene.name == "forest" and not scene.planar and scene.canopy is None
    assert len(scene.planes) == 1 + 2 * n and scene.plane_id.max() == 2 * n
    assert set(scene.classification[scene.plane_id == 0]) == {2}
    assert set(scene.classification[scene.plane_id > 0]) == {5}
    lo, hi = scene.bounds()
    assert lo[:2] == pytest.approx([-70.0, -70.0]) and hi[2] == pytest.approx(trees.height.max())


def test_forest_scene_with_voxel_crowns_carries_the_stand_canopy():
    s = _Section(forest_size_m=40.0, forest_leaf_angles="planophile", forest_voxel_m=0.5)
    scene = forest_scene(s, 200.0, 3)
    lad, lower, cell = stand_voxels(stand(s, 3), 0.5)
    assert scene.plane_id.max() == len(stand(s, 3))  # stems only in the mesh
    assert np.array_equal(scene.canopy.lad, lad) and np.array_equal(scene.canopy.lower, lower)
    assert np.array_equal(scene.canopy.cell, [0.5, 0.5, 0.5])
    assert scene.canopy.leaf_reflectance == 0.45 and scene.canopy.leaf_angles == "planophile"
    assert forest_scene(_Section(forest_size_m=40.0, forest_lai=0.0), 200.0, 3).canopy is None


# ------------------------------------------------------------------------------------------------
# the command line


def flightsim(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "flightsim", *args], capture_output=True, text=True, env=env,
                          timeout=600)


def test_cli_writes_the_four_truth_files_identically_for_the_same_seed(tmp_path):
    import rasterio

    args = ["--set", "scene.forest_size_m=40", "--set", "scene.forest_slope=0.1", "--seed", "4"]
    first, second = flightsim("forest", *args, "--out", str(tmp_path / "a")), flightsim("forest", *args, "--out",
                                                                                           str(tmp_path / "b"))
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    for name in ("chm.tif", "trees.csv", "canopy.npz", "forest.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    info = json.loads((tmp_path / "a" / "forest.json").read_text())
    rows = (tmp_path / "a" / "trees.csv").read_text().splitlines()
    assert info["stems"] == len(rows) - 1 and info["seed"] == 4 and info["settings"]["forest_slope"] == 0.1
    assert info["lai_achieved"] == pytest.approx(3.0, rel=1e-5) and 0.0 < info["canopy_cover"] < 1.0
    with rasterio.open(tmp_path / "a" / "chm.tif") as chm:
        assert chm.crs.to_epsg() == 32648 and chm.shape == (40, 40)
        assert (chm.bounds.left, chm.bounds.top) == (409000.0 - 20.0, 3393000.0 + 20.0)
        assert chm.read(1).max() == pytest.approx(max(float(r.split(",")[4]) for r in rows[1:]), abs=1e-4)
    from flightsim.scenes.canopy_io import read_canopy

    read = read_canopy(tmp_path / "a" / "canopy.npz", "EPSG:32648", (409000.0, 3393000.0, 450.0))
    built = forest_scene(_Section(forest_size_m=40.0, forest_slope=0.1), 30.0, 4).canopy
    assert np.array_equal(read.lad, built.lad) and read.lower == pytest.approx(built.lower, abs=1e-9)
    assert (read.leaf_angles, read.leaf_reflectance, read.leaf_transmittance) == ("spherical", 0.45, 0.45)
    canopy = np.load(tmp_path / "a" / "canopy.npz")
    assert canopy["lad"].dtype == np.float32 and "PROJCRS" in str(canopy["crs"])
    assert canopy["lad"].sum(dtype=np.float64) * np.prod(canopy["cell"]) / 40.0 ** 2 == pytest.approx(3.0, rel=1e-5)
    assert canopy["lower_world"][0] <= 409000.0 - 20.0 + 3.0  # some crown reaches within 3 m of the stand's west


@pytest.mark.parametrize("setting, field", [
    ("scene.forest_lai=-1", "scene.forest_lai"),
    ("scene.forest_stems_per_ha=0", "scene.forest_stems_per_ha"),
    ("scene.forest_height_sd_m=-0.5", "scene.forest_height_sd_m"),
    ("scene.forest_size_m=20000", "scene.forest_size_m"),
    ("scene.forest_crown_shape=sphere", "scene.forest_crown_shape"),
])
def test_cli_refuses_bad_forest_settings_in_one_line(tmp_path, setting, field):
    result = flightsim("forest", "--set", setting, "--out", str(tmp_path / "out"))
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and field in lines[0] and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("device, allowed", [("gpu", "cpu, cuda or cuda:N"), ("cuda:7", "a device present")])
def test_cli_refuses_a_device_to_integrate_on_in_one_line(tmp_path, device, allowed):
    result = flightsim("forest", "--set", "scene.forest_size_m=20", "--device", device, "--out", str(tmp_path / "out"))
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and "run.device" in lines[0] and allowed in lines[0]
    assert not (tmp_path / "out").exists()


def test_cli_refuses_an_output_under_a_file(tmp_path):
    (tmp_path / "taken").write_text("not a directory")
    result = flightsim("forest", "--set", "scene.forest_size_m=20", "--out", str(tmp_path / "taken" / "out"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "--out" in result.stderr


def test_config_lists_the_forest_settings():
    result = flightsim("config", "--set", "scene.name=forest")
    assert result.returncode == 0, result.stderr
    for name in (f.name for f in dataclasses.fields(ForestSettings)):
        assert f"\n{name} = " in result.stdout
