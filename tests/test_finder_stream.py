"""The signal finder while a run goes on (flightsim.scoring.finder_stream): blocks classified on worker processes as
a beam's photons come, the rest at the close, every confidence as the whole beam classified at once."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from flightsim.core.process_map import ProcessMap
from flightsim.scoring.finder_stream import FinderStream
from flightsim.scoring.signal_finder import SignalFinder, along_spread

BLOCK = 1000


def _beam(seed: int, late_slant: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(along [m], h [m], pulse) of 4000 shots: a surface at 50 m and noise over 300 m, each photon shifted along
    track by its height above 150 m times a slant (an off-nadir beam): 0.1, ``late_slant`` from shot 3000; one photon
    in a hundred without a position (NaN distance and height: noise, nobody's neighbour)."""
    rng = np.random.default_rng(seed)
    pulse = np.repeat(np.arange(4000), rng.poisson(5.0, 4000))
    h = np.where(rng.random(pulse.size) < 0.2, 50.0 + rng.normal(0, 0.1, pulse.size),
                 rng.uniform(0.0, 300.0, pulse.size))
    along = pulse * 0.7 + (h - 150.0) * np.where(pulse < 3000, 0.1, late_slant)
    lost = rng.random(pulse.size) < 0.01
    along[lost], h[lost] = np.nan, np.nan
    return along, h, pulse


def _stream_of(beam: tuple, out: np.ndarray) -> tuple:
    """The close's (n, read, write, block, spread) of a beam, its confidences written into ``out``."""
    along, h, pulse = beam
    return (len(h), lambda lo, hi: (along[lo:hi], h[lo:hi], pulse[lo:hi]),
            lambda lo, values: out.__setitem__(slice(lo, lo + len(values)), values), BLOCK, along_spread(along)[0])


@pytest.mark.parametrize("late_slant, most_waiting", [(0.1, 1000), (0.15, 1000), (0.1, 0)])
def test_a_stream_classifies_as_the_whole_beam(late_slant, most_waiting):
    """Two beams appended in turn in 31 parts of random sizes each, the workers given after the first; blocks of
    1000 photons. A slant that grows in a beam's last quarter (0.1 → 0.15) widens its spread after blocks were read for
    the narrower one: those blocks are classified again at the close. With no block allowed to wait for the workers
    (``most_waiting`` 0; 1000: all may) every block is left to the close. Every confidence as the whole beam's."""
    finder, rng = SignalFinder(), np.random.default_rng(3)
    beams = {"gt1": _beam(1, late_slant), "gt2": _beam(2, late_slant)}
    cuts = {name: np.r_[0, np.sort(rng.choice(np.arange(1, len(h)), 30, replace=False)), len(h)]
            for name, (_, h, _) in beams.items()}
    stream, workers = FinderStream(finder, block=BLOCK, most_waiting=most_waiting), ProcessMap(2)
    out = {name: np.full(len(h), -1, dtype=np.int8) for name, (_, h, _) in beams.items()}
    try:
        for k in range(31):  # the beams' parts in turn, as a run appends them
            if k == 1:
                stream.start(workers)
            for name, (along, h, pulse) in beams.items():
                lo, hi = cuts[name][k], cuts[name][k + 1]
                stream.add(name, along[lo:hi], h[lo:hi], pulse[lo:hi], along_spread(along[:hi])[0])
        streams = {name: _stream_of(beam, out[name]) for name, beam in beams.items()}
        left = stream.finish(streams)
        finder.classify_spans(left, workers)
    finally:
        workers.stop()
    sent = sum(len(pieces) for pieces in stream.pieces.values())
    kept = sum(piece.holds(finder.reach_m(streams[name][4])) for name, pieces in stream.pieces.items()
               for piece in pieces)
    if most_waiting == 0:
        assert sent == 0
    else:
        assert min(len(stream.pieces[name]) for name in beams) >= 10  # most of each beam classified while it came
        assert (kept < sent) if late_slant > 0.1 else (kept == sent)  # blocks read short of the final spread: again
    assert sum(end - start for _, start, end in left) == sum(len(h) for _, h, _ in beams.values()) - kept * BLOCK
    for name, (along, h, pulse) in beams.items():
        assert np.array_equal(out[name], finder.classify(along, h, pulse)), name


def test_a_stream_without_workers_holds_the_photons_and_leaves_every_block_to_the_close():
    """No workers given (a run that stayed small): no block made, the close's spans the whole beam's blocks."""
    along, h, pulse = _beam(4, 0.1)
    stream, out = FinderStream(SignalFinder(), block=BLOCK), np.zeros(len(h), dtype=np.int8)
    stream.add("gt1", along, h, pulse, along_spread(along)[0])
    left = stream.finish({"gt1": _stream_of((along, h, pulse), out)})
    assert [(start, end) for _, start, end in left] == [(a, min(a + BLOCK, len(h))) for a in range(0, len(h), BLOCK)]
    assert stream.pieces == {}


def test_a_block_that_fails_on_the_workers_fails_the_close_and_the_stream_ends():
    """A worker's error (here the map raising at once) is held by the stream's thread and raised by finish, the
    thread ended (no hang); stop after it is harmless."""

    class Failing:
        processes = [None, None]

        def map(self, function, chunks, done=None):
            raise OSError("worker 1 ended with exit status -9")

    along, h, pulse = _beam(5, 0.1)
    stream = FinderStream(SignalFinder(), block=BLOCK)
    stream.start(Failing())
    stream.add("gt1", along, h, pulse, along_spread(along)[0])
    with pytest.raises(OSError, match="exit status -9"):
        stream.finish({"gt1": _stream_of((along, h, pulse), np.zeros(len(h), dtype=np.int8))})
    assert not [thread for thread in threading.enumerate() if thread.name == "finder"]
    stream.stop()
