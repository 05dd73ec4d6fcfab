"""LAZ tiles compressed in worker processes, so that compression never holds this process's GIL.

lazrs holds the GIL of the process that calls it for as long as it compresses. A LAZ
:class:`~flightsim.outputs.las_tiles.TileWriter` with workers therefore only hands each write's record
bytes to a worker, and every worker runs an in-process ``TileWriter`` over the same directory for the
tiles it owns, compressing each write as it arrives. Each tile belongs to one worker (a new tile to the
worker with the fewest record bytes so far), whose socket delivers a tile's records in the order they
were written: the tiles are byte-identical to those written in one process.

A write copies the records into its worker's queue and returns; one sender thread per worker feeds the
worker's socket (``sendmsg``, which releases the GIL). A worker busy compressing therefore holds up
only its own queue, not the writes meant for idle workers; a write waits only while its worker's queue
holds :data:`QUEUE_BYTES` already, so memory stays bounded.

A worker is a fresh interpreter (``sys.executable``, fork-free: this process may hold a CUDA context and
threads) that imports this module, :mod:`flightsim.outputs.las_tiles` and what they import — not Warp,
and not the parent's ``__main__`` (multiprocessing's spawn would re-run a script's top level). It takes
the parent's ``sys.path`` (on its command line), so it imports flightsim from where the parent does.

Protocol on each worker's socket (a Unix socket pair), in frames of a fixed head (:data:`_FRAME`) and a
body: the parent sends the ``TileWriter`` options (pickled), then one frame per write — tile key and
bounds in the head, the records' bytes as the body, one ``sendmsg`` call — and finally a finish frame. A
worker sends one pickled message and exits: ``("finished",)`` once its tile files are finished under
their temporary names (the parent renames them), or ``("error", exception, traceback text)`` as soon as
one of its writes fails (after deleting its temporaries). It ignores Ctrl-C (the parent stops it) and
stops, deleting its temporaries, when the parent goes away.
"""
from __future__ import annotations

import contextlib
import json
import pickle
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import traceback
import weakref
from collections import deque

import numpy as np

QUEUE_BYTES = 64 << 20
"""Most record bytes waiting in this process for one worker (a write that would exceed it waits, unless
the queue is empty)."""
EXIT_WAIT_S = 60.0
"""How long a worker that has finished its tiles may take to exit before it is killed [s]."""
_ENTRY = ("import json, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "  # the parent stops its workers
          "sys.path[:] = json.loads(sys.argv[2]); "
          "from flightsim.outputs.laz_workers import serve; serve(int(sys.argv[1]))")
_FRAME = struct.Struct("<B8qQ")
"""Head of a frame: its kind; a write's tile key (x, y indices) and least and greatest stored X, Y, Z [mm]
(zeros in other frames); the byte length of the body that follows."""
_OBJECT, _WRITE, _FINISH = 0, 1, 2  # frame kinds: a pickled object, records of one tile, no more records
_NO_NUMBERS = (0,) * 8


class LazWorkers:
    """The worker processes that write the tiles of one LAZ ``TileWriter``, and a sender thread for each.

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
        self._senders: list[_Sender] = []
        self._stop = weakref.finalize(self, _kill, self.processes, self._sockets, self._senders)
        self._messages = select.poll()  # any worker's message (or end) is a failure until finish()
        self._worker_of_fd: dict[int, int] = {}
        self._owner: dict[tuple[int, int], int] = {}
        self._assigned = [0] * count  # record bytes handed to each worker so far
        self._error: BaseException | None = None
        try:
            for _ in range(count):
                self._start(writer_options)
        except BaseException:
            self.stop()
            raise

    def write(self, key: tuple[int, int], records: np.ndarray, lowest, highest) -> None:
        """Queue a copy of ``records`` (a C-contiguous array) of tile ``key`` for the worker that owns the
        tile, with the least and greatest stored X, Y, Z of the records [mm]."""
        self._raise_failure()
        key = (int(key[0]), int(key[1]))
        worker = self._owner.get(key)
        if worker is None:
            worker = self._owner[key] = self._assigned.index(min(self._assigned))
        body = records.view(np.uint8).reshape(-1).copy()
        self._assigned[worker] += body.nbytes
        numbers = (*key, *(int(v) for v in lowest), *(int(v) for v in highest))
        self._send(worker, _WRITE, numbers, body)

    def finish(self) -> None:
        """Have every worker finish its tile files under their temporary names, and wait until they have
        exited; raise the first worker's error, if any."""
        self._raise_failure()
        try:
            for worker in range(len(self.processes)):
                self._send(worker, _FINISH)
            for worker, sender in enumerate(self._senders):
                if not sender.drain():
                    self._receive(worker)
            for worker in range(len(self.processes)):
                self._receive(worker)
            for process in self.processes:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(EXIT_WAIT_S)
        finally:
            self.stop()

    def stop(self) -> None:
        """Kill every worker that is still running, reap it, and close the sockets (idempotent)."""
        self._stop()

    def _start(self, writer_options: dict) -> None:
        parent, child = socket.socketpair()
        try:
            with child:
                process = subprocess.Popen(
                    [sys.executable, "-c", _ENTRY, str(child.fileno()), json.dumps(sys.path)],
                    pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL)
        except BaseException:
            parent.close()
            raise
        self._worker_of_fd[parent.fileno()] = len(self.processes)
        self.processes.append(process)
        self._sockets.append(parent)
        self._messages.register(parent, select.POLLIN)
        self._senders.append(_Sender(parent))
        self._send(len(self.processes) - 1, _OBJECT, body=np.frombuffer(pickle.dumps(writer_options), np.uint8))

    def _send(self, worker: int, kind: int, numbers: tuple = _NO_NUMBERS, body: np.ndarray | None = None) -> None:
        """Queue a frame for ``worker``; if it has gone, raise why."""
        if not self._senders[worker].put((kind, numbers, body)):
            self._receive(worker)  # the worker has gone: its message, or its death, says why

    def _raise_failure(self) -> None:
        """Raise the error a worker has reported (or its death), if any (one ``poll`` call)."""
        if self._error is None:
            for fd, _ in self._messages.poll(0):
                self._receive(self._worker_of_fd[fd])
        if self._error is not None:
            raise self._error

    def _receive(self, worker: int) -> None:
        """Read the one message of ``worker``: return if it finished its tiles, else raise its error or,
        if it died without one, a ``RuntimeError`` (kept, and raised again by later calls)."""
        process = self.processes[worker]
        try:
            message = _receive_object(self._sockets[worker])
        except (EOFError, OSError):
            message = ("died",)
        if message[0] == "finished":
            return
        if self._error is None:
            self._error = _worker_error(worker, process, message)
        raise self._error


class _Sender:
    """The thread that sends one worker its queued frames, in order; at most :data:`QUEUE_BYTES` of bodies
    wait in its queue (a larger frame waits for an empty queue)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self._frames: deque[tuple[int, tuple, np.ndarray | None]] = deque()
        self._queued = 0  # body bytes in the queue
        self._changed = threading.Condition()
        self._failed = False  # a send failed: the worker has gone
        self._stopped = False
        self._thread = threading.Thread(target=self._run, daemon=True, name="LAZ worker sender")
        self._thread.start()

    def put(self, frame: tuple[int, tuple, np.ndarray | None]) -> bool:
        """Queue ``frame`` (kind, head numbers, body), waiting for room; False if the worker has gone."""
        size = _body_size(frame)
        with self._changed:
            self._changed.wait_for(lambda: self._failed or self._stopped or not self._queued
                                   or self._queued + size <= QUEUE_BYTES)
            if self._failed or self._stopped:
                return False
            self._frames.append(frame)
            self._queued += size
            self._changed.notify_all()
        return True

    def drain(self) -> bool:
        """Wait until every queued frame is sent; False if the worker has gone first."""
        with self._changed:
            self._changed.wait_for(lambda: self._failed or self._stopped or not self._frames)
            return not (self._failed or self._stopped)

    def stop(self) -> None:
        """Drop the queue and have the thread end once the send under way, if any, ends."""
        with self._changed:
            self._stopped = True
            self._frames.clear()
            self._changed.notify_all()

    def join(self) -> None:
        """Wait until the thread has ended (after :meth:`stop`, and its worker's end)."""
        self._thread.join()

    def _run(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._stopped or self._frames)
                if self._stopped:
                    return
                frame = self._frames[0]
            kind, numbers, body = frame
            try:
                _send_frame(self._sock, kind, numbers, None if body is None else memoryview(body))
            except OSError:
                with self._changed:
                    self._failed = True
                    self._changed.notify_all()
                return
            with self._changed:
                if self._frames and self._frames[0] is frame:  # not dropped by stop() meanwhile
                    self._frames.popleft()
                    self._queued -= _body_size(frame)
                self._changed.notify_all()


def _body_size(frame: tuple[int, tuple, np.ndarray | None]) -> int:
    return 0 if frame[2] is None else frame[2].nbytes


def serve(fd: int) -> None:
    """Body of a worker process: write the tiles the parent hands over on the socket ``fd``, then finish
    them or report the first error (see the module docstring)."""
    from flightsim.outputs.las_tiles import TileWriter  # here: las_tiles imports this module

    with socket.socket(fileno=fd) as parent:
        writer = None
        try:
            writer = TileWriter(**_receive_object(parent))
            while (frame := _receive_frame(parent))[0] == _WRITE:
                _, numbers, records = frame
                writer.write_records(numbers[:2], records, numbers[2:5], numbers[5:])
            writer._finish_files()
        except BaseException as exc:  # includes EOFError: the parent has gone
            if writer is not None:
                writer.abort()
            with contextlib.suppress(OSError):
                _send_frame(parent, _OBJECT, body=memoryview(pickle.dumps(("error", *_portable(exc)))))
            return
        _send_frame(parent, _OBJECT, body=memoryview(pickle.dumps(("finished",))))


def _send_frame(sock: socket.socket, kind: int, numbers: tuple = _NO_NUMBERS, body: memoryview | None = None) -> None:
    """Send one frame: head and body in one ``sendmsg`` call (the GIL released while it blocks), finished
    by ``sendall`` where a signal cut it short."""
    body = memoryview(b"") if body is None else body
    head = _FRAME.pack(kind, *numbers, body.nbytes)
    sent = sock.sendmsg([head, body])
    if sent < len(head):
        sock.sendall(head[sent:])
    if sent < len(head) + body.nbytes:
        sock.sendall(body[max(0, sent - len(head)):])


def _receive_frame(sock: socket.socket) -> tuple[int, tuple, np.ndarray]:
    """The next frame: its kind, the numbers of its head, and its body (uint8)."""
    kind, *numbers, size = _FRAME.unpack(_receive_exactly(sock, _FRAME.size))
    return kind, tuple(numbers), _receive_exactly(sock, size)


def _receive_object(sock: socket.socket):
    """The object of the next frame (a pickled one)."""
    return pickle.loads(_receive_frame(sock)[2])


def _receive_exactly(sock: socket.socket, size: int) -> np.ndarray:
    """The next ``size`` bytes (uint8); ``EOFError`` if the peer closes first."""
    data = np.empty(size, dtype=np.uint8)
    view, got = memoryview(data), 0
    while got < size:
        n = sock.recv_into(view[got:])
        if n == 0:
            raise EOFError("the peer closed its socket")
        got += n
    return data


def _portable(exc: BaseException) -> tuple[BaseException, str]:
    """``exc`` (or, where it does not survive pickling, a ``RuntimeError`` naming its type and message)
    and its formatted traceback."""
    where = "".join(traceback.format_exception(exc))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        exc = RuntimeError(f"{type(exc).__module__}.{type(exc).__qualname__}: {exc}")
    return exc, where


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


def _kill(processes: list[subprocess.Popen], sockets: list[socket.socket], senders: list[_Sender]) -> None:
    """Stop ``senders``, kill and reap ``processes``, and close ``sockets``."""
    for sender in senders:
        sender.stop()
    for process in processes:
        process.kill()  # a no-op for a process that has exited (a sender blocked on it fails)
    for process in processes:
        process.wait()
    for sender in senders:
        sender.join()  # before its socket is closed: its descriptor is not reused under a send
    for sock in sockets:
        sock.close()
