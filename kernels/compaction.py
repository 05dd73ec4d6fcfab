"""Compaction of a chunk's slots on the device: flag the slots that returned, and gather them in slot order."""
from typing import Any

import warp as wp

from kernels.frames import Segments
from kernels.trace import STATUS_LEAF, STATUS_RETURN

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


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


@wp.func
def _returns_before(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_slots: int, b: int) -> int:
    """The number of returns among the slots before slot ``b`` (0 ≤ b ≤ n_slots)."""
    if b == n_slots:
        return offsets[n_slots - 1] + flags[n_slots - 1]
    return offsets[b]


@wp.kernel
def count_returns(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_slots: int,
                  total: wp.array(dtype=wp.int32)):
    """total[0] ← the number of returns among the chunk's ``n_slots`` slots (one thread)."""
    total[0] = _returns_before(flags, offsets, n_slots, n_slots)


@wp.kernel
def add_segment_returns(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_slots: int,
                        segments: Segments, slots_per_pulse: int, per_line: wp.array(dtype=wp.int64)):
    """per_line[line] += the returns of each segment of the chunk (one thread per segment): the chunk's segment table
    (the tracer's, already on the device), whose segment i holds the slots pulse_start[i] · slots_per_pulse up to
    the next segment's (pulse_start's last entry: the chunk's pulse count)."""
    i = wp.tid()
    n = (_returns_before(flags, offsets, n_slots, wp.min(segments.pulse_start[i + 1] * slots_per_pulse, n_slots)) -
         _returns_before(flags, offsets, n_slots, segments.pulse_start[i] * slots_per_pulse))
    wp.atomic_add(per_line, segments.line[i], wp.int64(n))
