"""The command line's entry point (``flightsim``, ``python -m flightsim``). Its modules import with Python's
cyclic garbage collector paused, then frozen: an import allocates long-lived objects only (Warp's built-ins, the
parts' kernels, ~1e6 of them), which the collector would otherwise traverse again and again while they grow
(~0.1 s of a 0.45 s import on a 2-core machine, collecting nothing); the objects made before the run are then left
out of later collections (``gc.freeze``), which go on as usual."""
from __future__ import annotations

import gc


def main(argv: list[str] | None = None) -> int:
    """Run the command line (:func:`flightsim.cli.main`)."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        from flightsim.cli import main as command_line  # noqa: PLC0415  (imported with the collector paused)
    finally:
        gc.freeze()
        if collecting:
            gc.enable()
    return command_line(argv)
