"""Warp start-up and device selection, done once per process."""
from __future__ import annotations

import contextlib
import functools
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from flightsim.core.errors import InputError


NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"  # expected on CPU-only machines


@contextlib.contextmanager
def _native_stderr_without(noise: str):
    """Hold back what native code writes to stderr (fd 2) and pass on every line but ``noise``."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            kept = [line for line in held.read().decode(errors="replace").splitlines(True) if noise not in line]
            sys.stderr.write("".join(kept))


@functools.cache
def init_warp() -> None:
    """Initialise Warp quietly (the kernel cache is Warp's default or ``WARP_CACHE_PATH``, seeded with flightsim's
    prebuilt kernels: :mod:`flightsim.core.prebuilt`); the missing-driver notice of a machine without a GPU is
    dropped, anything else is shown."""
    from flightsim.core.prebuilt import seed_kernel_cache

    wp.config.log_level = wp.LOG_WARNING
    with _native_stderr_without(NO_DRIVER):
        wp.init()
    _name_cpu_objects()
    seed_kernel_cache()


def _name_cpu_objects() -> None:
    """Have Warp work out, once and on this thread, the LLVM version and target its CPU objects' file names carry.
    It does so on first use and keeps the answer, but its native call for the version is not safe to make from
    several threads at once (it can return an empty string): a module first loaded by parallel loads
    (:func:`compile_ahead`) could then be looked up without the name's target hash, miss its cached or prebuilt
    object and be compiled again."""
    from warp._src import context

    context._get_cpu_toolchain_version()
    context._get_cpu_target_triple()


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



def compile_ahead(device: str, kernels) -> None:
    """Compile (or load from Warp's kernel cache) the modules of ``kernels`` on ``device`` at once, one thread per
    module up to the machine's cores, before their first launch would compile them one at a time. Modules
    already loaded are skipped; Warp compiles a module's code generation under its own lock and the
    compilers (NVRTC, clang) in parallel. Warp is started first (:func:`init_warp`: the kernel cache seeded, the CPU
    objects' names worked out on this thread)."""
    init_warp()
    context = wp.get_device(device).context
    modules = [m for m in {id(k.module): k.module for k in kernels}.values()
               if not any(ctx == context for ctx, _ in m.execs)]  # a loaded module costs nothing more
    if modules:
        wp.force_load(device=device, modules=modules, max_workers=min(len(modules), os.cpu_count() or 1))


_PINNED: dict[tuple[str, type], wp.array] = {}


def loaded_modules() -> int:
    """How many Warp modules this process has loaded, on any device."""
    return sum(1 for module in wp._src.context.user_modules.values() if module.execs)


def host_array(a: wp.array) -> np.ndarray:
    """``a`` (contiguous) on the host as an array of the caller's own: on the CPU a copy of the device memory
    (which a reused buffer's next use overwrites), from a GPU through :func:`copy_into` (``wp.array.numpy``
    page-locks a fresh buffer of the array's size each call: ~1 GB/s)."""
    if a.device.is_cpu:
        return a.numpy().copy()
    like = wp.empty(0, dtype=a.dtype, device="cpu").numpy()  # the dtype and the shape of an element
    out = np.empty(a.shape + like.shape[1:], dtype=like.dtype)
    copy_into(out, a)
    return out


def to_host(a: wp.array) -> np.ndarray:
    """A host copy of a (small) device array, through a page-locked buffer kept per device and type
    (``wp.array.numpy`` of a CUDA array page-locks a fresh buffer each time, ~1 ms per call)."""
    if a.device.is_cpu:
        return a.numpy().copy()
    key = (str(a.device), a.dtype)
    buffer = _PINNED.get(key)
    if buffer is None or len(buffer) < len(a):
        buffer = _PINNED[key] = wp.empty(max(len(a), 1024), dtype=a.dtype, device="cpu", pinned=True)
    wp.copy(buffer, a, count=len(a))
    wp.synchronize_device(a.device)
    return buffer.numpy()[:len(a)].copy()


STAGING_BYTES = 64 << 20  # the page-locked buffer a large device array reaches the host through


def copy_into(out: np.ndarray, a: wp.array) -> None:
    """Copy the contiguous device array ``a`` into the host array ``out`` (as many scalars, of its scalar type:
    a vector element is a row of them) through a page-locked buffer of at most STAGING_BYTES kept per device and
    type: DMA at the bus's rate, and no fresh page-locked allocation per call as ``wp.array.numpy`` makes."""
    flat_out, flat = out.reshape(-1), a.flatten()
    if a.device.is_cpu:
        flat_out[:] = flat.numpy().reshape(-1)
        return
    key = (str(a.device), a.dtype)
    per_element = flat_out.size // max(flat.size, 1)  # scalars of one element
    step = max(1, STAGING_BYTES // (np.dtype(out.dtype).itemsize * max(per_element, 1)))
    buffer = _PINNED.get(key)
    if buffer is None or len(buffer) < min(step, flat.size):
        buffer = _PINNED[key] = wp.empty(min(step, max(flat.size, 1024)), dtype=a.dtype, device="cpu", pinned=True)
    host = buffer.numpy().reshape(len(buffer), -1)
    for first in range(0, flat.size, len(buffer)):
        count = min(len(buffer), flat.size - first)
        wp.copy(buffer, flat, src_offset=first, count=count)
        wp.synchronize_device(a.device)
        parallel_copy(flat_out[first * per_element:(first + count) * per_element], host[:count].reshape(-1))


HOST_COPY_SLICE = 8 << 20  # bytes a thread of parallel_copy takes at a time


@functools.cache
def _host_copiers() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=min(16, os.cpu_count() or 1), thread_name_prefix="host-copy")


def parallel_copy(out: np.ndarray, src: np.ndarray) -> None:
    """out[:] = src (1-D, same length and dtype) in slices of HOST_COPY_SLICE bytes over a pool of threads: a copy
    into freshly allocated memory is bound by its page faults (~4 GB/s on one thread), which threads take side by
    side (NumPy copies without the GIL)."""
    step = max(1, HOST_COPY_SLICE // max(out.itemsize, 1))
    if out.size <= step or (os.cpu_count() or 1) == 1:
        out[:] = src
        return

    def part(first: int) -> None:
        out[first:first + step] = src[first:first + step]

    for done in [_host_copiers().submit(part, first) for first in range(0, out.size, step)]:
        done.result()
