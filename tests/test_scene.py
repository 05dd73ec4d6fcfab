"""Tests of flightsim.scenes.scene and flightsim.scenes.meshio.

Geometry is checked against independent math: normals recomputed from the triangles, areas
and volumes from closed forms, mesh files written here with struct (not with the code under test).
"""
from __future__ import annotations

import math
import struct
from collections import Counter

import numpy as np
import pyproj
import pytest

from flightsim.core.errors import InputError
from flightsim.scenes.meshio import load_mesh, save_obj
from flightsim.scenes.calibration import calibration_houses, calibration_min_half_extent, calibration_scene
from flightsim.scenes.plane import plane_scene
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, Scene, parse_crs, plane_info, required_half_extent
from flightsim.scenes.triangulate import triangulate_polygon_with_holes

HALF = 400.0


@pytest.fixture(scope="module")
def field() -> Scene:
    return calibration_scene(HALF)


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (right-hand rule) and areas of triangles."""
    p = vertices[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(cross, axis=1)
    return cross / length[:, None], 0.5 * length


def directed_edges(triangles: np.ndarray) -> np.ndarray:
    return np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])


def position_keys(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles re-indexed by vertex position (rounded to 1 µm), independent of the mesh indexing."""
    _, index = np.unique(np.round(vertices, 6), axis=0, return_inverse=True)
    return index.reshape(-1)[triangles]


# --------------------------------------------------------------------------------------------
# Calibration field
# --------------------------------------------------------------------------------------------

def test_every_plane_matches_its_triangles(field):
    normals, _ = triangle_normals(field.vertices, field.triangles)
    assert len(np.unique(field.plane_id)) == len(field.planes)
    for plane in field.planes:
        rows = field.plane_id == plane.id
        assert np.allclose(normals[rows], plane.normal, atol=1e-9), plane
        corners = field.vertices[field.triangles[rows]].reshape(-1, 3)
        assert np.max(np.abs((corners - plane.point) @ plane.normal)) < 1e-9, plane
        n = plane.normal
        assert plane.pitch_deg == pytest.approx(math.degrees(math.acos(min(1.0, abs(n[2])))), abs=1e-7)
        if plane.pitch_deg > 1e-6:
            assert plane.azimuth_deg == pytest.approx(math.degrees(math.atan2(n[0], n[1])) % 360.0, abs=1e-7)
        else:
            assert math.isnan(plane.azimuth_deg)
        assert np.all(field.classification[rows] == plane.classification)


def test_plane_kinds_classes_and_counts(field):
    kinds = Counter(p.kind for p in field.planes)
    buildings = {p.building for p in field.planes if p.building >= 0}
    assert len(buildings) >= 16
    assert kinds["ground"] == 1 and kinds["road"] == 2
    assert kinds["roof"] == 2 * len(buildings) and kinds["wall"] == 4 * len(buildings)
    expected_class = {"ground": 2, "road": 11, "roof": 6, "wall": 6, "surface": 6}
    for plane in field.planes:
        assert plane.classification == expected_class[plane.kind]
        assert (plane.building >= 0) == (plane.kind in ("roof", "wall", "surface"))
    roofs_up = [p.normal[2] > 0.2 for p in field.planes if p.kind == "roof"]
    walls_vertical = [abs(p.normal[2]) < 1e-12 for p in field.planes if p.kind == "wall"]
    assert all(roofs_up) and all(walls_vertical)


def test_gable_end_walls_are_pentagons(field):
    for plane in (p for p in field.planes if p.kind == "wall"):
        corners = np.unique(np.round(field.vertices[field.triangles[field.plane_id == plane.id]].reshape(-1, 3), 9), axis=0)
        assert len(corners) in (4, 5)
    pentagons = [
        p for p in field.planes if p.kind == "wall"
        and len(np.unique(field.triangles[field.plane_id == p.id])) == 5
    ]
    assert len(pentagons) == 2 * len(calibration_houses())


def test_orientations_pitches_heights_footprints(field):
    ridge_azimuths, pitches, eaves, lengths, widths = set(), [], [], [], []
    for building in sorted({p.building for p in field.planes if p.building >= 0}):
        ids = [p.id for p in field.planes if p.building == building]
        tris = field.triangles[np.isin(field.plane_id, ids)]
        pts = field.vertices[np.unique(tris)]
        top = pts[pts[:, 2] > pts[:, 2].max() - 1e-9]
        assert len(top) == 2  # the ridge's two ends
        ridge = top[1] - top[0]
        ridge_azimuths.add(round(math.degrees(math.atan2(ridge[0], ridge[1])) % 180.0, 6) % 180.0)
        levels = np.unique(np.round(pts[:, 2], 9))
        assert len(levels) == 3 and levels[0] == 0.0  # floor, eaves, ridge
        eaves.append(levels[1])
        floor = pts[pts[:, 2] == 0.0]
        sides = sorted({round(float(np.linalg.norm(a[:2] - b[:2])), 6) for a in floor for b in floor} - {0.0})
        widths.append(sides[0])
        lengths.append(sides[1])
        normals, _ = triangle_normals(field.vertices, field.triangles[np.isin(field.plane_id, ids)])
        roof = normals[(normals[:, 2] > 1e-9)]
        pitches.extend(np.degrees(np.arccos(roof[:, 2])))
    assert {15.0 * k for k in range(12)} <= ridge_azimuths
    assert min(pitches) == pytest.approx(15.0) and max(pitches) == pytest.approx(45.0)
    assert len({round(p, 6) for p in pitches}) >= 5
    assert 6.0 == pytest.approx(min(eaves)) and max(eaves) == pytest.approx(25.0)
    assert len(set(eaves)) >= 4
    assert 20.0 <= min(lengths) and max(lengths) <= 40.0
    assert 10.0 <= min(widths) and max(widths) <= 18.0


def test_every_ridge_direction_has_both_roof_faces_and_all_azimuths(field):
    azimuths = {round(p.azimuth_deg, 6) % 360.0 for p in field.planes if p.kind == "roof"}
    assert {15.0 * k for k in range(24)} <= azimuths


@pytest.mark.parametrize("half", [None, HALF, 3000.0])
def test_ground_roads_and_floors_tile_the_square_without_overlap(field, half):
    if half is None:
        half = calibration_min_half_extent() + 0.25
    if half != HALF:
        field = calibration_scene(half)
    normals, areas = triangle_normals(field.vertices, field.triangles)
    kind = np.array([field.planes[i].kind for i in field.plane_id])
    flat = np.isin(kind, ["ground", "road", "surface"])
    assert np.all(np.abs(field.vertices[field.triangles[flat]][..., 2]) == 0.0)
    ground_road = np.isin(kind, ["ground", "road"])
    assert np.all(normals[ground_road, 2] == pytest.approx(1.0))
    assert np.all(normals[kind == "surface", 2] == pytest.approx(-1.0))
    footprints = sum(h.length_m * h.width_m for h in calibration_houses())
    assert areas[kind == "surface"].sum() == pytest.approx(footprints)
    road_area = 2 * (2 * half * 10.0) - 10.0 * 10.0
    assert areas[kind == "road"].sum() == pytest.approx(road_area)
    assert areas[flat].sum() == pytest.approx((2 * half) ** 2)
    # conforming tiling: flip floors to face up, then every edge is used once each way,
    # except the square's outline which is used once.
    tris = field.triangles[flat].copy()
    down = (kind == "surface")[flat]
    tris[down] = tris[down][:, ::-1]
    keyed = position_keys(field.vertices, tris)
    edges = Counter(map(tuple, directed_edges(keyed)))
    xy = np.unique(np.round(field.vertices, 6), axis=0)  # coordinates of the position keys
    outline = [(a, b) for a, b in edges if (b, a) not in edges]
    for a, b in edges:
        assert edges[(a, b)] == 1
    for a, b in outline:  # unmatched edges lie on the square's outline
        assert (xy[a, 0] == xy[b, 0] and abs(xy[a, 0]) == half) or (xy[a, 1] == xy[b, 1] and abs(xy[a, 1]) == half)
    assert len(outline) == 4 + 4 * 2  # 4 sides, each cut by both road edges of the crossing road


def test_roads_cross_at_centre_and_houses_stay_off_them(field):
    for plane in (p for p in field.planes if p.kind == "road"):
        pts = field.vertices[field.triangles[field.plane_id == plane.id]].reshape(-1, 3)
        span = pts.max(axis=0) - pts.min(axis=0)
        assert sorted(span[:2]) == pytest.approx([10.0, 2 * HALF])
    centroids = field.vertices[field.triangles].mean(axis=1)
    kind = np.array([field.planes[i].kind for i in field.plane_id])
    on_road = (np.abs(centroids[:, 0]) < 5.0) | (np.abs(centroids[:, 1]) < 5.0)
    assert np.all(on_road[kind == "road"])
    assert not np.any(on_road[kind == "ground"])
    building = np.array([field.planes[i].building >= 0 for i in field.plane_id])
    house_xy = field.vertices[np.unique(field.triangles[building])][:, :2]
    assert np.all(np.abs(house_xy) > 5.0)
    assert np.all(np.abs(house_xy) <= 150.0)


def test_houses_are_closed_outward_and_have_the_right_volume(field):
    houses = calibration_houses()
    for building, house in enumerate(houses):
        ids = [p.id for p in field.planes if p.building == building]
        tris = position_keys(field.vertices, field.triangles[np.isin(field.plane_id, ids)])
        directed = Counter(map(tuple, directed_edges(tris)))
        undirected = Counter(tuple(sorted(e)) for e in directed_edges(tris))
        assert set(undirected.values()) == {2}
        assert set(directed.values()) == {1}  # each edge once in each direction: consistent winding
        p = field.vertices[field.triangles[np.isin(field.plane_id, ids)]]
        volume = np.sum(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2]))) / 6.0
        rise = 0.5 * house.width_m * math.tan(math.radians(house.pitch_deg))
        expected = house.length_m * house.width_m * (house.eave_m + 0.5 * rise)
        assert volume == pytest.approx(expected, rel=1e-9)  # > 0: outward winding


def test_houses_fit_inside_the_smallest_field_and_too_small_is_rejected():
    h = calibration_min_half_extent() + 0.5
    small = calibration_scene(h)
    lo, hi = small.bounds()
    assert lo[:2] == pytest.approx([-h, -h]) and hi[:2] == pytest.approx([h, h])
    with pytest.raises(InputError) as info:
        calibration_scene(100.0)
    assert info.value.field == "scene.half_extent_m"
    with pytest.raises(InputError):
        calibration_scene(float("nan"))


def test_calibration_is_deterministic(field):
    again = calibration_scene(HALF)
    assert np.array_equal(again.vertices, field.vertices)
    assert np.array_equal(again.triangles, field.triangles)
    assert np.array_equal(again.plane_id, field.plane_id)


def test_scene_defaults(field):
    assert field.origin.dtype == np.float64 and tuple(field.origin) == DEFAULT_ORIGIN
    assert field.crs == pyproj.CRS.from_user_input(DEFAULT_CRS)
    assert field.triangles.dtype == np.int32 and field.plane_id.dtype == np.int32
    assert field.classification.dtype == np.uint8 and field.vertices.dtype == np.float64
    assert field.ground_z == 0.0


def test_triangulation_with_holes_covers_the_polygon_once():
    outer = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]])
    square = np.array([[2.0, 2.0], [2.0, 4.0], [4.0, 4.0], [4.0, 2.0]])  # clockwise
    tilted = np.array([[7.0, 3.0], [8.0, 5.0], [7.0, 7.0], [6.0, 5.0]])  # counter-clockwise
    points, tris = triangulate_polygon_with_holes(outer, [square, tilted])
    p = points[tris]
    signed = 0.5 * ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                    - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
    assert np.all(signed > 0.0)
    assert signed.sum() == pytest.approx(80.0 - 4.0 - 4.0)
    rng = np.random.default_rng(1)
    samples = rng.uniform([0, 0], [10, 8], size=(2000, 2))
    in_holes = (np.all((samples > 2) & (samples < 4), axis=1)
                | (np.abs(samples[:, 0] - 7) / 1 + np.abs(samples[:, 1] - 5) / 2 < 1))
    hits = np.zeros(len(samples), dtype=int)
    for a, b, c in p:
        d = lambda u, v, w: (v[0] - u[0]) * (w[:, 1] - u[1]) - (v[1] - u[1]) * (w[:, 0] - u[0])  # noqa: E731
        hits += (d(a, b, samples) >= 0) & (d(b, c, samples) >= 0) & (d(c, a, samples) >= 0)
    assert np.all(hits[~in_holes] >= 1)
    assert np.all(hits[in_holes] == 0)


# --------------------------------------------------------------------------------------------
# Plane scene, helpers
# --------------------------------------------------------------------------------------------

def test_plane_scene_slope_normal_and_heights():
    scene = plane_scene(300.0, DEFAULT_ORIGIN, DEFAULT_CRS, slope=0.20, slope_azimuth_deg=30.0)
    a = math.radians(30.0)
    expected = np.array([0.2 * math.sin(a), 0.2 * math.cos(a), 1.0]) / math.sqrt(1.04)
    normals, areas = triangle_normals(scene.vertices, scene.triangles)
    assert np.allclose(normals, expected, atol=1e-12)
    plane = scene.planes[0]
    assert np.allclose(plane.normal, expected, atol=1e-12)
    assert plane.pitch_deg == pytest.approx(math.degrees(math.atan(0.2)))
    assert plane.azimuth_deg == pytest.approx(30.0)
    assert plane.classification == 2 and np.all(scene.classification == 2)
    assert areas.sum() == pytest.approx(600.0**2 * math.sqrt(1.04))  # horizontal area / cos(pitch)
    # 1 m towards azimuth 30° the plane is 0.2 m lower
    for x, y, z in scene.vertices:
        assert z == pytest.approx(-0.2 * (x * math.sin(a) + y * math.cos(a)))
    assert scene.ground_z == 0.0


def test_plane_scene_horizontal():
    scene = plane_scene(100.0)
    assert scene.planes[0].pitch_deg == 0.0 and math.isnan(scene.planes[0].azimuth_deg)
    lo, hi = scene.bounds()
    assert np.array_equal(lo, [-100, -100, 0]) and np.array_equal(hi, [100, 100, 0])
    with pytest.raises(InputError):
        plane_scene(-1.0)
    rising = plane_scene(100.0, slope=-0.2, slope_azimuth_deg=0.0)  # rises to the north
    assert rising.planes[0].azimuth_deg == pytest.approx(180.0)
    assert rising.terrain_top(-1, 99, 1, 100) == pytest.approx(20.0)


def test_required_half_extent_contains_the_scan():
    altitude, theta, half_line = 5000.0, math.radians(15.0), 700.0
    half = required_half_extent(altitude, theta, half_line, margin_m=50.0)
    assert half == pytest.approx(half_line + altitude * math.tan(theta) + 50.0)
    radius = altitude * math.tan(theta)
    for heading in np.radians(np.arange(0.0, 360.0, 7.5)):
        along = np.array([math.sin(heading), math.cos(heading)])
        s = np.linspace(-half_line, half_line, 11)[:, None, None]
        ring = np.linspace(0, 2 * math.pi, 73)
        pts = s * along + radius * np.stack([np.cos(ring), np.sin(ring)], axis=-1)[None]
        assert np.max(np.abs(pts)) <= half - 50.0 + 1e-9
    with pytest.raises(InputError):
        required_half_extent(-1.0, theta, 0.0)


def test_terrain_top(field):
    house = calibration_houses()[5]
    x, y = house.center
    top = field.terrain_top(x - 1.0, y - 1.0, x + 1.0, y + 1.0)
    rise = 0.5 * house.width_m * math.tan(math.radians(house.pitch_deg))
    assert top == pytest.approx(house.eave_m + rise)
    assert field.terrain_top(HALF - 20, HALF - 20, HALF - 10, HALF - 10) == 0.0
    assert field.terrain_top(2 * HALF, 2 * HALF, 3 * HALF, 3 * HALF) == -math.inf
    sloped = plane_scene(100.0, slope=0.1, slope_azimuth_deg=90.0)  # descends to the east
    assert sloped.terrain_top(-100, -100, 100, 100) == pytest.approx(10.0)


def test_world_local_round_trip(field):
    world = np.array([[409123.456789, 3393456.123456, 471.25]])
    local = field.world_to_local(world)
    assert local.dtype == np.float64
    assert local == pytest.approx(np.array([[123.456789, 456.123456, 21.25]]), abs=1e-9)
    assert np.array_equal(field.local_to_world(local), world)


def test_parse_crs():
    assert parse_crs("EPSG:32648").to_epsg() == 32648
    for bad in ("EPSG:999999", "not a crs", "", None, "EPSG:4326", "EPSG:2263"):
        with pytest.raises(InputError) as info:
            parse_crs(bad)
        assert info.value.field == "scene.crs"
    with pytest.raises(InputError) as info:
        plane_scene(10.0, crs="EPSG:4326")
    assert info.value.field == "scene.crs"


def test_scene_validation():
    plane = plane_info(0, "ground", 2, (0, 0, 1), (0, 0, 0))
    good = dict(name="t", crs=DEFAULT_CRS, origin=(0, 0, 0), vertices=np.eye(3), triangles=[[0, 1, 2]],
                plane_id=[0], classification=[2], planes=[plane], ground_z=0.0)
    Scene(**good)
    bad_cases = [
        dict(triangles=np.zeros((0, 3), int), plane_id=[], classification=[]),
        dict(triangles=[[0, 1, 3]]),
        dict(vertices=[[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]),
        dict(plane_id=[1]),
        dict(origin=(0, np.inf, 0)),
    ]
    for change in bad_cases:
        with pytest.raises(InputError) as info:
            Scene(**{**good, **change})
        assert info.value.field.startswith("scene")
    with pytest.raises(InputError) as info:
        Scene(**{**good, "triangles": np.zeros((0, 3), int), "plane_id": [], "classification": []})
    assert "at least one triangle" in str(info.value)


# --------------------------------------------------------------------------------------------
# Mesh files
# --------------------------------------------------------------------------------------------

def test_obj_round_trip_of_the_calibration_field(field, tmp_path):
    path = tmp_path / "field.obj"
    save_obj(field, path)
    loaded = load_mesh(path, "EPSG:32648")
    assert loaded.name == "field"
    assert len(loaded.planes) == len(field.planes)
    assert loaded.dropped_degenerate == 0
    assert np.allclose(loaded.local_to_world(loaded.vertices), field.local_to_world(field.vertices), atol=1e-6)
    order = np.argsort(field.plane_id, kind="stable")  # save_obj writes triangles plane by plane
    assert np.array_equal(loaded.triangles, field.triangles[order])
    assert np.array_equal(loaded.plane_id, field.plane_id[order])
    assert np.array_equal(loaded.classification, field.classification[order])
    for a, b in zip(field.planes, loaded.planes):
        assert (a.kind, a.classification) == (b.kind, b.classification)
        assert np.allclose(a.normal, b.normal, atol=1e-6)
    world_ground = field.origin[2] + field.ground_z
    assert loaded.origin[2] + loaded.ground_z == pytest.approx(world_ground, abs=1e-6)
    assert np.all(loaded.origin == np.round(loaded.origin))


def test_obj_syntax_polygons_negative_indices_groups(tmp_path):
    text = """# a house-less test
mtllib nothing.mtl
v 0 0 0
v 10 0 0
v 10 10 0
v 0 10 0
vt 0 0
vn 0 0 1
o Terrain
g ground
usemtl grass
f 1/1/1 2/1/1 3/1/1 4/1/1
v 0 0 5
v 10 0 5
v 10 10 5
v 0 10 5
g roof_3
s off
f -4//1 -3//1 -2//1
f -4/1 -2/1 -1/1
g road
f 1 2 6
"""
    path = tmp_path / "mesh.OBJ"
    path.write_text(text)
    scene = load_mesh(path, "EPSG:32648", origin=(500000.0, 3400000.0, 100.0), name="t")
    assert scene.name == "t"
    assert len(scene.triangles) == 5
    assert np.array_equal(scene.classification, [2, 2, 6, 6, 11])
    assert [p.kind for p in scene.planes] == ["ground", "roof", "road"]
    assert np.array_equal(scene.plane_id, [0, 0, 1, 1, 2])
    assert scene.origin == pytest.approx([500005.0, 3400005.0, 102.0])  # rounded bbox centre (2.5 → 2)
    assert scene.ground_z == pytest.approx(-2.0)
    world = scene.local_to_world(scene.vertices[scene.triangles[3]])
    assert world == pytest.approx(np.array([[500000, 3400000, 105], [500010, 3400010, 105], [500000, 3400010, 105]]))


def test_obj_with_absolute_utm_coordinates_keeps_precision(tmp_path):
    base = np.array([409512.123, 3393777.456, 452.789])
    pts = base + np.array([[0, 0, 0], [0.001, 0, 0], [0, 0.001, 0]])
    path = tmp_path / "utm.obj"
    path.write_text("".join(f"v {x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in pts) + "f 1 2 3\n")
    scene = load_mesh(path, "EPSG:32648")
    assert np.all(np.abs(scene.vertices) < 1.0)
    assert scene.vertices[1] - scene.vertices[0] == pytest.approx([0.001, 0, 0], abs=1e-9)


def write_ply(path, vertices, faces, fmt="ascii", plane_id=None, classification=None,
              index_name="vertex_indices", extra_vertex=False, trailing_element=False):
    """An independent PLY writer (struct / text), for the reader's tests."""
    endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    head = ["ply", f"format {fmt} 1.0", "comment written by test_scene", f"element vertex {len(vertices)}",
            "property double x", "property double y", "property double z"]
    if extra_vertex:
        head += ["property float nx", "property uchar red"]
    head += [f"element face {len(faces)}", f"property list uchar int {index_name}"]
    if plane_id is not None:
        head.append("property int plane_id")
    if classification is not None:
        head.append("property uchar classification")
    if trailing_element:
        head += ["element edge 1", "property int vertex1", "property int vertex2"]
    head.append("end_header")
    header = ("\n".join(head) + "\n").encode("ascii")
    if endian is None:
        rows = []
        for v in vertices:
            rows.append(" ".join(repr(float(c)) for c in v) + (" 0.5 7" if extra_vertex else ""))
        for k, f in enumerate(faces):
            row = [str(len(f))] + [str(i) for i in f]
            row += [str(plane_id[k])] if plane_id is not None else []
            row += [str(classification[k])] if classification is not None else []
            rows.append(" ".join(row))
        if trailing_element:
            rows.append("0 1")
        path.write_bytes(header + ("\n".join(rows) + "\n").encode("ascii"))
        return
    body = b""
    for v in vertices:
        body += struct.pack(endian + "ddd", *v) + (struct.pack(endian + "fB", 0.5, 7) if extra_vertex else b"")
    for k, f in enumerate(faces):
        body += struct.pack(endian + "B" + "i" * len(f), len(f), *f)
        body += struct.pack(endian + "i", plane_id[k]) if plane_id is not None else b""
        body += struct.pack(endian + "B", classification[k]) if classification is not None else b""
    if trailing_element:
        body += struct.pack(endian + "ii", 0, 1)
    path.write_bytes(header + body)


BOX_VERTICES = np.array([[x, y, z] for x in (0.0, 4.0) for y in (0.0, 3.0) for z in (0.0, 2.0)]) + [100.0, 200.0, 10.0]
BOX_QUADS = [[0, 2, 6, 4], [1, 5, 7, 3], [0, 4, 5, 1], [2, 3, 7, 6], [0, 1, 3, 2], [4, 6, 7, 5]]  # outward


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_round_trip_with_labels(field, tmp_path, fmt):
    world = field.local_to_world(field.vertices)
    path = tmp_path / f"field_{fmt}.ply"
    write_ply(path, world, field.triangles.tolist(), fmt, plane_id=(field.plane_id * 3 + 7).tolist(),
              classification=field.classification.tolist(), extra_vertex=True, trailing_element=True)
    loaded = load_mesh(path, DEFAULT_CRS)
    assert np.allclose(loaded.local_to_world(loaded.vertices), world, atol=1e-9)
    assert np.array_equal(loaded.triangles, field.triangles)
    assert np.array_equal(loaded.plane_id, field.plane_id)  # labels renumbered in increasing order
    assert np.array_equal(loaded.classification, field.classification)
    for a, b in zip(field.planes, loaded.planes):
        assert np.allclose(a.normal, b.normal, atol=1e-9)
        assert (a.kind, a.classification) == (b.kind, b.classification)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_unlabelled_box_quads_and_mixed_faces(tmp_path, fmt):
    path = tmp_path / "box.ply"
    faces = BOX_QUADS[:3] + [[a, b, c] for q in BOX_QUADS[3:] for a, b, c in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
    write_ply(path, BOX_VERTICES, faces, fmt, index_name="vertex_index")
    scene = load_mesh(path, DEFAULT_CRS)
    assert len(scene.triangles) == 12 and len(scene.planes) == 6
    normals = sorted(tuple(np.round(p.normal, 12)) for p in scene.planes)
    expected = sorted(tuple(float(c) for c in row) for row in np.vstack([np.eye(3), -np.eye(3)]))
    assert normals == expected
    assert all(p.classification == 1 for p in scene.planes)
    assert scene.ground_z == pytest.approx(BOX_VERTICES[:, 2].min() - scene.origin[2])


def test_unlabelled_triangle_soup_box_groups_into_six_planes(tmp_path):
    lines = []
    for quad in BOX_QUADS:  # every triangle with its own copies of its corners
        for tri in ((quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])):
            lines += [f"v {x} {y} {z}" for x, y, z in BOX_VERTICES[list(tri)]]
    lines += [f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}" for k in range(12)]
    path = tmp_path / "soup.obj"
    path.write_text("\n".join(lines) + "\n")
    scene = load_mesh(path, DEFAULT_CRS)
    assert len(scene.planes) == 6
    assert sorted(Counter(scene.plane_id.tolist()).values()) == [2] * 6
    for plane in scene.planes:  # outward normals: from the box centre towards the face
        assert np.dot(plane.normal, plane.point - (BOX_VERTICES.mean(axis=0) - scene.origin)) > 0


def test_coplanar_grouping_tolerances(tmp_path):
    """Two 10 m × 10 m squares sharing an edge, the second folded down by ``fold_deg`` and
    ``run`` m long: one plane while the fold is within 1° and the far edge within 0.05 m."""
    def planes(fold_deg, run=10.0, step=0.0):
        z = run * math.tan(math.radians(fold_deg)) + step
        pts = [(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0), (10 + run, 0, z), (10 + run, 10, z)]
        body = "".join(f"v {x} {y} {z}\n" for x, y, z in pts)
        body += "f 1 2 3\nf 1 3 4\nf 2 5 6\nf 2 6 3\n"
        path = tmp_path / f"strip_{fold_deg}_{run}_{step}.obj"
        path.write_text(body)
        return len(load_mesh(path, DEFAULT_CRS).planes)
    assert planes(0.2) == 1                 # 0.2°, far edge 0.035 m off
    assert planes(2.0) == 2                 # 2°
    assert planes(2.0, run=1.0) == 2        # 2°, far edge only 0.035 m off: the angle splits
    assert planes(0.0, step=0.1) == 2       # 0.57°, far edge 0.1 m off: the offset splits


def test_obj_group_with_a_whole_house_splits_into_faces(tmp_path):
    lines = [f"v {x} {y} {z}" for x, y, z in BOX_VERTICES] + ["g building_1"]
    lines += ["f " + " ".join(str(i + 1) for i in q) for q in BOX_QUADS]
    path = tmp_path / "house.obj"
    path.write_text("\n".join(lines) + "\n")
    scene = load_mesh(path, DEFAULT_CRS)
    assert len(scene.planes) == 6
    assert Counter(p.kind for p in scene.planes) == {"wall": 4, "roof": 1, "surface": 1}
    assert np.all(scene.classification == 6)


def test_obj_with_latin1_names_loads(tmp_path):
    path = tmp_path / "latin1.obj"
    path.write_bytes("# caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\ng toit_\xe9t\xe9\nf 1 2 3\n".encode("latin-1"))
    assert len(load_mesh(path, DEFAULT_CRS).triangles) == 1


def test_ground_wound_clockwise_gets_an_upward_normal(tmp_path):
    """A slope of 0.1 descending to the east, its triangles wound to face down."""
    path = tmp_path / "slope.obj"
    path.write_text("v 0 0 0\nv 10 0 -1\nv 10 10 -1\nv 0 10 0\ng ground\nf 1 3 2\nf 1 4 3\n")
    plane = load_mesh(path, DEFAULT_CRS).planes[0]
    assert plane.normal == pytest.approx(np.array([0.1, 0.0, 1.0]) / math.sqrt(1.01))
    assert plane.azimuth_deg == pytest.approx(90.0)
    assert plane.pitch_deg == pytest.approx(math.degrees(math.atan(0.1)))


def test_degenerate_triangles_are_dropped_and_counted(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\nf 1 1 3\n"
    path = tmp_path / "degenerate.obj"
    path.write_text(text)
    scene = load_mesh(path, DEFAULT_CRS)
    assert len(scene.triangles) == 1 and scene.dropped_degenerate == 2


MALFORMED = {
    "no_faces.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "empty.obj": b"",
    "bad_number.obj": b"v 0 0 zero\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "short_vertex.obj": b"v 0 0\nf 1 1 1\n",
    "index_range.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
    "index_zero.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
    "index_negative.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n",
    "two_vertex_face.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",
    "nan.obj": b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "inf.obj": b"v 0 0 0\nv 1e400 0 0\nv 0 1 0\nf 1 2 3\n",
    "binary.obj": bytes(range(256)) * 4,
    "zero_area.obj": b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n",
    "no_magic.ply": b"hello\nformat ascii 1.0\nend_header\n",
    "no_end.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n",
    "bad_format.ply": b"ply\nformat binary_middle_endian 1.0\nend_header\n",
    "bad_type.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n0\n",
    "no_face.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                   b"property float z\nend_header\n0 0 0\n",
    "no_xyz.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                  b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0\n1 0\n0 1\n3 0 1 2\n",
    "ascii_truncated.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                           b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                           b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1\n",
    "ascii_garbage.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                         b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                         b"end_header\n0 0 0\n1 zz 0\n0 1 0\n3 0 1 2\n",
    "ascii_index.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                       b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                       b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n",
}


def binary_ply_cases() -> dict[str, bytes]:
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    verts = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
    good_face = struct.pack("<B3i", 3, 0, 1, 2)
    return {
        "binary_truncated_vertices.ply": head + verts[:20],
        "binary_truncated_faces.ply": head + verts + good_face[:9],
        "binary_index.ply": head + verts + struct.pack("<B3i", 3, 0, 1, 99),
        "binary_negative_index.ply": head + verts + struct.pack("<B3i", 3, 0, -1, 2),
        "binary_nan.ply": head + struct.pack("<9f", 0, 0, 0, 1, 0, float("nan"), 0, 1, 0) + good_face,
        "binary_huge_count.ply": head.replace(b"vertex 3", b"vertex 4000000000") + verts + good_face,
        "binary_huge_list.ply": head + verts + struct.pack("<B3i", 255, 0, 1, 2),
        "binary_empty_face.ply": head + verts + struct.pack("<B", 0),
        "binary_two_vertex_face.ply": head + verts + struct.pack("<B2i", 2, 0, 1),
    }


@pytest.mark.parametrize("name", sorted(MALFORMED) + sorted(binary_ply_cases()))
def test_malformed_files_raise_input_error(tmp_path, name):
    path = tmp_path / name
    path.write_bytes({**MALFORMED, **binary_ply_cases()}[name])
    with pytest.raises(InputError) as info:
        load_mesh(path, DEFAULT_CRS)
    assert info.value.field == "scene.path"
    assert info.value.value == str(path)
    assert "OBJ or PLY" in info.value.allowed


def test_missing_file_directory_and_unknown_extension(tmp_path):
    (tmp_path / "mesh.stl").write_bytes(b"solid x\nendsolid x\n")
    (tmp_path / "folder.obj").mkdir()
    for path, reason in ((tmp_path / "missing.obj", "not found"), (tmp_path / "mesh.stl", "extension"),
                         (tmp_path / "folder.obj", "cannot read")):
        with pytest.raises(InputError) as info:
            load_mesh(path, DEFAULT_CRS)
        assert info.value.field == "scene.path" and reason in info.value.allowed


def test_load_mesh_rejects_a_bad_crs_or_origin(tmp_path):
    path = tmp_path / "t.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError) as info:
        load_mesh(path, "EPSG:0")
    assert info.value.field == "scene.crs"
    with pytest.raises(InputError) as info:
        load_mesh(path, DEFAULT_CRS, origin=(0, 0))
    assert info.value.field == "scene.origin"
