"""The statistics reduction (kernels/statistics.py) against float64 NumPy sums: the plain kernel (consecutive slots
per thread, any number of them, any copies of the sums) and the staged one a GPU runs (each block's records first
copied into shared memory), which must add the same records in the same runs."""
import numpy as np
import pytest
import warp as wp

from flightsim.scoring.reduction import replica_totals
from kernels import statistics

UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def _records(rng, n_slots: int, planes: int):
    """Codes in runs of one plane (as beams of neighbouring pulses hit), with TIR, missed and edge-excluded slots
    scattered between them; float32 points near each plane's reference."""
    run_planes = rng.integers(0, planes, n_slots // 7 + 1)
    codes = np.repeat(run_planes, rng.integers(1, 14, len(run_planes)))[:n_slots]
    codes = np.concatenate([codes, np.zeros(n_slots - len(codes), dtype=codes.dtype)]).astype(np.int32)
    left = rng.random(n_slots) < 0.1
    codes[left] = rng.choice([statistics.CODE_TIR, statistics.CODE_MISS, statistics.CODE_EDGE], left.sum())
    references = rng.uniform(-500.0, 500.0, (planes, 3))
    points = (references[np.maximum(codes, 0)] + rng.normal(0.0, 20.0, (n_slots, 3))).astype(np.float32)
    return codes, points, references


def _reduce(device, codes, points, references, staged: bool, slots_per_thread: int, replicas: int):
    planes = len(references)
    shape = (replicas, 2, planes)
    sums = [wp.zeros(shape, dtype=wp.int64, device=device), wp.zeros(shape, dtype=wp.vec3d, device=device),
            wp.zeros(shape, dtype=statistics.vec6d, device=device), wp.zeros(3, dtype=wp.int32, device=device)]
    args = dict(codes=wp.array(codes, dtype=wp.int32, device=device),
                points=wp.array(points, dtype=wp.vec3f, device=device),
                references=wp.array(references, dtype=wp.vec3d, device=device))
    n = len(codes)
    if staged:
        stage = statistics.REDUCE_BLOCK * statistics.REDUCE_SLOTS
        wp.launch_tiled(statistics.reduce_records_staged, dim=[(n + stage - 1) // stage],
                        inputs=[args["codes"], args["points"], 0, 1, n, args["references"]], outputs=sums,
                        block_dim=statistics.REDUCE_BLOCK, device=device)
    else:
        wp.launch(statistics.reduce_records, (n + slots_per_thread - 1) // slots_per_thread,
                  inputs=[args["codes"], args["points"], 0, 1, n, slots_per_thread, args["references"]],
                  outputs=sums, device=device)
    count, first, second = replica_totals(sums[:3])
    return count[0], first[0], second[0], sums[3].numpy()


@pytest.mark.parametrize("staged,slots_per_thread,replicas", [(False, 256, 1), (False, 16, 64), (False, 5, 7),
                                                              (True, statistics.REDUCE_SLOTS, 64)])
def test_reduction_is_the_float64_sum_of_each_planes_points(device, staged, slots_per_thread, replicas):
    rng = np.random.default_rng(3)
    n_slots, planes = 20011, 17  # not a whole number of stages: the last block's stage runs past the records
    codes, points, references = _records(rng, n_slots, planes)
    count, first, second, left = _reduce(device, codes, points, references, staged, slots_per_thread, replicas)
    scored = codes >= 0
    d = points[scored].astype(np.float64) - references[codes[scored]]
    plane = codes[scored]
    assert np.array_equal(count, np.bincount(plane, minlength=planes))
    np.testing.assert_allclose(first, np.stack([np.bincount(plane, d[:, a], planes) for a in range(3)], axis=1),
                               rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(second, np.stack([np.bincount(plane, d[:, a] * d[:, b], planes) for a, b in UPPER],
                                                axis=1), rtol=1e-12)
    expected = [int((codes == c).sum()) for c in (statistics.CODE_TIR, statistics.CODE_MISS, statistics.CODE_EDGE)]
    assert left.tolist() == expected


def test_staged_reduction_adds_what_the_plain_one_adds(device):
    """One copy of the sums and the same slots per thread: the same runs, flushed in the same order on the CPU."""
    rng = np.random.default_rng(11)
    codes, points, references = _records(rng, 9000, 5)
    plain = _reduce(device, codes, points, references, False, statistics.REDUCE_SLOTS, 1)
    staged = _reduce(device, codes, points, references, True, statistics.REDUCE_SLOTS, 1)
    for a, b in zip(plain, staged):
        if device == "cpu":
            assert np.array_equal(a, b)  # threads run one after another: the same additions in the same order
        else:
            np.testing.assert_allclose(a, b, rtol=1e-13)
