"""The frames a LAZ tile writer (:mod:`.laz_workers`) and its worker processes (:mod:`.laz_serve`) exchange.

Protocol on each worker's socket (a Unix socket pair), in frames of a fixed head (:data:`FRAME`) and a
body: the parent sends the ``TileWriter`` options (pickled), then one head per write — tile key, bounds,
and where the records lie in the ring — and finally a finish frame. The worker answers each write with a
"freed" frame, and ends with one pickled message before it exits: ``("finished",)`` once its tile files
are finished under their temporary names (the parent renames them), or ``("error", exception, traceback
text)`` as soon as one of its writes fails (after deleting its temporaries). It ignores Ctrl-C (the
parent stops it) and stops, deleting its temporaries, when the parent goes away.
"""
from __future__ import annotations

import pickle
import socket
import struct

import numpy as np

FRAME = struct.Struct("<B10qQ")
"""Head of a frame: its kind; a write's tile key (x, y indices), least and greatest stored X, Y, Z [mm], and
the offset and length of its records in the ring (zeros in other frames); the byte length of the body that
follows."""
OBJECT, WRITE, FINISH, FREED = 0, 1, 2, 3  # a pickled object, records of one tile, no more records, a write done
NO_NUMBERS = (0,) * 10


def send_frame(sock: socket.socket, kind: int, numbers: tuple = NO_NUMBERS, body: memoryview | None = None) -> None:
    """Send one frame: head and body in one ``sendmsg`` call (the GIL released while it blocks), finished
    by ``sendall`` where a signal cut it short."""
    body = memoryview(b"") if body is None else body
    head = FRAME.pack(kind, *numbers, body.nbytes)
    sent = sock.sendmsg([head, body])
    if sent < len(head):
        sock.sendall(head[sent:])
    if sent < len(head) + body.nbytes:
        sock.sendall(body[max(0, sent - len(head)):])


def receive_frame(sock: socket.socket) -> tuple[int, tuple, np.ndarray]:
    """The next frame: its kind, the numbers of its head, and its body (uint8)."""
    kind, *numbers, size = FRAME.unpack(_receive_exactly(sock, FRAME.size))
    return kind, tuple(numbers), _receive_exactly(sock, size)


def receive_object(sock: socket.socket):
    """The object of the next frame (a pickled one)."""
    return pickle.loads(receive_frame(sock)[2])


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
