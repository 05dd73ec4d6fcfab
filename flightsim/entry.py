"""The command line's entry point (``flightsim``, ``python -m flightsim``).

Where the command line names a CUDA device (``--device cuda``, ``--device=cuda:N``), the CUDA driver starts and
makes that device's primary context on a thread while the command's modules import: two calls into the driver
that hold no interpreter lock (~0.2 s of a run's start on an H100 machine). Warp, started later by the run, finds
the driver initialised and the context made (the primary context is one per device and process). A command that
ends before the thread has (a bad flag) waits for it: the process never exits inside the driver's start.

The modules import with Python's cyclic garbage collector paused, then frozen: an import allocates long-lived
objects only (Warp's built-ins, the parts' kernels, ~1e6 of them), which the collector would otherwise traverse
again and again while they grow (~0.1 s of a 0.45 s import on a 2-core machine, collecting nothing); the objects
made before the run are then left out of later collections (``gc.freeze``), which go on as usual."""
from __future__ import annotations

import ctypes
import gc
import re
import sys
import threading


def main(argv: list[str] | None = None) -> int:
    """Run the command line (:func:`flightsim.cli.main`)."""
    argv = sys.argv[1:] if argv is None else argv
    device = cuda_ordinal(argv)
    starting = threading.Thread(target=start_cuda, args=(device,), name="cuda-start", daemon=True)
    if device is not None:
        starting.start()
    try:
        return _command_line(argv)
    finally:  # a command that ends at once (a bad flag) leaves only after the driver's start, never inside it
        if starting.is_alive():
            starting.join()


def _command_line(argv: list[str]) -> int:
    """Import the command line's modules with the collector paused, then run it."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        from flightsim.cli import main as command_line  # noqa: PLC0415  (imported with the collector paused)
    finally:
        gc.freeze()
        if collecting:
            gc.enable()
    return command_line(argv)


def cuda_ordinal(argv: list[str]) -> int | None:
    """The ordinal of the CUDA device a command line's ``--device`` flag names ("cuda": 0, "cuda:N": N), else None."""
    for flag, value in zip(argv, argv[1:] + [""]):
        named = value if flag == "--device" else flag.removeprefix("--device=") if flag.startswith("--device=") else ""
        if found := re.fullmatch(r"cuda(?::(\d+))?", named):
            return int(found.group(1) or 0)
    return None


def start_cuda(ordinal: int) -> int | None:
    """Initialise the CUDA driver and retain device ``ordinal``'s primary context (the one Warp uses); its handle,
    or None where there is no driver or no such device (nothing is reported: the run's own start says so)."""
    try:
        driver = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    device, context = ctypes.c_int(), ctypes.c_void_p()
    made = (driver.cuInit(0) == 0 and driver.cuDeviceGet(ctypes.byref(device), ordinal) == 0
            and driver.cuDevicePrimaryCtxRetain(ctypes.byref(context), device) == 0)
    return context.value if made else None
