"""The built-in small-body scenes: the 12 m sandbox heightfield and the closed ellipsoid body,
checked against independent geometry (bounds, cell areas, closed-surface volume and area)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from flightsim.core.errors import InputError
from flightsim.scenes import smallbody
from flightsim.scenes.smallbody import ellipsoid_scene, sandbox_scene


def _cross(scene) -> np.ndarray:
    """(T, 3) cross(b − a, c − a) of every triangle: twice its area along its normal [m²]."""
    v = scene.vertices[scene.triangles]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


def _ellipsoid_radius(direction: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """Distance [m] from the centre to the ellipsoid surface along unit ``direction`` (N, 3)."""
    return 1.0 / np.sqrt((direction[:, 0] / a) ** 2 + (direction[:, 1] / b) ** 2 + (direction[:, 2] / c) ** 2)


# ------------------------------------------------------------------------------------------- sandbox

def test_sandbox_is_a_12_m_heightfield_of_half_cells():
    scene = sandbox_scene(seed=3, cell_m=0.05)
    nodes = 241  # 12 m / 0.05 m + 1
    assert scene.name == "sandbox" and len(scene.vertices) == nodes ** 2
    assert len(scene.triangles) == 2 * (nodes - 1) ** 2
    lo, hi = scene.bounds()
    assert lo[:2] == pytest.approx([-6.0, -6.0], abs=1e-12) and hi[:2] == pytest.approx([6.0, 6.0], abs=1e-12)
    normal_z = _cross(scene)[:, 2]
    assert (normal_z > 0).all()  # counter-clockwise from +z: no overhangs
    assert normal_z == pytest.approx(np.full(len(normal_z), 0.05 ** 2), abs=1e-12)  # 2·area = one cell
    z = scene.vertices[:, 2].reshape(nodes, nodes)
    assert scene.vertices[nodes * 120 + 120, :2] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert scene.ground_z == z[120, 120]


def test_sandbox_labels_and_reflectance():
    scene = sandbox_scene(cell_m=0.1)
    assert len(scene.planes) == 1 and scene.planes[0].kind == "surface" and scene.planes[0].classification == 2
    assert (scene.plane_id == 0).all() and (scene.classification == 2).all()
    assert smallbody.SANDBOX_REFLECTANCE == 0.2


def test_sandbox_heights_are_sane():
    z = sandbox_scene(seed=5, cell_m=0.03).vertices[:, 2]
    assert np.isfinite(z).all()
    assert 0.005 < z.std() < 0.5
    # (this seed has no deep crater overlaps) deepest point: about a 3 m crater's floor (0.16 D
    # below the surroundings) plus roughness; highest: a 0.8 m boulder (0.4 m) on a 3 m rim (0.12 m)
    assert z.min() > -0.16 * 3.0 - 0.1 and z.max() < 0.4 + 0.12 + 0.1


def test_sandbox_has_boulders_and_craters_in_their_size_ranges():
    rng = np.random.default_rng(11)
    craters = smallbody._sandbox_craters(rng, 60.0)  # a 120 m square: many of each
    boulders = smallbody._sandbox_boulders(rng, 60.0)
    d = np.array([c[2] for c in craters])
    assert d.min() >= 0.3 and d.max() <= 3.0 and (np.diff(d) <= 0).all()
    area = 120.0 ** 2
    expected = smallbody.SANDBOX_CRATER_K * area * (1.0 ** -2 - 3.0 ** -2)
    assert (d > 1.0).sum() == pytest.approx(expected, rel=5 / math.sqrt(expected))
    b = np.array([c[2] for c in boulders])
    assert b.min() >= 0.1 and b.max() <= 0.8
    expected = smallbody.SANDBOX_BOULDER_K * area * (2.0 ** -2.5 - 8.0 ** -2.5)  # 0.2 m < D ≤ 0.8 m
    assert (b > 0.2).sum() == pytest.approx(expected, rel=5 / math.sqrt(expected))


def test_sandbox_seed_repeats_and_varies():
    a, b, c = (sandbox_scene(seed=s, cell_m=0.1).vertices for s in (1, 1, 2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_sandbox_grid_is_odd_and_capped():
    assert len(sandbox_scene(size_m=12.0, cell_m=0.08).vertices) == 151 ** 2  # 12 / 0.08 + 1 = 151
    assert len(sandbox_scene(size_m=12.0, cell_m=0.1).vertices) == 121 ** 2
    assert len(sandbox_scene(size_m=11.9, cell_m=0.1).vertices) == 121 ** 2  # 120 nodes → 121
    assert len(sandbox_scene(size_m=100.0, cell_m=0.02).vertices) == smallbody.MAX_NODES ** 2


@pytest.mark.parametrize("kwargs, field", [
    ({"size_m": 0.0}, "scene.size_m"), ({"size_m": float("nan")}, "scene.size_m"),
    ({"size_m": "big"}, "scene.size_m"), ({"cell_m": 0.0}, "scene.cell_m"),
    ({"cell_m": 2.0}, "scene.cell_m"), ({"cell_m": float("inf")}, "scene.cell_m"),
])
def test_bad_sandbox_parameters_name_the_field(kwargs, field):
    with pytest.raises(InputError, match=field):
        sandbox_scene(**kwargs)


# ----------------------------------------------------------------------------------------- ellipsoid

def test_icosphere_counts():
    for n in range(4):
        v, t = smallbody.icosphere(n)
        assert len(v) == 10 * 4 ** n + 2 and len(t) == 20 * 4 ** n
        assert np.linalg.norm(v, axis=1) == pytest.approx(np.ones(len(v)))


def test_ellipsoid_is_closed_and_outward():
    scene = ellipsoid_scene(seed=4, subdivisions=4)
    t = scene.triangles.astype(np.int64)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    n = len(scene.vertices)
    directed_keys = directed[:, 0] * n + directed[:, 1]
    assert len(np.unique(directed_keys)) == len(directed)  # consistent winding: no directed edge twice
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    assert (counts == 2).all()  # every edge shared by exactly two triangles
    assert len(scene.vertices) - len(counts) + len(t) == 2  # Euler characteristic of a sphere
    centroid = scene.vertices[scene.triangles].mean(axis=1)
    assert (np.einsum("ij,ij->i", _cross(scene), centroid) > 0).all()


def test_ellipsoid_vertices_lie_on_the_body_within_the_roughness():
    a, b, c, rough = 250.0, 120.2, 120.2, 0.5
    scene = ellipsoid_scene(seed=1)
    v = scene.vertices
    assert len(v) == 40962 and len(scene.triangles) == 81920
    r = np.linalg.norm(v, axis=1)
    offset = r - _ellipsoid_radius(v / r[:, None], a, b, c)
    assert np.abs(offset).max() <= 5 * rough
    assert math.sqrt(np.mean(offset ** 2)) == pytest.approx(rough, rel=1e-6)
    assert abs(offset.mean()) < 1e-9
    lo, hi = scene.bounds()
    assert hi == pytest.approx([a, b, c], abs=5 * rough) and lo == pytest.approx([-a, -b, -c], abs=5 * rough)
    assert scene.ground_z == c and scene.name == "ellipsoid"
    assert scene.planes[0].kind == "surface" and (scene.classification == 2).all() and (scene.plane_id == 0).all()


def test_smooth_ellipsoid_is_exactly_on_the_surface():
    a, b, c = 300.0, 150.0, 100.0
    v = ellipsoid_scene(a_m=a, b_m=b, c_m=c, roughness_m=0.0, subdivisions=3).vertices
    assert (v[:, 0] / a) ** 2 + (v[:, 1] / b) ** 2 + (v[:, 2] / c) ** 2 == pytest.approx(np.ones(len(v)), abs=1e-12)


def _volume_and_area(scene) -> tuple[float, float]:
    """Enclosed volume (sum of signed tetrahedra with the origin) [m³] and surface area [m²]."""
    v = scene.vertices[scene.triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    return float(volume), float(0.5 * np.linalg.norm(_cross(scene), axis=1).sum())


@pytest.mark.parametrize("a, b, c", [(250.0, 120.2, 120.2), (300.0, 150.0, 100.0), (100.0, 100.0, 100.0)])
def test_smooth_ellipsoid_volume_and_area(a, b, c):
    volume, area = _volume_and_area(ellipsoid_scene(a_m=a, b_m=b, c_m=c, roughness_m=0.0, subdivisions=5))
    assert volume == pytest.approx(4.0 / 3.0 * math.pi * a * b * c, rel=0.01)
    p = 1.6075  # Knud Thomsen's approximation (≤ 1.061 % off)
    thomsen = 4.0 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)
    assert area == pytest.approx(thomsen, rel=0.01)


def test_smooth_prolate_area_matches_the_closed_form():
    a, b = 250.0, 120.2
    e = math.sqrt(1.0 - (b / a) ** 2)
    exact = 2.0 * math.pi * b * b * (1.0 + a / (b * e) * math.asin(e))
    _, area = _volume_and_area(ellipsoid_scene(a_m=a, b_m=b, c_m=b, roughness_m=0.0))
    assert area == pytest.approx(exact, rel=2e-3)  # the inscribed mesh is slightly smaller
    assert area < exact


def test_rough_ellipsoid_volume_barely_changes():
    smooth, _ = _volume_and_area(ellipsoid_scene(roughness_m=0.0, subdivisions=5))
    rough, _ = _volume_and_area(ellipsoid_scene(roughness_m=0.5, subdivisions=5, seed=2))
    assert rough == pytest.approx(smooth, rel=0.01)


def test_ellipsoid_seed_repeats_and_varies():
    a, b, c = (ellipsoid_scene(seed=s, subdivisions=3).vertices for s in (1, 1, 2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.mark.parametrize("kwargs, field", [
    ({"a_m": 0.0}, "scene.a_m"), ({"b_m": -1.0}, "scene.b_m"), ({"c_m": float("nan")}, "scene.c_m"),
    ({"subdivisions": -1}, "scene.subdivisions"), ({"subdivisions": 9}, "scene.subdivisions"),
    ({"subdivisions": 2.5}, "scene.subdivisions"), ({"subdivisions": True}, "scene.subdivisions"),
    ({"roughness_m": -0.1}, "scene.roughness_m"), ({"roughness_m": 50.0}, "scene.roughness_m"),
])
def test_bad_ellipsoid_parameters_name_the_field(kwargs, field):
    with pytest.raises(InputError, match=field):
        ellipsoid_scene(**kwargs)
