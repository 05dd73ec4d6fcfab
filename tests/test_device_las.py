"""The points path at the device's speed: LAS records packed on the device, written by writer threads.

Every tile must hold the bytes the host writer (``host_reference.HostLasOutput``: numpy quantisation and
laspy packing of host arrays, flightsim's writer before records were packed on the device) makes from the
same run, and the per-plane moments summed on the device must equal numpy's.
"""
import errno
import hashlib

import numpy as np
import pytest

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.run import simulate_to_directory
from flightsim.engine.tracer import Tracer
from flightsim.outputs import las_points, las_tiles
from flightsim.outputs.consumers import PlaneStatistics
from flightsim.outputs.device_las import DeviceLasOutput
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.world import edge_buffer_m
from flightsim.engine.readouts.points import Points
from host_reference import HostLasOutput, HostPlaneStatistics


def _config(device: str, **settings) -> RunConfig:
    cfg = RunConfig()
    base = {"flight.duration_s": 0.25, "flight.lines": 2, "flight.line_spacing_m": 60.0, "output.tile_size_m": 40,
            "instrument.errors": ["ranging"], "ranging.noise_m": 0.03, "output.position_error": True, "run.device": device,
            "run.chunk_pulses": 97}  # many chunks, each cutting lines and tiles at odd places
    for key, value in {**base, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def _digests(directory) -> dict[str, str]:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*.la[sz]"))}


def _both_writers(cfg: RunConfig, tmp_path):
    """Tiles of the same run from the device path (``dev``) and the host reference (``host``)."""
    scene = build_scene(cfg)
    buffer = edge_buffer_m(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene), with_truth=True, edge_buffer_m=buffer)
    device = DeviceLasOutput(tmp_path / "dev", cfg.output, simulator, buffer > 0.0, cfg.flight.start_gps_time)
    simulator.run(Points(on_device=True), device)
    device_tiles = device.close()
    host = HostLasOutput(tmp_path / "host", cfg, scene, simulator.timing, edge_distance=buffer > 0.0)
    simulator.run(Points(), host)
    return device_tiles, host.close()


@pytest.mark.parametrize("settings", [
    {},
    {"output.laz": True},
    {"scene.crs": "EPSG:3857", "scene.origin": "-1000.0005,-20.0,12.0", "scoring.edge_buffer_m": 0.0},
], ids=["las", "laz", "negative-coordinates"])
def test_device_records_are_the_host_writers_bytes(device, tmp_path, settings):
    cfg = _config(device, **settings)
    device_tiles, host_tiles = _both_writers(cfg, tmp_path)
    assert device_tiles == host_tiles
    assert sum(len(tiles) for tiles in host_tiles.values()) >= 8  # both models, tiles cut at 40 m
    assert sum(n for tiles in host_tiles.values() for n in tiles.values()) > 5000
    dev, host = _digests(tmp_path / "dev"), _digests(tmp_path / "host")
    assert len(dev) == sum(len(tiles) for tiles in host_tiles.values())
    assert dev == host


def test_records_handed_over_in_slabs_that_cut_tiles_are_the_host_writers_bytes(device, tmp_path, monkeypatch):
    """Slabs of 37 records (most tiles of a chunk split between slabs, a slab holding the ends of some and the
    starts of others; two slabs a model, so the copies wait for the writers): the same bytes."""
    from flightsim.outputs import device_las

    words = device_las.kl.pack_kernel(True, True, False).words  # records with position_error and edge_distance
    monkeypatch.setattr(device_las, "SLAB_BYTES", 37 * 4 * words)
    monkeypatch.setattr(device_las, "SLABS_PER_MODEL", 2)
    handed: list[tuple[int, int]] = []
    real = device_las._write_slab
    monkeypatch.setattr(device_las, "_write_slab", lambda w, slab: handed.append((slab.first, slab.count)) or
                        real(w, slab))
    device_tiles, host_tiles = _both_writers(_config(device), tmp_path)
    assert device_tiles == host_tiles
    assert _digests(tmp_path / "dev") == _digests(tmp_path / "host")
    assert max(count for _, count in handed) == 37 and len(handed) > 100
    assert any(first > 0 for first, _ in handed)


def test_device_plane_moments_equal_numpys(device):
    cfg = _config(device, **{"output.position_error": False})
    scene = build_scene(cfg)
    buffer = edge_buffer_m(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene), edge_buffer_m=buffer)
    on_device = PlaneStatistics(simulator, buffer)
    counts = simulator.run(Points(on_device=True), on_device)
    host = HostPlaneStatistics(scene, simulator.models, buffer)
    simulator.run(Points(), host)
    moments = on_device.sums.moments()
    for model in ("exact", "nominal"):
        reference = host.moments[model]
        assert np.array_equal(moments[model].count, reference.count)
        assert np.allclose(moments[model].first, reference.first, rtol=1e-12, atol=1e-9)
    assert 0 < reference.count.sum() < counts.returns  # the edge buffer left some out
    nominal = on_device.rms_m()["nominal"]
    assert nominal == pytest.approx(np.sqrt(sum(f.n * f.rms_m**2 for f in reference.fits())
                                            / sum(f.n for f in reference.fits())), rel=1e-9)


def test_returns_per_line_are_counted_on_the_device(device):
    cfg = _config(device, **{"flight.lines": 3})
    scene = build_scene(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    chunks = []
    counts = simulator.run(Points(), chunks.append)
    per_line = {}
    for chunk in chunks:
        per_line[chunk.line_id] = per_line.get(chunk.line_id, 0) + len(chunk)
    assert counts.per_line == per_line and len(per_line) == 3
    assert counts.returns == sum(per_line.values())


def test_a_disk_that_fills_up_leaves_no_tile(tmp_path, monkeypatch):
    cfg = _config("cpu")
    real = las_tiles.TileWriter.write_records
    calls = []

    def fill_up(self, *args):
        calls.append(1)
        if len(calls) > 5:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(self, *args)

    monkeypatch.setattr(las_tiles.TileWriter, "write_records", fill_up)
    with pytest.raises(OSError, match="No space left"):
        simulate_to_directory(cfg, tmp_path / "run")
    left = [p.name for p in (tmp_path / "run").rglob("*") if p.is_file()]
    assert left == ["run.toml"]  # no tile, no temporary, no summary


def test_laz_records_held_back_for_parallel_compression_give_the_same_bytes(tmp_path, monkeypatch):
    """A LAZ tile compresses its records in batches (many chunks per call, spread over the cores); the
    bytes must be those of compressing every write as it comes, and of batches cut short by the cap on
    held bytes."""
    cfg = _config("cpu", **{"output.laz": True, "run.chunk_pulses": 4999, "flight.duration_s": 4.0,
                            "output.tile_size_m": 2000})  # tiles of several 50 000-point LAZ chunks
    digests = {}
    for name, batch, held in (("one by one", 1, las_tiles.LAZ_HELD_BYTES), ("batched", 60_000, 1 << 40),
                              ("capped", 60_000, 200_000)):
        monkeypatch.setattr(las_tiles, "LAZ_BATCH_POINTS", batch)
        monkeypatch.setattr(las_tiles, "LAZ_HELD_BYTES", held)
        simulate_to_directory(cfg, tmp_path / name.replace(" ", "-"))
        digests[name] = _digests(tmp_path / name.replace(" ", "-"))
    tiles = [las_points.read_points(p)[0] for p in sorted((tmp_path / "batched").rglob("*.laz"))]
    assert max(len(t.x) for t in tiles) > 3 * las_tiles.LAZ_CHUNK_POINTS
    assert digests["batched"] == digests["one by one"] == digests["capped"]


def test_face_labels_are_uploaded_once_per_scene_and_end_with_the_leaves(tmp_path):
    """The records' class and plane tables are the scene's meshes' (made once, like its BVH), not each LAS
    output's; a forest's leaf faces follow its triangles with their classes and plane −1."""
    cfg = _config("cpu")
    scene = build_scene(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    first = DeviceLasOutput(tmp_path / "a", cfg.output, simulator, False, cfg.flight.start_gps_time)
    second = DeviceLasOutput(tmp_path / "b", cfg.output, simulator, False, cfg.flight.start_gps_time)
    assert first.tables.face_class.ptr == second.tables.face_class.ptr == simulator.meshes.face_labels[0].ptr
    assert np.array_equal(first.tables.face_plane.numpy(), scene.plane_id)
    assert np.array_equal(first.tables.face_class.numpy(), scene.classification)
    first.abort(), second.abort()
    from flightsim.scenes.canopy import LEAF_CLASSES

    forest = build_scene(validate(_config("cpu", **{"scene.name": "forest", "scene.forest_size_m": 20.0})))
    classes, planes = forest.face_labels()
    n = len(forest.triangles)
    assert list(classes[n:]) == list(LEAF_CLASSES) and list(planes[n:]) == [-1] * len(LEAF_CLASSES)
    assert np.array_equal(classes[:n], forest.classification) and np.array_equal(planes[:n], forest.plane_id)
    custom = forest.face_labels(np.arange(n, dtype=np.int64))[1]
    assert custom.dtype == np.int32 and list(custom[:3]) == [0, 1, 2] and custom[-1] == -1
