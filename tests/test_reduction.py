"""The statistics reduction (kernels/statistics.py reduce_records) against float64 NumPy sums: every layout of the
reducing threads (consecutive slots, or 32 interleaved lanes as on a GPU), slots per thread and copies of the sums
gives the per-plane moments and the counts of the slots that do not count."""
import numpy as np
import pytest
import warp as wp

from flightsim.scoring.reduction import reduce_models, replica_totals
from kernels import statistics


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


@pytest.mark.parametrize("lanes,slots_per_thread,replicas", [(1, 256, 1), (1, 16, 64), (32, 16, 64), (32, 5, 7)])
def test_reduction_is_the_float64_sum_of_each_planes_points(device, lanes, slots_per_thread, replicas):
    rng = np.random.default_rng(3)
    n_slots, planes = 20011, 17
    codes, points, references = _records(rng, n_slots, planes)
    shape = (replicas, 2, planes)
    sums = [wp.zeros(shape, dtype=wp.int64, device=device), wp.zeros(shape, dtype=wp.vec3d, device=device),
            wp.zeros(shape, dtype=statistics.vec6d, device=device), wp.zeros(3, dtype=wp.int32, device=device)]
    model_points = [wp.array(points, dtype=wp.vec3f, device=device), wp.array(points[::-1].copy(), dtype=wp.vec3f,
                                                                              device=device)]
    reduce_models(wp.array(codes, dtype=wp.int32, device=device), model_points, ("exact", "nominal"), n_slots,
                  slots_per_thread, wp.array(references, dtype=wp.vec3d, device=device), sums, device, lanes=lanes)
    count, first, second = replica_totals(sums[:3])
    for k, p in enumerate((points, points[::-1])):
        scored = codes >= 0
        d = p[scored].astype(np.float64) - references[codes[scored]]
        plane = codes[scored]
        assert np.array_equal(count[k], np.bincount(plane, minlength=planes))
        expected_first = np.stack([np.bincount(plane, d[:, a], planes) for a in range(3)], axis=1)
        np.testing.assert_allclose(first[k], expected_first, rtol=1e-12, atol=1e-9)
        upper = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        expected_second = np.stack([np.bincount(plane, d[:, a] * d[:, b], planes) for a, b in upper], axis=1)
        np.testing.assert_allclose(second[k], expected_second, rtol=1e-12)
    left = [int((codes == c).sum()) for c in (statistics.CODE_TIR, statistics.CODE_MISS, statistics.CODE_EDGE)]
    assert sums[3].numpy().tolist() == left
