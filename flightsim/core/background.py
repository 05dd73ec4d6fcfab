"""A chunk writer run on a thread of its own: the caller hands it each chunk and goes on (tracing the next chunk,
or feeding the other writers of the same chunk) while the writer converts and writes this one; a writer whose
conversion can run apart from its writing has its chunks converted on several threads at once. Each writer's time
is kept (:meth:`Background.timing`): where a run's writers spend it, and how long they held the caller back."""
from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor, wait

HELD_CHUNKS = 2  # chunks a writer may have waiting or in hand before the caller waits for the oldest


class Background:
    """``writer(chunk)`` on a thread of its own, chunk after chunk in the order given; ``close()`` and ``abort()``
    once every chunk handed over is done. The writer's error is raised in the caller at its next chunk, at
    :meth:`settle` or at :meth:`close`. A chunk must not change after it was handed over (the writer reads it
    later). The wrapped writer is :attr:`writer` (read its state after :meth:`settle`).

    With ``threads`` > 1 a writer that has ``prepare(chunk)`` and ``take(prepared)`` (``writer(chunk)`` being
    ``take(prepare(chunk))``, ``prepare`` safe on several threads at once) has up to ``threads`` chunks prepared side
    by side, each taken in the order given on the writer's own thread; it then holds ``threads − 1`` more chunks."""

    def __init__(self, writer, name: str, held: int = HELD_CHUNKS, threads: int = 1):
        self.writer = writer
        staged = threads > 1 and hasattr(writer, "prepare")
        self._held = held + threads - 1 if staged else held
        self._thread = ThreadPoolExecutor(1, thread_name_prefix=name)
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix=name + "-prepare") if staged else None
        self._pending: deque[Future] = deque()
        self._times = {"busy": 0.0, "cpu": 0.0, "prepare": 0.0, "held_back": 0.0, "close": 0.0}
        self._lock = threading.Lock()

    def __call__(self, chunk, after: Future | None = None, wait: bool = True) -> Future:
        """Hand ``chunk`` over (the writer starts on it once ``after``, when given, has ended: another writer's work
        that should have the cores first); its future. With ``wait`` the caller first waits while ``held`` chunks are
        in hand; without, it goes on at once (the caller holds the chunk anyway)."""
        if wait and len(self._pending) >= self._held:
            started = time.perf_counter()
            while len(self._pending) >= self._held:
                self._pending.popleft().result()
            self._add("held_back", time.perf_counter() - started)
        if self._pool is None:
            self._pending.append(self._thread.submit(self._write, chunk, after))
        else:
            prepared = self._pool.submit(self._prepare, chunk, after)
            self._pending.append(self._thread.submit(self._take, prepared))
        return self._pending[-1]

    def _write(self, chunk, after: Future | None) -> None:
        if after is not None:
            wait([after])
        self._timed(self.writer, chunk)

    def _take(self, prepared: Future) -> None:
        self._timed(self.writer.take, prepared.result())

    def _prepare(self, chunk, after: Future | None):
        if after is not None:
            wait([after])
        started = time.perf_counter()
        try:
            return self.writer.prepare(chunk)
        finally:
            self._add("prepare", time.perf_counter() - started)

    def _timed(self, work, item) -> None:
        """``work(item)`` on the writer's thread, its wall and the thread's CPU time kept."""
        started, cpu = time.perf_counter(), time.thread_time()
        try:
            work(item)
        finally:
            self._add("busy", time.perf_counter() - started)
            self._add("cpu", time.thread_time() - cpu)

    def _add(self, name: str, seconds: float) -> None:
        with self._lock:
            self._times[name] += seconds

    def timing(self) -> dict[str, float]:
        """[s] so far: ``busy``, the writer's calls on its own thread (``take`` for a staged writer) and ``cpu``, that
        thread's CPU time in them (busy − cpu: waiting for Python's lock, the disk, or threads it started);
        ``prepare``, a staged writer's ``prepare`` calls summed over its threads; ``held_back``, the caller's waits
        for the writer to take a chunk; ``close``, the writer's ``close``."""
        with self._lock:
            return {name: round(value, 3) for name, value in self._times.items()}

    def settle(self) -> None:
        """Wait until every chunk handed over is written; raise the first error."""
        while self._pending:
            self._pending.popleft().result()

    def close(self, *args):
        """The writer's ``close(*args)`` once its chunks are written (its return value)."""
        try:
            self.settle()
        finally:
            self._shutdown()
        started = time.perf_counter()
        try:
            return self.writer.close(*args)
        finally:
            self._add("close", time.perf_counter() - started)

    def abort(self) -> None:
        """The writer's ``abort()`` once the chunks being written have ended (their errors dropped: the run is
        failing already)."""
        for future in self._pending:
            future.cancel()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        for future in self._pending:
            with contextlib.suppress(BaseException):
                future.result()
        self._pending.clear()
        self._shutdown()
        self.writer.abort()

    def _shutdown(self) -> None:
        """End the threads (once nothing is left for them)."""
        if self._pool is not None:
            self._pool.shutdown()
        self._thread.shutdown()
