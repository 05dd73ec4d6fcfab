"""Shared fixtures: every kernel test runs on each available device (CPU always, CUDA when present)."""
import os

import pytest

os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp-cache"))


def _devices() -> list[str]:
    from flightsim.core.warp_runtime import init_warp
    import warp as wp

    init_warp()
    return ["cpu"] + [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]


@pytest.fixture(params=_devices())
def device(request) -> str:
    """A Warp device name; tests taking it run once per device."""
    return request.param
