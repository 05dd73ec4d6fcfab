"""A chunk's slots split by flight line (Tracer.by_line) against the definition, slot by slot."""
from types import SimpleNamespace

import numpy as np

from flightsim.engine.chunks import Segment
from flightsim.engine.tracer import Tracer


def test_a_chunks_slots_split_by_line_give_each_line_its_pulses_and_beams():
    """Segments of 0-6 pulses of 30 lines (some holding no slot) with 4 beams a pulse: every segment that holds
    slots gets its line, the slots' pulses within its line (its first pulse on), their beams and their rows, in
    order; none other."""
    rng = np.random.default_rng(21)
    beams = 4
    chunk = [Segment(int(rng.integers(0, 30)), int(rng.integers(0, 1000)), int(rng.integers(0, 7))) for _ in range(60)]
    total = sum(s.count for s in chunk)
    slots = np.flatnonzero(rng.random(total * beams) < 0.4).astype(np.int64)
    tracer = SimpleNamespace(beams_per_pulse=beams, trajectories=[f"line {k}" for k in range(30)])
    got = [(t, p.tolist(), b.tolist(), a, z) for t, p, b, a, z in Tracer.by_line(tracer, chunk, slots)]
    expected, first = [], 0
    for segment in chunk:
        rows = [i for i, slot in enumerate(slots.tolist()) if first <= slot // beams < first + segment.count]
        if rows:
            expected.append((f"line {segment.line}", [segment.first + slots[i] // beams - first for i in rows],
                             [slots[i] % beams for i in rows], rows[0], rows[-1] + 1))
        first += segment.count
    assert got == expected and any(s.count == 0 for s in chunk) and len(got) > 30
    assert all(p.dtype == np.int64 and b.dtype == np.int32 for _, p, b, _, _ in Tracer.by_line(tracer, chunk, slots))
