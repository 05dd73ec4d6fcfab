"""The numeric libraries set up to give the same bits on every x86-64 machine; imported (for its side effect) before
NumPy or SciPy by the test suite's conftest and by pin_products.py, so that the product pins hold wherever they run.

- OpenBLAS picks its kernels by the CPU it runs on (AVX-512 ones on Skylake-X and later), and those round the plane
  fits' eigen-decompositions and the solvers' steps differently in the last bits: name the AVX2 (Haswell) ones.
- NumPy picks its loops by the CPU too: with AVX-512 its float64 exp, log and trigonometric functions are vectorised
  approximations (within a few ulp), without it glibc's; a DEM's relief, a Monte Carlo's draws or a waveform fit then
  differ in the last bits between machines. Switch its AVX-512 targets off (the names of NumPy ≥ 2.4 and earlier;
  names a NumPy does not know are ignored), so that every machine runs the AVX2 loops or the baseline ones.

``tests/test_blas.py`` checks that both took effect.
"""
import os

os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
NUMPY_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL"
os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", NUMPY_AVX512)
