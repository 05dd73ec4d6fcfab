"""Body of a LAZ worker process (started by :class:`.laz_workers.LazWorkers`): an in-process
:class:`~flightsim.outputs.las_tiles.TileWriter` for the tiles the parent hands over, their records read
from the shared ring (protocol: :mod:`.laz_protocol`)."""
from __future__ import annotations

import contextlib
import mmap
import os
import pickle
import socket
import traceback

import numpy as np

from flightsim.outputs.las_tiles import TileWriter
from flightsim.outputs.laz_protocol import FREED, OBJECT, WRITE, receive_frame, receive_object, send_frame


def serve(fd: int, ring_fd: int) -> None:
    """Body of a worker process: write the tiles the parent hands over on the socket ``fd`` (records in the
    shared ring ``ring_fd``), then finish them or report the first error (see :mod:`.laz_protocol`)."""
    ring = np.frombuffer(mmap.mmap(ring_fd, 0), dtype=np.uint8)
    os.close(ring_fd)
    with socket.socket(fileno=fd) as parent:
        writer = None
        try:
            writer = TileWriter(**receive_object(parent))
            while (frame := receive_frame(parent))[0] == WRITE:
                numbers = frame[1]
                offset, size = numbers[8:]
                writer.write_records(numbers[:2], ring[offset:offset + size], numbers[2:5], numbers[5:8])
                send_frame(parent, FREED)
            writer._finish_files()
        except BaseException as exc:  # includes EOFError: the parent has gone
            if writer is not None:
                writer.abort()
            with contextlib.suppress(OSError):
                send_frame(parent, OBJECT, body=memoryview(pickle.dumps(("error", *_portable(exc)))))
            return
        send_frame(parent, OBJECT, body=memoryview(pickle.dumps(("finished",))))


def _portable(exc: BaseException) -> tuple[BaseException, str]:
    """``exc`` (or, where it does not survive pickling, a ``RuntimeError`` naming its type and message)
    and its formatted traceback."""
    where = "".join(traceback.format_exception(exc))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        exc = RuntimeError(f"{type(exc).__module__}.{type(exc).__qualname__}: {exc}")
    return exc, where
