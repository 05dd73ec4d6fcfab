"""The BLAS kernels and NumPy loops the suite runs with (``same_bits``): the product pins hold only for those they were
made with."""
import ctypes
import glob
import os
import platform

import numpy as np
import pytest


def _openblas_core() -> str | None:
    """The core type NumPy's OpenBLAS runs its kernels for, or None where NumPy uses another BLAS."""
    libs = glob.glob(os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs", "libscipy_openblas*.so"))
    for path in libs:
        lib = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename"):
            if hasattr(lib, name):
                getter = getattr(lib, name)
                getter.restype = ctypes.c_char_p
                return getter().decode()
    return None


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="OpenBLAS's Haswell kernels are x86-64's")
def test_openblas_runs_the_kernels_the_pins_were_made_with():
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"]
    core = _openblas_core()
    if core is None:
        # only a NumPy built against another BLAS may skip; a wheel with its OpenBLAS must be found and asked
        assert "openblas" not in blas.lower(), f"NumPy's {blas} library not found in numpy.libs"
        pytest.skip(f"NumPy uses {blas} here, not its own OpenBLAS")
    assert core.lower() == os.environ["OPENBLAS_CORETYPE"].lower() == "haswell"


def test_numpy_runs_no_avx512_loops():
    from numpy._core._multiarray_umath import __cpu_features__

    assert "X86_V4" in os.environ["NPY_DISABLE_CPU_FEATURES"]
    on = sorted(name for name, enabled in __cpu_features__.items() if enabled and ("AVX512" in name or name == "X86_V4"))
    assert on == [], f"NumPy dispatches to {on}: NPY_DISABLE_CPU_FEATURES was set after NumPy loaded"
