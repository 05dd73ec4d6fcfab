"""Files that appear complete or not at all: written under a temporary name, then renamed."""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


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
