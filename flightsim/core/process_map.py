"""A module-level function mapped over chunks of work in worker interpreters: a product's per-shot SciPy fits
(waveforms.h5's host ranging, l2a.h5's lowest modes) on every core instead of one.

A worker is a fresh interpreter (``sys.executable -c``, fork-free: this process may hold a CUDA context and
threads) that imports the function's module by name, and not the parent's ``__main__`` (multiprocessing's spawn
would re-run a script's top level); it takes the parent's ``sys.path`` and environment, so it runs the same
NumPy and SciPy with the same dispatch, and a chunk's results are bit for bit those of the parent. Arguments and
results travel pickled over a socket (:class:`multiprocessing.connection.Connection`); each worker gets its next
chunk as it returns one, and :meth:`ProcessMap.map` gives the results in the chunks' order. A message's NumPy arrays
travel after its pickle as they are (:func:`send`): pickling a 24 MB block of photons into the message copied it
under Python's lock (87-146 ms on the 2-core CPU, ~5 ms on a GPU host, where the signal finder's stream sends ~90).

An exception in a worker is raised again by :meth:`ProcessMap.map` with the worker's traceback as a note, and
stops every worker (a map cut short leaves chunks in flight); :meth:`ProcessMap.stop` (also on garbage
collection and at interpreter exit) ends them.
"""
from __future__ import annotations

import contextlib
import importlib
import json
import os
import pickle
import socket
import struct
import subprocess
import sys
import threading
import traceback
import weakref
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection, wait
from typing import Callable, Iterable

MIN_ROWS_PER_CHUNK = 64  # the fewest rows a chunk of a map over rows holds
CHUNKS_PER_WORKER = 4  # a map over rows cuts them into about this many chunks per worker (the fits' times vary)

_ENTRY = ("import json, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "  # the parent stops its workers
          "sys.path[:] = json.loads(sys.argv[2]); "
          "from flightsim.core.process_map import serve; serve(int(sys.argv[1]), json.loads(sys.argv[3]))")


MAX_THREADS = 16  # the most threads a host step spreads its pieces of work over
ROWS_PER_PIECE = 1 << 18  # the fewest rows of a piece of an elementwise host step (by_pieces)


def thread_count(pieces: int) -> int:
    """Threads for ``pieces`` independent pieces of host work: as many as the pieces, the usable cores and
    MAX_THREADS allow, at least 1."""
    return max(1, min(pieces, usable_cores(), MAX_THREADS))


def by_pieces(rows: int, work: Callable[[slice], object], least: int | None = None) -> list:
    """``work(piece)`` of each slice of ``rows`` rows (pieces of at least ``least`` rows, None: ROWS_PER_PIECE; about
    two a thread) on :func:`thread_count` threads, NumPy's loops releasing Python's lock; the results in the pieces'
    order. A piece's temporaries stay small, where one pass over all the rows would allocate (and fault in) arrays of
    them all."""
    least = least or ROWS_PER_PIECE
    threads = thread_count(-(-rows // least))
    size = max(least, -(-rows // (2 * threads)))
    pieces = [slice(first, min(first + size, rows)) for first in range(0, rows, size)]
    if len(pieces) < 2:
        return [work(piece) for piece in pieces]
    with ThreadPoolExecutor(threads, thread_name_prefix="pieces") as pool:
        return list(pool.map(work, pieces))


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a batch scheduler sets it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def row_chunks(rows: int, workers: "ProcessMap | None") -> list[slice]:
    """``rows`` rows cut for :func:`map_rows`: one chunk without workers, else about CHUNKS_PER_WORKER per worker
    of at least MIN_ROWS_PER_CHUNK rows."""
    if workers is None:
        return [slice(0, rows)]
    size = max(MIN_ROWS_PER_CHUNK, -(-rows // (CHUNKS_PER_WORKER * len(workers.processes))))
    return [slice(first, min(first + size, rows)) for first in range(0, rows, size)]


def map_rows(function: Callable, chunks: Iterable[tuple], workers: "ProcessMap | None") -> list:
    """``[function(*chunk) for chunk in chunks]``, in this process without workers (``chunks`` may be made as they
    are taken: a generator)."""
    return [function(*chunk) for chunk in chunks] if workers is None else workers.map(function, chunks)


class ProcessMap:
    """``count`` worker interpreters (>= 1) that run module-level functions on pickled arguments; each imports the
    modules ``preload`` names as it starts (while the parent goes on), not at its first task, and calls the functions
    it names as ``module:function`` (no arguments: e.g. Warp's start)."""

    def __init__(self, count: int, preload: tuple[str, ...] = ()):
        self.processes: list[subprocess.Popen] = []
        self.connections: list[Connection] = []
        self._lock = threading.Lock()  # one map at a time (a writer's thread and the writer may both map)
        self._stop = weakref.finalize(self, _stop, self.processes, self.connections)
        try:
            for _ in range(count):
                self._start(preload)
        except BaseException:
            self.stop()
            raise

    def _start(self, preload: tuple[str, ...]) -> None:
        parent, child = socket.socketpair()
        with child:
            try:
                process = subprocess.Popen([sys.executable, "-c", _ENTRY, str(child.fileno()), json.dumps(sys.path),
                                            json.dumps(list(preload))],
                                           pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL)
            except BaseException:
                parent.close()
                raise
        self.processes.append(process)
        self.connections.append(Connection(parent.detach()))

    def map(self, function: Callable, chunks: Iterable[tuple], done: Callable[[int, object], None] | None = None) -> list:
        """``[function(*chunk) for chunk in chunks]``, the chunks spread over the workers, each taken from ``chunks``
        as a worker frees (a map asked for from another thread meanwhile waits for this one); ``done(index, result)``
        is called as each result comes back, in whatever order (then the list holds None: the results are not kept)."""
        with self._lock:
            return self._map(function, chunks, done)

    def _map(self, function: Callable, chunks: Iterable[tuple], done: Callable[[int, object], None] | None) -> list:
        task = (function.__module__, function.__qualname__)
        results: dict[int, object] = {}
        waiting = iter(enumerate(chunks))  # a chunk is made as a worker frees to take it
        busy: dict[Connection, int] = {}

        def give(conn: Connection) -> None:
            try:
                index, chunk = next(waiting, (None, None))
            except BaseException:
                self.stop()  # the answers the other workers still owe would reach the next map
                raise
            if index is not None:
                send(conn, (*task, chunk))
                busy[conn] = index

        for conn in self.connections:
            give(conn)
        while busy:
            for conn in wait(list(busy)):
                index = busy.pop(conn)
                results[index] = self._answer(conn)
                if done is not None:
                    done(index, results[index])
                    results[index] = None
                give(conn)
        return [results[index] for index in range(len(results))]

    def _answer(self, conn: Connection):
        worker = self.connections.index(conn)
        try:
            message = receive(conn)
        except (EOFError, OSError):
            message = None
        if message is not None and message[0] == "ok":
            return message[1]
        process = self.processes[worker]
        self.stop()
        if message is None:
            raise RuntimeError(f"worker {worker} (pid {process.pid}) ended with exit status {process.returncode}")
        error = message[1]
        error.add_note(f"raised in worker {worker} (pid {process.pid}):\n{message[2].rstrip()}")
        raise error

    def stop(self) -> None:
        """End every worker (idempotent)."""
        self._stop()


def _stop(processes: list[subprocess.Popen], connections: list[Connection]) -> None:
    for conn in connections:
        conn.close()
    for process in processes:
        try:
            process.wait(timeout=5.0)  # a worker ends when its connection closes
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def serve(fd: int, preload: list[str] = ()) -> None:
    """A worker's loop: import the ``preload`` modules (and call the ``module:function`` ones), then run each (module,
    name, arguments) received on the connection ``fd`` and send back ("ok", result) or ("error", exception,
    traceback), until the connection closes (a preload that fails is left to the task that needs it, which then
    reports the error)."""
    for entry in preload:
        module, _, call = entry.partition(":")
        with contextlib.suppress(Exception):
            loaded = importlib.import_module(module)
            if call:
                getattr(loaded, call)()
    conn = Connection(fd)
    while True:
        try:
            module, name, args = receive(conn)
        except EOFError:
            return
        try:
            function = importlib.import_module(module)
            for part in name.split("."):
                function = getattr(function, part)
            send(conn, ("ok", function(*args)))
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
            send(conn, ("error", exc, traceback.format_exc()))


def send(conn: Connection, message) -> None:
    """Send ``message`` pickled (protocol 5), the buffers it lends pickle (contiguous NumPy arrays' data) sent after it
    as they are: no copy of them is made under Python's lock (the socket's writes let go of it). The first message
    holds their count and sizes, then the pickle."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    views = [buffer.raw() for buffer in buffers]
    conn.send_bytes(struct.pack(f"<I{len(views)}Q", len(views), *(view.nbytes for view in views)) + head)
    for view in views:
        conn.send_bytes(view)


def receive(conn: Connection):
    """A message of :func:`send`: its buffers received into writable memory of their own (the arrays as writable as
    a pickle's own copies)."""
    first = conn.recv_bytes()
    (count,) = struct.unpack_from("<I", first)
    buffers = [bytearray(size) for size in struct.unpack_from(f"<{count}Q", first, 4)]
    for buffer in buffers:
        conn.recv_bytes_into(buffer)
    return pickle.loads(memoryview(first)[4 + 8 * count:], buffers=buffers)
