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
