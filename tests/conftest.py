"""Shared fixtures: every kernel test runs on each available device (CPU always, CUDA when present).

Scenes read from files are cached in a folder of this test session (removed at exit), never in the
user's ``~/.cache/flightsim``: a test must not reuse, or leave behind, an entry of another run.
"""
import atexit
import os
import shutil
import tempfile

# The product pins (test_product_pins.py) were made with OpenBLAS's AVX2 (Haswell) kernels. OpenBLAS picks its kernels
# by the CPU it runs on (AVX-512 ones on Skylake-X and later), and those round the plane fits' eigen-decompositions
# and the solvers' steps differently in the last bits. Name the kernels before NumPy or SciPy load OpenBLAS, so that
# the suite gives the same bits on every x86-64 machine (test_blas.py checks that this took effect).
os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import pytest  # noqa: E402

os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp-cache"))
_SCENE_CACHE = tempfile.mkdtemp(prefix="flightsim-test-scenes-")
os.environ["FLIGHTSIM_CACHE"] = _SCENE_CACHE
atexit.register(shutil.rmtree, _SCENE_CACHE, ignore_errors=True)


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
