"""The memory traffic of one SPAD frame on the device, stage by stage, against the GPU's own bandwidth.

A frame of S beam slots (pulses × 1024 pixels), P photons and C = grid² angle cells goes through (CUDA, one
chunk; launches in brackets; no host sync before the gridding):

| stage | launches | device memory read + written (logical bytes; caches and 32-byte sectors left out) |
| --- | --- | --- |
| pulse poses, pulse optics | 2 | per pulse ~1 kB of its table: negligible |
| points kernel, ranges only (kernels/trace.py) | 1 | writes status, range, face, scan angle, cos θ: 20 B/slot (+ the BVH's reads) |
| photon sampling and dead time (kernels/photon.py) | 1 | reads 16 B/slot, writes the count 4 B/slot and 9 B/photon |
| scan of the counts | ~3 | reads 4, writes 4 B/slot (twice over, up and down) |
| placing into the frame (kernels/photon_frame.py) | 2 | reads 8 B/slot and 9 B/photon, writes 32 B/photon |
| gridding: extent (1 sync), keys, radix sort, cell bounds and the positions in sorted order, one thread per cell (fullest pair of bins, background test, two window means), compaction (2 syncs) | ~12 | per photon 32 (extent) + 44 (keys) + 24 per 8-bit sort pass + 8 (bounds) + 52 (the sorted positions: the permutation, the position, its copy) + 8 (the cell's keys) + 24 (the window's positions, about one photon in two read twice); per cell ~100 B |

The separate gather, placing and appending passes it replaced moved about 150 B/photon and synced the host
twice per chunk. :func:`frame_traffic` adds these up for a frame's counts; :func:`copy_bandwidth` measures
what the device moves in a large device-to-device copy (read + write), the frame's traffic over it the wall a
frame would take were it only moving memory.
"""
from __future__ import annotations

import math
import time

import warp as wp

SORT_PASS_BITS = 8  # bits of the key sorted per pass of the device radix sort


def key_bits(cells: int, gate_m: float, bin_m: float) -> int:
    """Bits of the gridding's sort keys: cells × (height bins of the gate + 2)."""
    return (cells * (int(math.floor(gate_m / bin_m)) + 2)).bit_length()


def frame_traffic(slots: int, photons: int, cells: int, bits: int) -> dict[str, float]:
    """Logical bytes read and written per stage of one frame (see the module's table)."""
    passes = math.ceil(bits / SORT_PASS_BITS)
    return {"trace": 20.0 * slots, "photons": 20.0 * slots + 9.0 * photons, "scan": 16.0 * slots,
            "place": 8.0 * slots + 41.0 * photons,
            "grid": (32.0 + 44.0 + 24.0 * passes + 8.0 + 52.0 + 8.0 + 24.0) * photons + 100.0 * cells}


def copy_bandwidth(device: str, size: int = 1 << 30, repeats: int = 3) -> float | None:
    """Bytes per second a device-to-device copy of ``size`` bytes moves (read + write), best of ``repeats``;
    None on the CPU."""
    if wp.get_device(device).is_cpu:
        return None
    a = wp.zeros(size // 8, dtype=wp.float64, device=device)
    b = wp.empty_like(a)
    wp.copy(b, a)
    best = math.inf
    for _ in range(repeats):
        wp.synchronize_device(device)
        started = time.perf_counter()
        wp.copy(b, a)
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - started)
    return 2.0 * size / best


def traffic_record(slots: int, photons: int, cells: int, bits: int, wall_s: float, device: str) -> dict:
    """The frame's traffic per stage [bytes], its total, the copy bandwidth [B/s] and the wall a frame would take
    moving only that memory at it [s]."""
    stages = frame_traffic(slots, photons, cells, bits)
    total = sum(stages.values())
    bandwidth = copy_bandwidth(device)
    floor = total / bandwidth if bandwidth else None
    return {"stages_bytes": stages, "total_bytes": total, "key_bits": bits, "copy_bandwidth_Bps": bandwidth,
            "memory_floor_s": floor, "floor_over_wall": floor / wall_s if floor else None}
