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
from flightsim.studies.spad import HALF_FIELD_DEG, frame_config, frame_simulator, photon_frame, simulate_frame
from flightsim.studies.spad_traffic import frame_traffic, key_bits
from test_photon_grid import _reference_grid  # the gridding rule cell by cell in plain Python

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
    assert np.array_equal(a[1].photons, b[1].photons) and np.array_equal(a[1].cell, b[1].cell)
    if device == "cpu":
        assert np.array_equal(a[1].points, b[1].points)
    else:  # a GPU's atomic sums add in any order
        np.testing.assert_allclose(a[1].points, b[1].points, rtol=0.0, atol=1e-9)


def test_a_study_frame_holds_a_saturated_frame_at_its_first_fill():
    """MODE-B at 34 m: every shot detects its echo and the background adds ~0.2 a pulse, more photons than
    beams; the study's frame is sized for them, so the frame is not run twice."""
    sim = frame_simulator(frame_config(34.0, "B", "cpu", pulses=40))[1]
    frame = photon_frame(sim, GRID)
    counts, held = _filled(sim, frame)
    beams = sim.planned_pulses() * sim.beams_per_pulse
    assert held and counts.returns == frame.count > 1.1 * beams
    assert len(frame.xyz) <= 1.25 * beams  # sized by the bound, not by the largest case


def _photons(n: int, seed: int):
    """(positions, cells) of n photons over 12 × 12 cells: a sloped surface, background, a few invalid."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(0, 12, (n, 2))
    cells[rng.random(n) < 0.02] = -1
    z = np.where(rng.random(n) < 0.6, 0.3 * cells[:, 0] + rng.normal(0, 0.04, n), rng.uniform(-20, 20, n))
    xyz = np.column_stack([cells[:, 0] + rng.random(n), cells[:, 1] + rng.random(n), z])
    xyz[rng.random(n) < 0.01, 2] = np.nan
    return xyz, cells


class _Chunk:
    """Photons as the frame's ``add`` takes them, their directions chosen to fall in the given angle cells."""

    def __init__(self, xyz, cells, device):
        half = math.radians(HALF_FIELD_DEG)
        angle = (cells + 0.5) / 12 * 2 * half - half
        d = np.column_stack([np.tan(angle[:, 0]), np.tan(angle[:, 1]), -np.ones(len(cells))])
        d[cells[:, 0] < 0] = (1.0, 0.0, 0.0)  # outside the field
        self.count = len(xyz)
        self.points = wp.array(xyz, dtype=wp.vec3d, device=device)
        self.directions = wp.array(d.astype(np.float32), dtype=wp.vec3f, device=device)
        self.signal = wp.zeros(len(xyz), dtype=wp.int8, device=device)


def test_a_frame_grids_frame_after_frame_in_its_kept_memory_as_the_cell_by_cell_rule(device):
    frame = PhotonFrame(math.radians(HALF_FIELD_DEG), 12, device, capacity=64)
    for n, seed in ((9000, 3), (2500, 4), (6000, 5)):  # larger, smaller, between: the kept arrays are reused
        xyz, cells = _photons(n, seed)
        frame.reset()
        frame.add(_Chunk(xyz[: n // 2], cells[: n // 2], device))
        frame.add(_Chunk(xyz[n // 2:], cells[n // 2:], device))
        got = frame.grid(bin_m=0.1, min_count=4, window_m=0.12)
        assert frame.count == n and np.array_equal(frame.cell.numpy()[:n], cells)
        expected, occupied = _reference_grid(xyz, cells, 0.1, 4, 0.12)
        assert got.cells == occupied and len(got.points) == len(expected) > 50
        for point, cell, photons, peak in zip(got.points, got.cell, got.photons, got.peak):
            mean, count, window = expected[tuple(cell)]
            assert (photons, peak) == (count, window)
            assert point == pytest.approx(mean, abs=1e-9)


def test_traffic_adds_the_stages_bytes():
    bits = key_bits(1100 ** 2, 595.0, 0.13)
    assert bits == (1100 ** 2 * (int(595.0 / 0.13) + 2)).bit_length() == 33
    t = frame_traffic(1000, 900, 100, bits)
    assert t["place"] == pytest.approx(8 * 1000 + 41 * 900)
    assert t["grid"] == pytest.approx((32 + 44 + 24 * 5 + 8 + 52 + 8 + 24) * 900 + 100 * 100)
