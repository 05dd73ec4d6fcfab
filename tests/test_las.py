"""LAS tile output (flightsim.outputs.las_tiles): format, tiling, atomicity, determinism, readers.

Every check compares what a reader gets back with the input batch (the truth), or with facts
from the LAS 1.4 R15 specification; two readers that share no code with laspy (rapidlasso
LASzip through the ``laszip`` pip package, and copc.js under node) read the same tiles.
"""
from __future__ import annotations

import datetime
import os
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest

from copcjs import read_with_copcjs
from flightsim.core import atomic
from flightsim.core.errors import InputError
from flightsim.outputs.las_format import gps_week_date
from flightsim.outputs.las_points import PointBatch, read_points
from flightsim.outputs import las_tiles
from flightsim.outputs.las_tiles import TileWriter

UTM48N = pyproj.CRS.from_epsg(32648)
CREATED = datetime.date(2021, 3, 17)
EXTRA_SCHEMA = {  # LAS name -> (copc.js type, bytes, PointBatch field)
    "beam_row": ("unsigned", 1, "beam_row"),
    "beam_col": ("unsigned", 1, "beam_col"),
    "prism_angle": ("float", 4, "prism_angle_deg"),
    "range": ("float", 4, "range_m"),
    "plane_id": ("signed", 4, "plane_id"),
    "position_error": ("float", 4, "position_error_m"),
}
EXTRA_UNITS = {"prism_angle": "[deg]", "range": "[m]", "position_error": "[m]"}
MM = 1e-3


def make_batch(x, y, z=None, *, seed=0, position_error=False) -> PointBatch:
    """A batch at the given coordinates with varied, known values in every other field."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    rng = np.random.default_rng(seed)
    return PointBatch(
        x=x,
        y=np.asarray(y, dtype=np.float64),
        z=rng.uniform(-20.0, 80.0, n) if z is None else np.asarray(z, dtype=np.float64),
        gps_time=3.0e8 + 1.0e-4 * np.arange(n) + 0.123456,
        point_source_id=rng.integers(1, 6, n),
        classification=rng.choice([2, 6, 11], n),
        scan_angle_deg=rng.uniform(-15.0, 15.0, n),
        intensity=rng.integers(0, 65536, n),
        beam_row=rng.integers(0, 64, n),
        beam_col=rng.integers(0, 64, n),
        prism_angle_deg=rng.uniform(0.0, 360.0, n),
        range_m=rng.uniform(480.0, 5200.0, n),
        plane_id=rng.integers(-1, 500, n),
        position_error_m=rng.uniform(0.0, 0.3, n) if position_error else None,
    )


def random_batch(n, *, seed=0, position_error=False) -> PointBatch:
    """``n`` points scattered over 2 x 2 tiles of 500 m at UTM 48N coordinates."""
    rng = np.random.default_rng(seed + 1000)
    return make_batch(
        409000.0 + rng.uniform(0.0, 1000.0, n),
        3392000.0 + rng.uniform(0.0, 1000.0, n),
        seed=seed,
        position_error=position_error,
    )


def write_tiles(directory, batches, **options) -> dict[str, int]:
    options = {"creation_date": CREATED, **options}
    with TileWriter(directory, UTM48N, **options) as writer:
        for batch in batches if isinstance(batches, list) else [batches]:
            writer.write(batch)
    return writer.tile_counts


def _counts(directory) -> dict[str, int]:
    """{file name: point count from its header} of every file in ``directory``."""
    counts = {}
    for path in sorted(Path(directory).iterdir()):
        with laspy.open(path) as reader:
            counts[path.name] = reader.header.point_count
    return counts


def expected_tile(batch: PointBatch, size=500.0) -> list[str]:
    """Tile name of each point by definition: corner = floor(x / size) * size, x on the mm grid."""
    xq = np.round(batch.x * 1000.0) / 1000.0
    yq = np.round(batch.y * 1000.0) / 1000.0
    e = (np.floor(xq / size) * size).astype(np.int64)
    n = (np.floor(yq / size) * size).astype(np.int64)
    return [f"{a}_{b}" for a, b in zip(e, n)]


def points_of_tile(batch: PointBatch, tile_stem: str, size=500.0) -> PointBatch:
    return batch.select(np.array(expected_tile(batch, size)) == tile_stem)


def assert_points_match(got: PointBatch, want: PointBatch, *, extras=True) -> None:
    assert len(got) == len(want)
    np.testing.assert_allclose(got.x, want.x, rtol=0, atol=0.5 * MM + 1e-9)
    np.testing.assert_allclose(got.y, want.y, rtol=0, atol=0.5 * MM + 1e-9)
    np.testing.assert_allclose(got.z, want.z, rtol=0, atol=0.5 * MM + 1e-9)
    np.testing.assert_allclose(got.gps_time, want.gps_time, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got.classification, want.classification)
    np.testing.assert_array_equal(got.point_source_id, want.point_source_id)
    np.testing.assert_array_equal(got.intensity, want.intensity)
    np.testing.assert_allclose(got.scan_angle_deg, want.scan_angle_deg, rtol=0, atol=0.003 + 1e-5)
    if extras:
        for field in ("beam_row", "beam_col", "prism_angle_deg", "range_m", "plane_id"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)


# ---------------------------------------------------------------- round trip through laspy


def test_round_trip_laspy_header_points_and_crs(tmp_path):
    batch = random_batch(4000)
    with TileWriter(tmp_path, UTM48N, creation_date=CREATED) as writer:
        writer.write(batch)
    assert _counts(tmp_path) == writer.tile_counts
    assert sorted(writer.tile_counts) == sorted(f"{s}.las" for s in set(expected_tile(batch)))
    assert sum(writer.tile_counts.values()) == len(batch)
    for path in sorted(tmp_path.iterdir()):
        las = laspy.read(path)
        header = las.header
        east, north = (float(v) for v in path.stem.split("_"))
        assert (header.version.major, header.version.minor) == (1, 4)
        assert header.point_format.id == 6
        np.testing.assert_array_equal(header.scales, [0.001, 0.001, 0.001])
        np.testing.assert_array_equal(header.offsets, [east, north, 0.0])
        assert header.global_encoding.value & 0b1 == 1  # adjusted standard GPS time
        assert header.global_encoding.value & 0b1_0000 == 0b1_0000  # WKT CRS
        assert header.parse_crs() == UTM48N
        assert header.parse_crs().to_epsg() == 32648
        assert header.creation_date == CREATED
        assert header.system_identifier == "flightsim"
        assert header.generating_software.startswith("flightsim ")
        assert header.uuid.int == 0
        assert header.file_source_id == 0
        np.testing.assert_array_equal(las.return_number, 1)
        np.testing.assert_array_equal(las.number_of_returns, 1)
        want = points_of_tile(batch, path.stem)
        got = PointBatch(
            x=las.x, y=las.y, z=las.z, gps_time=las.gps_time,
            point_source_id=las.point_source_id, classification=las.classification,
            scan_angle_deg=np.asarray(las.scan_angle) * 0.006, intensity=las.intensity,
            beam_row=las.beam_row, beam_col=las.beam_col, prism_angle_deg=las.prism_angle,
            range_m=las.range, plane_id=las.plane_id,
        )
        assert_points_match(got, want)
        # the raw integers are the scan angle in 0.006 deg units, sign kept
        np.testing.assert_array_equal(las.scan_angle, np.round(want.scan_angle_deg / 0.006))
        # stored coordinates lie within [0, 500 m) of the tile offset
        assert las.X.min() >= 0 and las.X.max() < 500_000
        assert las.Y.min() >= 0 and las.Y.max() < 500_000
        assert "position_error" not in las.point_format.dimension_names


def test_crs_record_is_ogc_wkt1(tmp_path):
    """LAS 1.4 R15 §2.5: the LASF_Projection/2112 record holds OGC 01-009 WKT (WKT1)."""
    write_tiles(tmp_path, make_batch([409010.0], [3392010.0]))
    header = laspy.read(next(tmp_path.iterdir())).header
    wkt_records = [v for v in header.vlrs if (v.user_id, v.record_id) == ("LASF_Projection", 2112)]
    assert len(wkt_records) == 1
    geotiff = [v for v in header.vlrs if v.user_id == "LASF_Projection" and v.record_id != 2112]
    assert geotiff == []
    wkt = wkt_records[0].string
    assert wkt.startswith('PROJCS["WGS 84 / UTM zone 48N"')
    assert 'AUTHORITY["EPSG","32648"]' in wkt
    assert pyproj.CRS.from_wkt(wkt).to_epsg() == 32648


def test_compound_crs_round_trips(tmp_path):
    crs = pyproj.CRS("EPSG:32648+5773")  # UTM 48N + EGM96 height
    with TileWriter(tmp_path, crs, creation_date=CREATED) as writer:
        writer.write(make_batch([409010.0], [3392010.0]))
    got = laspy.read(next(tmp_path.iterdir())).header.parse_crs()
    assert got.is_compound
    assert [sub.to_epsg() for sub in got.sub_crs_list] == [32648, 5773]


def test_position_error_written_only_when_asked(tmp_path):
    batch = random_batch(300, position_error=True)
    write_tiles(tmp_path / "with", batch, extras=("position_error",))
    write_tiles(tmp_path / "without", batch)
    got, _ = read_points(sorted((tmp_path / "with").iterdir()))
    order = np.argsort(got.gps_time)
    np.testing.assert_array_equal(got.position_error_m[order], batch.position_error_m)
    got, _ = read_points(sorted((tmp_path / "without").iterdir()))
    assert got.position_error_m is None
    with pytest.raises(ValueError, match="position_error"):
        write_tiles(tmp_path / "x", random_batch(10), extras=("position_error",))


def test_extra_bytes_descriptors_give_units_and_claim_no_wrong_statistics(tmp_path):
    batch = random_batch(500, position_error=True)
    write_tiles(tmp_path, batch, extras=("position_error",))
    header = laspy.read(sorted(tmp_path.iterdir())[0]).header
    descriptors = header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs
    assert [d.name.decode() for d in descriptors] == list(EXTRA_SCHEMA)
    for d in descriptors:
        description = d.description.decode()
        assert "[" in description and "]" in description, description
        assert EXTRA_UNITS.get(d.name.decode(), "[") in description
        assert d.options & 0b110 == 0  # min/max not flagged: laspy 2.7 would get them wrong


# ---------------------------------------------------------------- independent reader 1: LASzip


def _laszip_module():
    try:
        import laszip
    except ImportError:
        pytest.fail("the independent LAS reader is missing: pip install 'laszip>=0.3' (test extra)")
    return laszip


def _read_with_laszip(path: Path) -> tuple[dict, dict]:
    """Header fields and per-point values as rapidlasso LASzip's C API returns them."""
    laszip = _laszip_module()
    reader = laszip.LasZipDll()
    is_compressed = reader.open_reader(str(path))  # raises LaszipError on failure
    h = reader.header()
    header = {
        "compressed": is_compressed,
        "version": (h.version_major, h.version_minor),
        "format": h.point_data_format,
        "global_encoding": h.global_encoding,
        "scale": (h.x_scale_factor, h.y_scale_factor, h.z_scale_factor),
        "offset": (h.x_offset, h.y_offset, h.z_offset),
        "count": h.extended_number_of_point_records,
        "record_length": h.point_data_record_length,
        "system_identifier": h.system_identifier.rstrip("\0"),
        "created": (h.file_creation_year, h.file_creation_day),
    }
    columns = {k: [] for k in ("X", "Y", "Z", "gps", "cls", "angle", "source", "rn", "nr", "extra")}
    for _ in range(header["count"]):
        reader.read_point()
        p = reader.point()
        columns["X"].append(p.X)
        columns["Y"].append(p.Y)
        columns["Z"].append(p.Z)
        columns["gps"].append(p.gps_time)
        columns["cls"].append(p.extended_classification)
        columns["angle"].append(p.extended_scan_angle)
        columns["source"].append(p.point_source_ID)
        columns["rn"].append(p.extended_return_number)
        columns["nr"].append(p.extended_number_of_returns)
        columns["extra"].append(bytes(np.asarray(p.extra_bytes, dtype=np.uint8)))
    reader.close_reader()
    return header, {k: np.array(v) for k, v in columns.items()}


@pytest.mark.parametrize("compress", [False, True], ids=["las", "laz"])
def test_independent_reader_laszip(tmp_path, compress):
    batch = random_batch(1500, position_error=True)
    write_tiles(tmp_path, batch, compress=compress, extras=("position_error",))
    # extra bytes after the 30-byte format-6 record, in the order documented by las_format
    extra_dtype = np.dtype(
        [("beam_row", "u1"), ("beam_col", "u1"), ("prism_angle", "<f4"), ("range", "<f4"),
         ("plane_id", "<i4"), ("position_error", "<f4")]
    )
    seen = 0
    for path in sorted(tmp_path.iterdir()):
        header, pts = _read_with_laszip(path)
        east, north = (float(v) for v in path.stem.split("_"))
        want = points_of_tile(batch, path.stem)
        assert header["compressed"] is compress
        assert header["version"] == (1, 4)
        assert header["format"] == 6
        assert header["global_encoding"] & 0b1_0001 == 0b1_0001
        assert header["scale"] == (0.001, 0.001, 0.001)
        assert header["offset"] == (east, north, 0.0)
        assert header["count"] == len(want)
        assert header["record_length"] == 30 + extra_dtype.itemsize
        assert header["system_identifier"] == "flightsim"
        assert header["created"] == (2021, CREATED.timetuple().tm_yday)
        np.testing.assert_allclose(pts["X"] * 0.001 + east, want.x, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["Y"] * 0.001 + north, want.y, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["Z"] * 0.001, want.z, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["gps"], want.gps_time, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(pts["cls"], want.classification)
        np.testing.assert_allclose(
            pts["angle"] * 0.006, want.scan_angle_deg, rtol=0, atol=0.003 + 1e-5
        )
        np.testing.assert_array_equal(pts["source"], want.point_source_id)
        np.testing.assert_array_equal(pts["rn"], 1)
        np.testing.assert_array_equal(pts["nr"], 1)
        extra = np.frombuffer(b"".join(pts["extra"]), dtype=extra_dtype)
        for name, (_, _, field) in EXTRA_SCHEMA.items():
            np.testing.assert_array_equal(extra[name], getattr(want, field), err_msg=name)
        seen += len(want)
    assert seen == len(batch)


# ---------------------------------------------------------------- independent reader 2: copc.js


@pytest.mark.parametrize("compress", [False, True], ids=["las", "laz"])
def test_independent_reader_copcjs(tmp_path, compress):
    batch = random_batch(1200, position_error=True)
    write_tiles(tmp_path, batch, compress=compress, extras=("position_error",))
    seen = 0
    for path in sorted(tmp_path.iterdir()):
        got = read_with_copcjs("read_las.js", path)
        header, pts = got["header"], got["points"]
        east, north = (float(v) for v in path.stem.split("_"))
        want = points_of_tile(batch, path.stem)
        assert got["compressed"] is compress
        assert (header["majorVersion"], header["minorVersion"]) == (1, 4)
        assert header["pointDataRecordFormat"] == 6
        assert header["globalEncoding"] & 0b1_0001 == 0b1_0001
        assert header["scale"] == [0.001, 0.001, 0.001]
        assert header["offset"] == [east, north, 0]
        assert header["pointCount"] == len(want)
        assert header["projectId"].replace("-", "") == "0" * 32
        assert pyproj.CRS.from_wkt(got["wkt"]).to_epsg() == 32648
        assert got["wkt"].startswith("PROJCS[")
        schema = {eb["name"]: (eb["type"], eb["length"]) for eb in got["extraBytes"]}
        assert schema == {name: spec[:2] for name, spec in EXTRA_SCHEMA.items()}
        for eb in got["extraBytes"]:
            assert EXTRA_UNITS.get(eb["name"], "[") in eb["description"], eb
            assert "min" not in eb and "max" not in eb
        np.testing.assert_allclose(pts["X"], want.x, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["Y"], want.y, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["Z"], want.z, rtol=0, atol=0.5 * MM + 1e-9)
        np.testing.assert_allclose(pts["GpsTime"], want.gps_time, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(pts["Classification"], want.classification)
        np.testing.assert_allclose(pts["ScanAngle"], want.scan_angle_deg, rtol=0, atol=0.003 + 1e-5)
        np.testing.assert_array_equal(pts["PointSourceId"], want.point_source_id)
        np.testing.assert_array_equal(pts["Intensity"], want.intensity)
        np.testing.assert_array_equal(pts["ReturnNumber"], 1)
        np.testing.assert_array_equal(pts["NumberOfReturns"], 1)
        for name, (_, _, field) in EXTRA_SCHEMA.items():
            truth = getattr(want, field)
            np.testing.assert_array_equal(np.array(pts[name], truth.dtype), truth, err_msg=name)
        seen += len(want)
    assert seen == len(batch)


# ---------------------------------------------------------------- tiling


def test_tiles_split_at_boundaries_upper_tile_owns_the_edge(tmp_path):
    x = [409499.999, 409500.0, 409500.001, 409499.9996, 408999.9, -0.001, 0.0, 409250.0]
    y = [3392000.0, 3392000.0, 3392499.999, 3392500.0, 3392250.0, -250.0, 0.0, 3392500.0]
    batch = make_batch(x, y)
    with TileWriter(tmp_path, UTM48N, creation_date=CREATED) as writer:
        writer.write(batch)
    counts = _counts(tmp_path)
    want = {
        "409000_3392000.las": 1,  # 409499.999: last mm of the lower tile
        "409500_3392000.las": 2,  # exactly on the edge, and 1 mm above it
        "409500_3392500.las": 1,  # 409499.9996 rounds onto the edge: stored as 409500.000
        "408500_3392000.las": 1,
        "-500_-500.las": 1,  # floor, not truncation, below zero
        "0_0.las": 1,
        "409000_3392500.las": 1,
    }
    assert counts == want
    assert writer.tile_counts == want
    for path in tmp_path.iterdir():
        las = laspy.read(path)
        east, north = (float(v) for v in path.stem.split("_"))
        np.testing.assert_array_equal(las.header.offsets, [east, north, 0.0])
        assert np.all((las.X >= 0) & (las.X < 500_000) & (las.Y >= 0) & (las.Y < 500_000))
        assert np.all((las.x >= east) & (las.x < east + 500.0))
        assert np.all((las.y >= north) & (las.y < north + 500.0))


def test_close_returns_counts_per_tile_name(tmp_path):
    batch = random_batch(2000)
    writer = TileWriter(tmp_path, UTM48N, tile_size_m=250, creation_date=CREATED)
    writer.write(batch.select(slice(0, 700)))
    writer.write(batch.select(slice(700, None)))
    counts = writer.close()
    stems, numbers = np.unique(expected_tile(batch, 250.0), return_counts=True)
    assert counts == {f"{s}.las": int(k) for s, k in zip(stems, numbers)}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(counts)
    assert _counts(tmp_path) == counts


def test_points_keep_batch_order_within_a_tile(tmp_path):
    batch = random_batch(3000)
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED)
    for start in range(0, 3000, 400):
        writer.write(batch.select(slice(start, start + 400)))
    writer.close()
    for path in tmp_path.iterdir():
        gps = np.asarray(laspy.read(path).gps_time)
        assert np.all(np.diff(gps) > 0)  # input gps_time is increasing


def test_points_stream_to_disk_before_close(tmp_path):
    """Memory stays bounded: written points are already in the temporary file, not buffered."""
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED)
    n = 20_000
    writer.write(make_batch(np.full(n, 409100.0), np.full(n, 3392100.0)))
    part = tmp_path / ".409000_3392000.las.part"
    assert part.stat().st_size >= n * 48 // 2  # record length 48 B; some may sit in the io buffer
    writer.close()


@pytest.mark.skipif(not atomic.FADVISE, reason="no posix_fadvise on this system")
def test_each_write_is_handed_to_the_disk_write_back(tmp_path, monkeypatch):
    """Every LAS write asks the kernel to start writing exactly the bytes it added (one range after another,
    from the end of the header to the end of the points, a reopened tile's from its old end), so a run's
    output reaches the disk while it traces; the tile keeps every point."""
    asked: list[tuple[int, int, int]] = []
    monkeypatch.setattr(las_tiles.os, "posix_fadvise", lambda fd, offset, length, advice:
                        asked.append((offset, length, advice)))
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED, max_open_tiles=1)
    for k, n in enumerate((1000, 2500, 700)):  # the third batch goes to a second tile, evicting the first
        writer.write(make_batch(np.full(n, 409100.0 + 600.0 * (k == 2)), np.full(n, 3392100.0), seed=k))
    writer.write(make_batch(np.full(300, 409100.0), np.full(300, 3392100.0), seed=3))  # the first, reopened
    writer.close()
    first = laspy.read(tmp_path / "409000_3392000.las")
    start, record = first.header.offset_to_point_data, first.header.point_format.size
    assert [a[2] for a in asked] == [las_tiles.os.POSIX_FADV_DONTNEED] * 4
    first_ranges = [asked[0][:2], asked[1][:2], asked[3][:2]]
    assert first_ranges == [(start, 1000 * record), (start + 1000 * record, 2500 * record),
                            (start + 3500 * record, 300 * record)]
    assert asked[2][1] == 700 * record
    assert len(first.points) == 3800


def test_durable_tiles_are_all_synced_at_close_before_any_rename(tmp_path, monkeypatch):
    """A LAS tile closed to make room (more tiles than may be open) is not synced then: the writer's close syncs
    every tile, then renames them, then syncs the folder, so no tile gets its final name before each is on disk."""
    events: list[tuple[str, object]] = []
    fsync, replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(("sync", os.fstat(fd).st_ino)), fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("rename", Path(a).stat().st_ino)), replace(a, b))[1])
    batch = random_batch(3000, seed=5)
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED, max_open_tiles=1, processes=0)
    for s in range(0, 3000, 700):
        writer.write(batch.select(slice(s, s + 700)))
    assert events == []  # tiles were closed to make room, none synced
    writer.close()
    tiles = {p.stat().st_ino for p in tmp_path.glob("*.las")}
    kinds = [kind for kind, _ in events]
    first_rename = kinds.index("rename")
    assert len(tiles) == 4 and {ino for kind, ino in events[:first_rename] if kind == "sync"} >= tiles
    assert kinds[first_rename:] == ["rename"] * 4 + ["sync"]  # then the folder
    assert events[-1][1] == tmp_path.stat().st_ino


@pytest.mark.parametrize("compress", [False, True])
def test_transient_tiles_are_the_same_bytes_left_to_the_page_cache(tmp_path, monkeypatch, compress):
    """durable=False (a survey's part files): no write-back asked for, no file or folder synced; the same bytes."""
    calls: list[str] = []
    for name in ("fsync", "fdatasync", "posix_fadvise"):
        if hasattr(las_tiles.os, name):
            monkeypatch.setattr(las_tiles.os, name, lambda *args, name=name: calls.append(name))
    batch = random_batch(3000, seed=5)
    pieces = [batch.select(slice(s, s + 700)) for s in range(0, 3000, 700)]
    options = dict(compress=compress, processes=0, max_open_tiles=2)
    write_tiles(tmp_path / "transient", pieces, durable=False, **options)
    assert calls == []
    write_tiles(tmp_path / "durable", pieces, **options)
    synced = {"fsync", "fdatasync"} if compress else {"fsync", "posix_fadvise"} if atomic.FADVISE else {"fsync"}
    assert set(calls) == synced  # what a durable tile set asks for (the spies can see them)
    names = sorted(p.name for p in (tmp_path / "durable").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "transient").iterdir()) and len(names) == 4
    for name in names:
        assert (tmp_path / "durable" / name).read_bytes() == (tmp_path / "transient" / name).read_bytes()


def test_bounded_open_tiles_give_the_same_bytes(tmp_path):
    batch = random_batch(4000, seed=3)
    pieces = [batch.select(slice(s, s + 137)) for s in range(0, 4000, 137)]
    write_tiles(tmp_path / "many", pieces)
    write_tiles(tmp_path / "one", pieces, max_open_tiles=1)
    names = sorted(p.name for p in (tmp_path / "many").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "one").iterdir())
    assert len(names) == 4
    for name in names:
        assert (tmp_path / "many" / name).read_bytes() == (tmp_path / "one" / name).read_bytes()


@pytest.mark.parametrize("max_open", [64, 1])
def test_uncompressed_tiles_are_the_bytes_of_laspys_own_writer(tmp_path, max_open):
    """An uncompressed tile is written without a laspy writer per tile (the template's bytes with the tile's header
    fields patched in): laspy's own LasWriter, given a tile's header and its points, writes the same bytes (bounds
    and counts from its own pass over the points), tiles closed to make room and reopened (max_open 1) too; and a
    tile closed without points is laspy's empty file of its header."""
    from flightsim.outputs.las_plain_tile import PlainTile

    batch = random_batch(3000, seed=11)
    write_tiles(tmp_path / "tiles", [batch.select(slice(s, s + 700)) for s in range(0, 3000, 700)],
                max_open_tiles=max_open)
    paths = sorted((tmp_path / "tiles").iterdir())
    assert len(paths) == 4
    for path in paths:
        tile = laspy.read(path)
        with open(tmp_path / "laspy.las", "wb") as out, laspy.LasWriter(out, tile.header, closefd=False) as writer:
            writer.write_points(tile.points)
        assert (tmp_path / "laspy.las").read_bytes() == path.read_bytes(), path.name
    header = laspy.read(paths[0]).header
    with open(tmp_path / "empty.las", "wb") as out:
        laspy.LasWriter(out, header, closefd=False).close()
    empty = (tmp_path / "empty.las").read_bytes()
    PlainTile.create(tmp_path / "ours.las", empty, header.scales, header.offsets, durable=False).close()
    assert (tmp_path / "ours.las").read_bytes() == empty and header.offsets[0] != 0.0


def test_a_batchs_records_made_a_few_tiles_at_a_time_give_the_same_bytes(tmp_path, monkeypatch):
    """A batch's records are made in runs of whole tiles of at most RECORDS_AT_ONCE points (a larger tile alone):
    a bound of a few points, tiles split across runs of every length, writes the bytes of one run for all."""
    import flightsim.outputs.las_tiles as las_tiles

    batch = random_batch(5000, seed=8)
    write_tiles(tmp_path / "together", [batch])
    monkeypatch.setattr(las_tiles, "RECORDS_AT_ONCE", 7)
    runs = []
    original = las_tiles._tile_runs
    monkeypatch.setattr(las_tiles, "_tile_runs", lambda starts, n: runs.append(original(starts, n)) or runs[-1])
    write_tiles(tmp_path / "runs", [batch])
    assert len(runs[0]) == 4  # every tile (~1,250 points) in a run of its own
    names = sorted(p.name for p in (tmp_path / "together").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "runs").iterdir()) and len(names) == 4
    for name in names:
        assert (tmp_path / "together" / name).read_bytes() == (tmp_path / "runs" / name).read_bytes()


def test_batches_packed_on_threads_and_written_in_order_give_the_same_bytes(tmp_path):
    """``pack`` on several threads at once (the first of them making the tiles' format), ``write_packed`` in the
    batches' order: the bytes of ``write`` batch after batch; packing touches no tile file."""
    from concurrent.futures import ThreadPoolExecutor

    pieces = [random_batch(700, seed=s) for s in range(12)]
    write_tiles(tmp_path / "written", pieces)
    with TileWriter(tmp_path / "packed", UTM48N, creation_date=CREATED) as writer:
        with ThreadPoolExecutor(4) as pool:
            packed = list(pool.map(writer.pack, pieces))
        assert not any((tmp_path / "packed").iterdir())
        assert all(isinstance(part, las_tiles.TileRecords) for parts in packed for part in parts)
        for parts in packed:
            writer.write_packed(parts)
    names = sorted(p.name for p in (tmp_path / "written").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "packed").iterdir()) and len(names) == 4
    for name in names:
        assert (tmp_path / "written" / name).read_bytes() == (tmp_path / "packed" / name).read_bytes()


def test_tile_runs_hold_whole_tiles_within_the_bound(monkeypatch):
    import flightsim.outputs.las_tiles as las_tiles

    monkeypatch.setattr(las_tiles, "RECORDS_AT_ONCE", 10)
    runs = las_tiles._tile_runs(np.array([0, 3, 9, 25, 27, 28]), 40)
    assert [r.tolist() for r in runs] == [[0, 3, 9], [9, 25], [25, 27, 28], [28, 40]]


def test_bounded_open_tiles_laz_keeps_every_point(tmp_path):
    batch = random_batch(4000, seed=4)
    pieces = [batch.select(slice(s, s + 250)) for s in range(0, 4000, 250)]
    write_tiles(tmp_path, pieces, compress=True, max_open_tiles=1)
    for path in sorted(tmp_path.iterdir()):
        got, _ = read_points(path)
        assert_points_match(got, points_of_tile(batch, path.stem.split(".")[0]))


# ---------------------------------------------------------------- atomicity and determinism


class Boom(RuntimeError):
    pass


def test_failure_mid_run_leaves_no_files(tmp_path):
    batch = random_batch(3000)
    with pytest.raises(Boom):
        with TileWriter(tmp_path, UTM48N, creation_date=CREATED) as writer:
            writer.write(batch.select(slice(0, 1500)))
            assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
                f".{s}.las.part" for s in set(expected_tile(batch.select(slice(0, 1500))))
            )
            raise Boom()
    assert list(tmp_path.iterdir()) == []


def test_failure_after_evictions_leaves_no_files(tmp_path):
    batch = random_batch(3000)
    with pytest.raises(Boom):
        options = dict(creation_date=CREATED, compress=True, max_open_tiles=1)
        with TileWriter(tmp_path, UTM48N, **options) as writer:
            for start in range(0, 3000, 300):
                writer.write(batch.select(slice(start, start + 300)))
            raise Boom()
    assert list(tmp_path.iterdir()) == []


def test_unfinished_run_has_no_final_names(tmp_path):
    """Before close() (e.g. the process dies), only dot-prefixed temporaries exist."""
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED)
    writer.write(random_batch(1000))
    names = [p.name for p in tmp_path.iterdir()]
    assert names and all(n.startswith(".") and n.endswith(".las.part") for n in names)
    writer.abort()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("compress", [False, True], ids=["las", "laz"])
def test_identical_input_gives_identical_bytes(tmp_path, compress):
    batch = random_batch(5000, seed=7, position_error=True)
    options = dict(compress=compress, extras=("position_error",))
    write_tiles(tmp_path / "a", batch, **options)
    pieces = [batch.select(slice(s, s + 999)) for s in range(0, 5000, 999)]
    write_tiles(tmp_path / "b", pieces, **options)
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "b").iterdir())
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


def test_creation_date_comes_from_the_caller_not_today(tmp_path):
    batch = make_batch([409001.0], [3392001.0])
    write_tiles(tmp_path, batch, creation_date=datetime.date(2019, 4, 7))
    raw = next(tmp_path.iterdir()).read_bytes()
    day, year = int.from_bytes(raw[90:92], "little"), int.from_bytes(raw[92:94], "little")
    assert (year, day) == (2019, 97)
    assert raw[8:24] == bytes(16)  # project GUID
    assert raw[26:58] == b"flightsim".ljust(32, b"\0")


def test_laz_round_trip(tmp_path):
    batch = random_batch(6000, seed=5, position_error=True)
    counts = write_tiles(tmp_path, batch, compress=True, extras=("position_error",))
    assert sorted(counts) == sorted(p.name for p in tmp_path.iterdir())
    assert all(name.endswith(".laz") for name in counts)
    for path in sorted(tmp_path.iterdir()):
        las = laspy.read(path)
        assert las.header.are_points_compressed
        got, crs = read_points(path)
        assert crs == UTM48N
        want = points_of_tile(batch, path.stem)
        assert_points_match(got, want)
        np.testing.assert_array_equal(got.position_error_m, want.position_error_m)


def test_empty_run_writes_nothing(tmp_path):
    with TileWriter(tmp_path, UTM48N, creation_date=CREATED) as writer:
        writer.write(random_batch(0))
    assert list(tmp_path.iterdir()) == []


def test_writer_cannot_be_used_after_close(tmp_path):
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED)
    assert writer.close() == {}
    with pytest.raises(RuntimeError):
        writer.write(random_batch(5))


# ---------------------------------------------------------------- read_points


def test_read_points_of_a_run_directory(tmp_path):
    batch = random_batch(2500, seed=9)
    write_tiles(tmp_path, batch)
    got, crs = read_points(sorted(tmp_path.iterdir()))
    assert crs == UTM48N
    order = np.argsort(got.gps_time)
    assert_points_match(got.select(order), batch)


def test_read_points_of_a_foreign_las_12_file(tmp_path):
    """A LAS 1.2 point format 1 file without our extra bytes, written by laspy directly."""
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales = [0.01, 0.01, 0.01]
    header.offsets = [500000.0, 4000000.0, 0.0]
    las = laspy.LasData(header)
    las.x = np.array([500001.25, 500002.5])
    las.y = np.array([4000001.0, 4000003.75])
    las.z = np.array([10.0, 12.5])
    las.gps_time = np.array([1.5, 2.5])
    las.classification = np.array([2, 6])
    las.scan_angle_rank = np.array([-12, 7])
    las.point_source_id = np.array([3, 4])
    las.intensity = np.array([100, 200])
    las.write(tmp_path / "foreign.las")
    got, crs = read_points(tmp_path / "foreign.las")
    assert crs is None
    np.testing.assert_array_equal(got.x, [500001.25, 500002.5])
    np.testing.assert_array_equal(got.z, [10.0, 12.5])
    np.testing.assert_array_equal(got.gps_time, [1.5, 2.5])
    np.testing.assert_array_equal(got.classification, [2, 6])
    np.testing.assert_array_equal(got.scan_angle_deg, [-12.0, 7.0])
    np.testing.assert_array_equal(got.plane_id, [-1, -1])
    assert got.beam_row is None and got.range_m is None and got.position_error_m is None


def test_read_points_refuses_files_in_different_crs(tmp_path):
    batch = make_batch([409001.0], [3392001.0])
    write_tiles(tmp_path / "a", batch)
    with TileWriter(tmp_path / "b", pyproj.CRS.from_epsg(32647), creation_date=CREATED) as w:
        w.write(batch)
    with pytest.raises(InputError, match="same CRS"):
        read_points([*(tmp_path / "a").iterdir(), *(tmp_path / "b").iterdir()])


def test_read_points_rejects_non_las(tmp_path):
    bad = tmp_path / "notes.las"
    bad.write_text("not a point cloud")
    with pytest.raises(InputError, match="path"):
        read_points(bad)
    with pytest.raises(InputError, match="paths"):
        read_points([])


# ---------------------------------------------------------------- helpers and input checks


def test_gps_week_date_at_known_gps_week_rollovers():
    # GPS week 1024 began 1999-08-22 and week 2048 began 2019-04-07 (the two week-number rollovers)
    week = 604800.0
    assert gps_week_date(1024 * week - 1e9) == datetime.date(1999, 8, 22)
    assert gps_week_date(2048 * week - 1e9) == datetime.date(2019, 4, 7)
    assert gps_week_date(2048 * week - 1e9 - 1.0) == datetime.date(2019, 4, 6)
    # standard GPS second 1e9 (adjusted 0) fell on 2011-09-14
    assert gps_week_date(0.0) == datetime.date(2011, 9, 14)
    with pytest.raises(InputError, match="gps_time_adjusted"):
        gps_week_date(float("nan"))


@pytest.mark.parametrize("size", [0, -500, 250.5, float("inf"), "big"])
def test_bad_tile_size_is_refused(tmp_path, size):
    with pytest.raises(InputError, match="tile_size_m"):
        TileWriter(tmp_path, UTM48N, tile_size_m=size, creation_date=CREATED)


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:2263", "not a crs"])
def test_crs_must_be_projected_in_metres(tmp_path, crs):
    with pytest.raises(InputError, match="crs"):
        TileWriter(tmp_path, crs, creation_date=CREATED)


def test_bad_header_strings_are_refused(tmp_path):
    with pytest.raises(InputError, match="software"):
        TileWriter(tmp_path, UTM48N, creation_date=CREATED, software="x" * 33)
    with pytest.raises(InputError, match="creation_date"):
        TileWriter(tmp_path, UTM48N, creation_date="2021-03-17")


def test_point_batch_checks_and_combines():
    batch = random_batch(10)
    assert len(batch) == 10
    picked = batch.select(batch.classification == batch.classification[0])
    assert np.all(picked.classification == batch.classification[0])
    both = PointBatch.concatenate([batch, picked])
    assert len(both) == 10 + len(picked)
    np.testing.assert_array_equal(both.x[10:], picked.x)
    assert both.position_error_m is None
    with pytest.raises(ValueError, match="entries"):
        PointBatch(**{**vars(batch), "z": batch.z[:5]})
    with pytest.raises(ValueError, match="integers"):
        PointBatch(**{**vars(batch), "beam_row": batch.beam_row + 0.5})
    with pytest.raises(ValueError, match="range"):
        PointBatch(**{**vars(batch), "beam_row": np.full(10, 300)})


def test_out_of_range_values_are_refused(tmp_path):
    writer = TileWriter(tmp_path, UTM48N, creation_date=CREATED)
    batch = random_batch(3)
    with pytest.raises(ValueError, match="finite"):
        writer.write(PointBatch(**{**vars(batch), "x": np.array([np.nan, 1.0, 2.0])}))
    with pytest.raises(ValueError, match="scan_angle"):
        writer.write(PointBatch(**{**vars(batch), "scan_angle_deg": np.array([0.0, 181.0, 0.0])}))
    writer.abort()


@pytest.mark.parametrize("span", [(3, 5), (256, 256), (1, 1 << 16), (300, 300), (1 << 20, 2)])
def test_tile_order_is_a_stable_sort_by_tile_either_way(span):
    """Tiles within 2^16 places of their bounding box sorted as one 16-bit key, others by both indices: either way
    the stable order of (ix, iy) with input order kept within a tile (np.lexsort), and where each tile starts."""
    rng = np.random.default_rng(sum(span))
    ix = rng.integers(-5, span[0] - 5, 20_000) * (1 if span[0] > 1 else 0) + 7
    iy = rng.integers(0, span[1], 20_000) - 40_000
    ix[:2], iy[:2] = (ix.min(), ix.min() + span[0] - 1), (iy.min(), iy.min() + span[1] - 1)  # the box's corners
    order, starts = las_tiles._tile_order(ix, iy)
    expected = np.lexsort((iy, ix))
    np.testing.assert_array_equal(order, expected)
    keys = list(zip(ix[expected].tolist(), iy[expected].tolist()))
    assert starts.tolist() == [k for k in range(len(keys)) if k == 0 or keys[k] != keys[k - 1]]
