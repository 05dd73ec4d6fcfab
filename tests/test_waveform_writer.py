"""waveforms.h5's writer (flightsim/outputs/waveforms_h5.py) takes flight lines' parts of waveforms and writes them
together: parts of several lines and beams gathered into one batch must make the file, returns.las's points and
their order that the parts written one at a time make, and a run of the shots platform (a line per footprint) must
append each beam's datasets once, not once per footprint."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from flightsim.core import process_map
from flightsim.engine.readouts.waveforms import WaveformChunk
from flightsim.instrument import waveform_model as model
from flightsim.outputs import h5_product, waveforms_h5
from flightsim.outputs.waveforms_h5 import WaveformWriter
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN, PlaneInfo, Scene

SYSTEM = model.WaveformSystem(pulse_fwhm_s=1.5e-8, sample_interval_s=1e-9)
SAMPLES = 200
PRF_HZ = 242.0


def _scene() -> Scene:
    vertices = np.array([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [0.0, 50.0, 0.0]])
    return Scene("plate", DEFAULT_CRS, np.asarray(DEFAULT_ORIGIN, dtype=np.float64), vertices, np.array([[0, 1, 2]]),
                 np.zeros(1), np.full(1, 2), [PlaneInfo(0, "ground", 2, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0,
                                                         float("nan"))], 0.0)


def _parts(seed: int = 3) -> list[WaveformChunk]:
    """Three lines, each with shots of beams 0 and 1 in turn: one or two Gaussian echoes a waveform at
    known times, amplitudes and widths (so every waveform has components, and returns.las points)."""
    rng = np.random.default_rng(seed)
    parts = []
    for line, shots in ((4, 3), (9, 5), (11, 2)):
        t0 = 6.6e-6 + rng.uniform(0.0, 1e-8, shots)
        times = t0[:, None] + SYSTEM.sample_interval_s * np.arange(SAMPLES)
        power = np.zeros((shots, SAMPLES))
        for _ in range(2):
            centre = t0 + rng.uniform(40e-9, 160e-9, shots)
            power += rng.uniform(1e-7, 1e-6, shots)[:, None] * np.exp(
                -0.5 * ((times - centre[:, None]) / rng.uniform(6e-9, 12e-9, shots)[:, None]) ** 2)
        direction = np.tile([0.0, 0.0, -1.0], (shots, 1)) + rng.normal(0.0, 1e-3, (shots, 3))
        parts.append(WaveformChunk(
            line, 1.0e8 + 10.0 * line, np.arange(shots, dtype=np.int64) * 2 + 5, np.arange(shots, dtype=np.int32) % 2,
            t0, power.astype(np.float32), np.column_stack([np.ones(shots), np.zeros((shots, 2)), np.ones(shots)]),
            np.column_stack([rng.uniform(-9.0, 9.0, (shots, 2)), np.full(shots, 1000.0)]),
            direction / np.linalg.norm(direction, axis=1, keepdims=True)))
    return parts


def _write(directory, parts, one_at_a_time: bool) -> WaveformWriter:
    directory.mkdir()
    writer = WaveformWriter(directory, "", SYSTEM, PRF_HZ, _scene(), (np.ones(30), -1.5e-8), {"footprint_sigma_m": 5.5})
    for part in parts:
        writer(part)
        if one_at_a_time:
            writer.flush()
    writer.close()
    return writer


def _datasets(path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path) as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_line_parts_written_together_are_the_parts_written_one_at_a_time(tmp_path, monkeypatch):
    appends = []
    original = h5_product.H5Product.append
    monkeypatch.setattr(h5_product.H5Product, "append",
                        lambda self, group, columns, **kw: appends.append(group) or original(self, group, columns, **kw))
    together = _write(tmp_path / "together", _parts(), one_at_a_time=False)
    assert appends == ["BEAM0000"] * 3 + ["BEAM0001"] * 3  # waveforms, pulses, columns: once per beam
    appends.clear()
    alone = _write(tmp_path / "alone", _parts(), one_at_a_time=True)
    assert len(appends) == 3 * 6  # three lines of two beams
    a, b = _datasets(tmp_path / "together" / "waveforms.h5"), _datasets(tmp_path / "alone" / "waveforms.h5")
    assert sorted(a) == sorted(b) and len(a) > 30
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert list(a["BEAM0001/line_id"]) == [4, 9, 9, 11] and list(a["BEAM0001/pulse"]) == [7, 7, 11, 7]
    assert np.array_equal(a["BEAM0001/delta_time"], 1.0e8 + 10.0 * a["BEAM0001/line_id"] + np.array([7, 7, 11, 7]) / PRF_HZ)
    points, times = (np.concatenate(w) for w in (together.returns, together.return_times))
    assert len(points) >= 10 and together.shots == alone.shots == 10
    np.testing.assert_array_equal(points, np.concatenate(alone.returns))  # returns.las's points, in the same order
    np.testing.assert_array_equal(times, np.concatenate(alone.return_times))
    count = {(line, pulse, beam): n for beam in (0, 1) for line, pulse, n in
             zip(*(a[f"BEAM{beam:04d}/{c}"] for c in ("line_id", "pulse", "ranging/n_components")))}
    order = [np.repeat(p.start_time + p.pulse[i] / PRF_HZ, count[p.line_id, p.pulse[i], beam])  # part, beam, shot
             for p in _parts() for beam in (0, 1) for i in np.flatnonzero(p.beam == beam)]
    np.testing.assert_array_equal(times, np.concatenate(order))
    assert (tmp_path / "together" / "returns.las").read_bytes() == (tmp_path / "alone" / "returns.las").read_bytes()


def test_parts_are_written_once_they_hold_flush_bytes(tmp_path, monkeypatch):
    parts = _parts()
    monkeypatch.setattr(waveforms_h5, "FLUSH_BYTES", parts[0].power_w.nbytes + parts[1].power_w.nbytes)
    (tmp_path / "out").mkdir()
    writer = WaveformWriter(tmp_path / "out", "", SYSTEM, PRF_HZ, _scene(), (np.ones(30), -1.5e-8))
    writer(parts[0])
    assert writer.shots == 0 and len(writer.pending) == 1
    writer(parts[1])
    assert writer.shots == 8 and not writer.pending
    writer(parts[2])
    assert writer.shots == 8
    writer.close()
    assert writer.shots == 10 and not (tmp_path / "out" / "waveforms.h5.part").exists()
    with h5py.File(tmp_path / "out" / "waveforms.h5") as f:
        assert len(f["BEAM0000/pulse"]) + len(f["BEAM0001/pulse"]) == 10


@pytest.mark.parametrize("flush_bytes", [1, 1 << 40])
def test_the_components_are_the_reference_models_either_way(tmp_path, monkeypatch, flush_bytes):
    """Whatever the batching, each shot's ranging/ columns are the float64 model's of its own waveform."""
    monkeypatch.setattr(waveforms_h5, "FLUSH_BYTES", flush_bytes)
    parts = _parts(seed=8)
    _write(tmp_path / "out", parts, one_at_a_time=False)
    f = _datasets(tmp_path / "out" / "waveforms.h5")
    for beam in (0, 1):
        rows = [(p, i) for p in parts for i in np.flatnonzero(p.beam == beam)]
        for k, (part, i) in enumerate(rows):
            times = part.window_start_s[i] + SYSTEM.sample_interval_s * np.arange(SAMPLES)
            gs = model.decompose(SYSTEM, times, part.power_w[i].astype(np.float64))
            assert f[f"BEAM{beam:04d}/ranging/n_components"][k] == len(gs) > 0
            want = [0.5 * model.C * (g.time_s - 0.5 * SYSTEM.pulse_fwhm_s) for g in gs]
            assert np.array_equal(f[f"BEAM{beam:04d}/ranging/component_range_m"][k, :len(gs)], want)


def test_the_fits_on_worker_processes_write_the_same_file(tmp_path, monkeypatch):
    """A writer whose batches reach PARALLEL_ROWS spreads the host ranging over worker processes: the same
    waveforms.h5 as one process, and the workers stopped once it is closed."""
    parts = _parts(seed=11)
    alone = _write(tmp_path / "alone", parts, one_at_a_time=False)
    assert alone.workers is None  # 10 shots: below PARALLEL_ROWS
    monkeypatch.setattr(waveforms_h5, "PARALLEL_ROWS", 2)
    monkeypatch.setattr(waveforms_h5, "usable_cores", lambda: 2)
    monkeypatch.setattr(process_map, "MIN_ROWS_PER_CHUNK", 1)
    spread = _write(tmp_path / "spread", parts, one_at_a_time=False)
    assert spread.workers is not None and len(spread.workers.processes) == 2
    assert all(p.poll() is not None for p in spread.workers.processes)
    a, b = _datasets(tmp_path / "alone" / "waveforms.h5"), _datasets(tmp_path / "spread" / "waveforms.h5")
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def _l2a_batch(seed: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """(columns, rx, ground) of one beam's batch for L2AProduct.add: _parts' waveforms of one line, nadir, bin0 at
    100 m and one sample 0.15 m lower each."""
    rx = _parts(seed)[1].power_w.astype(np.float64)
    s = len(rx)
    columns = {"geolocation/z_bin0": np.full(s, 100.0),
               "geolocation/z_lastbin": np.full(s, 100.0 - 0.15 * (SAMPLES - 1)),
               "shot_number": np.arange(s, dtype=np.uint64) + np.uint64(seed << 8),
               "delta_time": 1.0e8 + np.arange(s) + seed}
    for tag in ("bin0", "lastbin"):
        columns[f"geolocation/latitude_{tag}"] = np.full(s, 30.7)
        columns[f"geolocation/longitude_{tag}"] = np.full(s, 104.1)
    return columns, rx, np.full(s, 75.0)


def _l2a_product(path):
    return waveforms_h5.L2AProduct(path, SYSTEM.sample_interval_s, 6.4e-9, 5.5, {}, {})


def test_l2a_batches_are_worked_out_on_a_thread_while_the_writer_goes_on(tmp_path, monkeypatch):
    """add returns while its batch's metrics are still being worked out (on the product's thread); close waits for
    them, and l2a.h5 holds every batch in the order they came, each l2a_metrics of its waveforms."""
    import threading

    from flightsim.outputs.l2a import L2ASettings, l2a_metrics

    started, release, threads = threading.Event(), threading.Event(), []

    def held(*args, **kwargs):
        threads.append(threading.current_thread().name)
        started.set()
        assert release.wait(30.0)
        return l2a_metrics(*args, **kwargs)

    monkeypatch.setattr(waveforms_h5, "l2a_metrics", held)
    product, batches = _l2a_product(tmp_path / "l2a.h5"), [_l2a_batch(5), _l2a_batch(8)]
    product.add(0, batches[0][0], batches[0][1], batches[0][1], batches[0][2])
    assert started.wait(30.0) and not release.is_set()  # add has returned; its metrics are waiting, elsewhere
    release.set()
    product.add(0, batches[1][0], batches[1][1], batches[1][1], batches[1][2])
    name, counts = product.close()
    assert name == "l2a.h5" and counts["shots"] == 5 + 5 and len(threads) == 2
    assert all(t.startswith("l2a") for t in threads) and threading.current_thread().name not in threads
    with h5py.File(tmp_path / "l2a.h5") as f:
        for k, (columns, rx, _) in enumerate(batches):
            geo = {f"{q}_{tag}": columns[f"geolocation/{n}_{tag}"] for tag in ("bin0", "lastbin")
                   for q, n in (("elevation", "z"), ("latitude", "latitude"), ("longitude", "longitude"))}
            want = l2a_metrics(rx, SYSTEM.sample_interval_s, pulse_sigma_s=6.4e-9,
                               settings=L2ASettings(footprint_sigma_m=5.5), **geo)
            rows = slice(5 * k, 5 * k + 5)
            assert np.array_equal(f["BEAM0000/shot_number"][rows], columns["shot_number"])
            for field in ("elev_lowestmode", "rh", "quality_flag", "sensitivity"):  # in the file's types
                stored = f[f"BEAM0000/{field}"]
                assert np.array_equal(stored[rows], want[field].astype(stored.dtype), equal_nan=True), field


def test_an_l2a_batchs_error_is_raised_by_the_next_add_or_close_and_abort_drops_it(tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise ValueError("no metrics")

    monkeypatch.setattr(waveforms_h5, "l2a_metrics", refuse)
    batch = _l2a_batch(5)
    product = _l2a_product(tmp_path / "a.h5")
    product.add(0, batch[0], batch[1], batch[1], batch[2])
    with pytest.raises(ValueError, match="no metrics"):
        product.add(1, batch[0], batch[1], batch[1], batch[2])
    product.abort()  # the second batch's error too: dropped
    assert product._thread is None and not (tmp_path / "a.h5").exists()
    product = _l2a_product(tmp_path / "b.h5")
    product.add(0, batch[0], batch[1], batch[1], batch[2])
    with pytest.raises(ValueError, match="no metrics"):
        product.close()
    assert product._thread is None and not (tmp_path / "b.h5").exists()


def test_an_abort_cut_short_while_waiting_for_the_l2a_batch_still_removes_the_files_part(tmp_path, monkeypatch):
    """A second ^C while abort waits for the running L2A batch: the workers still stop and waveforms.h5's temporary
    file still goes."""
    l2a = _l2a_product(tmp_path / "l2a.h5")
    writer = WaveformWriter(tmp_path, "", SYSTEM, PRF_HZ, _scene(), (np.ones(30), -1.5e-8), {}, l2a=l2a)
    writer(_parts()[0])
    writer.flush()

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(l2a, "abort", interrupted)
    stopped = []
    monkeypatch.setattr(writer, "_stop_workers", lambda: stopped.append(True))
    assert writer.product.part.exists()
    with pytest.raises(KeyboardInterrupt):
        writer.abort()
    assert stopped == [True] and not writer.product.part.exists() and not (tmp_path / "waveforms.h5").exists()
    l2a.settle()  # the batch itself finished on its thread
