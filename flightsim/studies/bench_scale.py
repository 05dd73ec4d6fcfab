"""`flightsim bench` sections of production scale: the LAS output path, terrain meshes of 1e4–5e7 triangles (readiness,
statistics and LAS throughput, disk rate), the statistics reduction's knobs and a survey to LAZ through the CLI."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.config import RunConfig, copy_config, set_value, validate
from flightsim.engine.meshes import SceneMeshes
from flightsim.engine.readouts.points import Points
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.core.atomic import start_writeback
from flightsim.studies.bench_common import (DISK_PROBE_BYTES, REDUCE_KNOBS, REDUCE_TRIANGLES, SCALE_TRIANGLES,
                                            SURVEY_CELL_M, SURVEY_KM, bare_raycast, kernel_times, simulator, Sizes,
                                            run_measured, timed_statistics, workload)


def las_output(device: str, s: Sizes) -> list[dict]:
    """Points/s and peak memory of LAS runs of two lengths (memory must not grow with length), and the
    CLI's fixed start-up (interpreter, Warp, scene, kernels: a run of 0.01 s) that each of them pays, measured after
    a first such run has filled the kernel cache (as the runs it is taken from find it)."""
    _las_run(device, 5000.0 * 64 * 0.01)
    startup = _las_run(device, 5000.0 * 64 * 0.01)["wall_s"]
    records = [_las_run(device, s.las_returns / scale) for scale in (10, 1)]
    for r in records:
        r["startup_s"] = startup
        after = r["wall_s"] - startup  # None where the run is too short to tell from its start-up
        r["points_per_s_after_startup"] = r["points_written"] / after if after > 0.1 * r["wall_s"] else None
    return records


def _las_run(device: str, returns: float) -> dict:
    array = 8
    duration = returns / (5000.0 * array * array)
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "flightsim", "simulate", "--scene", "plane", "--array", str(array),
                   "--duration", f"{duration:.3f}", "--device", device, "--out", str(Path(tmp) / "run")]
        wall, code, peak_mib, _ = run_measured(command)
        if code != 0:
            raise RuntimeError(f"LAS benchmark run failed: {' '.join(command)}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    points = sum(summary["points"].values())
    return {"device": resolve_device(device), "points_written": points, "wall_s": wall,
            "points_per_s": points / wall, "peak_rss_mib": peak_mib}


def scale(device: str, s: Sizes) -> dict:
    """Terrain of 1e4 to 5e7 triangles (``flightsim.scenes.testdem``, 3 km square, read from a GeoTIFF): the
    time to ready a run (scene read without the cache, flight plan, BVH) and again from the scene cache,
    statistics-mode and LAS-mode throughput of the 8×8 workload at 500 m, the bare ray cast of the same rays,
    device memory; and the output disk's sequential write rate, measured in the same run."""
    kind = "cpu" if resolve_device(device) == "cpu" else "cuda"
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        disk = disk_write_rate(Path(tmp) / "probe", DISK_PROBE_BYTES[kind])
        scenes = [_scale_record(device, int(n), s, Path(tmp)) for n in SCALE_TRIANGLES[kind]]
    return {"disk_write_bytes_per_s": disk, "scenes": scenes}


def reduce_knobs(device: str, s: Sizes) -> list[dict]:
    """GPU statistics mode ÷ bare ray cast of the same rays for each (sum replicas, slots per reducing thread)
    of REDUCE_KNOBS, on the calibration field (3×3, 8×8: planes change along a thread's slots) and on terrain
    (REDUCE_TRIANGLES: every return adds to one plane). Each case's scene and BVH are built once; the
    settings take turns, best of three each.

    CUDA only: the CPU reduces with one copy of the sums and long runs of slots per thread.
    """
    if resolve_device(device) == "cpu":
        return []
    rows = []
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        cases = [(f"calibration {a}×{a}", workload(device, a, s.scale_returns)) for a in s.arrays]
        for n in REDUCE_TRIANGLES:
            dem = _terrain_file(int(n), 3000.0, Path(tmp) / f"dem-{n:.0e}")
            cases.append((f"terrain {n:.0e}", _scale_workload(device, s.scale_returns, **{
                "scene.name": str(dem), "run.scene_cache": False})))
        for case, cfg in cases:
            rows.append(_reduce_row(case, cfg, device))
    return rows


def _reduce_row(case: str, cfg: RunConfig, device: str) -> dict:
    """One case of :func:`reduce_knobs`: each setting's ratio, the settings sharing one scene and BVH."""
    meshes = SceneMeshes(build_scene(cfg), resolve_device(device), cfg.run.bvh)
    sims = {}
    for replicas, spt in REDUCE_KNOBS:
        knob_cfg = copy_config(cfg)
        set_value(knob_cfg, "run.sum_replicas", replicas)
        set_value(knob_cfg, "run.slots_per_thread", spt)
        sims[replicas, spt] = simulator(knob_cfg, meshes)
    walls = {knob: timed_statistics(sim, repeats=1)[0] for knob, sim in sims.items()}
    for _ in range(2):
        for knob, sim in sims.items():
            wp.synchronize_device(sim.device)
            _, counts = run_statistics(sim)
            walls[knob] = min(walls[knob], counts.wall_s)
    sample = min(counts.beams_fired, 1 << 24)
    bare_wall, hits = bare_raycast(sim, sample, max(1, round(counts.beams_fired / sample)))
    bare = hits / bare_wall
    return {"case": case, "triangles": len(meshes.scene.triangles), "planes": len(meshes.scene.planes),
            "returns": counts.returns, "raycast_returns_per_s": bare,
            "ratios": [{"sum_replicas": r, "slots_per_thread": spt, "replicas_used": sims[r, spt].sum_replicas(),
                        "ratio": counts.returns / walls[r, spt] / bare} for r, spt in REDUCE_KNOBS]}


def disk_write_rate(path: Path, size: int, block: int = 16 << 20) -> float:
    """Sequential write rate of the disk holding ``path`` [bytes/s]: ``size`` bytes in ``block`` writes, each handed
    to the disk's write-back as it is written and the whole fsync'ed, as the tile writers write (a probe that left
    the write-back to its fsync would add the time to fill the page cache to the disk's and understate it)."""
    data = os.urandom(block)
    blocks = max(1, size // block)
    started = time.perf_counter()
    with open(path, "wb") as fh:
        for k in range(blocks):
            fh.write(data)
            fh.flush()
            start_writeback(fh.fileno(), k * block, block)
        os.fsync(fh.fileno())
    wall = time.perf_counter() - started
    path.unlink()
    return blocks * block / wall


def idle_disk_rate(path: Path, size: int) -> float:
    """:func:`disk_write_rate` once what earlier steps wrote (the scene's files, the warm-up's tiles) has reached
    the disk, so that the probe, and then the run measured against it, start on an idle disk."""
    os.sync()
    return disk_write_rate(path, size)


def _terrain_file(triangles: int, size_m: float, folder: Path) -> Path:
    """The testdem GeoTIFF of about ``triangles`` triangles (two per cell) over a ``size_m`` square."""
    from flightsim.scenes import testdem

    cells = max(1, round(float(np.sqrt(triangles / 2.0))))
    return testdem.write(folder, size_m=size_m, cell_m=size_m / cells)["dem"]


def _ready(cfg: RunConfig, device: str) -> tuple[dict, object, list, SceneMeshes]:
    """Seconds to read ``cfg``'s scene, plan its flight and build its BVH, with the scene and its pieces."""
    times = {}
    started = time.perf_counter()
    scene = build_scene(cfg)
    times["load_s"] = time.perf_counter() - started
    started = time.perf_counter()
    trajectories = flight_trajectories(cfg, scene)
    times["plan_s"] = time.perf_counter() - started
    started = time.perf_counter()
    meshes = SceneMeshes(scene, resolve_device(device), cfg.run.bvh)
    wp.synchronize_device(resolve_device(device))
    times["bvh_build_s"] = time.perf_counter() - started
    times["ready_s"] = sum(times.values())
    started = time.perf_counter()
    flight_trajectories(cfg, scene)  # again, the scene's height grid built: the per-line work alone
    times["plan_ms_per_line"] = 1000.0 * (time.perf_counter() - started) / len(trajectories)
    return times, scene, trajectories, meshes


def _ready_from_cache(cfg: RunConfig, device: str, folder: Path) -> tuple[float, dict]:
    """(seconds to read the scene and store it in an empty scene cache in ``folder``, :func:`_ready`'s times
    of the next run, which reads it from there)."""
    cached = copy_config(cfg)
    set_value(cached, "run.scene_cache", True)
    before = os.environ.get("FLIGHTSIM_CACHE")
    os.environ["FLIGHTSIM_CACHE"] = str(folder)
    try:
        started = time.perf_counter()
        build_scene(cached)  # a miss: read and stored
        write_s = time.perf_counter() - started
        return write_s, _ready(cached, device)[0]
    finally:
        os.environ.pop("FLIGHTSIM_CACHE") if before is None else os.environ.update(FLIGHTSIM_CACHE=before)
        shutil.rmtree(folder, ignore_errors=True)


def _scale_record(device: str, triangles: int, s: Sizes, tmp: Path) -> dict:
    dem = _terrain_file(triangles, 3000.0, tmp / f"dem-{triangles}")
    cfg = _scale_workload(device, s.scale_returns, **{"scene.name": str(dem), "run.scene_cache": False})
    cold, scene, trajectories, meshes = _ready(cfg, device)
    cache_write_s, warm = _ready_from_cache(cfg, device, tmp / "scene-cache")
    sim = Tracer(cfg, scene, trajectories, meshes=meshes)
    wall, counts = timed_statistics(sim, repeats=1)
    sample = min(counts.beams_fired, 1 << (24 if sim.device_kind == "cuda" else 20))
    bare_wall, hits = bare_raycast(sim, sample, max(1, round(counts.beams_fired / sample)))
    kernels = kernel_times(lambda: run_statistics(sim)) if sim.device_kind == "cuda" else None
    las_cfg = _scale_workload(device, s.scale_las_returns)
    las_sim = Tracer(las_cfg, scene, trajectories[:las_cfg.flight.lines], meshes=meshes)
    _las_run_into(las_sim, las_cfg, tmp / "warm-up")  # compiles the points path's kernels
    shutil.rmtree(tmp / "warm-up")
    disk = idle_disk_rate(tmp / "probe", DISK_PROBE_BYTES[sim.device_kind])
    las_wall, las_counts, written = _las_run_into(las_sim, las_cfg, tmp / "las")
    shutil.rmtree(tmp / "las")
    points = las_counts.returns * len(las_sim.models)
    shutil.rmtree(dem.parent)
    return {"triangles": len(scene.triangles), **cold,
            "cache_write_s": cache_write_s, "cached_load_s": warm["load_s"], "ready_cached_s": warm["ready_s"],
            "stats_returns_per_s": counts.returns / wall, "raycast_returns_per_s": hits / bare_wall,
            "stats_ratio": counts.returns / wall / (hits / bare_wall),
            "las_points_per_s": points / las_wall, "las_bytes_per_s": written / las_wall,
            "disk_write_bytes_per_s": disk, "las_fraction_of_disk": written / las_wall / disk,
            "las_fraction_of_stats": las_counts.returns / las_wall / (counts.returns / wall),
            "device_memory_mib": _device_memory_mib(resolve_device(device)), "stats_kernels_s": kernels}


def _scale_workload(device: str, returns: float, **settings) -> RunConfig:
    """The scale section's flight: 50 s lines (2.8 km) back and forth over the same track across the 3 km
    terrain, 8×8 array at 500 m, as many as ``returns`` beams take (at most those of the statistics run)."""
    line_s = 50.0
    lines = max(1, round(returns / (5000.0 * 64 * line_s)))
    return workload(device, 8, returns, **{"scoring.edge_buffer_m": 0.0, "flight.duration_s": line_s,
                                           "flight.lines": lines, **settings})


def _las_run_into(sim: Tracer, cfg: RunConfig, directory: Path):
    """(wall [s] until every tile is closed, counts, bytes written) of a LAS-mode run into ``directory``."""
    from flightsim.outputs.device_las import DeviceLasOutput

    started = time.perf_counter()
    las = DeviceLasOutput(directory, cfg.output, sim, False, cfg.flight.start_gps_time)
    counts = sim.run(Points(on_device=True), las)
    tiles = las.close()
    wall = time.perf_counter() - started
    written = sum((directory / model / name).stat().st_size for model, names in tiles.items() for name in names)
    return wall, counts, written


def survey_area(device: str, s: Sizes) -> dict:
    """A production survey as a user runs it: ``flightsim simulate`` (a fresh process) over a testdem square
    of SURVEY_KM (10 km on a GPU: 100 km²) with its land cover and town, 5 m pixels, the default instrument
    at 500 m following the terrain, lines spaced as ``flightsim survey`` spaces them (30 % sidelap), both
    models to LAZ. Wall clock, points, bytes and peak memory of the whole command."""
    from flightsim.engine.config_io import to_toml
    from flightsim.scenes import testdem
    from flightsim.studies.survey_plan import SurveySpec, plan_survey

    kind = "cpu" if resolve_device(device) == "cpu" else "cuda"
    km = SURVEY_KM[kind]
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        paths = testdem.write(Path(tmp) / "dem", size_m=km * 1000.0, cell_m=SURVEY_CELL_M)
        cfg = RunConfig()
        for key, value in {"run.device": device, "output.laz": True, "run.scene_cache": False}.items():
            set_value(cfg, key, value)
        lines = plan_survey(validate(cfg), SurveySpec(size_km=km)).cfg.flight
        settings = {"scene.name": str(paths["dem"]), "scene.landcover": str(paths["landcover"]),
                    "scene.buildings": str(paths["buildings"]), "flight.terrain_following": True,
                    "flight.lines": lines.lines, "flight.line_spacing_m": lines.line_spacing_m,
                    "flight.duration_s": km * 1000.0 / (cfg.flight.speed_kmh / 3.6)}
        for key, value in settings.items():
            set_value(cfg, key, value)
        (Path(tmp) / "survey.toml").write_text(to_toml(validate(cfg)))
        command = [sys.executable, "-m", "flightsim", "simulate", "--config", str(Path(tmp) / "survey.toml"),
                   "--out", str(Path(tmp) / "run")]
        wall, code, peak_mib, process = run_measured(command, stderr=subprocess.PIPE)
        if code != 0:
            raise RuntimeError(f"survey benchmark failed: {' '.join(command)}: {process.stderr.read().decode()[-2000:]}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
        written = sum(f.stat().st_size for f in (Path(tmp) / "run").rglob("*.laz"))
    points = sum(summary["points"].values())
    return {"area_km2": km * km, "dem_cell_m": SURVEY_CELL_M, "lines": lines.lines, "line_km": km,
            "beams": summary["beams_fired"], "points_written": points, "laz_bytes": written, "wall_s": wall,
            "simulate_wall_s": summary["wall_s"], "points_per_s": points / wall,
            "peak_rss_mib": peak_mib, "tiles": sum(len(t) for t in summary["tiles"].values()),
            "stages_s": summary["stages_s"],
            "patch_rms_m": summary.get("patches", {}).get("rms_m")}


def _device_memory_mib(device: str) -> float | None:
    """High-water mark of Warp's memory pool on a GPU [MiB]; None on the CPU."""
    if device == "cpu":
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20
