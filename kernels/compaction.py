"""Compaction of a chunk's slots on the device: flag the slots that returned, and gather them in slot order."""
from typing import Any

import warp as wp

from kernels.trace import STATUS_LEAF, STATUS_RETURN

wp.set_module_options({"enable_backward": False})


@wp.kernel
def flag_returns(status: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where slot i produced a return (of a surface or of leaves)."""
    i = wp.tid()
    flags[i] = wp.where(status[i] == STATUS_RETURN or status[i] == STATUS_LEAF, 1, 0)


@wp.kernel
def compact_slots(
    flags: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),  # exclusive prefix sum of flags
    src: wp.array(dtype=Any),
    dst: wp.array(dtype=Any),
):
    """Gather the returning slots of ``src`` into ``dst``, keeping their order."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = src[i]


@wp.kernel
def slot_indices(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    """dst[k] = slot index of the k-th return of the chunk."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = i


@wp.kernel
def returns_before(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_slots: int,
                   bounds: wp.array(dtype=wp.int32)):
    """bounds[i] ← the number of returns among the slots before slot bounds[i] (0 ≤ bounds[i] ≤ n_slots)."""
    i = wp.tid()
    b = bounds[i]
    if b == n_slots:
        bounds[i] = offsets[n_slots - 1] + flags[n_slots - 1]
    else:
        bounds[i] = offsets[b]
