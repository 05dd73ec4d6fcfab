"""LAZ tiles compressed in worker processes (flightsim.outputs.laz_workers): the bytes of the in-process
writer, errors raised in the parent as the worker's own, a dead worker named, no process left behind.

Every check compares the workers' tiles with the in-process writer's (the reference) or with the input
points; failures are real (a file-size limit the kernel enforces, a killed process) or injected into the
workers the way ``test_device_las`` injects a full disk into the in-process writer.
"""
from __future__ import annotations

import datetime
import errno
import gc
import hashlib
import os
import resource
import signal
import subprocess
import sys

import numpy as np
import pyproj
import pytest

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.outputs import las_tiles, laz_workers
from flightsim.outputs.las_points import PointBatch, read_points
from flightsim.outputs.las_tiles import TileWriter

UTM48N = pyproj.CRS.from_epsg(32648)
TILE_M = 500.0
OPTIONS = dict(tile_size_m=TILE_M, compress=True, extras=("position_error",),
               creation_date=datetime.date(2021, 3, 17))


def _points(n: int, tiles: int, seed: int = 0) -> PointBatch:
    """``n`` points scattered over ``tiles`` tiles in a row (so every write reaches each tile), times rising,
    every field varied."""
    rng = np.random.default_rng(seed)
    return PointBatch(
        x=409000.0 + rng.uniform(0.0, tiles * TILE_M, n), y=3392000.0 + rng.uniform(0.0, TILE_M, n),
        z=rng.uniform(-20.0, 80.0, n),
        gps_time=3.0e8 + 1.0e-5 * np.arange(n), point_source_id=rng.integers(1, 6, n),
        classification=rng.choice([2, 6, 11], n), scan_angle_deg=rng.uniform(-15.0, 15.0, n),
        intensity=rng.integers(0, 65536, n), beam_row=rng.integers(0, 64, n), beam_col=rng.integers(0, 64, n),
        prism_angle_deg=rng.uniform(0.0, 360.0, n), range_m=rng.uniform(480.0, 5200.0, n),
        plane_id=rng.integers(-1, 500, n), position_error_m=rng.uniform(0.0, 0.3, n))


def _write(directory, points: PointBatch, piece: int, **options) -> TileWriter:
    with TileWriter(directory, UTM48N, **OPTIONS, **options) as writer:
        for start in range(0, len(points), piece):
            writer.write(points.select(slice(start, start + piece)))
    return writer


def _digests(directory) -> dict[str, str]:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def _reaped(processes) -> bool:
    return bool(processes) and all(p.returncode is not None for p in processes)


def test_workers_write_the_bytes_of_one_process(tmp_path):
    """Several tiles of several 50 000-point LAZ chunks each, interleaved writes; in the workers also with
    one open file each (tiles closed and reopened)."""
    points = _points(390_000, tiles=3)
    reference = _write(tmp_path / "one", points, 9001, processes=0)
    counts = reference.tile_counts
    assert len(counts) == 3 and min(counts.values()) > 2 * las_tiles.LAZ_CHUNK_POINTS
    for name, options in (("workers", {}), ("evicting", {"max_open_tiles": 1})):
        writer = _write(tmp_path / name, points, 9001, processes=2, **options)
        assert writer.tile_counts == counts
        assert _digests(tmp_path / name) == _digests(tmp_path / "one")
        assert _reaped(writer._workers.processes)
        assert [p.returncode for p in writer._workers.processes] == [0, 0]  # they finished, not killed
    for path in sorted((tmp_path / "evicting").iterdir()):
        got, crs = read_points(path)
        x0 = float(path.stem.split("_")[0])
        want = points.select((points.x >= x0) & (points.x < x0 + TILE_M))
        assert crs == UTM48N and len(got) == counts[path.name]  # in write order
        for field in ("x", "y", "z"):
            assert np.abs(getattr(got, field) - getattr(want, field)).max() <= 0.0005 + 1e-9  # the 1 mm grid
        for field in ("gps_time", "point_source_id", "classification", "intensity", "beam_row", "beam_col",
                      "prism_angle_deg", "range_m", "plane_id", "position_error_m"):
            assert np.array_equal(getattr(got, field), getattr(want, field)), field


def _config(**settings) -> RunConfig:
    cfg = RunConfig()
    base = {"flight.duration_s": 0.25, "flight.lines": 2, "flight.line_spacing_m": 60.0, "output.tile_size_m": 40,
            "instrument.errors": ["ranging"], "ranging.noise_m": 0.03, "output.position_error": True, "output.laz": True, "run.device": "cpu",
            "run.chunk_pulses": 97}  # many chunks, each cutting lines and tiles at odd places
    for key, value in {**base, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


@pytest.fixture
def started(monkeypatch) -> list[laz_workers.LazWorkers]:
    """Runs get LAZ workers by default (2 per writer); the list collects every writer's workers."""
    pools = []

    class Recorded(laz_workers.LazWorkers):
        def __init__(self, *args):
            super().__init__(*args)
            pools.append(self)

    monkeypatch.setattr(las_tiles, "LAZ_PROCESSES", 2)
    monkeypatch.setattr(las_tiles, "LazWorkers", Recorded)
    return pools


def test_a_laz_run_with_workers_gives_the_same_bytes(tmp_path, monkeypatch, started):
    from flightsim.engine.run import simulate_to_directory

    cfg = _config()
    simulate_to_directory(cfg, tmp_path / "workers")
    assert len(started) == 2 and all(_reaped(pool.processes) for pool in started)  # one writer per model
    monkeypatch.setattr(las_tiles, "LAZ_PROCESSES", 0)
    simulate_to_directory(cfg, tmp_path / "one")
    assert len(started) == 2
    tiles = {name: digest for name, digest in _digests(tmp_path / "one").items() if name.endswith(".laz")}
    assert len(tiles) >= 8  # both models, tiles cut at 40 m
    workers = _digests(tmp_path / "workers")
    assert {name: workers.get(name) for name in tiles} == tiles


def fill_up_disk_after(writes: int) -> None:
    """Run in a worker (see below): its writer's ``write_records`` fails as on a full disk after ``writes``
    calls, as ``test_device_las.test_a_disk_that_fills_up_leaves_no_tile`` makes the in-process one."""
    real = las_tiles.TileWriter.write_records

    def fill_up(self, *args):
        nonlocal writes
        writes -= 1
        if writes < 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(self, *args)

    las_tiles.TileWriter.write_records = fill_up


def test_a_worker_whose_disk_fills_up_leaves_no_tile(tmp_path, monkeypatch, started):
    from flightsim.engine.run import simulate_to_directory

    entry = laz_workers._ENTRY.replace("serve(", "__import__('test_laz_workers').fill_up_disk_after(5); serve(")
    assert entry != laz_workers._ENTRY
    monkeypatch.setattr(laz_workers, "_ENTRY", entry)
    with pytest.raises(OSError, match="No space left") as raised:
        simulate_to_directory(_config(), tmp_path / "run")
    assert raised.value.errno == errno.ENOSPC
    assert any("raised in LAZ worker" in note for note in raised.value.__notes__)
    left = [p.name for p in (tmp_path / "run").rglob("*") if p.is_file()]
    assert left == ["run.toml"]  # no tile, no temporary, no summary
    assert started and all(_reaped(pool.processes) for pool in started)


def test_a_real_write_error_in_a_worker_is_the_in_process_writers(tmp_path, monkeypatch):
    """A file-size limit (inherited by the workers) makes the kernel refuse a tile's write: the parent
    raises the exception the in-process writer raises (compressing as a worker does, in its own thread),
    and abort() leaves nothing."""
    points = _points(120_000, tiles=1)
    monkeypatch.setattr(laz_workers, "RING_BYTES", 256 << 10)  # the limit holds for the shared ring too
    errors = {}
    for processes in (0, 1):
        directory = tmp_path / str(processes)
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, hard))  # 1 MiB; the tile needs ~3 MiB
        try:
            writer = TileWriter(directory, UTM48N, **OPTIONS, processes=processes, parallel_compression=False)
            if processes == 0:
                errors[processes] = _error_of_writing(writer, points)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        if processes:
            errors[processes] = _error_of_writing(writer, points)
            assert _reaped(writer._workers.processes)
        assert list(directory.iterdir()) == []
    assert type(errors[1]) is type(errors[0]) and str(errors[1]) == str(errors[0])


def _error_of_writing(writer: TileWriter, points: PointBatch) -> BaseException:
    """The error writing and closing ``points`` raises (``writer`` aborted)."""
    try:
        for start in range(0, len(points), 10_000):
            writer.write(points.select(slice(start, start + 10_000)))
        writer.close()
    except Exception as exc:  # noqa: BLE001 - the error is what is compared
        writer.abort()
        return exc
    raise AssertionError("the file-size limit did not stop the writer")


def test_a_stalled_worker_holds_up_only_its_own_tiles(tmp_path, monkeypatch):
    """With one worker stopped (SIGSTOP), writes to the other worker's tile go through and writes to its own
    fill its ring, up to RING_BYTES; one more waits until the worker runs again. The tiles are still those
    of one process."""
    import threading

    monkeypatch.setattr(laz_workers, "RING_BYTES", 8 << 20)
    points = _points(400_000, tiles=2)  # 48-byte records: ~4.8 MB per tile in each half
    pieces = (slice(0, 100), slice(100, 200_000), slice(200_000, 400_000))
    writer = TileWriter(tmp_path / "workers", UTM48N, **OPTIONS, processes=2)
    writer.write(points.select(pieces[0]))
    assert sorted(writer._workers._owner.values()) == [0, 1]  # one tile each (in turn)
    stalled = writer._workers.processes[writer._workers._owner[(818, 6784)]]
    stalled.send_signal(signal.SIGSTOP)
    try:
        queued = threading.Thread(target=writer.write, args=(points.select(pieces[1]),))
        queued.start()
        queued.join(timeout=60.0)
        assert not queued.is_alive()  # ~4.8 MB in the stalled worker's ring, the rest gone to the other
        over = threading.Thread(target=writer.write, args=(points.select(pieces[2]),))
        over.start()
        over.join(timeout=2.0)
        assert over.is_alive()  # another ~4.8 MB does not fit in the stalled worker's ring: it waits
    finally:
        stalled.send_signal(signal.SIGCONT)
    over.join(timeout=60.0)
    assert not over.is_alive()
    writer.close()
    with TileWriter(tmp_path / "one", UTM48N, **OPTIONS, processes=0) as reference:
        for piece in pieces:
            reference.write(points.select(piece))
    assert _digests(tmp_path / "workers") == _digests(tmp_path / "one")


@pytest.mark.parametrize("then", ["write", "close"])
def test_a_killed_worker_is_named_not_waited_for(tmp_path, then):
    points = _points(40_000, tiles=2)
    writer = TileWriter(tmp_path, UTM48N, **OPTIONS, processes=2)
    writer.write(points.select(slice(0, 20_000)))
    victim = writer._workers.processes[1]
    victim.send_signal(signal.SIGKILL)
    victim.wait()
    dead = rf"LAZ worker 1 \(pid {victim.pid}\) was killed by SIGKILL"
    with pytest.raises(RuntimeError, match=dead):
        if then == "write":
            writer.write(points.select(slice(20_000, 40_000)))
        else:
            writer.close()
    if then == "write":
        with pytest.raises(RuntimeError, match=dead):  # the writer stays failed; close() aborts
            writer.close()
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    assert _reaped(writer._workers.processes)


def test_workers_are_reaped_on_abort_and_garbage_collection(tmp_path):
    points = _points(20_000, tiles=2)
    writer = TileWriter(tmp_path / "aborted", UTM48N, **OPTIONS, processes=2)
    writer.write(points)
    writer.abort()
    assert _reaped(writer._workers.processes)
    assert list((tmp_path / "aborted").iterdir()) == []
    writer = TileWriter(tmp_path / "dropped", UTM48N, **OPTIONS, processes=2)
    writer.write(points)
    processes = writer._workers.processes
    del writer
    gc.collect()
    assert _reaped(processes)


def test_a_worker_imports_no_warp_nor_scipy():
    """What a worker imports (its entry module and the tile writer) must not bring Warp in, nor SciPy (the
    package's API, config and trajectories are imported on first use, not with the tile writer)."""
    code = ("import sys, flightsim.outputs.laz_serve; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('warp', 'scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert out.stdout.strip() == "[]"


def test_the_ring_never_hands_out_bytes_in_use():
    """Random takes and oldest-first releases: the pieces in use never overlap and stay inside the ring, and
    a take refused while the ring is empty never happens (any piece up to the ring's size fits then)."""
    rng = np.random.default_rng(3)
    ring = laz_workers._Ring(1000)
    live = []
    for _ in range(20_000):
        if live and rng.random() < 0.45:
            ring.release()
            live.pop(0)
            continue
        n = int(rng.integers(1, 400))
        offset = ring.take(n)
        if offset is None:
            assert live  # refused only with pieces in use
            continue
        assert 0 <= offset and offset + n <= 1000
        assert all(offset + n <= a or b <= offset for a, b in live), (offset, n, live)
        live.append((offset, offset + n))
    assert ring.take(1000) is None if live else ring.take(1000) == 0
