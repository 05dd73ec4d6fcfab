"""The canopy points kernels on every device (kernels/canopy_returns.py: ``trace_canopy_beams`` traces each beam's
surface hit into a scratch row, ``trace_canopy_points`` walks the leaves and writes the slots) and the points
readout's counts summed on the device:

- over a leaf layer of zero density every beam returns once, from the surface, exactly where the plain points
  kernel (kernels/trace.py ``points_kernel``, no canopy) puts it: the same slots, ranges, faces, scan angles, edge
  distances, true points and both models' points, bit for bit; its echo is the surface's albedo times the cosine of
  incidence;
- through a real leaf layer, flown as three lines in chunks that straddle them, the returns per line and in all
  (summed on the device, read once at the end) are the host returns counted line by line, the same with the
  consumer on the device, and each chunk's ``count`` is its number of host returns;
- the register cap of a run (``run.max_registers``) reaches both canopy kernels.
"""
from __future__ import annotations

import numpy as np
import pytest

import flightsim
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import write_canopy_npz

ORIGIN = np.array([409000.0, 3393000.0, 450.0])


def _layer(tmp_path, lad: float) -> str:
    """Leaves of density ``lad`` from 10 to 18 m over the plane, 200 m square."""
    grid = np.zeros((20, 20, 20), np.float32)
    grid[:, :, 10:18] = lad
    canopy = VoxelCanopy(grid, np.array([-100.0, -100.0, 0.0]), np.array([10.0, 10.0, 1.0]))
    return str(write_canopy_npz(tmp_path / f"layer{lad}.npz", canopy, "EPSG:32648", ORIGIN))


def _tracer(device: str, canopy: str | None, **settings) -> Tracer:
    overrides = {"scene.name": "plane", "flight.altitude_m": 150.0, "flight.duration_s": 0.1, "run.device": device,
                 "output.models": ["exact", "nominal"], **settings}
    if canopy:
        overrides["scene.canopy"] = canopy
    cfg = flightsim.load_config(overrides=overrides)
    scene = build_scene(cfg)
    return Tracer(cfg, scene, flight_trajectories(cfg, scene), with_truth=True, edge_buffer_m=0.5)


def _host_run(tracer: Tracer):
    chunks = []
    counts = tracer.run(Points(), chunks.append)
    return chunks, counts


def _joined(chunks, field: str) -> np.ndarray:
    return np.concatenate([getattr(c, field) for c in chunks])


def test_zero_density_leaves_give_the_plain_kernels_surface_returns(device, tmp_path):
    leaves, leaves_counts = _host_run(_tracer(device, _layer(tmp_path, 0.0), **{"run.chunk_pulses": 150}))
    plain, plain_counts = _host_run(_tracer(device, None, **{"run.chunk_pulses": 150}))
    assert leaves_counts.returns == plain_counts.returns == leaves_counts.beams_returned > 1000
    assert leaves_counts.leaf_returns == 0 and leaves_counts.dark == 0
    for field in ("pulse", "beam", "range_m", "face", "scan_angle_deg", "edge_distance_m", "true_points"):
        a, b = _joined(leaves, field), _joined(plain, field)
        assert a.dtype == b.dtype and np.array_equal(a, b), field
    for model in ("exact", "nominal"):
        assert np.array_equal(np.concatenate([c.points[model] for c in leaves]),
                              np.concatenate([c.points[model] for c in plain])), model
    assert set(_joined(leaves, "return_number")) == {1} and set(_joined(leaves, "number_of_returns")) == {1}
    albedo = flightsim.load_config().discrete.reflectance
    np.testing.assert_allclose(_joined(leaves, "cos_incidence"), albedo * _joined(plain, "cos_incidence"),
                               rtol=1e-6)


def test_returns_per_line_summed_on_the_device_are_the_host_returns(device, tmp_path):
    settings = {"flight.lines": 3, "flight.duration_s": 0.06, "run.chunk_pulses": 110}  # 301 pulses a line
    tracer = _tracer(device, _layer(tmp_path, 0.25), **settings)
    chunks, counts = _host_run(tracer)
    by_line: dict[int, int] = {}
    for c in chunks:
        by_line[c.line_id] = by_line.get(c.line_id, 0) + len(c)
    assert len(by_line) == 3 and counts.leaf_returns > 0
    assert counts.per_line == by_line and counts.returns == sum(by_line.values())
    seen = []
    device_counts = tracer.run(Points(on_device=True), lambda returns: seen.append(returns.count))
    assert device_counts.per_line == by_line and device_counts.returns == counts.returns
    assert sum(seen) == counts.returns and len(seen) > 8
    silent = tracer.run(Points(on_device=True), lambda returns: None)  # nobody reads a chunk's count
    assert silent.per_line == by_line and (silent.leaf_returns, silent.dark) == (counts.leaf_returns, counts.dark)


@pytest.mark.parametrize("cap, blocks", [(64, 4), (72, 4), (100, 3), (128, 2), (255, 2)])  # 64, 64, 85, 128, 128 a thread
def test_the_register_cap_reaches_both_canopy_kernels(tmp_path, cap, blocks):
    """The trace kernel gets the cap as it is; the walk kernel as launch bounds: blocks of 256 threads, as many per
    multiprocessor (65536 registers) as keep each thread at or under the cap, with spilling to shared memory."""
    tracer = _tracer("cpu", _layer(tmp_path, 0.25), **{"run.max_registers": cap})
    kernels = {k.key.split("_locals__")[-1]: k for k in Points().kernels_needed(tracer)}
    trace, walk = kernels["trace_canopy_beams"], kernels["trace_canopy_points"]
    assert trace.options.get("cuda_max_registers") == cap
    assert walk.options.get("launch_bounds") == (256, blocks) and walk.options.get("enable_cuda_smem_spilling")
