"""LAZ tiles compressed in worker processes, so that compression never holds this process's GIL.

lazrs holds the GIL of the process that calls it for as long as it compresses. A LAZ
:class:`~flightsim.outputs.las_tiles.TileWriter` with workers therefore only hands each write's records
to a worker, and every worker runs an in-process ``TileWriter`` over the same directory for the tiles it
owns, compressing each write as it arrives. Each tile belongs to one worker (the first tile seen to worker
0, the next to worker 1, ...), which gets a tile's records in the order they were written: the tiles are
byte-identical to those written in one process. Taking tiles in turn as they are first seen keeps a stretch
of a flight line's neighbouring tiles on different workers; giving a new tile to the worker with the fewest
bytes so far instead left the work of a chunk on a few workers (a 25 km² survey's trace stage on an H100
machine: 22.8 s against 11.0 s).

Records travel through shared memory: each worker has a ring of :data:`RING_BYTES` (a ``memfd`` both
processes map). A write copies its records into the worker's ring (one ``memcpy``) and sends a small
head over the worker's socket; the worker compresses straight from the ring and answers with a "freed"
frame once it has. So a write waits only while its own worker's ring is full, never for another worker,
and no record byte crosses a socket (which would move it in pieces of the socket buffer's few hundred
kB, each a GIL hand-over in both processes).

A worker is a fresh interpreter (``sys.executable``, fork-free: this process may hold a CUDA context and
threads) that imports :mod:`.laz_serve`, :mod:`flightsim.outputs.las_tiles` and what they import — not Warp,
and not the parent's ``__main__`` (multiprocessing's spawn would re-run a script's top level). It takes
the parent's ``sys.path`` (on its command line), so it imports flightsim from where the parent does.

The frames on each worker's socket are :mod:`.laz_protocol`'s; a worker's body is :func:`.laz_serve.serve`.
"""
from __future__ import annotations

import contextlib
import json
import mmap
import os
import pickle
import select
import signal
import socket
import subprocess
import sys
import weakref
from collections import deque

import numpy as np

from flightsim.outputs.laz_protocol import FINISH, FREED, NO_NUMBERS, OBJECT, WRITE, receive_frame, send_frame

RING_BYTES = 64 << 20
"""Shared-memory ring of record bytes per worker: a write waits while its worker's ring is full (one larger
than half a ring goes in pieces)."""
EXIT_WAIT_S = 60.0
"""How long a worker that has finished its tiles may take to exit before it is killed [s]."""
_ENTRY = ("import json, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "  # the parent stops its workers
          "sys.path[:] = json.loads(sys.argv[3]); "
          "from flightsim.outputs.laz_serve import serve; serve(int(sys.argv[1]), int(sys.argv[2]))")


class LazWorkers:
    """The worker processes that write the tiles of one LAZ ``TileWriter``.

    An error in a worker (e.g. a full disk) is raised, as the same exception with the worker's traceback
    as a note, by the next :meth:`write` or by :meth:`finish`, and again by every later call; a worker
    that dies gives a ``RuntimeError`` naming it. :meth:`stop` (also on garbage collection and at
    interpreter exit) kills and reaps every worker.

    Args:
        count: number of worker processes (>= 1).
        writer_options: keyword arguments of each worker's in-process ``TileWriter``.
    """

    def __init__(self, count: int, writer_options: dict) -> None:
        self.processes: list[subprocess.Popen] = []  #: the worker processes, in worker order
        self._sockets: list[socket.socket] = []
        self._rings: list[_Ring] = []
        self._stop = weakref.finalize(self, _kill, self.processes, self._sockets)
        self._readable = select.poll()  # a worker's "freed" frames, its message, or its end
        self._worker_of_fd: dict[int, int] = {}
        self._owner: dict[tuple[int, int], int] = {}
        self._error: BaseException | None = None
        try:
            for _ in range(count):
                self._start(writer_options)
        except BaseException:
            self.stop()
            raise

    def write(self, key: tuple[int, int], records: np.ndarray, lowest, highest) -> None:
        """Copy ``records`` (a C-contiguous array) of tile ``key`` into the ring of the worker that owns the
        tile and tell it so, with the least and greatest stored X, Y, Z of the records [mm]."""
        self._raise_failure()
        key = (int(key[0]), int(key[1]))
        worker = self._owner.setdefault(key, len(self._owner) % len(self.processes))
        data = records.reshape(-1).view(np.uint8)
        ring, piece = self._rings[worker], self._rings[worker].size // 2
        piece -= piece % records.dtype.itemsize  # whole records in each piece
        bounds = (*(int(v) for v in lowest), *(int(v) for v in highest))
        for start in range(0, data.nbytes, piece):
            part = data[start:start + piece]
            while (offset := ring.take(part.nbytes)) is None:
                self._read(worker, block=True)  # until the worker frees its oldest write
            np.copyto(ring.array[offset:offset + part.nbytes], part)
            self._send(worker, WRITE, (*key, *bounds, offset, part.nbytes))

    def finish(self) -> None:
        """Have every worker finish its tile files under their temporary names, and wait until they have
        exited; raise the first worker's error, if any."""
        self._raise_failure()
        try:
            for worker in range(len(self.processes)):
                self._send(worker, FINISH)
            for worker in range(len(self.processes)):
                while self._read(worker, block=True) != "finished":
                    pass
            for process in self.processes:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(EXIT_WAIT_S)
        finally:
            self.stop()

    def stop(self) -> None:
        """Kill every worker that is still running, reap it, and close the sockets (idempotent)."""
        self._stop()

    def _start(self, writer_options: dict) -> None:
        ring = _Ring(RING_BYTES)
        parent, child = socket.socketpair()
        try:
            with child:
                process = subprocess.Popen(
                    [sys.executable, "-c", _ENTRY, str(child.fileno()), str(ring.fd), json.dumps(sys.path)],
                    pass_fds=(child.fileno(), ring.fd), stdin=subprocess.DEVNULL)
        except BaseException:
            parent.close()
            raise
        finally:
            ring.close_fd()  # the mapping stays
        self._worker_of_fd[parent.fileno()] = len(self.processes)
        self.processes.append(process)
        self._sockets.append(parent)
        self._rings.append(ring)
        self._readable.register(parent, select.POLLIN)
        self._send(len(self.processes) - 1, OBJECT, body=memoryview(pickle.dumps(writer_options)))

    def _send(self, worker: int, kind: int, numbers: tuple = NO_NUMBERS, body: memoryview | None = None) -> None:
        """Send a frame to ``worker``; if it has gone, raise why."""
        try:
            send_frame(self._sockets[worker], kind, numbers, body)
            return
        except OSError:
            pass  # the worker has gone: its message, or its death, says why
        while True:
            self._read(worker, block=True)  # raises once its message (or its end) comes

    def _raise_failure(self) -> None:
        """Take in what the workers have sent (``poll`` calls, no waiting): rings freed, or the error a worker
        has reported (or its death), which is raised."""
        if self._error is None:
            for fd, _ in self._readable.poll(0):
                worker = self._worker_of_fd[fd]
                while self._read(worker, block=False) is not None:
                    pass
        if self._error is not None:
            raise self._error

    def _read(self, worker: int, block: bool) -> str | None:
        """Read one frame of ``worker`` (None without ``block`` if none is waiting): a "freed" frame frees the
        ring's oldest write ("freed"); its message returns "finished" or raises its error or, if it died
        without one, a ``RuntimeError`` (kept, and raised again by later calls)."""
        sock = self._sockets[worker]
        if not block and not select.select([sock], [], [], 0)[0]:
            return None
        try:
            kind, _, body = receive_frame(sock)
            message = ("freed",) if kind == FREED else pickle.loads(body)
        except (EOFError, OSError):
            message = ("died",)
        if message[0] == "freed":
            self._rings[worker].release()
            return "freed"
        if message[0] == "finished":
            return "finished"
        if self._error is None:
            self._error = _worker_error(worker, self.processes[worker], message)
        raise self._error


class _Ring:
    """A shared-memory ring of ``size`` bytes (a ``memfd``, mapped here and in one worker) handed out in
    contiguous pieces, and freed oldest first."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.fd = os.memfd_create("flightsim-laz-ring")
        os.ftruncate(self.fd, size)
        self._map = mmap.mmap(self.fd, size)
        self.array = np.frombuffer(self._map, dtype=np.uint8)  #: the ring's bytes
        self._live: deque[tuple[int, int]] = deque()  # (start, end) of the pieces in use, oldest first

    def close_fd(self) -> None:
        """Close this process's descriptor of the ring (the mapping stays; the worker has its own copy)."""
        os.close(self.fd)

    def take(self, n: int) -> int | None:
        """The offset of ``n`` (<= size) free contiguous bytes, now in use; None if there is no room yet."""
        if not self._live:
            start = 0
        else:
            oldest, head = self._live[0][0], self._live[-1][1]
            if head > oldest:  # in use: [oldest, head)
                start = head if head + n <= self.size else (0 if n <= oldest else None)
            else:  # in use: [oldest, size) and [0, head)
                start = head if head + n <= oldest else None
        if start is not None:
            self._live.append((start, start + n))
        return start

    def release(self) -> None:
        """Free the oldest piece in use."""
        self._live.popleft()


def _worker_error(worker: int, process: subprocess.Popen, message: tuple) -> BaseException:
    """The exception a worker's message reports, or a ``RuntimeError`` for a worker that died."""
    name = f"LAZ worker {worker} (pid {process.pid})"
    if message[0] == "error":
        _, error, where = message
        error.add_note(f"raised in {name}:\n{where.rstrip()}")
        return error
    try:
        status = process.wait(EXIT_WAIT_S)
    except subprocess.TimeoutExpired:
        status = None
    if status is not None and status < 0:
        how = f"was killed by {signal.Signals(-status).name}"
    else:
        how = f"exited with status {status}" if status is not None else "closed its socket"
    return RuntimeError(f"{name} {how} without finishing its tiles")


def _kill(processes: list[subprocess.Popen], sockets: list[socket.socket]) -> None:
    """Kill and reap ``processes``, and close ``sockets``."""
    for process in processes:
        process.kill()  # a no-op for a process that has exited
    for process in processes:
        process.wait()
    for sock in sockets:
        sock.close()
