"""What the CUDA driver says about the kernels a run has loaded: registers and local (spill) memory per thread,
shared memory per block and the theoretical occupancy at the block size Warp launches them with.

Warp launches every kernel with its module's ``block_dim`` (256 by default); the occupancy here is the fraction
of an SM's warp slots that blocks of that size can fill given the kernel's registers and shared memory
(``cuOccupancyMaxActiveBlocksPerMultiprocessor``), an upper bound on the achieved occupancy that Nsight Compute
would measure.
"""
from __future__ import annotations

import ctypes

import warp as wp

# CUfunction_attribute and CUdevice_attribute values (cuda.h)
_SHARED_SIZE_BYTES, _LOCAL_SIZE_BYTES, _NUM_REGS = 1, 3, 4
_MAX_THREADS_PER_SM = 39


def _driver():
    return ctypes.CDLL("libcuda.so.1")


def _func_attribute(lib, func: int, attribute: int) -> int:
    value = ctypes.c_int(0)
    lib.cuFuncGetAttribute(ctypes.byref(value), ctypes.c_int(attribute), ctypes.c_void_p(func))
    return value.value


def _max_threads_per_sm(lib, ordinal: int) -> int:
    handle, value = ctypes.c_int(0), ctypes.c_int(0)
    lib.cuDeviceGet(ctypes.byref(handle), ctypes.c_int(ordinal))
    lib.cuDeviceGetAttribute(ctypes.byref(value), ctypes.c_int(_MAX_THREADS_PER_SM), handle)
    return value.value


def _loaded_kernels(device):
    """(mangled name, block_dim, CUfunction) of every kernel loaded on ``device`` (Warp's module registry)."""
    from warp._src import context

    for module in list(context.user_modules.values()):
        for (ctx, block_dim), module_exec in list(module.execs.items()):
            if ctx != device.context:
                continue
            for name, hooks in list(module_exec.kernel_hooks.items()):
                if hooks.forward:
                    yield name, block_dim, int(hooks.forward)


def kernel_attributes(device_name: str) -> dict[str, dict]:
    """Per loaded kernel (named as :func:`flightsim.studies.bench_common.kernel_name` names the timing
    records): registers/thread, local bytes/thread (register spills), static shared bytes/block, block size and
    theoretical occupancy [0-1]. Empty where the driver cannot be asked (no CUDA, another Warp layout)."""
    from flightsim.studies.bench_common import kernel_name

    device = wp.get_device(device_name)
    if not device.is_cuda:
        return {}
    try:
        lib = _driver()
        slots = _max_threads_per_sm(lib, device.ordinal)
        rows = {}
        with wp.ScopedDevice(device):
            for name, block_dim, func in _loaded_kernels(device):
                blocks = ctypes.c_int(0)
                lib.cuOccupancyMaxActiveBlocksPerMultiprocessor(ctypes.byref(blocks), ctypes.c_void_p(func),
                                                                ctypes.c_int(block_dim), ctypes.c_size_t(0))
                rows[kernel_name(name)] = {
                    "registers": _func_attribute(lib, func, _NUM_REGS),
                    "local_bytes": _func_attribute(lib, func, _LOCAL_SIZE_BYTES),
                    "shared_bytes": _func_attribute(lib, func, _SHARED_SIZE_BYTES),
                    "block_dim": block_dim,
                    "occupancy": blocks.value * block_dim / slots if slots else None}
        return rows
    except (OSError, AttributeError, ImportError):
        return {}
