"""A chunk's returns compacted on the device (``kernels.compaction``, ``PointBuffers.compact_index``): each beam's
returning slots counted, the returning slots listed in slot order, gathered, and counted per flight line, against
NumPy's ``flatnonzero`` of the same statuses, with ``per_beam`` slots a beam (1: one return a beam; 3: a canopy's)."""
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from kernels import compaction, frames
from kernels.trace import STATUS_LEAF, STATUS_MISS, STATUS_RETURN, STATUS_TIR

STATUSES = np.array([STATUS_RETURN, STATUS_LEAF, STATUS_MISS, STATUS_TIR], dtype=np.int32)


def _statuses(beams: int, per_beam: int, seed: int) -> np.ndarray:
    """Random slot statuses, a beam's returns not only at its first slots (a TIR or miss between two returns)."""
    rng = np.random.default_rng(seed)
    return STATUSES[rng.integers(0, len(STATUSES), beams * per_beam)]


def _compacted(device: str, status: np.ndarray, per_beam: int):
    """(counts, offsets, index, total) from the device kernels, as the points readout launches them."""
    beams = len(status) // per_beam
    s = wp.array(status, dtype=wp.int32, device=device)
    counts = wp.empty(beams, dtype=wp.int32, device=device)
    offsets = wp.empty(beams, dtype=wp.int32, device=device)
    index = wp.full(len(status), -7, dtype=wp.int32, device=device)
    total = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(compaction.beam_returns, beams, inputs=[s, per_beam], outputs=[counts], device=device)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    wp.launch(compaction.slot_indices, beams, inputs=[s, per_beam, offsets], outputs=[index], device=device)
    wp.launch(compaction.count_returns, 1, inputs=[counts, offsets, beams], outputs=[total], device=device)
    return counts, offsets, index, int(total.numpy()[0])


@pytest.mark.parametrize("per_beam", [1, 3, 5])
def test_returning_slots_are_listed_in_slot_order(device, per_beam):
    status = _statuses(2001, per_beam, seed=per_beam)
    counts, offsets, index, total = _compacted(device, status, per_beam)
    returned = np.flatnonzero((status == STATUS_RETURN) | (status == STATUS_LEAF))
    assert total == len(returned)
    np.testing.assert_array_equal(index.numpy()[:total], returned)
    assert (index.numpy()[total:] == -7).all()  # nothing written past the returns
    per_beam_counts = np.isin(status, [STATUS_RETURN, STATUS_LEAF]).reshape(-1, per_beam).sum(axis=1)
    np.testing.assert_array_equal(counts.numpy(), per_beam_counts)
    np.testing.assert_array_equal(offsets.numpy(), np.cumsum(per_beam_counts) - per_beam_counts)
    src = wp.array(np.arange(len(status), dtype=np.float32) * 0.5 + 3.0, dtype=wp.float32, device=device)
    dst = wp.zeros(len(status), dtype=wp.float32, device=device)
    wp.launch(compaction.gather_returns, total, inputs=[index, src], outputs=[dst], device=device)
    np.testing.assert_array_equal(dst.numpy()[:total], returned * 0.5 + 3.0)


def test_no_return_lists_nothing(device):
    status = np.full(12, STATUS_MISS, dtype=np.int32)
    counts, offsets, index, total = _compacted(device, status, 3)
    assert total == 0 and (counts.numpy() == 0).all() and (index.numpy() == -7).all()


@pytest.mark.parametrize("per_beam", [1, 3])
def test_returns_are_added_to_their_segments_lines(device, per_beam):
    beams_per_pulse, pulses = 4, 50
    status = _statuses(pulses * beams_per_pulse, per_beam, seed=11)
    counts, offsets, _, _ = _compacted(device, status, per_beam)
    starts, lines = [0, 7, 8, 31, pulses], [2, 0, 1, 2]  # a one-pulse segment, a line met twice
    segments = frames.Segments()
    segments.pulse_start = wp.array(starts, dtype=wp.int32, device=device)
    segments.line = wp.array(lines, dtype=wp.int32, device=device)
    segments.first_pulse = wp.zeros(len(lines), dtype=wp.int64, device=device)
    per_line = wp.zeros(3, dtype=wp.int64, device=device)
    wp.launch(compaction.add_segment_returns, len(lines),
              inputs=[counts, offsets, pulses * beams_per_pulse, segments, beams_per_pulse], outputs=[per_line],
              device=device)
    returned = np.isin(status, [STATUS_RETURN, STATUS_LEAF]).reshape(pulses, -1).sum(axis=1)
    expected = np.zeros(3, dtype=np.int64)
    for a, b, line in zip(starts[:-1], starts[1:], lines):
        expected[line] += returned[a:b].sum()
    np.testing.assert_array_equal(per_line.numpy(), expected)


FRESH_GATHERS = """
import numpy as np, warp as wp
from flightsim.core.warp_runtime import compile_ahead
from kernels import compaction
compile_ahead("cpu", [compaction.gather_returns])  # the module loaded as a run loads it, before its first gather
changed = []
mark = wp.Module.mark_modified
wp.Module.mark_modified = lambda self, *a, **k: changed.append(self.name) or mark(self, *a, **k)
index = wp.array([4, 0, 2], dtype=wp.int32, device="cpu")
ok = []
for dtype, values in ((wp.float32, np.arange(5, dtype=np.float32) + 0.5), (wp.int32, np.arange(5, dtype=np.int32) * 3),
                      (wp.vec3f, np.arange(15, dtype=np.float32).reshape(5, 3))):
    src, dst = wp.array(values, dtype=dtype, device="cpu"), wp.zeros(3, dtype=dtype, device="cpu")
    wp.launch(compaction.gather_returns, 3, inputs=[index, src], outputs=[dst], device="cpu")
    ok.append(bool(np.array_equal(dst.numpy(), values[[4, 0, 2]])))
print(ok, sorted(set(changed)))
"""


def test_the_gathers_of_a_points_readout_change_no_module():
    """A points readout gathers float32, int32 and vec3f columns with one generic kernel: its overloads are made with
    the module, so that the first gather of each kind does not change the module (which Warp would then compile and
    load again mid-run, and which another thread's launch could find half made). In a fresh process, the module
    loaded first: the right rows, no module changed."""
    out = subprocess.run([sys.executable, "-c", FRESH_GATHERS], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[True, True, True] []", out.stdout + out.stderr
