"""Warp start-up and device selection, done once per process."""
from __future__ import annotations

import functools

import warp as wp

from flightsim.errors import InputError


@functools.cache
def init_warp() -> None:
    """Initialise Warp quietly (the kernel cache is Warp's default or ``WARP_CACHE_PATH``)."""
    wp.config.log_level = wp.LOG_WARNING
    wp.init()


def resolve_device(name: str) -> str:
    """Check that a device name ("cpu", "cuda", "cuda:N") exists here and return Warp's name for it."""
    init_warp()
    if name == "cpu":
        return "cpu"
    count = wp.get_cuda_device_count()
    index = 0 if name == "cuda" else int(name.split(":", 1)[1])
    if index >= count:
        available = "cpu" + "".join(f", cuda:{i}" for i in range(count))
        raise InputError("run.device", name, f"a device present on this machine ({available})")
    return f"cuda:{index}"
