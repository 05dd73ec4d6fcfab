"""The statistics reduction's host side: how many copies of the per-group sums the reducing threads spread their
atomics over, and the totals of those copies (added on the device)."""
from __future__ import annotations

import numpy as np
import warp as wp

from flightsim.core.constants import MODELS
from kernels import statistics

SLOTS_PER_THREAD = {"cpu": 256, "cuda": 64}  # consecutive slots per reducing thread
SUM_REPLICAS = 512  # copies of the per-group sums on a GPU, so busy groups' atomics spread
SUM_REPLICA_BYTES = 1 << 26  # ... within this much device memory
REPLICA_BLOCK = 32  # replicas one thread adds (replica_totals)


def sum_replicas(device_kind: str, groups: int, asked: int = 0) -> int:
    """Copies of the sums of ``groups`` groups: one on the CPU (one thread per launch), ``asked`` (run.sum_replicas)
    or else SUM_REPLICAS on a GPU, within SUM_REPLICA_BYTES."""
    if device_kind == "cpu":
        return 1
    per_copy = 2 * groups * (8 + 24 + 48)
    return max(1, min(asked or SUM_REPLICAS, SUM_REPLICA_BYTES // per_copy))


def reduce_models(codes: wp.array, points: list[wp.array], models, n_slots: int, slots_per_thread: int,
                  references: wp.array, sums: list[wp.array], device: str) -> None:
    """Add a chunk's records to the per-group ``sums`` [counts, Σd, Σddᵀ, counters]: one launch of
    :func:`kernels.statistics.reduce_records` per model in ``models`` (``points`` indexed as MODELS: exact,
    nominal), the first also counting the TIR, missed and edge-excluded slots."""
    present = [k for k, model in enumerate(MODELS) if model in models]
    for k in present:
        wp.launch(statistics.reduce_records, (n_slots + slots_per_thread - 1) // slots_per_thread,
                  inputs=[codes, points[k], k, int(k == present[0]), n_slots, slots_per_thread, references],
                  outputs=sums, device=device)


def replica_totals(sums: list[wp.array], block: int = REPLICA_BLOCK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reduction's (count, Σd, Σ upper triangle of ddᵀ) per model and group, its replicas added on the device:
    (2, G), (2, G, 3), (2, G, 6). Replicas are added in order in blocks of ``block``, then the blocks in order
    (a single replica, as on the CPU: as it is)."""
    while True:
        blocks = -(-sums[0].shape[0] // block)
        shape, d = (blocks, *sums[0].shape[1:]), sums[0].device
        added = [wp.empty(shape, dtype=wp.int64, device=d), wp.empty(shape, dtype=wp.vec3d, device=d),
                 wp.empty(shape, dtype=statistics.vec6d, device=d)]
        wp.launch(statistics.add_replicas, shape, inputs=[*sums, block], outputs=added, device=d)
        if blocks == 1:
            return tuple(a.numpy()[0] for a in added)
        sums, block = added, blocks


def symmetric(upper: np.ndarray) -> np.ndarray:
    """(P, 6) upper triangles xx, xy, xz, yy, yz, zz → (P, 3, 3) symmetric matrices."""
    rows, cols = np.triu_indices(3)
    full = np.zeros((len(upper), 3, 3))
    full[:, rows, cols] = upper
    full[:, cols, rows] = upper
    return full
