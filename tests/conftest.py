"""Shared fixtures: every kernel test runs on each available device (CPU always, CUDA when present).

Scenes read from files are cached in a folder of this test session (removed at exit), never in the
user's ``~/.cache/flightsim``: a test must not reuse, or leave behind, an entry of another run.
"""
import atexit
import os
import shutil
import tempfile

import same_bits  # noqa: E402,F401  (before NumPy loads: its loops and OpenBLAS's kernels named)
import pytest  # noqa: E402

os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp-cache"))
_SCENE_CACHE = tempfile.mkdtemp(prefix="flightsim-test-scenes-")
os.environ["FLIGHTSIM_CACHE"] = _SCENE_CACHE
atexit.register(shutil.rmtree, _SCENE_CACHE, ignore_errors=True)


MAX_WORKERS = 4  # processes of `-n auto` (pyproject's addopts): each holds Warp, its kernels and a CUDA context


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto`: a process per core the suite may use, at most MAX_WORKERS."""
    return max(1, min(len(os.sched_getaffinity(0)), MAX_WORKERS))


def _devices() -> list[str]:
    from flightsim.core.warp_runtime import init_warp
    import warp as wp

    init_warp()
    return ["cpu"] + [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]


@pytest.fixture(params=_devices())
def device(request) -> str:
    """A Warp device name; tests taking it run once per device."""
    return request.param


@pytest.fixture(params=[None, *_devices()], ids=lambda d: d or "host")
def voxels_on(request) -> str | None:
    """Where a stand's leaf voxels are integrated: None the host's NumPy, else the kernel on that Warp device."""
    return request.param
