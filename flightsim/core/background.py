"""A chunk writer run on a thread of its own: the caller hands it each chunk and goes on (tracing the next chunk,
or feeding the other writers of the same chunk) while the writer converts and writes this one; a writer whose
conversion can run apart from its writing has its chunks converted on several threads at once."""
from __future__ import annotations

import contextlib
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

    def __call__(self, chunk, after: Future | None = None, wait: bool = True) -> Future:
        """Hand ``chunk`` over (the writer starts on it once ``after``, when given, has ended: another writer's work
        that should have the cores first); its future. With ``wait`` the caller first waits while ``held`` chunks are
        in hand; without, it goes on at once (the caller holds the chunk anyway)."""
        while wait and len(self._pending) >= self._held:
            self._pending.popleft().result()
        if self._pool is None:
            self._pending.append(self._thread.submit(self._write, chunk, after))
        else:
            prepared = self._pool.submit(self._prepare, chunk, after)
            self._pending.append(self._thread.submit(lambda: self.writer.take(prepared.result())))
        return self._pending[-1]

    def _write(self, chunk, after: Future | None) -> None:
        if after is not None:
            wait([after])
        self.writer(chunk)

    def _prepare(self, chunk, after: Future | None):
        if after is not None:
            wait([after])
        return self.writer.prepare(chunk)

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
        return self.writer.close(*args)

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
