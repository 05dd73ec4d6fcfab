"""Milestones of a run for start-up measurements: with ``FLIGHTSIM_TIMELINE=PATH`` in the environment,
:func:`mark` appends ``event epoch_seconds`` to PATH the first time each event happens in the process;
without it, nothing is written."""
from __future__ import annotations

import os
import time

_marked: set[str] = set()


def mark(event: str) -> None:
    """Record the first time ``event`` happens [s since the epoch] where FLIGHTSIM_TIMELINE asks for it."""
    path = os.environ.get("FLIGHTSIM_TIMELINE")
    if not path or event in _marked:
        return
    _marked.add(event)
    with open(path, "a", encoding="utf-8") as f:
        f.write(f"{event} {time.time():.6f}\n")
