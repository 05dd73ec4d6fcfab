"""SPAD frames filled by the photons readout itself (kernels/photon_frame.py): the same photons, in the same order,
as the detections the readout hands over chunk by chunk, placed and binned independently; counts kept on the
device across chunks; a frame too small for its photons runs again in grown arrays."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from flightsim.engine.config import validate
from flightsim.engine.readouts.photons import Photons
from flightsim.scoring.photon_grid import PhotonFrame
from flightsim.studies.spad import HALF_FIELD_DEG, frame_config, frame_simulator, simulate_frame
from flightsim.studies.spad_traffic import frame_traffic, key_bits

GRID = 160


def _sim(device: str, pulses: int = 6, chunk_pulses: int = 0):
    cfg = frame_config(100.0, "A", device, pulses)
    cfg.photon.noise_hz = 2e6  # several background photons per gate
    cfg.run.chunk_pulses = chunk_pulses
    return frame_simulator(validate(cfg))[1]


def _frame(sim, capacity: int = 1 << 16) -> PhotonFrame:
    return PhotonFrame(math.radians(HALF_FIELD_DEG), GRID, sim.cfg.run.device, capacity)


def _filled(sim, frame: PhotonFrame):
    frame.reset()
    counts = sim.run(Photons(frame=frame))
    return counts, frame.settle()


def _reference(sim):
    """Every detection of the run handed over chunk by chunk: (points, directions, signal) in launch order."""
    parts = []
    sim.run(Photons(on_device=True), lambda f: parts.append(
        (f.points.numpy().copy(), f.directions.numpy().copy(), f.signal.numpy().copy())))
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))


def _angle_cells(d: np.ndarray) -> np.ndarray:
    """Column and row of each direction in the GRID × GRID angle grid, float64 NumPy (−1 outside)."""
    half = math.radians(HALF_FIELD_DEG)
    d = d.astype(np.float64)
    depth = -d[:, 2]
    ij = np.floor((np.stack([np.arctan2(d[:, 0], depth), np.arctan2(d[:, 1], depth)], 1) + half) / (2 * half) * GRID)
    ij = ij.astype(np.int64)
    ij[((ij < 0) | (ij >= GRID)).any(axis=1)] = -1
    return ij


def test_the_frame_holds_every_detection_placed_and_binned_in_launch_order(device):
    sim = _sim(device)
    points, directions, signal = _reference(sim)
    frame = _frame(sim)
    counts, fits = _filled(sim, frame)
    assert fits and frame.count == counts.returns == len(points) > 6 * 1024
    xyz, cells = frame.xyz.numpy()[:frame.count], frame.cell.numpy()[:frame.count]
    if device == "cpu":
        assert np.array_equal(xyz, points, equal_nan=True)
    else:  # the compiler may contract the placing's multiply-adds differently
        np.testing.assert_allclose(xyz, points, rtol=0.0, atol=1e-9)
    expected = _angle_cells(directions)
    assert np.mean(np.all(cells == expected, axis=1)) > 0.999  # but a direction within rounding of a cell edge
    assert frame.signal_photons == int(np.count_nonzero(signal))


def test_chunks_and_a_frame_run_again_after_overflowing_give_the_same_photons(device):
    whole = _sim(device)
    frame = _frame(whole)
    _filled(whole, frame)
    reference = frame.xyz.numpy()[:frame.count].copy(), frame.cell.numpy()[:frame.count].copy()
    split = _sim(device, chunk_pulses=2)
    small = _frame(split, capacity=100)
    counts, fits = _filled(split, small)
    assert not fits and small.count == len(reference[0]) <= len(small.xyz)  # grown to hold them
    counts, fits = _filled(split, small)
    assert fits and counts.returns == len(reference[0])
    assert np.array_equal(small.xyz.numpy()[:small.count], reference[0], equal_nan=True)
    assert np.array_equal(small.cell.numpy()[:small.count], reference[1])


def test_simulate_frame_grows_a_small_frame_and_grids_the_same_points(device):
    sim = _sim(device)
    big, small = _frame(sim), _frame(sim, capacity=10)
    a, b = simulate_frame(sim, big), simulate_frame(sim, small)
    assert a[0].returns == b[0].returns and len(a[1].points) > 0
    assert np.array_equal(a[1].points, b[1].points) and np.array_equal(a[1].photons, b[1].photons)


def test_traffic_adds_the_stages_bytes():
    bits = key_bits(1100 ** 2, 595.0, 0.13)
    assert bits == (1100 ** 2 * (int(595.0 / 0.13) + 2)).bit_length() == 33
    t = frame_traffic(1000, 900, 100, bits)
    assert t["place"] == pytest.approx(8 * 1000 + 41 * 900)
    assert t["grid"] == pytest.approx((32 + 44 + 24 * 5 + 28 + 80) * 900 + 100 * 100)
