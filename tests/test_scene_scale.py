"""Scene preparation at scale: the vectorised OBJ reader, plane grouping, the height grid, terrain
following and the scene cache, each against independent arithmetic or the line-by-line reader."""
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.core.errors import InputError
from flightsim.engine import world as plan
from flightsim.platforms.lines import MAX_CLIMB_MPS
from flightsim.scenes import cache, forest_scene, height_grid, mesh_obj, mesh_ply, meshio
from flightsim.scenes import mesh as scene_mesh
from flightsim.scenes.height_grid import HeightGrid
from flightsim.scenes.mesh_planes import COPLANAR_ANGLE_DEG, COPLANAR_OFFSET_M
from flightsim.scenes.meshio import load_mesh
from flightsim.scenes.scene import DEFAULT_CRS
from test_properties import clipped_top  # the exact terrain top over a rectangle, by polygon clipping
from trajectories import climb_limited, plan_parallel_lines


def grid_mesh(z, step=1.0):
    """Vertices (n·n, 3) and triangles of heights z (n, n) on a square grid of ``step`` [m]."""
    n = len(z)
    x, y = np.meshgrid(np.arange(n) * step, np.arange(n) * step, indexing="xy")
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    a = (np.arange(n - 1)[None, :] + n * np.arange(n - 1)[:, None]).ravel()
    triangles = np.concatenate([np.column_stack([a, a + 1, a + n + 1]), np.column_stack([a, a + n + 1, a + n])])
    return vertices, triangles


def obj_text(vertices, triangles, group="") -> str:
    head = f"g {group}\n" if group else ""
    return ("".join(f"v {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in vertices) + head
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in triangles))


# --------------------------------------------------------------------------------------------
# OBJ reading


number = st.floats(-1e6, 1e6, allow_nan=False).map(float)
spelling = st.sampled_from(["{!r}", "{:.3f}", "{:e}", "{:+.6E}"])


@st.composite
def obj_files(draw):
    """OBJ text with known vertices, 0-based faces and per-face group names."""
    n = draw(st.integers(3, 12))
    vertices = [tuple(draw(number) for _ in range(3)) for _ in range(n)]
    lines, expected_faces, expected_groups, group = [], [], [], ""
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    written = 0
    for k, v in enumerate(vertices):
        spelled = [draw(spelling).format(c) for c in v]
        vertices[k] = tuple(float(c) for c in spelled)  # what the text says, exactly
        lines.append("v " + " ".join(spelled) + draw(st.sampled_from(["", " 1.0", " # c"])))
        written += 1
        if written >= 3 and draw(st.booleans()):
            if draw(st.booleans()):
                group = draw(st.sampled_from(["ground", "roof 2", "Road_1", "wall"]))
                lines.append(draw(st.sampled_from(["g ", "o ", "g  "])) + group)
            size = draw(st.integers(3, 5))
            face = [draw(st.integers(0, written - 1)) for _ in range(size)]
            tokens = []
            for i in face:
                head = str(i + 1) if draw(st.booleans()) else str(i - written)
                tokens.append(head + draw(st.sampled_from(["", "/1", "//2", "/1/2"])))
            lines.append(draw(st.sampled_from(["f ", "f\t", "  f "])) + " ".join(tokens))
            lines.append(draw(st.sampled_from(["vt 0 0", "usemtl grass", "# comment", "", "s off"])))
            expected_faces.append(face)
            expected_groups.append(group)
    if not expected_faces:
        lines.append("f 1 2 3")
        expected_faces.append([0, 1, 2])
        expected_groups.append(group)
    return newline.join(lines) + draw(st.sampled_from(["", newline])), vertices, expected_faces, expected_groups


@settings(max_examples=150, deadline=None)
@given(obj_files())
def test_vectorised_obj_reader_reads_what_was_written_and_agrees_with_the_line_reader(case):
    text, vertices, faces, groups = case
    data = text.encode("utf-8")
    fast = mesh_obj._read_obj_vectorised(data)
    assert fast is not None
    assert np.array_equal(fast["vertices"], np.array(vertices))
    assert fast["corners"].tolist() == [i for f in faces for i in f]
    assert fast["sizes"].tolist() == [len(f) for f in faces]
    names = [""] + list(dict.fromkeys(g for g in groups if g))
    assert fast["group"].tolist() == [names.index(g) for g in groups]
    slow = mesh_obj._read_obj_lines(data)
    for key, value in slow.items():
        assert np.array_equal(fast[key], value) if isinstance(value, np.ndarray) else fast[key] == value


@pytest.mark.parametrize("text", [
    b"v 0 0 0\x0bv 1 0 0\nv 0 1 0\nf 1 2 3\n",         # a vertical tab breaks lines in Python
    "v 0 0 0\nv 1 0 0\nv 0 1 0\n\u00a0f 1 2 3\n".encode(),  # a no-break space is whitespace
    b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 +3\n",
    b"v 0 0 0\nv 1 0 0\nv 0 1_0 0\nf 1 2 3\n",
    b"v 0 0 inf\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
])
def test_unusual_obj_text_goes_to_the_line_reader(text):
    assert mesh_obj._read_obj_vectorised(text) is None
    mesh_obj.read_obj(text)  # the line reader takes it (or reports the line)


def test_the_common_obj_forms_never_need_the_line_reader(tmp_path, monkeypatch):
    text = ("# exported\nmtllib a.mtl\no Terrain\nv 0 0 0\nv 10 0 0\nv 10 10 0.5\nv 0 10 0.5\nvt 0 0\nvn 0 0 1\n"
            "g ground\nusemtl grass\nf 1/1/1 2/1/1 3/1/1\nf -4//1 -2//1 -1//1\n")
    path = tmp_path / "common.obj"
    path.write_text(text)
    monkeypatch.setattr(mesh_obj, "_read_obj_lines", None)
    scene = load_mesh(path, DEFAULT_CRS)
    assert len(scene.triangles) == 2 and scene.classification.tolist() == [2, 2]


def test_ascii_ply_faces_of_one_size_are_read_at_once_and_still_refuse_non_integers(tmp_path, monkeypatch):
    vertices, triangles = rough_terrain(6)
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty double x\nproperty double y\n"
            f"property double z\nelement face {len(triangles)}\nproperty list uchar int vertex_indices\n"
            "property uchar classification\nend_header\n")
    body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist())
    body += "".join(f"3 {a} {b} {c} 2\n" for a, b, c in triangles.tolist())
    path = tmp_path / "terrain.ply"
    path.write_text(head + body)
    read_at_once = []
    one_size = mesh_ply._ply_ascii_uniform_lists
    monkeypatch.setattr(mesh_ply, "_ply_ascii_uniform_lists",
                        lambda *args: read_at_once.append(one_size(*args)) or read_at_once[-1])
    raw = meshio._read(path)
    assert len(read_at_once) == 1 and read_at_once[0] is not None  # the faces, not row by row
    assert np.array_equal(raw["vertices"], vertices) and raw["corners"].tolist() == triangles.reshape(-1).tolist()
    assert np.all(raw["classification"] == 2) and np.all(raw["sizes"] == 3)
    monkeypatch.undo()
    path.write_text(head + body.replace(f"3 {triangles[0, 0]} ", f"3 {triangles[0, 0]}.0 ", 1))
    with pytest.raises(InputError) as info:
        load_mesh(path, DEFAULT_CRS)
    assert "int()" in info.value.allowed


# --------------------------------------------------------------------------------------------
# Plane grouping


def area_weighted_plane(corners):
    """Independent: unit normal and centroid of triangles (m, 3, 3), each weighted by its area."""
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross.sum(axis=0)
    return normal / np.linalg.norm(normal), (corners.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()


def test_a_curved_surface_splits_into_planes_that_are_planar(tmp_path):
    """A paraboloid bowl (curvature 1/200 m⁻¹): no plane may bend by more than the tolerances."""
    xy = np.arange(41) * 5.0 - 100.0
    x, y = np.meshgrid(xy, xy)
    vertices, triangles = grid_mesh((x * x + y * y) / 400.0, 5.0)
    path = tmp_path / "bowl.obj"
    path.write_text(obj_text(vertices, triangles, "ground"))
    scene = load_mesh(path, DEFAULT_CRS)
    assert 10 < len(scene.planes) < len(scene.triangles)
    cos_limit = math.cos(math.radians(COPLANAR_ANGLE_DEG))
    for plane in range(len(scene.planes)):
        corners = scene.vertices[scene.triangles[scene.plane_id == plane]]
        normal, centroid = area_weighted_plane(corners)
        assert np.abs((corners - centroid) @ normal).max() <= COPLANAR_OFFSET_M + 1e-9
        own = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        assert np.all(own @ normal / np.linalg.norm(own, axis=1) >= cos_limit - 1e-12)


@pytest.mark.parametrize("gap, planes", [(0.0, 1), (0.02, 1), (0.2, 2)])
def test_pieces_of_one_group_apart_merge_only_when_coplanar(tmp_path, gap, planes):
    """Two squares of the group "ground", 10 m apart, the second raised by ``gap`` [m]."""
    body = "v 0 0 0\nv 10 0 0\nv 10 10 0\nv 0 10 0\n"
    body += "".join(f"v {x} {y} {gap}\n" for x, y in ((20, 0), (30, 0), (30, 10), (20, 10)))
    body += "g ground\nf 1 2 3\nf 1 3 4\nf 5 6 7\nf 5 7 8\n"
    path = tmp_path / f"apart_{gap}.obj"
    path.write_text(body)
    assert len(load_mesh(path, DEFAULT_CRS).planes) == planes


def test_planes_none_keeps_one_label_per_group_and_is_not_planar(tmp_path):
    xy = np.arange(11) * 5.0
    x, y = np.meshgrid(xy, xy)
    vertices, triangles = grid_mesh((x * x + y * y) / 100.0, 5.0)
    path = tmp_path / "terrain.obj"
    path.write_text(obj_text(vertices, triangles, "ground"))
    scene = load_mesh(path, DEFAULT_CRS, planes="none")
    assert len(scene.planes) == 1 and np.all(scene.plane_id == 0) and np.all(scene.classification == 2)
    assert not scene.planar and load_mesh(path, DEFAULT_CRS).planar
    with pytest.raises(InputError) as info:
        load_mesh(path, DEFAULT_CRS, planes="some")
    assert info.value.field == "scene.planes"
    cfg = RunConfig()
    set_value(cfg, "scene.planes", "flat")
    with pytest.raises(InputError) as info:
        validate(cfg)
    assert info.value.field == "scene.planes"


# --------------------------------------------------------------------------------------------
# Height grid


def rough_terrain(n=30, seed=3):
    rng = np.random.default_rng(seed)
    return grid_mesh(rng.normal(0.0, 3.0, (n, n)), 2.0)


def test_height_grid_bounds_and_exact_tops_over_rectangles():
    vertices, triangles = rough_terrain()
    grid = HeightGrid.build(vertices, triangles)
    corners = vertices[triangles]
    rng = np.random.default_rng(7)
    rects = []
    for _ in range(40):
        x0, y0 = rng.uniform(-5, 60, 2)
        w, h = rng.uniform(0, 15, 2)
        rects.append((x0, y0, x0 + w, y0 + h))
    tops = grid.tops(rects)
    for rect, top in zip(rects, tops):
        expected = max(clipped_top(t, *rect) for t in corners)
        assert top == pytest.approx(expected, abs=1e-9)
        assert grid.top_bound(*rect) >= expected


def grid_cases():
    """Meshes whose grids differ in kind: a rough terrain, the same with big sloped triangles across many
    cells, vertical walls and unused far vertices, and a single triangle."""
    vertices, triangles = rough_terrain()
    rng = np.random.default_rng(5)
    big = rng.uniform(-10.0, 70.0, (12, 3, 3))
    walls = np.repeat(rng.uniform(0.0, 58.0, (6, 1, 3)), 3, axis=1) + [[0, 0, 0], [4.0, 3.0, 0], [0, 0, 9.0]]
    extra = np.concatenate([big, walls]).reshape(-1, 3)
    far = np.array([[1e4, -3e4, 500.0]])
    mixed_v = np.concatenate([vertices, extra, far])
    mixed_t = np.concatenate([triangles, len(vertices) + np.arange(len(extra)).reshape(-1, 3)])
    return {"terrain": (vertices, triangles), "mixed": (mixed_v, mixed_t),
            "single": (np.array([[0.0, 0.0, 1.0], [3.0, 0.0, 2.0], [0.0, 2.0, 3.0]]), np.array([[0, 1, 2]]))}


@pytest.mark.parametrize("case", ["terrain", "mixed", "single"])
def test_the_device_builds_the_numpy_grid_bit_for_bit(case, device):
    vertices, triangles = grid_cases()[case]
    on_device, in_numpy = HeightGrid.build(vertices, triangles, device), HeightGrid.build(vertices, triangles)
    assert (on_device.x0, on_device.y0, on_device.cell_m) == (in_numpy.x0, in_numpy.y0, in_numpy.cell_m)
    for name in ("top", "start", "members"):
        got, want = getattr(on_device, name), getattr(in_numpy, name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    if case == "mixed":
        assert np.diff(in_numpy.start).max() > 4 and np.isinf(in_numpy.top).any()  # crowded and empty cells


@pytest.mark.parametrize("piece", [None, 50])  # 50: the triangles' terms worked out in pieces on threads
def test_ground_height_is_the_surface_under_each_point(monkeypatch, piece):
    """A tilted plane z = 0.3x − 0.2y + 5 with a hole: the grid reads the plane, NaN off the mesh."""
    from flightsim.core import process_map

    if piece is not None:
        monkeypatch.setattr(process_map, "ROWS_PER_PIECE", piece)
        monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    xy = np.arange(21) * 3.0
    x, y = np.meshgrid(xy, xy)
    vertices, triangles = grid_mesh(0.3 * x - 0.2 * y + 5.0, 3.0)
    hole = np.all(vertices[triangles][:, :, :2].mean(axis=1) // 3.0 == [10, 10], axis=1)
    grid = HeightGrid.build(vertices, triangles[~hole])
    rng = np.random.default_rng(1)
    px, py = rng.uniform(0, 60, 500), rng.uniform(0, 60, 500)
    in_hole = (px // 3.0 == 10) & (py // 3.0 == 10)
    height = grid.ground_height(px, py)
    assert np.allclose(height[~in_hole], 0.3 * px[~in_hole] - 0.2 * py[~in_hole] + 5.0, atol=1e-9)
    assert np.all(np.isnan(height[in_hole]))
    assert np.isnan(grid.ground_height(-1.0, 5.0)) and np.isnan(grid.ground_height(5.0, 61.0))


@pytest.mark.parametrize("block", [1, 7, 1 << 40])
def test_ground_height_in_blocks_is_the_surface_under_each_point(block, monkeypatch):
    """The points tested a few listings at a time (one point a block at 1, points off the mesh among them) read
    the same surface as in one block: the crowded "mixed" mesh against each point's highest triangle under it,
    found by a loop over every triangle in float64."""
    vertices, triangles = grid_cases()["mixed"]
    grid = HeightGrid.build(vertices, triangles)
    rng = np.random.default_rng(4)
    px, py = rng.uniform(-5.0, 65.0, 400), rng.uniform(-5.0, 65.0, 400)  # the terrain spans 0-58 m
    monkeypatch.setattr(height_grid, "LISTINGS_PER_BLOCK", block)
    height = grid.ground_height(px, py)
    corners = vertices[triangles]
    for x, y, got in zip(px, py, height):
        best = -np.inf
        for (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) in corners:
            det = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
            if det == 0.0:
                continue
            w1 = ((x - x0) * (y2 - y0) - (y - y0) * (x2 - x0)) / det
            w2 = ((x1 - x0) * (y - y0) - (y1 - y0) * (x - x0)) / det
            if min(w1, w2) >= -1e-12 and w1 + w2 <= 1.0 + 1e-12:
                best = max(best, z0 + w1 * (z1 - z0) + w2 * (z2 - z0))
        assert (np.isnan(got) and best == -np.inf) or got == pytest.approx(best, abs=1e-9)
    assert np.isnan(height).any() and np.isfinite(height).sum() > 200


# --------------------------------------------------------------------------------------------
# Terrain following


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=2, max_size=30), st.floats(0.01, 2.0))
def test_climb_limited_profile_is_the_least_one_above_the_heights(heights, grade):
    along = np.cumsum(np.r_[0.0, np.full(len(heights) - 1, 7.0)])
    z = climb_limited(along, heights, grade)
    brute = [max(h - grade * abs(a - b) for h, b in zip(heights, along)) for a in along]
    assert z == pytest.approx(brute, abs=1e-9)
    assert np.all(z >= np.asarray(heights) - 1e-9)
    assert np.all(np.abs(np.diff(z)) <= grade * 7.0 + 1e-9)


def ridge_config(tmp_path, **settings):
    """A ridge along x (height 40 m at y = 0, slope 1:5 on either side) as OBJ, flown north-south."""
    xy = np.arange(61) * 10.0 - 300.0
    x, y = np.meshgrid(xy, xy)
    vertices, triangles = grid_mesh(np.maximum(40.0 - np.abs(y) / 5.0, 0.0), 10.0)
    path = tmp_path / "ridge.obj"
    path.write_text(obj_text(vertices - [300.0, 300.0, 0.0], triangles, "ground"))
    cfg = RunConfig()
    for key, value in {"scene.name": str(path), "scene.origin": "0,0,0", "scene.planes": "none",
                       "flight.altitude_m": "100", "flight.duration_s": "9", "flight.speed_kmh": "200",
                       "run.scene_cache": "false", **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def test_terrain_following_keeps_the_altitude_over_the_ground_within_the_climb_rate(tmp_path):
    cfg = ridge_config(tmp_path, **{"flight.terrain_following": "true"})
    scene = plan.build_scene(cfg)
    (line,) = plan.flight_trajectories(cfg, scene)
    north = line.position[:, 1] - scene.origin[1]
    ground = np.maximum(40.0 - np.abs(north) / 5.0, 0.0)  # the ridge, in closed form
    above = line.position[:, 2] - ground  # world heights
    assert np.all(above >= 100.0 - 1e-6)
    speed = 200.0 / 3.6
    climb = np.abs(np.diff(line.position[:, 2])) / np.diff(line.gps_time)
    assert np.all(climb <= MAX_CLIMB_MPS + 1e-6)
    assert np.any(above < 100.0 + 1e-6)  # it does come down to the altitude where the slope allows
    assert np.ptp(line.position[:, 2]) > 10.0 and speed * 9.0 > 400.0


def test_without_terrain_following_the_lines_are_the_planned_straight_lines(tmp_path):
    cfg = ridge_config(tmp_path)
    scene = plan.build_scene(cfg)
    (line,) = plan.flight_trajectories(cfg, scene)
    lo, hi = scene.bounds()
    centre = scene.local_to_world([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, scene.ground_z])
    (planned,) = plan_parallel_lines(centre[0], centre[1], 0.0, 500.0, 100.0, 1, 200.0, speed_mps=200.0 / 3.6,
                                     start_gps_time=cfg.flight.start_gps_time)
    expected = planned.trajectory(ground_height_m=centre[2])
    assert np.array_equal(line.position, expected.position) and np.array_equal(line.gps_time, expected.gps_time)


def test_a_line_too_low_for_the_terrain_is_refused(tmp_path):
    cfg = ridge_config(tmp_path, **{"flight.altitude_m": "20"})
    scene = plan.build_scene(cfg)
    with pytest.raises(InputError) as info:
        plan.flight_trajectories(cfg, scene)
    assert info.value.field == "flight.altitude_m"


# --------------------------------------------------------------------------------------------
# Scene cache


def cached_config(tmp_path, monkeypatch):
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "cache"))
    vertices, triangles = rough_terrain(12)
    path = tmp_path / "terrain.obj"
    path.write_text(obj_text(vertices, triangles, "ground"))
    cfg = RunConfig()
    set_value(cfg, "scene.name", str(path))
    set_value(cfg, "scene.origin", "500000,3400000,100")
    return validate(cfg), path


def same_scene(a, b):
    for name in ("origin", "vertices", "triangles", "plane_id", "classification"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert (a.name, a.ground_z, a.planar, a.dropped_degenerate) == (b.name, b.ground_z, b.planar, b.dropped_degenerate)
    assert a.crs == b.crs and len(a.planes) == len(b.planes)
    for p, q in zip(a.planes, b.planes):
        assert (p.id, p.kind, p.classification, p.building) == (q.id, q.kind, q.classification, q.building)
        assert np.array_equal(p.normal, q.normal) and np.array_equal(p.point, q.point)


def refuse_to_load(*args, **kwargs):
    raise AssertionError("the scene should have come from the cache")


def test_a_second_run_reads_the_scene_from_the_cache(tmp_path, monkeypatch):
    cfg, _ = cached_config(tmp_path, monkeypatch)
    fresh = plan.build_scene(cfg)
    entries = list((tmp_path / "cache").glob("*.npz"))
    assert len(entries) == 1 and not list((tmp_path / "cache").glob(".*"))  # no temporary left
    monkeypatch.setattr(scene_mesh, "load_mesh", refuse_to_load)
    same_scene(plan.build_scene(cfg), fresh)


def test_the_cache_keeps_the_height_grid_so_a_second_run_does_not_build_it(tmp_path, monkeypatch):
    cfg, _ = cached_config(tmp_path, monkeypatch)
    built = plan.build_scene(cfg).height_grid
    monkeypatch.setattr(HeightGrid, "build", refuse_to_load)
    monkeypatch.setattr(scene_mesh, "load_mesh", refuse_to_load)
    scene = plan.build_scene(cfg)
    grid = scene.height_grid
    assert (grid.x0, grid.y0, grid.cell_m) == (built.x0, built.y0, built.cell_m)
    for name in ("top", "start", "members"):
        assert np.array_equal(getattr(grid, name), getattr(built, name))
    assert grid.vertices is scene.vertices and grid.triangles is scene.triangles
    plan.flight_trajectories(cfg, scene)  # plans (clearance and all) from the stored grid


def test_a_stored_height_grid_that_cannot_be_the_meshs_is_never_trusted(tmp_path, monkeypatch):
    cfg, _ = cached_config(tmp_path, monkeypatch)
    fresh = plan.build_scene(cfg)
    (entry,) = (tmp_path / "cache").glob("*.npz")
    with np.load(entry) as data:
        arrays = dict(data)
    arrays["grid_members"] = arrays["grid_members"].copy()
    arrays["grid_members"][-1] = len(fresh.triangles)  # a triangle the mesh does not have
    with open(entry, "wb") as fh:
        np.savez(fh, **arrays)
    calls = []
    real = scene_mesh.load_mesh
    monkeypatch.setattr(scene_mesh, "load_mesh", lambda *a, **k: calls.append(1) or real(*a, **k))
    same_scene(plan.build_scene(cfg), fresh)
    assert calls == [1]


def test_a_changed_file_or_option_is_read_afresh(tmp_path, monkeypatch):
    cfg, path = cached_config(tmp_path, monkeypatch)
    plan.build_scene(cfg)
    text = path.read_text()
    path.write_text(text.replace("g ground", "g roof"))  # same size, new time and content
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))
    assert np.all(plan.build_scene(cfg).classification == 6)
    set_value(cfg, "scene.planes", "none")
    assert not plan.build_scene(cfg).planar


@pytest.mark.parametrize("damage", ["garbage", "truncated", "other_key", "compressed", "object_array"])
def test_a_damaged_entry_is_never_trusted(tmp_path, monkeypatch, damage):
    cfg, path = cached_config(tmp_path, monkeypatch)
    fresh = plan.build_scene(cfg)
    (entry,) = (tmp_path / "cache").glob("*.npz")
    data = entry.read_bytes()
    if damage == "garbage":
        entry.write_bytes(b"not a zip file" * 10)
    elif damage == "truncated":
        entry.write_bytes(data[: len(data) // 2])
    elif damage in ("compressed", "object_array"):  # an .npz, but not one the cache writes (it maps members)
        with np.load(entry) as stored:
            arrays = {name: stored[name] for name in stored.files}
        if damage == "compressed":
            np.savez_compressed(entry, **arrays)
        else:
            np.savez(entry, **{**arrays, "planar": np.array([True], dtype=object)})
    else:  # a valid entry made for another key, under this entry's name
        other = tmp_path / "other.obj"
        other.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        cache.cached_scene(other, {}, lambda: load_mesh(other, DEFAULT_CRS), tmp_path / "elsewhere")
        entry.write_bytes(next((tmp_path / "elsewhere").glob("*.npz")).read_bytes())
    calls = []
    real = scene_mesh.load_mesh
    monkeypatch.setattr(scene_mesh, "load_mesh", lambda *a, **k: calls.append(1) or real(*a, **k))
    same_scene(plan.build_scene(cfg), fresh)
    assert calls == [1]
    monkeypatch.setattr(scene_mesh, "load_mesh", refuse_to_load)  # the entry was written again
    same_scene(plan.build_scene(cfg), fresh)


def test_an_unwritable_cache_or_scene_cache_off_still_loads(tmp_path, monkeypatch):
    cfg, _ = cached_config(tmp_path, monkeypatch)
    (tmp_path / "cache").write_text("a file where the folder should be")
    first = plan.build_scene(cfg)
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "unused"))
    set_value(cfg, "run.scene_cache", "false")
    same_scene(plan.build_scene(cfg), first)
    assert not (tmp_path / "unused").exists()


def test_entries_of_vanished_sources_are_removed(tmp_path, monkeypatch):
    cfg, path = cached_config(tmp_path, monkeypatch)
    plan.build_scene(cfg)
    path.unlink()
    other = tmp_path / "other.obj"
    other.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    set_value(cfg, "scene.name", str(other))
    plan.build_scene(cfg)
    assert [p.name.split("-")[0] for p in (tmp_path / "cache").glob("*.npz")] == ["other"]


def forest_config(tmp_path, monkeypatch, **settings):
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "cache"))
    cfg = RunConfig()
    for key, value in {"scene.name": "forest", "scene.forest_size_m": 30.0, "flight.duration_s": 0.1,
                       **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def test_a_second_forest_run_reads_its_voxels_from_the_cache_bit_for_bit(tmp_path, monkeypatch):
    cfg = forest_config(tmp_path, monkeypatch)
    fresh = plan.build_scene(cfg).canopy
    (entry,) = (tmp_path / "cache").glob("forest-*.npz")
    monkeypatch.setattr(forest_scene, "stand_voxels", refuse_to_load)
    cached = plan.build_scene(cfg).canopy
    for name in ("lad", "lower", "cell"):
        assert getattr(cached, name).tobytes() == getattr(fresh, name).tobytes()
        assert getattr(cached, name).dtype == getattr(fresh, name).dtype
    # another seed, voxel size or stand setting is another stand: computed afresh, kept beside the first
    for key, value in (("run.seed", 5), ("scene.forest_voxel_m", 0.5), ("scene.forest_stems_per_ha", 300.0)):
        other = forest_config(tmp_path, monkeypatch, **{key: value})
        with pytest.raises(AssertionError, match="from the cache"):
            plan.build_scene(other)
    monkeypatch.undo()
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "cache"))
    entry.write_bytes(entry.read_bytes()[: entry.stat().st_size // 2])  # cut short: computed again
    assert plan.build_scene(cfg).canopy.lad.tobytes() == fresh.lad.tobytes()


def test_forest_voxels_outlive_the_orphan_sweep_and_stay_out_with_the_cache_off(tmp_path, monkeypatch):
    cfg = forest_config(tmp_path, monkeypatch)
    plan.build_scene(cfg)
    mesh_cfg, _ = cached_config(tmp_path, monkeypatch)  # a file scene's entry: the sweep of vanished sources runs
    plan.build_scene(mesh_cfg)
    assert sorted(p.name.split("-")[0] for p in (tmp_path / "cache").glob("*.npz")) == ["forest", "terrain"]
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "unused"))
    set_value(cfg, "run.scene_cache", "false")
    assert plan.build_scene(cfg).canopy is not None
    assert not (tmp_path / "unused").exists()


def test_the_forest_truth_and_a_forest_run_compute_the_stands_voxels_once(tmp_path, monkeypatch, device):
    """On every device: `flightsim forest --device` integrates the voxels where a flight on that device does (the
    host for the CPU, the GPU for a GPU), so the flight reads the truth's voxels from the cache."""
    from flightsim.studies.forest_truth import run_forest

    cfg = forest_config(tmp_path, monkeypatch, **{"run.seed": 7, "run.device": device})
    run_forest(tmp_path / "truth", [("scene.forest_size_m", "30")], seed=7, device=device)
    monkeypatch.setattr(forest_scene, "stand_voxels", refuse_to_load)
    canopy = plan.build_scene(cfg).canopy
    with np.load(tmp_path / "truth" / "canopy.npz") as truth:
        assert truth["lad"].tobytes() == canopy.lad.tobytes()


def test_voxels_integrated_on_a_device_are_cached_apart_from_the_hosts(tmp_path, monkeypatch):
    """A run on a GPU integrates its stand's voxels there (``kernels.crown_voxels``, a few float64 ulps from the
    host's NumPy): each kind of integration keeps an entry of its own, read back bit for bit."""
    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "cache"))
    s = forest_config(tmp_path, monkeypatch).scene
    from flightsim.scenes.forest_voxels import stand_voxels

    kernel = forest_scene.forest_scene(s, 30.0, 3, use_cache=True, device="cpu").canopy
    assert kernel.lad.tobytes() == stand_voxels(forest_scene.stand(s, 3), s.forest_voxel_m, "cpu")[0].tobytes()
    host = forest_scene.forest_scene(s, 30.0, 3, use_cache=True).canopy  # not the kernel's entry
    assert host.lad.tobytes() == stand_voxels(forest_scene.stand(s, 3), s.forest_voxel_m)[0].tobytes()
    assert len(list((tmp_path / "cache").glob("forest-*.npz"))) == 2
    monkeypatch.setattr(forest_scene, "stand_voxels", refuse_to_load)
    for device, made in (("cpu", kernel), (None, host)):
        again = forest_scene.forest_scene(s, 30.0, 3, use_cache=True, device=device).canopy
        assert again.lad.tobytes() == made.lad.tobytes()
    assert forest_scene.voxel_device("cpu") is None and forest_scene.voxel_device("cuda:1") == "cuda:1"
