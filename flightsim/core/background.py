"""A chunk writer run on a thread of its own: the caller hands it each chunk and goes on (tracing the next chunk,
or feeding the other writers of the same chunk) while the writer converts and writes this one."""
from __future__ import annotations

import contextlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor, wait

HELD_CHUNKS = 2  # chunks a writer may have waiting or in hand before the caller waits for the oldest


class Background:
    """``writer(chunk)`` on a thread of its own, chunk after chunk in the order given; ``close()`` and ``abort()``
    once every chunk handed over is done. The writer's error is raised in the caller at its next chunk, at
    :meth:`settle` or at :meth:`close`. A chunk must not change after it was handed over (the writer reads it
    later). The wrapped writer is :attr:`writer` (read its state after :meth:`settle`)."""

    def __init__(self, writer, name: str, held: int = HELD_CHUNKS):
        self.writer, self._held = writer, held
        self._thread = ThreadPoolExecutor(1, thread_name_prefix=name)
        self._pending: deque[Future] = deque()

    def __call__(self, chunk, after: Future | None = None, wait: bool = True) -> Future:
        """Hand ``chunk`` over (the writer starts on it once ``after``, when given, has ended: another writer's work
        that should have the cores first); its future. With ``wait`` the caller first waits while ``held`` chunks are
        in hand; without, it goes on at once (the caller holds the chunk anyway)."""
        while wait and len(self._pending) >= self._held:
            self._pending.popleft().result()
        self._pending.append(self._thread.submit(self._write, chunk, after))
        return self._pending[-1]

    def _write(self, chunk, after: Future | None) -> None:
        if after is not None:
            wait([after])
        self.writer(chunk)

    def settle(self) -> None:
        """Wait until every chunk handed over is written; raise the first error."""
        while self._pending:
            self._pending.popleft().result()

    def close(self, *args):
        """The writer's ``close(*args)`` once its chunks are written (its return value)."""
        try:
            self.settle()
        finally:
            self._thread.shutdown()
        return self.writer.close(*args)

    def abort(self) -> None:
        """The writer's ``abort()`` once the chunks being written have ended (their errors dropped: the run is
        failing already)."""
        for future in self._pending:
            future.cancel()
        for future in self._pending:
            with contextlib.suppress(BaseException):
                future.result()
        self._pending.clear()
        self._thread.shutdown()
        self.writer.abort()
