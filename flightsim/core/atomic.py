"""Files that appear complete or not at all: written under a temporary name, then renamed."""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

FADVISE = hasattr(os, "posix_fadvise")
"""Whether this system can be asked to start writing a file's pages back early (not on macOS or Windows)."""


def temporary_name(path: Path) -> Path:
    """The hidden name a file is written under before it is renamed to ``path``."""
    return path.with_name(f".{path.name}.part")


def write_atomic(path: Path, text: str) -> None:
    """Write a text file under a temporary name, then rename it into place."""
    tmp = temporary_name(Path(path))
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def save_figure(fig, path: Path, **savefig_options) -> Path:
    """Save a matplotlib figure under a temporary name, then rename it into place."""
    path = Path(path)
    tmp = temporary_name(path)
    fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", **savefig_options)
    os.replace(tmp, path)
    return path


@contextlib.contextmanager
def replaced_atomically(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path``: fsync'ed and renamed to ``path`` when the block succeeds,
    deleted when it fails."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def start_writeback(fd: int, offset: int = 0, length: int = 0) -> None:
    """Have the kernel start writing a file range's dirty pages to disk (length 0: to the end), without waiting for
    them: POSIX_FADV_DONTNEED starts their write-back on Linux (a no-op where the call does not exist)."""
    if FADVISE:
        os.posix_fadvise(fd, offset, length, os.POSIX_FADV_DONTNEED)


def write_back_since(file, start: int) -> int:
    """Flush ``file`` and have the kernel start writing its bytes from ``start`` to its position (:func:`start_writeback`),
    without waiting for them: a run's output then reaches the disk while it goes on, rather than all in the syncs that
    finish it. The position, where the next call starts."""
    file.flush()
    end = file.tell()
    if end > start:
        start_writeback(file.fileno(), start, end - start)
    return end


def fsync_directory(directory: Path) -> None:
    """Make the renames in ``directory`` durable (skipped where a folder cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def fsync_all(files: Iterable[Path], threads: int = 16) -> None:
    """Wait until the disk has every byte of ``files`` and their folders' entries, the files' syncs run ``threads``
    at a time (a journalling file system commits concurrent syncs together)."""
    files = list(files)

    def sync(path: Path) -> None:
        with open(path, "rb") as fh:
            os.fsync(fh.fileno())

    with ThreadPoolExecutor(max(1, min(threads, len(files)))) as pool:
        list(pool.map(sync, files))
    for folder in sorted({path.parent for path in files}):
        fsync_directory(folder)
