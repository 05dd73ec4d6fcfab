"""`flightsim bench` section forest: large-footprint waveforms from a point cloud against the same method in
vectorised NumPy (the stand-in for today's CPU tools), GEDI shots over a point cloud end to end
(:mod:`flightsim.studies.bench_shots`), the leaf voxel walk, the procedural forest scene's build (its
voxels computed, and from the scene cache), and discrete ALS through a voxel forest against the same flight over its
bare ground. Every ratio is measured in one run."""
from __future__ import annotations

import os
import tempfile
import time

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.cloud_waveforms import cloud_waveforms, prepare_cloud
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.instrument.cloud_waveform_model import CloudBeam, model_waveforms, synthetic_forest
from flightsim.scenes import forest_voxels
from flightsim.studies.bench_common import Sizes
from flightsim.studies.bench_shots import cloud_shots
from kernels import canopy as kc

GEDI_SAMPLES, GEDI_DT_S = 1000, 1.0e-9  # a GEDI-like window: 1000 samples of 1 ns (150 m)
NUMPY_FOOTPRINTS = 100  # footprints the float64 NumPy model makes per measurement


def forest(device: str, s: Sizes) -> dict:
    """The section's measurements."""
    cuda = resolve_device(device) != "cpu"
    points = (1e6 if s.quick else 1e7) if cuda else (2e5 if s.quick else 1e6)
    footprints = (2e4 if s.quick else 1e5) if cuda else (500 if s.quick else 2000)
    size_m = 300.0 if s.quick else 1000.0
    shots = ((1e6, 2000) if s.quick else (1e7, 20000)) if cuda else ((2e5, 200) if s.quick else (1e6, 2000))
    return {"cloud": cloud_rate(device, int(points), int(footprints)),
            "shots": cloud_shots(device, *map(int, shots)),
            "voxels": walk_rate(device, 10 ** 5 if s.quick or not cuda else 10 ** 7),
            "scene": scene_build(size_m, device),
            "als": als_ratio(device, 2e5 if s.quick else (5e7 if cuda else 2e6), size_m)}


def scene_build(size_m: float, device: str = "cpu") -> dict:
    """Seconds to build the forest scene of ``size_m`` square (LAI 3; on the host): with the scene cache off (the
    stand's voxels computed), then twice through an empty cache folder (computed and stored; mapped from the entry);
    on a GPU ``device`` also with the voxels integrated there (:func:`device_build`)."""
    cfg = forest_config("cpu", 3.0, 1.0, size_m, **{"run.scene_cache": False})
    started = time.perf_counter()
    scene = build_scene(cfg)
    record = {"forest_size_m": size_m, "voxels": list(scene.canopy.dims), "threads": forest_voxels.threads(),
              "computed_s": time.perf_counter() - started}
    if resolve_device(device) != "cpu":
        record["device"] = device_build(size_m, device, scene.canopy.lad)
    set_value(cfg, "run.scene_cache", True)
    saved = os.environ.get("FLIGHTSIM_CACHE")
    with tempfile.TemporaryDirectory() as folder:
        os.environ["FLIGHTSIM_CACHE"] = folder
        try:
            for name in ("stored_s", "cached_s"):
                started = time.perf_counter()
                build_scene(cfg)
                record[name] = time.perf_counter() - started
        finally:
            if saved is None:
                os.environ.pop("FLIGHTSIM_CACHE", None)
            else:
                os.environ["FLIGHTSIM_CACHE"] = saved
    return record


def device_build(size_m: float, device: str, host_lad: np.ndarray) -> dict:
    """Seconds to build the same forest scene for a run on the GPU ``device`` (scene cache off: its voxels
    integrated there, the kernel compiled beforehand over a small stand), and how its float32 densities differ from
    the host's ``host_lad``: voxels that differ, the largest difference [m²/m³] and the largest density."""
    build_scene(forest_config(device, 3.0, 1.0, 30.0, **{"run.scene_cache": False}))
    started = time.perf_counter()
    lad = build_scene(forest_config(device, 3.0, 1.0, size_m, **{"run.scene_cache": False})).canopy.lad
    wall = time.perf_counter() - started
    difference = np.abs(lad.astype(np.float64) - host_lad)
    return {"computed_s": wall, "voxels_differing": int(np.count_nonzero(difference)),
            "max_difference": float(difference.max()), "max_lad": float(host_lad.max())}


def cloud_rate(device: str, points: int, footprints: int) -> dict:
    """Footprints per second of the device kernel (end to end: the waveforms on the host) and of the NumPy model
    over the same synthetic forest, and their largest difference on the model's footprints."""
    cloud = synthetic_forest(points, seed=1)
    low, high = cloud.bounds()
    rng = np.random.default_rng(7)
    centres = rng.uniform(low[:2] + 20.0, high[:2] - 20.0, (footprints, 2))
    z_top, beam = float(high[2]) + 5.0, CloudBeam()
    started = time.perf_counter()
    prepared = prepare_cloud(cloud, device=device, cell_m=beam.footprint_sigma_m / 2.0)
    prepare_s = time.perf_counter() - started
    args = (cloud, centres, z_top, 0.0, GEDI_DT_S, GEDI_SAMPLES, beam)
    cloud_waveforms(*args[:1], centres[:64], *args[2:], device=device, prepared=prepared)  # compile, warm up
    wp.synchronize_device(device)
    started = time.perf_counter()
    device_out = cloud_waveforms(*args, device=device, prepared=prepared)
    device_s = time.perf_counter() - started
    few = slice(0, min(NUMPY_FOOTPRINTS, footprints))
    started = time.perf_counter()
    model = model_waveforms(cloud, centres[few], z_top, 0.0, GEDI_DT_S, GEDI_SAMPLES, beam)
    numpy_s = time.perf_counter() - started
    a, b = device_out["rx"][few].astype(np.float64), model["rx"]
    corr = min(np.corrcoef(x, y)[0, 1] for x, y in zip(a, b) if y.any())
    return {"points": len(cloud), "footprints": footprints, "samples": GEDI_SAMPLES, "prepare_s": prepare_s,
            "device_s": device_s, "footprints_per_s": footprints / device_s,
            "numpy_footprints": few.stop, "numpy_s": numpy_s, "numpy_footprints_per_s": few.stop / numpy_s,
            "speedup": (footprints / device_s) / (few.stop / numpy_s), "min_correlation": float(corr)}


def walk_rate(device: str, rays: int) -> dict:
    """Ray-voxel steps per second of the leaf voxel walk (kernels/canopy.py) across a 100 × 100 × 30 grid."""
    from flightsim.scenes.canopy import VoxelCanopy

    rng = np.random.default_rng(3)
    lad = rng.uniform(0.0, 1.0, (100, 100, 30)).astype(np.float32)
    canopy = VoxelCanopy(lad, np.zeros(3), np.ones(3)).to_device(resolve_device(device))
    zenith, azimuth = np.arccos(rng.uniform(0.5, 1.0, rays)), rng.uniform(0.0, 2 * np.pi, rays)
    directions = np.column_stack([np.sin(zenith) * np.cos(azimuth), np.sin(zenith) * np.sin(azimuth), -np.cos(zenith)])
    starts = np.column_stack([rng.uniform(0.0, 100.0, (rays, 2)), np.full(rays, 30.0)])
    d = resolve_device(device)
    arrays = [wp.array(starts, dtype=wp.vec3d, device=d), wp.array(directions, dtype=wp.vec3d, device=d)]
    steps, depth = wp.zeros(rays, dtype=wp.int32, device=d), wp.zeros(rays, dtype=wp.float64, device=d)
    wp.launch(kc.walk_steps, rays, inputs=[canopy, *arrays], outputs=[steps, depth], device=d)
    wp.synchronize_device(d)
    started = time.perf_counter()
    wp.launch(kc.walk_steps, rays, inputs=[canopy, *arrays], outputs=[steps, depth], device=d)
    wp.synchronize_device(d)
    wall = time.perf_counter() - started
    total = int(steps.numpy().astype(np.int64).sum())
    return {"rays": rays, "grid": [100, 100, 30], "steps": total, "wall_s": wall, "steps_per_s": total / wall}


def als_ratio(device: str, beams: float, size_m: float) -> dict:
    """Beams per second of the discrete detector's points readout (on the device, nothing to the host) over a
    voxel forest of ``size_m`` square (1 km: 1 km²) and over its bare ground (the same flight, leaf area 0)."""
    records = {"forest_size_m": size_m}
    for name, lai in (("forest", 3.0), ("bare", 0.0)):
        tracer = forest_tracer(device, lai, beams, size_m)
        tracer.run(Points(on_device=True), consume=lambda returns: None)  # compile and warm up
        wp.synchronize_device(tracer.device)
        counts = tracer.run(Points(on_device=True), consume=lambda returns: None)
        records[name] = {"beams": counts.beams_fired, "returns": counts.returns, "wall_s": counts.wall_s,
                         "beams_per_s": counts.beams_fired / counts.wall_s}
    records["ratio"] = records["forest"]["beams_per_s"] / records["bare"]["beams_per_s"]
    return records


def forest_tracer(device: str, lai: float, beams: float, size_m: float) -> Tracer:
    """The default airborne instrument at 500 m over a procedural forest of ``size_m`` square and leaf area index
    ``lai`` (0: bare ground, no canopy), lines flown back and forth over it for about ``beams`` beams."""
    cfg = forest_config(device, lai, beams, size_m)
    scene = build_scene(cfg)
    return Tracer(cfg, scene, flight_trajectories(cfg, scene))


def forest_config(device: str, lai: float, beams: float, size_m: float, **settings) -> RunConfig:
    """:func:`forest_tracer`'s run config, with ``settings`` (config keys to values) over it; validated."""
    cfg = RunConfig()
    duration = size_m / (200.0 / 3.6)
    lines = max(1, round(beams / (5000.0 * 9 * duration)))
    for key, value in {"scene.name": "forest", "scene.forest_size_m": size_m, "scene.forest_lai": lai,
                       "flight.duration_s": duration, "flight.lines": lines, "flight.line_spacing_m": 0.01,
                       "output.models": ["exact"], "run.device": device, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)
