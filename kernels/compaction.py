"""Compaction of a chunk's slots on the device: count each beam's returning slots, list the returning slots in slot
order, and gather them (a beam holds ``per_beam`` consecutive slots: the returns a beam may have)."""
from typing import Any

import warp as wp

from kernels.frames import Segments
from kernels.trace import STATUS_LEAF, STATUS_RETURN

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def _returned(status: wp.int32) -> int:
    """1 where a slot of this status holds a return (of a surface or of leaves), else 0."""
    return wp.where(status == STATUS_RETURN or status == STATUS_LEAF, 1, 0)


@wp.kernel
def beam_returns(status: wp.array(dtype=wp.int32), per_beam: int, counts: wp.array(dtype=wp.int32)):
    """counts[b] = how many of beam b's ``per_beam`` slots (b · per_beam + k) hold a return."""
    b = wp.tid()
    n = int(0)
    for k in range(per_beam):
        n += _returned(status[b * per_beam + k])
    counts[b] = n


@wp.kernel
def slot_indices(status: wp.array(dtype=wp.int32), per_beam: int, offsets: wp.array(dtype=wp.int32),
                 dst: wp.array(dtype=wp.int32)):
    """dst[j] = the slot of the chunk's j-th return, in slot order (one thread per beam; ``offsets``: the exclusive
    prefix sum of :func:`beam_returns`' counts)."""
    b = wp.tid()
    j = offsets[b]
    for k in range(per_beam):
        slot = b * per_beam + k
        if _returned(status[slot]) != 0:
            dst[j] = slot
            j += 1


@wp.kernel
def gather_returns(index: wp.array(dtype=wp.int32), src: wp.array(dtype=Any), dst: wp.array(dtype=Any)):
    """dst[j] = src[index[j]]: the returning slots of ``src`` in slot order (one thread per return)."""
    j = wp.tid()
    dst[j] = src[index[j]]


# The overloads a points readout gathers (float32 ranges, angles and cosines; int32 faces and return numbers; vec3f
# points) made with the module: an overload a first launch makes changes the module, which Warp then hashes, compiles
# and loads again mid-run (three versions of this module in a fresh kernel cache, none of them the prebuilt one)
for _dtype in (wp.float32, wp.int32, wp.vec3f):
    wp.overload(gather_returns, {"src": wp.array(dtype=_dtype), "dst": wp.array(dtype=_dtype)})


@wp.func
def _returns_before(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_beams: int, b: int) -> int:
    """The number of returns of the beams before beam ``b`` (0 ≤ b ≤ n_beams)."""
    if b == n_beams:
        return offsets[n_beams - 1] + counts[n_beams - 1]
    return offsets[b]


@wp.kernel
def count_returns(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_beams: int,
                  total: wp.array(dtype=wp.int32)):
    """total[0] ← the number of returns of the chunk's ``n_beams`` beams (one thread)."""
    total[0] = _returns_before(counts, offsets, n_beams, n_beams)


@wp.kernel
def add_segment_returns(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_beams: int,
                        segments: Segments, beams_per_pulse: int, per_line: wp.array(dtype=wp.int64)):
    """per_line[line] += the returns of each segment of the chunk (one thread per segment): the chunk's segment table
    (the tracer's, already on the device), whose segment i holds the beams pulse_start[i] · beams_per_pulse up to
    the next segment's (pulse_start's last entry: the chunk's pulse count)."""
    i = wp.tid()
    n = (_returns_before(counts, offsets, n_beams, wp.min(segments.pulse_start[i + 1] * beams_per_pulse, n_beams)) -
         _returns_before(counts, offsets, n_beams, segments.pulse_start[i] * beams_per_pulse))
    wp.atomic_add(per_line, segments.line[i], wp.int64(n))
