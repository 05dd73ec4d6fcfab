"""The signal finder while a run goes on (:class:`FinderStream`): each beam's photons, as they are appended, cut into
blocks that worker processes classify as soon as the photons after a block reach far enough along track to hold its
background pools (:func:`~flightsim.scoring.signal_finder.reached`), so that at the close only the last stretch
of each beam is left to classify. A block classifies as the whole beam would; which blocks were read far enough is
settled at the close, against each beam's final along-track spread (a later photon may lie further behind an
earlier one than any before it): those that were not are classified again there.
"""
from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, field

import numpy as np

from flightsim.core.process_map import ProcessMap
from flightsim.scoring.signal_finder import SignalFinder, block_spans, classify_part, padded_rows

STREAM_BLOCK = 1 << 18  # photons of a beam in a block classified while the run goes on
WAITING_PER_WORKER = 2  # blocks handed over and not yet classified, per worker, beyond which blocks go to the close


@dataclass
class _Beam:
    """A beam's photons not yet in a block sent (and the block's rows before them), as appended."""

    parts: list = field(default_factory=list)  # (along, h, pulse) arrays, rows base … rows − 1
    base: int = 0  # the first row held
    rows: int = 0  # rows appended
    sent: int = 0  # the first row of the next block
    stopped: bool = False  # a block needed rows before those held: the rest of the beam is left to the close


@dataclass(frozen=True)
class Piece:
    """Rows [start, start + len(conf)) of a beam classified: ``conf``; ``near``, ``far`` [m]: how far the rows read
    around them reached before their nearest and beyond their furthest photon (inf: to the beam's start)."""

    start: int
    conf: np.ndarray
    near: float
    far: float

    def holds(self, reach_m: float) -> bool:
        """Whether the rows read held the pools of these photons at ``reach_m`` (:meth:`SignalFinder.reach_m`)."""
        return self.near > reach_m and self.far > reach_m


class FinderStream:
    """Blocks of ``block`` photons of each beam classified by ``finder`` on worker processes while the photons are
    appended with :meth:`add`: the photons are held from the first, and blocks made once :meth:`start` gave the
    workers (a thread of this process hands the blocks over as they are made); :meth:`finish` waits for them."""

    def __init__(self, finder: SignalFinder, block: int | None = None, most_waiting: int | None = None):
        """``most_waiting``: the most blocks handed over and not yet classified (None: WAITING_PER_WORKER per
        worker); a block completed beyond them is left to the close (read back from the file there), so the photons
        held stay bounded when the workers fall behind."""
        self.finder, self.block, self.workers = finder, block or STREAM_BLOCK, None
        self.most_waiting, self._waiting, self._lock = most_waiting, 0, threading.Lock()
        self.beams: dict[str, _Beam] = {}
        self.pieces: dict[str, list[Piece]] = {}
        self._blocks: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def start(self, workers: ProcessMap) -> None:
        """Make blocks from the next :meth:`add` on, classified on ``workers``."""
        self._thread = threading.Thread(target=self._serve, args=(workers,), name="finder", daemon=True)
        self._thread.start()
        if self.most_waiting is None:
            self.most_waiting = WAITING_PER_WORKER * len(workers.processes)
        self.workers = workers

    def add(self, name: str, along: np.ndarray, h: np.ndarray, pulse: np.ndarray, spread_m: float) -> None:
        """Append a beam's next photons (along-track distance [m], height [m], pulse id, in the order stored), and
        hand over the blocks they complete; ``spread_m``: :func:`~flightsim.scoring.signal_finder.along_spread` of
        the beam's photons so far."""
        beam = self.beams.setdefault(name, _Beam())
        if beam.stopped:
            return
        beam.parts.append((along, h, pulse))
        beam.rows += len(h)
        made = []
        while self.workers is not None and beam.rows - beam.sent >= self.block:
            if self._waiting + len(made) >= self.most_waiting:  # the workers behind: this block left to the close
                self._advance(beam, *self._held(beam))
                continue
            block = self._block(beam, self.finder.reach_m(spread_m))
            if block is None:
                break
            made.append((name, *block))
        if made:
            with self._lock:
                self._waiting += len(made)
            self._blocks.put(made)

    def finish(self, streams: dict[str, tuple]) -> list[tuple]:
        """Wait for every block handed over, write the confidences of those whose rows held their pools at each
        beam's final spread (``streams``: each beam's ``(n, read, write, block, spread_m)``, as
        :meth:`SignalFinder.classify_streams` takes them) and give the spans left to classify
        (:meth:`SignalFinder.classify_spans`): the rest of each beam, and blocks read short of the final spread.
        The error of a block that failed is raised here."""
        self.stop()
        if self._error is not None:
            raise self._error
        spans = []
        for name, stream in streams.items():
            n, _, write, _, spread = stream
            done = sorted((piece for piece in self.pieces.get(name, []) if piece.holds(self.finder.reach_m(spread))),
                          key=lambda piece: piece.start)  # they came back in any order
            for piece in done:
                write(piece.start, piece.conf)
            spans += block_spans(stream, _left(n, done))
        return spans

    def stop(self) -> None:
        """Let the thread end once the blocks handed over are done; drop the photons held."""
        self.beams.clear()
        if self._thread is not None:
            self._blocks.put(None)
            self._thread.join()
            self._thread = None

    def _block(self, beam: _Beam, reach_m: float) -> tuple | None:
        """The next block's (start, along, h, pulse, first, past, near, far), read with rows around it that hold its
        pools (the rows held before it then dropped); None while the rows after it do not reach far enough yet."""
        along, h, pulse = self._held(beam)
        start, end = beam.sent - beam.base, beam.sent - beam.base + self.block
        lo, _, rows, near, far = padded_rows(len(h), lambda a, b: (along[a:b], h[a:b], pulse[a:b]), start, end,
                                             self.block, reach_m, from_start=beam.base == 0, to_end=False)
        if near <= reach_m:  # it needs rows before those held
            beam.stopped, beam.parts = True, []
            return None
        if far <= reach_m:  # too few photons after it yet
            return None
        block = (beam.sent, *rows, start - lo, end - lo, near, far)
        self._advance(beam, along, h, pulse)
        return block

    @staticmethod
    def _held(beam: _Beam) -> tuple[np.ndarray, ...]:
        """The beam's photons held (rows base …), as one array a column."""
        held = tuple(np.concatenate(column) for column in zip(*beam.parts))
        beam.parts = [held]
        return held

    def _advance(self, beam: _Beam, along: np.ndarray, h: np.ndarray, pulse: np.ndarray) -> None:
        """Go past the next block (``along``, ``h``, ``pulse``: the rows held), holding its rows on as the rows
        before the block after it."""
        start = beam.sent - beam.base
        beam.parts = [(along[start:], h[start:], pulse[start:])]
        beam.base, beam.sent = beam.sent, beam.sent + self.block

    def _serve(self, workers: ProcessMap) -> None:
        """The thread's loop: one map over the blocks as they are handed over, each given to the first worker free
        (every worker busy while blocks wait), its piece kept as it comes back."""
        given: list[tuple] = []  # (beam, first row, near, far) of each block handed to the workers

        def blocks():
            while (made := self._blocks.get()) is not None:
                for name, start, *rows, near, far in made:
                    given.append((name, start, near, far))
                    yield (self.finder, *rows)

        def done(index: int, conf: np.ndarray) -> None:
            name, start, near, far = given[index]
            with self._lock:
                self._waiting -= 1
            self.pieces.setdefault(name, []).append(Piece(start, conf, near, far))

        try:
            workers.map(classify_part, blocks(), done)
        except BaseException as error:  # noqa: BLE001 - raised again by finish
            self._error = error
            while self._blocks.get() is not None:  # the blocks still handed over, dropped
                pass


def _left(n: int, done: list[Piece]) -> list[tuple[int, int]]:
    """The ranges of rows [0, n) outside the classified pieces ``done`` (in row order)."""
    ranges, start = [], 0
    for piece in done:
        if piece.start > start:
            ranges.append((start, piece.start))
        start = piece.start + len(piece.conf)
    return ranges + ([(start, n)] if start < n else [])
