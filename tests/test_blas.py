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
    """Every loop NumPy picks by the CPU (``numpy.lib.introspect.opt_func_info``: each function's current target) is
    below AVX-512. The CPU's feature list (``__cpu_features__``) is no test of it: NumPy 2.4 on an AVX-512 machine
    keeps reporting AVX512F, AVX512BW, ... there with the dispatch targets X86_V4 and AVX512_* switched off; without
    NPY_DISABLE_CPU_FEATURES set before NumPy loads, float64 exp runs X86_V4 there, with it X86_V3."""
    from numpy.lib.introspect import opt_func_info

    assert "X86_V4" in os.environ["NPY_DISABLE_CPU_FEATURES"]
    current = {d["current"] for signatures in opt_func_info().values() for d in signatures.values()}
    wide = sorted(t for t in current if t.startswith(("X86_V4", "AVX512")))
    assert wide == [], f"NumPy dispatches to {wide}: NPY_DISABLE_CPU_FEATURES was set after NumPy loaded"
