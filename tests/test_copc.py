"""COPC output (flightsim.outputs.copc, ``output.copc``): every point once, a valid octree, CRS and extra bytes.

The files are checked against the run's tiles read by ``read_points``, with laspy's COPC reader (a
query of the whole extent and of a sub-box), with a parser of the hierarchy written here from the
COPC 1.0 specification, and with copc.js under node (``Copc.create``, ``loadHierarchyPage``,
``loadPointDataView``: what a web viewer does).
"""
from __future__ import annotations

import struct
from pathlib import Path

import laspy
import lazrs
import numpy as np
import pyproj
import pytest

from copcjs import read_with_copcjs
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.config_io import load_toml, to_toml
from flightsim.core.errors import InputError
from flightsim.engine.run import simulate_to_directory
from flightsim.outputs import copc as copc_module
from flightsim.outputs.copc import NODE_GRID, write_copc
from flightsim.outputs.las_points import read_points

MM = 1e-3
SMALL_CAP = 200  # points per node in the deep octree written from the run's tiles
EXTRAS = ("beam_row", "beam_col", "prism_angle", "range", "plane_id", "edge_distance")
FIELD = {"beam_row": "beam_row", "beam_col": "beam_col", "prism_angle": "prism_angle_deg",
         "range": "range_m", "plane_id": "plane_id", "edge_distance": "edge_distance_m"}


def config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in settings.items():
        set_value(cfg, key.replace("__", "."), value)
    return validate(cfg)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short CPU run with ``output.copc``; also a deep octree (SMALL_CAP) of its exact model."""
    directory = tmp_path_factory.mktemp("copc") / "run"
    summary = simulate_to_directory(config(flight__duration_s=0.2, output__copc=True), directory)
    deep = directory.parent / "deep.copc.laz"
    write_copc(tiles_of(directory, "exact"), deep, max_node_points=SMALL_CAP)
    return directory, summary, deep


def tiles_of(directory: Path, model: str) -> list[Path]:
    return sorted((directory / model).glob("*.las"))


def tile_table(directory: Path, model: str) -> dict[str, np.ndarray]:
    """The model's points from its tiles (read_points): world mm integers, GPS time, extra bytes."""
    batch, _ = read_points(tiles_of(directory, model))
    table = {axis: np.rint(getattr(batch, axis.lower()) / MM).astype(np.int64) for axis in "XYZ"}
    table["gps_time"] = batch.gps_time
    table.update({name: getattr(batch, FIELD[name]) for name in EXTRAS})
    return table


def copc_table(points: laspy.ScaleAwarePointRecord, header: laspy.LasHeader) -> dict[str, np.ndarray]:
    """The same columns from laspy's COPC reader: stored integers shifted by the offsets [mm]."""
    table = {axis: np.asarray(points[axis], dtype=np.int64) + int(round(off / MM))
             for axis, off in zip("XYZ", header.offsets)}
    table["gps_time"] = np.asarray(points["gps_time"])
    table.update({name: np.asarray(points[name]) for name in EXTRAS})
    return table


def sorted_rows(table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Columns ordered by (gps_time, beam_row, beam_col, X, Y, Z)."""
    order = np.lexsort([table[k] for k in ("Z", "Y", "X", "beam_col", "beam_row", "gps_time")])
    return {k: v[order] for k, v in table.items()}


def assert_same_points(got: dict, want: dict) -> None:
    got, want = sorted_rows(got), sorted_rows(want)
    assert len(got["X"]) == len(want["X"])
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


# ---------------------------------------------------------------- independent parse of the file


def raw_vlrs(path: Path) -> dict[tuple[str, int], bytes]:
    """{(user id, record id): record bytes} of the VLRs and EVLRs, walked from the LAS 1.4 header."""
    data = path.read_bytes()
    header_size, = struct.unpack_from("<H", data, 94)
    n_vlrs, = struct.unpack_from("<I", data, 100)
    evlr_start, n_evlrs = struct.unpack_from("<QI", data, 235)
    records, at = {}, header_size
    for _ in range(n_vlrs):
        _, user, record, length, _ = struct.unpack_from("<H16sHH32s", data, at)
        records[(user.rstrip(b"\0").decode(), record)] = data[at + 54: at + 54 + length]
        at += 54 + length
    at = evlr_start
    for _ in range(n_evlrs):
        _, user, record, length, _ = struct.unpack_from("<H16sHQ32s", data, at)
        records[(user.rstrip(b"\0").decode(), record)] = data[at + 60: at + 60 + length]
        at += 60 + length
    return records


def copc_info(path: Path) -> dict:
    """The ``copc``/1 info VLR, which must be the first VLR (at byte 375 + 54)."""
    data = path.read_bytes()
    user, record = struct.unpack_from("<16sH", data, 375 + 2)
    assert (user.rstrip(b"\0"), record) == (b"copc", 1)
    values = struct.unpack_from("<5d2Q2d", data, 375 + 54)
    return dict(zip(("cx", "cy", "cz", "halfsize", "spacing", "page_offset", "page_size", "gps_min", "gps_max"),
                    values))


def hierarchy(path: Path) -> dict[tuple, tuple[int, int, int]]:
    """{(d, x, y, z): (chunk offset, byte size, point count)} of the root hierarchy page."""
    info = copc_info(path)
    page = path.read_bytes()[info["page_offset"]: info["page_offset"] + info["page_size"]]
    entries = [struct.unpack_from("<4iQii", page, k) for k in range(0, len(page), 32)]
    return {tuple(e[:4]): e[4:] for e in entries}


# ---------------------------------------------------------------- the run's files


def test_summary_names_one_copc_per_model(run):
    directory, summary, _ = run
    assert summary["copc"] == {"exact": "exact.copc.laz", "nominal": "nominal.copc.laz"}
    for name in summary["copc"].values():
        assert (directory / name).is_file()
    assert not [p.name for p in directory.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("model", ["exact", "nominal"])
def test_every_tile_point_exactly_once(run, model):
    directory, summary, _ = run
    with laspy.CopcReader.open(directory / f"{model}.copc.laz") as reader:
        points = reader.query()
        header = reader.header
    assert header.point_count == summary["points"][model] == len(points)
    assert_same_points(copc_table(points, header), tile_table(directory, model))


def test_deep_octree_holds_every_point_once(run):
    directory, _, deep = run
    with laspy.CopcReader.open(deep) as reader:
        points, header = reader.query(), reader.header
    assert_same_points(copc_table(points, header), tile_table(directory, "exact"))
    assert max(key[0] for key in hierarchy(deep)) >= 3


def test_sub_box_query_returns_exactly_the_tile_points_inside(run):
    directory, _, deep = run
    want = tile_table(directory, "exact")
    lo = np.array([np.percentile(want["X"], 10), np.percentile(want["Y"], 20), want["Z"].min()]).astype(np.int64)
    hi = np.array([np.percentile(want["X"], 50), np.percentile(want["Y"], 90), want["Z"].max()]).astype(np.int64)
    inside = np.all([(lo[i] <= want[a]) & (want[a] <= hi[i]) for i, a in enumerate("XYZ")], axis=0)
    assert 0 < inside.sum() < len(inside) / 2
    for path in (directory / "exact.copc.laz", deep):
        with laspy.CopcReader.open(path) as reader:
            bounds = laspy.copc.Bounds(mins=lo * MM, maxs=hi * MM)
            got = copc_table(reader.query(bounds=bounds), reader.header)
        assert_same_points(got, {k: v[inside] for k, v in want.items()})


def test_crs_and_extra_bytes_are_the_tiles(run):
    directory, _, _ = run
    tile = raw_vlrs(tiles_of(directory, "exact")[0])
    for name in ("exact.copc.laz", "nominal.copc.laz"):
        path = directory / name
        records = raw_vlrs(path)
        assert records[("LASF_Projection", 2112)] == tile[("LASF_Projection", 2112)]
        assert records[("LASF_Spec", 4)] == tile[("LASF_Spec", 4)]
        wkt = records[("LASF_Projection", 2112)].rstrip(b"\0").decode()
        assert wkt.startswith("PROJCS[")
        assert pyproj.CRS.from_wkt(wkt) == pyproj.CRS.from_user_input(RunConfig().scene.crs)
        with laspy.open(path) as reader:
            assert reader.header.parse_crs().to_epsg() == 32648
            assert list(reader.header.point_format.extra_dimension_names) == list(EXTRAS)
            assert reader.header.global_encoding.wkt
            assert reader.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD


def test_info_vlr_and_header(run):
    directory, _, deep = run
    want = tile_table(directory, "exact")
    for path in (directory / "exact.copc.laz", deep):
        info = copc_info(path)
        with laspy.open(path) as reader:
            header = reader.header
        assert header.version == "1.4" and header.point_format.id == 6
        assert info["gps_min"] == want["gps_time"].min() and info["gps_max"] == want["gps_time"].max()
        assert info["spacing"] == pytest.approx(2 * info["halfsize"] / NODE_GRID)
        centre = np.array([info["cx"], info["cy"], info["cz"]])
        np.testing.assert_array_less(centre - info["halfsize"], header.mins)
        np.testing.assert_array_less(header.maxs, centre + info["halfsize"])
        np.testing.assert_allclose(header.mins, [want[a].min() * MM for a in "XYZ"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(header.maxs, [want[a].max() * MM for a in "XYZ"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("which", ["run", "deep"])
def test_octree_is_valid(run, which):
    """Keys have parents, chunks tile the point data, each node's points lie in its voxel and take at
    most one cell of its grid (spacing / 2**d), and no node above the deepest level exceeds the cap."""
    directory, _, deep = run
    path = deep if which == "deep" else directory / "exact.copc.laz"
    cap = SMALL_CAP if which == "deep" else copc_module.MAX_NODE_POINTS
    nodes, info = hierarchy(path), copc_info(path)
    with laspy.open(path) as reader:
        header = reader.header
    assert (0, 0, 0, 0) in nodes
    for (d, x, y, z) in nodes:
        assert all(0 <= c < 2**d for c in (x, y, z))
        assert d == 0 or (d - 1, x >> 1, y >> 1, z >> 1) in nodes
    chunks = sorted(nodes.values())
    assert chunks[0][0] == header.offset_to_point_data + 8  # after the LAZ chunk-table offset
    assert all(a[0] + a[1] == b[0] for a, b in zip(chunks, chunks[1:]))
    assert sum(n for _, _, n in chunks) == header.point_count
    deepest = max(key[0] for key in nodes)
    low = np.array([info["cx"], info["cy"], info["cz"]]) - info["halfsize"]
    for key, (_, _, count) in nodes.items():
        d, xyz = key[0], np.array(key[1:])
        world = node_points(path, header, nodes[key])
        assert len(world) == count, key
        edge = 2 * info["halfsize"] / 2**d
        assert np.all(world >= low + xyz * edge - 0.5 * MM), key
        assert np.all(world <= low + (xyz + 1) * edge + 0.5 * MM), key
        if d < deepest:
            assert count <= cap, key
            cells = np.floor((world - low) / (info["spacing"] / 2**d) + 1e-9).astype(np.int64)
            assert len(np.unique(cells, axis=0)) == count, key


def node_points(path: Path, header: laspy.LasHeader, entry: tuple[int, int, int]) -> np.ndarray:
    """World x, y, z [m] of one node: its chunk alone, decompressed with the file's LAZ VLR."""
    offset, size, count = entry
    records = np.zeros(count * header.point_format.size, dtype=np.uint8)
    laszip = raw_vlrs(path)[("laszip encoded", 22204)]
    lazrs.decompress_points_with_chunk_table(path.read_bytes()[offset: offset + size], laszip, records,
                                             [(count, size)])
    points = laspy.PackedPointRecord.from_buffer(records, header.point_format)
    return np.column_stack([points[a] * header.scales[i] + header.offsets[i] for i, a in enumerate("XYZ")])


def test_level_query_streams_root_first(run):
    directory, _, deep = run
    nodes = hierarchy(deep)
    with laspy.CopcReader.open(deep) as reader:
        assert len(reader.query(level=0)) == nodes[(0, 0, 0, 0)][2]
        assert len(reader.query(level=range(0, 2))) == sum(n for k, (_, _, n) in nodes.items() if k[0] < 2)


# ---------------------------------------------------------------- copc.js


@pytest.mark.parametrize("which", ["run", "deep"])
def test_copcjs_reads_every_point_crs_and_extra_bytes(run, which):
    directory, summary, deep = run
    path = deep if which == "deep" else directory / "exact.copc.laz"
    got = read_with_copcjs("read_copc.js", path)
    header, pts = got["header"], got["points"]
    assert header["pointCount"] == summary["points"]["exact"] == len(pts["X"])
    assert pyproj.CRS.from_wkt(got["wkt"]).to_epsg() == 32648
    assert [eb["name"] for eb in got["extraBytes"]] == list(EXTRAS)
    assert got["nodes"] == {"-".join(map(str, k)): n for k, (_, _, n) in hierarchy(path).items()}
    assert got["pages"] == []
    table = {a: np.rint((np.array(pts[a]) - off) / MM).astype(np.int64) + int(round(off / MM))
             for a, off in zip("XYZ", header["offset"])}
    table["gps_time"] = np.array(pts["GpsTime"])
    table.update({name: np.array(pts[name]) for name in EXTRAS})
    want = tile_table(directory, "exact")
    for name in ("prism_angle", "range", "edge_distance"):  # copc.js gives float32 as JS numbers
        want[name] = want[name].astype(np.float64)
    assert_same_points(table, want)


# ---------------------------------------------------------------- config and bad input


def test_config_field_round_trips(tmp_path):
    cfg = config(output__copc=True)
    path = tmp_path / "run.toml"
    path.write_text(to_toml(cfg), encoding="utf-8")
    assert validate(load_toml(path)).output.copc is True
    assert "copc = false" in to_toml(RunConfig())


@pytest.mark.parametrize("detector", ["photon", "waveform"])
def test_copc_needs_discrete_returns(detector):
    with pytest.raises(InputError, match="output.copc"):
        config(output__copc=True, instrument__detector=detector)


def test_copc_value_must_be_boolean():
    with pytest.raises(InputError, match="output.copc"):
        set_value(RunConfig(), "output.copc", "sometimes")


def test_bad_tiles_are_refused(tmp_path, run):
    directory, _, _ = run
    with pytest.raises(InputError, match="tile_paths"):
        write_copc([], tmp_path / "a.copc.laz")
    junk = tmp_path / "junk.las"
    junk.write_bytes(b"not a LAS file")
    with pytest.raises(InputError, match="tile_paths"):
        write_copc([junk], tmp_path / "a.copc.laz")
    with pytest.raises(InputError, match="max_node_points"):
        write_copc(tiles_of(directory, "exact"), tmp_path / "a.copc.laz", max_node_points=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.las"]


def test_failed_write_leaves_nothing(tmp_path, run, monkeypatch):
    directory, _, _ = run

    def broken(*args):
        raise OSError("disk full")

    monkeypatch.setattr(copc_module, "_hierarchy", broken)
    with pytest.raises(OSError, match="disk full"):
        write_copc(tiles_of(directory, "exact"), tmp_path / "a.copc.laz")
    assert list(tmp_path.iterdir()) == []


def test_overwrite_without_copc_removes_the_old_files(tmp_path):
    directory = tmp_path / "run"
    assert "copc" in simulate_to_directory(config(flight__duration_s=0.1, output__copc=True), directory)
    summary = simulate_to_directory(config(flight__duration_s=0.1), directory, overwrite=True)
    assert "copc" not in summary
    assert not list(directory.glob("*.copc.laz"))
