"""The statistics reduction (kernels/statistics.py reduce_records) against float64 NumPy sums: any number of
consecutive slots per thread and any copies of the sums give each plane's moments and the counts of the slots that
do not count."""
import numpy as np
import pytest
import warp as wp

from flightsim.scoring.reduction import reduce_models, replica_totals
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
    points[codes < 0] = np.nan  # a slot without a return has no point written (a GPU reads them four at a time)
    return codes, points, references


def _reduce(device, codes, points, references, slots_per_thread: int, replicas: int, offset: int = 0):
    """The reduction's totals of the records from slot ``offset`` on (arrays whose data do not start at a multiple of
    16 bytes for an odd offset)."""
    shape = (replicas, 2, len(references))
    sums = [wp.zeros(shape, dtype=wp.int64, device=device), wp.zeros(shape, dtype=wp.vec3d, device=device),
            wp.zeros(shape, dtype=statistics.vec6d, device=device), wp.zeros(3, dtype=wp.int32, device=device)]
    codes_d = wp.array(codes, dtype=wp.int32, device=device)[offset:]
    points_d = wp.array(points, dtype=wp.vec3f, device=device)[offset:]
    reduce_models(codes_d, [points_d], ("exact",), len(codes) - offset, slots_per_thread, wp.array(references, dtype=wp.vec3d, device=device), sums,
                  device)
    count, first, second = replica_totals(sums[:3])
    return count[0], first[0], second[0], sums[3].numpy()


@pytest.mark.parametrize("slots_per_thread,replicas,offset", [(256, 1, 0), (16, 64, 0), (64, 512, 0), (5, 7, 0),
                                                              (1, 3, 0), (4096, 2, 0), (64, 512, 1), (12, 8, 3)])
def test_reduction_is_the_float64_sum_of_each_planes_points(device, slots_per_thread, replicas, offset):
    rng = np.random.default_rng(3)
    n_slots, planes = 20011, 17
    codes, points, references = _records(rng, n_slots, planes)
    count, first, second, left = _reduce(device, codes, points, references, slots_per_thread, replicas, offset)
    codes, points = codes[offset:], points[offset:]
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
