"""`flightsim profile`: where each instrument's time goes on the device, before anything is optimised.

For every workload of the bench's hardware targets (the Risley statistics run at 3×3 and 8×8, the galvo imager over
the plane and the lunar scene, the waveform altimeter over flat and sloped ground, a SPAD MODE-A frame, discrete
ALS through a voxel forest and point-cloud waveforms) it runs the workload once to compile and warm up, once timed,
and once under Warp's CUDA activity timing, and writes per kernel: launches, GPU time and its share of the wall
time, registers and spilled bytes per thread, theoretical occupancy (:mod:`flightsim.studies.profile_cuda`); and
per workload the memory copies, Warp's sort and scan primitives (:data:`NATIVE`: CUB kernels launched from Warp's
native code, which its activity timing does not see; timed here by CUDA events around each call), the time no
kernel ran (host work and launch gaps), and the bare ray cast of the same rays. Results go to DIR/profile.json and
DIR/profile.md.
"""
from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.config import set_value, validate
from flightsim.engine.readouts.points import Points
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.readouts.waveforms import Waveforms
from flightsim.studies.bench_common import bare_raycast, git_commit, gpu_name, kernel_name, simulator, workload
from flightsim.studies.profile_cuda import kernel_attributes

WORKLOADS = ("risley3", "risley8", "galvo_plane", "galvo_lunar", "waveform_flat", "waveform_slope", "spad",
             "forest_als", "cloud_waveforms")


@dataclass
class Workload:
    """A prepared run: ``run()`` does the work once and returns how many ``unit`` it made; ``bare()`` is the bare
    ray cast of the same rays in rays/s (None where there is no single ray cast to compare with)."""

    run: Callable[[], int]
    unit: str
    bare: Callable[[], float] | None


def _bare(sim, units: int, subrays: bool = False) -> Callable[[], float]:
    def rate() -> float:
        sample = min(units, 1 << 24)
        wall, hits = bare_raycast(sim, sample, max(1, round(units / sample)), subrays=subrays)
        return sample * max(1, round(units / sample)) / wall
    return rate


def _risley(device: str, array: int, returns: float) -> Workload:
    sim = simulator(workload(device, array, returns))
    run = lambda: run_statistics(sim)[1].beams_fired  # noqa: E731
    return Workload(run, "beams", _bare(sim, run()))


def _galvo(device: str, scene: str, returns: float) -> Workload:
    from flightsim.engine.config_io import preset_config

    cfg = preset_config("change3")
    frames = max(1, round(returns / (17 * 256 * 16)))
    for key, value in {"run.device": device, "flight.duration_s": frames * cfg.galvo.frame_s,
                       "scene.name": scene}.items():
        set_value(cfg, key, value)
    sim = simulator(validate(cfg))
    run = lambda: run_statistics(sim)[1].beams_fired  # noqa: E731
    return Workload(run, "beams", _bare(sim, run()))


def _waveform(device: str, scene: str, shots: int) -> Workload:
    from flightsim.studies.waveform import waveform_config

    cfg = waveform_config(scene, device, **{"fixed.prf_hz": 1000.0, "flight.duration_s": (shots - 0.5) / 1000.0})
    sim = simulator(cfg)
    run = lambda: sim.run(Waveforms(on_device=True), lambda found: None).returns  # noqa: E731
    return Workload(run, "sub-ray returns", _bare(sim, run(), subrays=True))


def _spad(device: str, pulses: int) -> Workload:
    from flightsim.studies.spad import PAPER, frame_config, frame_simulator, photon_frame, simulate_frame

    _, sim = frame_simulator(frame_config(100.0, "A", device, pulses))
    frame = photon_frame(sim, PAPER["mode_a"]["grid"])
    run = lambda: simulate_frame(sim, frame)[0].beams_fired  # noqa: E731
    return Workload(run, "beams", _bare(sim, run()))


def _forest_als(device: str, beams: float, size_m: float) -> Workload:
    from flightsim.studies.bench_forest import forest_tracer

    tracer = forest_tracer(device, 3.0, beams, size_m)
    run = lambda: tracer.run(Points(on_device=True), consume=lambda returns: None).beams_fired  # noqa: E731
    return Workload(run, "beams", _bare(tracer, run()))


def _cloud(device: str, points: int, footprints: int) -> Workload:
    from flightsim.engine.cloud_waveforms import cloud_waveforms, prepare_cloud
    from flightsim.instrument.cloud_waveform_model import CloudBeam, synthetic_forest
    from flightsim.studies.bench_forest import GEDI_DT_S, GEDI_SAMPLES

    cloud = synthetic_forest(points, seed=1)
    low, high = cloud.bounds()
    centres = np.random.default_rng(7).uniform(low[:2] + 20.0, high[:2] - 20.0, (footprints, 2))
    beam = CloudBeam()
    prepared = prepare_cloud(cloud, device=device, cell_m=beam.footprint_sigma_m / 2.0)

    def run() -> int:
        cloud_waveforms(cloud, centres, float(high[2]) + 5.0, 0.0, GEDI_DT_S, GEDI_SAMPLES, beam, device=device,
                        prepared=prepared)
        return footprints
    return Workload(run, "footprints", None)


def build(name: str, device: str, quick: bool) -> Workload:
    """The workload ``name`` at its CUDA size (a small one on the CPU or with ``quick``)."""
    small = quick or resolve_device(device) == "cpu"
    return {
        "risley3": lambda: _risley(device, 3, 2e6 if small else 2.5e8),
        "risley8": lambda: _risley(device, 8, 2e6 if small else 2.5e8),
        "galvo_plane": lambda: _galvo(device, "plane", 1e5 if small else 1e8),
        "galvo_lunar": lambda: _galvo(device, "lunar", 1e5 if small else 1e8),
        "waveform_flat": lambda: _waveform(device, "flat", 10 if small else 20000),
        "waveform_slope": lambda: _waveform(device, "slope", 2 if small else 500),
        "spad": lambda: _spad(device, 430 if small else 43000),
        "forest_als": lambda: _forest_als(device, 2e5 if small else 5e7, 300.0 if small else 1000.0),
        "cloud_waveforms": lambda: _cloud(device, 200000 if small else 10 ** 7, 200 if small else 10 ** 5),
    }[name]()


NATIVE = ("radix_sort_pairs", "array_scan", "runlength_encode")  # wp.utils primitives whose CUB kernels Warp's
# activity timing does not record


@contextlib.contextmanager
def native_timing(device: str):
    """Within the block, each call of a :data:`NATIVE` primitive is bracketed by two timing events on ``device``'s
    current stream; yields the list of (primitive, start event, end event), read once the device is synchronised.
    The primitives are restored on leaving."""
    spans: list[tuple[str, wp.Event, wp.Event]] = []
    saved = {name: getattr(wp.utils, name) for name in NATIVE}

    def timed(name: str, primitive: Callable) -> Callable:
        def call(*args, **kwargs):
            start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
            wp.record_event(start)
            out = primitive(*args, **kwargs)
            wp.record_event(end)
            spans.append((name, start, end))
            return out
        return call

    for name, primitive in saved.items():
        setattr(wp.utils, name, timed(name, primitive))
    try:
        yield spans
    finally:
        for name, primitive in saved.items():
            setattr(wp.utils, name, primitive)


def _activities(run: Callable[[], int], cuda: bool) -> tuple[float, dict[str, dict], dict[str, float]]:
    """(wall [s] of one timed run, per kernel {launches, gpu_s}, seconds per other activity kind: Warp's copies and
    memsets, and the :data:`NATIVE` primitives as "<name> (CUB)")."""
    if not cuda:
        started = time.perf_counter()
        run()
        return time.perf_counter() - started, {}, {}
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    with native_timing(wp.get_device()) as spans:
        started = time.perf_counter()
        run()
        wp.synchronize()
        wall = time.perf_counter() - started
    kernels: dict[str, dict] = {}
    other: dict[str, float] = {}
    for name, start, end in spans:
        other[f"{name} (CUB)"] = other.get(f"{name} (CUB)", 0.0) + wp.get_event_elapsed_time(start, end) * 1e-3
    for result in wp.timing_end():
        if result.filter == wp.TIMING_KERNEL:
            row = kernels.setdefault(kernel_name(result.name), {"launches": 0, "gpu_s": 0.0})
            row["launches"] += 1
            row["gpu_s"] += result.elapsed * 1e-3
        else:
            kind = result.name.split()[0].lower()
            other[kind] = other.get(kind, 0.0) + result.elapsed * 1e-3
    return wall, kernels, other


def profile_workload(name: str, device: str, quick: bool) -> dict:
    """One workload's record (see the module docstring)."""
    w = build(name, device, quick)
    dev = resolve_device(device)
    w.run()  # compile and warm up (the builders ran it once already: a second time settles allocations)
    wp.synchronize_device(dev)
    started = time.perf_counter()
    units = w.run()
    wp.synchronize_device(dev)
    wall = time.perf_counter() - started
    profiled_wall, kernels, other = _activities(w.run, dev != "cpu")
    attributes = kernel_attributes(dev)
    for kernel, row in kernels.items():
        row.update(share=row["gpu_s"] / profiled_wall, **attributes.get(kernel, {}))
    bare = w.bare() if w.bare else None
    busy = sum(row["gpu_s"] for row in kernels.values()) + sum(other.values())
    return {"workload": name, "unit": w.unit, "units": units, "wall_s": wall, "rate": units / wall,
            "bare_rays_per_s": bare, "ratio_to_bare": units / wall / bare if bare else None,
            "profiled_wall_s": profiled_wall, "kernels": dict(sorted(kernels.items(), key=lambda kv: -kv[1]["gpu_s"])),
            "other_activity_s": other, "idle_s": max(0.0, profiled_wall - busy)}


def run_profile(device: str, quick: bool, out: Path, workloads=WORKLOADS, ncu: bool = False) -> dict:
    """Profile ``workloads`` and write DIR/profile.json and DIR/profile.md; with ``ncu`` (CUDA, Nsight Compute on
    the machine) each workload's kernels are also measured by Nsight Compute (:mod:`profile_ncu`)."""
    from flightsim.studies import profile_ncu
    from flightsim.studies.profile_report import write_markdown

    dev = resolve_device(device)
    result = {"device": dev, "gpu_name": gpu_name(dev), "git_commit": git_commit(), "quick": quick,
              "date": time.strftime("%Y-%m-%d"), "workloads": _kept(out / "profile.json", dev, quick, workloads)}
    out.mkdir(parents=True, exist_ok=True)
    for name in workloads:  # written after each workload, so an interrupted profile keeps what it measured
        record = profile_workload(name, device, quick)
        if ncu and dev != "cpu" and profile_ncu.available():
            top = list(record["kernels"])[:profile_ncu.TOP_KERNELS]
            record["ncu"] = profile_ncu.workload_counters(name, dev, top, quick) if top else {}
        result["workloads"] = sorted(result["workloads"] + [record], key=lambda r: WORKLOADS.index(r["workload"]))
        (out / "profile.json").write_text(json.dumps(result, indent=1))
        (out / "profile.md").write_text(write_markdown(result))
    return result


def _kept(path: Path, device: str, quick: bool, redone) -> list[dict]:
    """The records of an earlier profile in ``path`` on the same device and sizes, but those of ``redone``."""
    if not path.exists():
        return []
    earlier = json.loads(path.read_text())
    if earlier.get("device") != device or earlier.get("quick") != quick:
        return []
    return [r for r in earlier["workloads"] if r["workload"] not in redone]
