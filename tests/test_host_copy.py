"""Copies to the host: ``parallel_copy`` (slices over a thread pool) and ``copy_into`` (through a page-locked
buffer) give the source's exact values at every length, including lengths that are not a multiple of a slice or of
the staging buffer."""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from flightsim.core import warp_runtime
from flightsim.core.warp_runtime import copy_into, parallel_copy


@pytest.mark.parametrize("count", [0, 1, 5, 1000, 1001, 4097])
def test_parallel_copy_is_the_source(monkeypatch, count):
    monkeypatch.setattr(warp_runtime, "HOST_COPY_SLICE", 64)  # 16 float32 a slice: many slices, a partial last one
    monkeypatch.setattr(warp_runtime.os, "cpu_count", lambda: 4)
    src = np.random.default_rng(count).random(count).astype(np.float32)
    out = np.full(count, np.nan, dtype=np.float32)
    parallel_copy(out, src)
    np.testing.assert_array_equal(out, src)


def test_parallel_copy_writes_only_its_slice(monkeypatch):
    monkeypatch.setattr(warp_runtime, "HOST_COPY_SLICE", 64)
    monkeypatch.setattr(warp_runtime.os, "cpu_count", lambda: 4)
    whole = np.zeros(500, dtype=np.float64)
    src = np.arange(1.0, 301.0)
    parallel_copy(whole[100:400], src)
    np.testing.assert_array_equal(whole[100:400], src)
    assert not whole[:100].any() and not whole[400:].any()


def test_copy_into_through_a_small_staging_buffer(device, monkeypatch):
    monkeypatch.setattr(warp_runtime, "STAGING_BYTES", 4 * 1000)  # 1000 float32 a round trip
    monkeypatch.setattr(warp_runtime, "HOST_COPY_SLICE", 256)
    monkeypatch.setattr(warp_runtime, "_PINNED", {})
    values = np.random.default_rng(3).random((7, 613)).astype(np.float32)  # 4291: five rounds, the last partial
    out = np.empty_like(values)
    copy_into(out, wp.array(values, dtype=wp.float32, device=device))
    np.testing.assert_array_equal(out, values)


@pytest.mark.parametrize("dtype, scalar, shape", [(wp.vec3d, np.float64, (1001, 3)), (wp.int32, np.int32, (1001,)),
                                                   (wp.float32, np.float32, (13, 77))])
def test_host_array_is_a_copy_of_the_callers_own(device, monkeypatch, dtype, scalar, shape):
    """Scalars, vectors (a row per element) and 2-D arrays, through a staging buffer smaller than the array; the
    result stays when the device array is overwritten."""
    monkeypatch.setattr(warp_runtime, "STAGING_BYTES", 4000)
    monkeypatch.setattr(warp_runtime, "HOST_COPY_SLICE", 256)
    monkeypatch.setattr(warp_runtime, "_PINNED", {})
    values = (np.random.default_rng(5).random(shape) * 1000).astype(scalar)
    a = wp.array(values, dtype=dtype, device=device)
    host = warp_runtime.host_array(a)
    a.zero_()
    assert host.shape == values.shape and host.dtype == values.dtype
    np.testing.assert_array_equal(host, values)
