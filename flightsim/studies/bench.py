"""`flightsim bench`: measured speed, the cost in accuracy of every speed knob, and what skipping saves.

Every number is measured in the run that reports it. Throughput records compare the end-to-end
pipeline with bare ``wp.mesh_query_ray`` on the same scene, the same rays and the same number of
processes, so the ratio holds however busy the machine is. Results merge into DIR/bench.json
(one entry per device kind) and DIR/bench.md; the knob study goes to DIR/pareto.csv and .png.
"""
from __future__ import annotations

import dataclasses
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.engine.config import RunConfig, copy_config, set_value, validate
from flightsim.engine.world import edge_buffer_m
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.meshes import SceneMeshes
from flightsim.engine.readouts.photons import Photons
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.readouts.waveforms import Waveforms, sample_subrays
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.core.warp_runtime import resolve_device
from kernels import trace

DELTA = 2.314
SECTIONS = ("throughput", "stages", "study", "las", "skip", "pareto", "galvo", "spad", "waveform", "scale",
            "reduce", "survey")
SCALE_TRIANGLES = {"cuda": (1e4, 1e6, 1e7, 5e7), "cpu": (1e4, 1e6)}  # terrain sizes of the scale section
REDUCE_TRIANGLES = (1e6, 1e7)  # terrain sizes of the reduce section
# the reduce section's settings: (run.sum_replicas, run.slots_per_thread)
REDUCE_KNOBS = [(replicas, spt) for replicas in (64, 512, 2048) for spt in (16, 32)]
SURVEY_KM = {"cuda": 10.0, "cpu": 1.0}  # side of the survey section's square area
SURVEY_CELL_M = 5.0  # the survey DEM's pixel size
DISK_PROBE_BYTES = {"cuda": 2 << 30, "cpu": 512 << 20}  # written to measure the disk's sequential rate


@dataclasses.dataclass
class Sizes:
    """How big each measurement is, per device kind and --quick."""

    returns: float  # returns per throughput record
    arrays: tuple[int, ...]
    study_grid: tuple[list[str], list[str], list[str]]  # altitudes, arrays, spacings
    las_returns: float  # returns per model of the LAS run (points written = 2×)
    pareto_returns: float
    quick: bool
    scale_returns: float = 1e6  # beams per statistics record of the scale section
    scale_las_returns: float = 1e6  # beams per LAS record of the scale section


def sizes(kind: str, quick: bool) -> Sizes:
    full_grid = ([str(500 * k) for k in range(1, 11)], ["2", "3", "4", "5", "6"],
                 [f"{k * DELTA:.3f}" for k in range(1, 6)])
    small_grid = (["500", "5000"], ["2", "6"], [f"{DELTA:.3f}", f"{5 * DELTA:.3f}"])
    if kind == "cuda":
        return Sizes(1e9 if not quick else 2e8, (3, 8), small_grid if quick else full_grid,
                     5e5 if quick else 5e7, 1e8, quick, 5e7 if quick else 3e8, 5e6 if quick else 2e7)
    return Sizes(1e6 if quick else 2e7, (3,) if quick else (3, 8), small_grid if quick else full_grid,
                 2e5 if quick else 5e7, 5e5 if quick else 5e6, quick, 2e5 if quick else 2e6, 2e5 if quick else 1e6)


LINE_S = 10.0  # each benchmark line: 10 s (556 m) centred over the calibration field


def workload(device: str, array: int, returns: float, **settings) -> RunConfig:
    """The benchmark flight: passes back and forth over the calibration field at 500 m, each a 10 s
    line over the same ground track, as many as it takes for ``returns`` beams."""
    cfg = RunConfig()
    per_line = 5000.0 * array * array * LINE_S
    base = {"flight.altitude_m": 500.0, "fan.array": array, "run.device": device,
            "flight.duration_s": min(LINE_S, max(0.2, returns / per_line * LINE_S)),
            "flight.lines": max(1, round(returns / per_line)), "flight.line_spacing_m": 0.01}
    for key, value in {**base, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def simulator(cfg: RunConfig, meshes: SceneMeshes | None = None, **kw) -> Tracer:
    scene = meshes.scene if meshes else build_scene(cfg)
    return Tracer(cfg, scene, flight_trajectories(cfg, scene), edge_buffer_m=edge_buffer_m(cfg), meshes=meshes,
                     **kw)


def timed_statistics(sim: Tracer, repeats: int = 2):
    """(best wall [s], counts) of run_statistics after a first run that compiles and warms up."""
    run_statistics(sim)
    best, counts = float("inf"), None
    for _ in range(repeats):
        wp.synchronize_device(sim.device)
        _, counts = run_statistics(sim)
        best = min(best, counts.wall_s)
    return best, counts


def bare_raycast(sim: Tracer, rays: int, repeats: int, subrays: bool = False) -> tuple[float, int]:
    """(wall [s], hits) of casting the run's first ``rays`` rays (the waveform detector's sub-rays with
    ``subrays``) ``repeats`` times with nothing else."""
    starts, directions = sample_subrays(sim, rays) if subrays else sim.sample_rays(rays)
    faces = wp.empty(starts.shape[0], dtype=wp.int32, device=sim.device)
    args = dict(dim=starts.shape[0], inputs=[sim.meshes.mesh.id, starts, directions, sim.cfg.instrument.max_range_m],
                outputs=[faces], device=sim.device)
    wp.launch(trace.cast_rays, **args)
    wp.synchronize_device(sim.device)
    started = time.perf_counter()
    for _ in range(repeats):
        wp.launch(trace.cast_rays, **args)
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - started
    return wall, int((faces.numpy() >= 0).sum()) * repeats


def _bare_in_process(cfg_toml: str, rays: int, repeats: int) -> tuple[float, int]:
    from flightsim.engine.parallel import _simulator

    return bare_raycast(_simulator(cfg_toml), rays, repeats)


# ---------------------------------------------------------------------------------------------
# sections


def throughput(device: str, s: Sizes) -> list[dict]:
    """End-to-end returns/s vs bare ray-cast returns/s on the same rays, per array size."""
    records = []
    for array in s.arrays:
        cfg = workload(device, array, s.returns)
        sim = simulator(cfg)
        wall, counts = timed_statistics(sim)
        sample = min(counts.beams_fired, 1 << (24 if sim.device_kind == "cuda" else 20))
        repeats = max(1, round(counts.beams_fired / sample))
        bare_wall, hits = bare_raycast(sim, sample, repeats)
        records.append(_record(sim, cfg, counts, wall, hits / bare_wall, processes=1))
        if sim.device_kind == "cpu":
            records.append(_two_process_record(cfg, sample, repeats))
    return records


def galvo(device: str, s: Sizes) -> dict:
    """The Chang'e-3 galvo imager (its preset, ranging errors on) hovering 100 m over the plane and over
    the lunar landing zone in statistics mode, each against the bare ray cast of the same rays; and a
    Monte Carlo budget of full 30°×30° frames."""
    from flightsim.engine.config_io import preset_config
    from flightsim.studies.budget import Frame, frame_config, monte_carlo

    records = []
    for scene in ("plane", "lunar"):
        cfg = preset_config("change3")
        frames = max(1, round(s.returns / (17 * 256 * 16)))
        for key, value in {"run.device": device, "flight.duration_s": frames * cfg.galvo.frame_s,
                           "scene.name": scene}.items():
            set_value(cfg, key, value)
        cfg = validate(cfg)
        sim = simulator(cfg)
        wall, counts = timed_statistics(sim)
        sample = min(counts.beams_fired, 1 << (24 if sim.device_kind == "cuda" else 20))
        repeats = max(1, round(counts.beams_fired / sample))
        bare_wall, hits = bare_raycast(sim, sample, repeats)
        record = _record(sim, cfg, counts, wall, hits / bare_wall, processes=1)
        record.update(instrument="change3", scene=scene, triangles=len(sim.scene.triangles))
        records.append(record)
    draws = 1000 if device != "cpu" and not s.quick else 20
    frame = Frame(frame_config(device=device))
    monte_carlo(frame, 2)  # compile and warm up
    mc = monte_carlo(frame, draws)
    return {"throughput": records, "budget": {"draws": draws, "slots_per_draw": frame.pulses * frame.beams,
                                              "wall_s": mc.wall_s, "draws_per_s": draws / mc.wall_s}}


def spad_frame(device: str, s: Sizes) -> dict:
    """One MODE-A frame of the SPAD lidar (the spad preset at 100 m over the sandbox: 43,000 pulses ×
    1024 pixels, photon sampling, gridding into the 1100 × 1100 points, only the points to the host)
    against the instrument's own 0.86 s and the bare ray cast of the same beams. Best of three after a
    run that compiles, in the same device and page-locked host memory (as frame after frame of a mission). On the CPU a slice of the frame (1/100, --quick 1/1000), its time scaled to the
    whole frame."""
    from flightsim.studies.spad import PAPER, frame_config, frame_simulator, photon_frame, simulate_frame

    frame_pulses = PAPER["mode_a"]["pulses"]
    pulses = frame_pulses if resolve_device(device) != "cpu" else frame_pulses // (1000 if s.quick else 100)
    _, sim = frame_simulator(frame_config(100.0, "A", device, pulses))
    frame = photon_frame(sim, PAPER["mode_a"]["grid"])  # one frame's memory, reused frame after frame
    simulate_frame(sim, frame)
    runs = [simulate_frame(sim, frame) for _ in range(3)]
    counts, points, wall = min(runs, key=lambda r: r[2])
    photons_only = min(sim.run(Photons(on_device=True), lambda found: None).wall_s for _ in range(2))
    sample = min(counts.beams_fired, 1 << 24)
    repeats = max(1, round(counts.beams_fired / sample))
    bare_wall, _ = bare_raycast(sim, sample, repeats)
    beams_per_s, bare_per_s = counts.beams_fired / wall, sample * repeats / bare_wall
    frame_wall = wall * frame_pulses / counts.pulses
    return {"pulses": counts.pulses, "frame_pulses": frame_pulses, "beams": counts.beams_fired,
            "photons": counts.returns, "points": len(points.points), "wall_s": wall,
            "trace_and_photons_s": photons_only, "frame_wall_s": frame_wall,
            "instrument_frame_s": PAPER["mode_a"]["frame_s"], "faster_than_instrument": PAPER["mode_a"]["frame_s"] / frame_wall,
            "beams_per_s": beams_per_s, "raycast_rays_per_s": bare_per_s, "ratio": beams_per_s / bare_per_s}


def waveform_altimeter(device: str, s: Sizes) -> list[dict]:
    """The waveform altimeter (the change1 preset: 7200 sub-rays per shot, 32,768 samples of 0.01 ns) over
    the flat and the 0.20-slope footprints, shots fired at 1 kHz: sub-ray returns/s with the waveform
    accumulation on the device (pilot ray, deposit, convolution with the pulse; nothing to the host),
    against the bare ray cast of the same sub-rays. Best of two after a run that compiles."""
    from flightsim.studies.waveform import waveform_config

    cuda = resolve_device(device) != "cpu"
    records = []
    for scene, shots in (("flat", 20000 if cuda else 20), ("slope", 500 if cuda else 4)):
        cfg = waveform_config(scene, device, **{"fixed.prf_hz": 1000.0, "flight.duration_s": (shots - 0.5) / 1000.0})
        sim = simulator(cfg)
        sim.run(Waveforms(on_device=True), lambda found: None)
        counts = min((sim.run(Waveforms(on_device=True), lambda found: None) for _ in range(2)), key=lambda c: c.wall_s)
        kernels = _kernel_times(lambda: sim.run(Waveforms(on_device=True), lambda found: None)) if cuda else {}
        sample = min(counts.returns, 1 << 24)
        bare_wall, hits = bare_raycast(sim, sample, max(1, round(counts.returns / sample)), subrays=True)
        rate, bare = counts.returns / counts.wall_s, hits / bare_wall
        accumulate = sum(t for name, t in kernels.items() if name in ("emit_rays", "pilot", "deposit"))
        records.append({"scene": scene, "shots": counts.pulses, "subrays": counts.returns, "samples": cfg.waveform.samples,
                        "wall_s": counts.wall_s, "subray_returns_per_s": rate, "raycast_returns_per_s": bare,
                        "ratio": rate / bare, "kernels_s": kernels,
                        "accumulation_returns_per_s": counts.returns / accumulate if accumulate else None})
    return records


def stages(device: str, s: Sizes) -> list[dict]:
    """Where a throughput run's time goes: GPU time of each kernel (Warp's CUDA activity timing),
    the rest of the wall time (host work and gaps), and the bare ray cast of as many rays.

    CUDA only: a CPU launch runs on the calling thread, so there the wall time is the kernels'.
    """
    if resolve_device(device) == "cpu":
        return []
    rows = []
    for array in s.arrays:
        sim = simulator(workload(device, array, s.returns / 4))
        wall, counts = timed_statistics(sim, repeats=1)
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        run_statistics(sim)
        kernels: dict[str, float] = {}
        for result in wp.timing_end():
            name = kernel_name(result.name)
            kernels[name] = kernels.get(name, 0.0) + result.elapsed * 1e-3
        sample = min(counts.beams_fired, 1 << 24)
        bare_wall, _ = bare_raycast(sim, sample, max(1, round(counts.beams_fired / sample)))
        rows.append({"array": array, "slots": counts.beams_fired, "returns": counts.returns, "wall_s": wall,
                     "kernels_s": kernels, "bare_raycast_s": bare_wall})
    return rows


def _kernel_times(run) -> dict[str, float]:
    """GPU time of each kernel [s] while ``run()`` runs (Warp's CUDA activity timing)."""
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    run()
    kernels: dict[str, float] = {}
    for result in wp.timing_end():
        name = kernel_name(result.name)
        kernels[name] = kernels.get(name, 0.0) + result.elapsed * 1e-3
    return kernels


def kernel_name(timing_name: str) -> str:
    """'forward kernel records_kernel__locals__trace_records_1a2b3c4' → 'trace_records'."""
    name = timing_name.removeprefix("forward kernel ")
    stem, _, suffix = name.rpartition("_")
    if stem and all(c in "0123456789abcdef" for c in suffix):
        name = stem
    return name.split("__")[-1]  # a kernel built by a factory function: the kernel's own name


def _two_process_record(cfg: RunConfig, sample: int, repeats: int) -> dict:
    from flightsim.engine.config_io import to_toml
    from flightsim.engine.parallel import ProcessPool

    pool = ProcessPool(2)
    try:
        pool.warm(cfg)
        sim = simulator(cfg)
        references = np.array([p.point for p in sim.scene.planes])
        _, counts, wall = pool.run_statistics(cfg, references)
        _, counts, wall = pool.run_statistics(cfg, references)
        text = to_toml(cfg)
        parts = list(pool.pool.map(_bare_in_process, [text] * 2, [sample] * 2, [max(1, repeats // 2)] * 2))
        bare_wall = max(w for w, _ in parts)  # the two casts run at the same time
        hits = sum(h for _, h in parts)
        return _record(sim, cfg, counts, wall, hits / bare_wall, processes=2)
    finally:
        pool.close()


def _record(sim: Tracer, cfg: RunConfig, counts, wall: float, raycast_rate: float, processes: int) -> dict:
    rate = counts.returns / wall
    return {
        "device": sim.device, "gpu_name": gpu_name(sim.device), "scene": cfg.scene.name,
        "triangles": int(len(sim.scene.triangles)), "array": cfg.fan.array, "processes": processes,
        "optics": cfg.run.optics, "pulses": counts.pulses, "returns": counts.returns, "wall_s": wall,
        "returns_per_s": rate, "raycast_returns_per_s": raycast_rate, "ratio": rate / raycast_rate,
        "git_commit": git_commit(),
    }


def study(device: str, s: Sizes) -> dict:
    """Wall time of the seed paper's grid over the calibration field, kernel compile included."""
    altitudes, arrays, spacings = s.study_grid
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, WARP_CACHE_PATH=str(Path(tmp) / "kernels"))
        command = [sys.executable, "-m", "flightsim", "sweep", "--scene", "calibration", "--device", device,
                   "--altitudes", ",".join(altitudes), "--arrays", ",".join(arrays),
                   "--spacings-mrad", ",".join(spacings), "--out", str(Path(tmp) / "sweep")]
        started = time.perf_counter()
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - started
        if done.returncode != 0:
            raise RuntimeError(f"study sweep failed: {' '.join(command)}\n{done.stderr[-4000:]}")
        rows = (Path(tmp) / "sweep" / "sweep.csv").read_text().splitlines()[1:]
    configs = len(altitudes) * len(arrays) * len(spacings)
    return {"device": resolve_device(device), "gpu_name": gpu_name(resolve_device(device)), "configurations": configs,
            "rows": len(rows), "wall_s": wall, "kernel_compile_included": True, "command": " ".join(command[1:])}


def las_output(device: str, s: Sizes) -> list[dict]:
    """Points/s and peak memory of LAS runs of two lengths (memory must not grow with length), and the
    CLI's fixed start-up (interpreter, Warp, scene, kernels: a run of 0.01 s) that each of them pays."""
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
        started = time.perf_counter()
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - started
        process.returncode = os.waitstatus_to_exitcode(status)
        if process.returncode != 0:
            raise RuntimeError(f"LAS benchmark run failed: {' '.join(command)}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    points = sum(summary["points"].values())
    return {"device": resolve_device(device), "points_written": points, "wall_s": wall,
            "points_per_s": points / wall, "peak_rss_mib": usage.ru_maxrss / 1024.0}


def scale(device: str, s: Sizes) -> dict:
    """Terrain of 1e4 to 5e7 triangles (``flightsim.scenes.testdem``, 3 km square, read from a GeoTIFF): the
    time to ready a run (scene read without the cache, flight plan, BVH) and again from the scene cache,
    statistics-mode and LAS-mode throughput of the 8×8 workload at 500 m, the bare ray cast of the same rays,
    device memory; and the output disk's sequential write rate, measured in the same run."""
    kind = "cpu" if resolve_device(device) == "cpu" else "cuda"
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        disk = disk_write_rate(Path(tmp) / "probe", DISK_PROBE_BYTES[kind])
        scenes = [_scale_record(device, int(n), s, Path(tmp)) for n in SCALE_TRIANGLES[kind]]
    for record in scenes:
        record["las_fraction_of_disk"] = record["las_bytes_per_s"] / disk
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
    """Sequential write rate of the disk holding ``path`` [bytes/s]: ``size`` bytes in ``block`` writes,
    fsync'ed, as the tile writers write."""
    data = os.urandom(block)
    started = time.perf_counter()
    with open(path, "wb") as fh:
        for _ in range(max(1, size // block)):
            fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    wall = time.perf_counter() - started
    written = max(1, size // block) * block
    path.unlink()
    return written / wall


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
    kernels = _kernel_times(lambda: run_statistics(sim)) if sim.device_kind == "cuda" else None
    las_cfg = _scale_workload(device, s.scale_las_returns)
    las_sim = Tracer(las_cfg, scene, trajectories[:las_cfg.flight.lines], meshes=meshes)
    _las_run_into(las_sim, las_cfg, tmp / "warm-up")  # compiles the points path's kernels
    las_wall, las_counts, written = _las_run_into(las_sim, las_cfg, tmp / "las")
    points = las_counts.returns * len(las_sim.models)
    shutil.rmtree(dem.parent)
    return {"triangles": len(scene.triangles), **cold,
            "cache_write_s": cache_write_s, "cached_load_s": warm["load_s"], "ready_cached_s": warm["ready_s"],
            "stats_returns_per_s": counts.returns / wall, "raycast_returns_per_s": hits / bare_wall,
            "stats_ratio": counts.returns / wall / (hits / bare_wall),
            "las_points_per_s": points / las_wall, "las_bytes_per_s": written / las_wall,
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
    """(wall [s] until every tile is closed, counts, bytes written) of a LAS-mode run into ``directory``,
    which is removed afterwards."""
    from flightsim.outputs.device_las import DeviceLasOutput

    started = time.perf_counter()
    las = DeviceLasOutput(directory, cfg, sim, edge_distance=False)
    counts = sim.run(Points(on_device=True), las)
    tiles = las.close()
    wall = time.perf_counter() - started
    written = sum((directory / model / name).stat().st_size for model, names in tiles.items() for name in names)
    shutil.rmtree(directory)
    return wall, counts, written


def survey_area(device: str, s: Sizes) -> dict:
    """A production survey as a user runs it: ``flightsim simulate`` (a fresh process) over a testdem square
    of SURVEY_KM (10 km on a GPU: 100 km²) with its land cover and town, 5 m pixels, the default instrument
    at 500 m following the terrain, lines spaced as ``flightsim survey`` spaces them (30 % sidelap), both
    models to LAZ. Wall clock, points, bytes and peak memory of the whole command."""
    from flightsim.engine.config_io import to_toml
    from flightsim.scenes import testdem
    from flightsim.studies.survey import SurveySpec, plan_survey

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
        started = time.perf_counter()
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - started
        if os.waitstatus_to_exitcode(status) != 0:
            raise RuntimeError(f"survey benchmark failed: {' '.join(command)}: {process.stderr.read().decode()[-2000:]}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
        written = sum(f.stat().st_size for f in (Path(tmp) / "run").rglob("*.laz"))
    points = sum(summary["points"].values())
    return {"area_km2": km * km, "dem_cell_m": SURVEY_CELL_M, "lines": lines.lines, "line_km": km,
            "beams": summary["beams_fired"], "points_written": points, "laz_bytes": written, "wall_s": wall,
            "simulate_wall_s": summary["wall_s"], "points_per_s": points / wall,
            "peak_rss_mib": usage.ru_maxrss / 1024.0, "tiles": sum(len(t) for t in summary["tiles"].values()),
            "stages_s": summary["stages_s"],
            "patch_rms_m": summary.get("patches", {}).get("rms_m")}


def _device_memory_mib(device: str) -> float | None:
    """High-water mark of Warp's memory pool on a GPU [MiB]; None on the CPU."""
    if device == "cpu":
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20


def skipping(device: str, s: Sizes) -> list[dict]:
    """Measured savings of each kind of skipped work."""
    cfg = workload(device, 3, s.pareto_returns)
    rows = [_culling_saving(cfg), _mode_saving(cfg), _build_once_saving(cfg)]
    both = timed_statistics(simulator(cfg))[0]
    for label, settings in (("exact model only", {"output.models": "exact"}),
                            ("nominal model only", {"output.models": "nominal"}),
                            ("edge buffer off", {"scoring.edge_buffer_m": 0.0}),
                            ("range noise on (0.02 m)", {"instrument.errors": "ranging", "ranging.noise_m": 0.02})):
        wall = timed_statistics(simulator(workload(device, 3, s.pareto_returns, **settings)))[0]
        rows.append({"what": label, "baseline_s": both, "variant_s": wall, "saving": 1 - wall / both})
    return rows


def _culling_saving(cfg: RunConfig) -> dict:
    scene = build_scene(cfg)  # sized for the nominal flight
    long = _with(cfg, {"flight.duration_s": 4 * cfg.flight.duration_s})
    walls = {}
    for cull in (True, False):
        run_cfg = _with(long, {"run.cull": cull})
        sim = Tracer(run_cfg, scene, flight_trajectories(run_cfg, scene), edge_buffer_m=edge_buffer_m(run_cfg))
        walls[cull], counts = timed_statistics(sim, repeats=1)
        if cull:
            culled = counts.pulses_culled / (counts.pulses + counts.pulses_culled)
    return {"what": f"culling a line 4x longer than the scene ({100 * culled:.0f}% of pulses culled)",
            "baseline_s": walls[False], "variant_s": walls[True], "saving": 1 - walls[True] / walls[False]}


def _with(cfg: RunConfig, settings: dict) -> RunConfig:
    """A validated copy of ``cfg`` with ``settings`` ({table.field: value}) set."""
    out = copy_config(cfg)
    for key, value in settings.items():
        set_value(out, key, value)
    return validate(out)


def _mode_saving(cfg: RunConfig) -> dict:
    sim = simulator(cfg)
    sim.run(Points(), lambda chunk: None)
    started = time.perf_counter()
    counts = sim.run(Points(), lambda chunk: None)
    points_wall = time.perf_counter() - started
    stats_wall, _ = timed_statistics(sim, repeats=1)
    per_return = 8 + 4 * 4 + 4 + 12 * len(sim.models) + 4  # slot, range, face, angle, cos, edge, points, flags
    return {"what": f"statistics mode instead of points mode ({per_return} B/return to the host vs "
                    f"{len(sim.scene.planes) * 2 * 80} B per run)",
            "baseline_s": points_wall, "variant_s": stats_wall, "saving": 1 - stats_wall / points_wall,
            "returns": counts.returns}


def _build_once_saving(cfg: RunConfig) -> dict:
    """A 5-configuration sweep with the scene, BVH and kernels built once vs per configuration."""
    configs = [_with(cfg, {"flight.altitude_m": a}) for a in (500.0, 600.0, 700.0, 800.0, 900.0)]
    extent_cfg = configs[-1]
    started = time.perf_counter()
    meshes = SceneMeshes(build_scene(extent_cfg), resolve_device(cfg.run.device))
    for c in configs:
        run_statistics(simulator(c, meshes))
    shared = time.perf_counter() - started
    started = time.perf_counter()
    for c in configs:
        scene = build_scene(extent_cfg)
        run_statistics(Tracer(c, scene, flight_trajectories(c, scene), edge_buffer_m=edge_buffer_m(c)))
    rebuilt = time.perf_counter() - started
    return {"what": "scene + BVH built once for a 5-configuration sweep (kernels are cached per process)",
            "baseline_s": rebuilt, "variant_s": shared, "saving": 1 - shared / rebuilt}


# ---------------------------------------------------------------------------------------------
# run time against error


def knob_variants(kind: str, quick: bool) -> list[tuple[str, str, dict]]:
    """(knob, value, config settings) for the run-time-against-error study."""
    variants = [("optics", v, {"run.optics": v}) for v in ("float64", "float32")]
    variants += [("optics", f"lut{m}", {"run.optics": "lut", "run.lut_samples": m})
                 for m in ((1024,) if quick else (256, 1024, 4096, 16384))]
    if quick:
        return variants
    constructors = ("sah", "median") + (("lbvh", "cubql") if kind == "cuda" else ())  # lbvh/cubql: GPU only
    variants += [("bvh", f"{c}/leaf{leaf or 'default'}", {"run.bvh": c, "run.bvh_leaf_size": leaf})
                 for c in constructors for leaf in (0, 1, 4)]
    slots = (1 << 16, 1 << 18, 1 << 20) + ((1 << 22, 1 << 24) if kind == "cuda" else ())
    variants += [("chunk", f"{n} slots", {"run.chunk_pulses": n // 9}) for n in slots]
    variants += [("slots_per_thread", f"{n}", {"run.slots_per_thread": n}) for n in (1, 4, 16, 64, 256)]
    if kind == "cuda":  # a register cap only exists for CUDA kernels; 255 = no cap
        variants += [("max_registers", f"{n}", {"run.max_registers": n}) for n in (48, 64, 96, 255)]
    return variants


def _knob_costs(device: str, s: Sizes, settings: dict) -> dict:
    """Wall time of the throughput workload and largest errors at 0.5 and 5 km for one knob setting."""
    from flightsim.studies.accuracy import measure_errors

    cfg = workload(device, 3, s.pareto_returns, **settings)
    wall, counts = timed_statistics(simulator(cfg))
    pointing, point = 0.0, 0.0
    for altitude in (500.0, 5000.0):
        check_cfg = workload(device, 3, 5e4 if s.quick else 2e5, **{**settings, "flight.altitude_m": altitude})
        errors = measure_errors(simulator(check_cfg, with_truth=True))
        pointing = max(pointing, errors.max_pointing_rad)
        point = max([point, *errors.max_point_error_m.values()])
    return {"wall_s": wall, "returns_per_s": counts.returns / wall, "max_pointing_urad": pointing * 1e6,
            "max_point_error_mm": point * 1e3}


def pareto(device: str, s: Sizes) -> list[dict]:
    """Wall time and largest errors against the float64 reference for each knob setting."""
    rows = []
    kind = "cpu" if resolve_device(device) == "cpu" else "cuda"
    for knob, value, settings in knob_variants(kind, s.quick):
        row = {"device": resolve_device(device), "knob": knob, "value": value}
        try:
            row.update(_knob_costs(device, s, settings))
        except Exception as exc:  # an experimental constructor may be unavailable: record it and go on
            row["error"] = f"{type(exc).__name__}: {exc}"[:200]
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------
# reporting


def gpu_name(device: str) -> str:
    return wp.get_device(device).name if device != "cpu" else platform.processor() or "cpu"


def git_commit() -> str:
    """The measured code's commit: FLIGHTSIM_COMMIT where set (a copied working tree, as on the GPU
    machine, may carry stale git metadata), else git's HEAD."""
    if os.environ.get("FLIGHTSIM_COMMIT"):
        return os.environ["FLIGHTSIM_COMMIT"]
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_bench(device: str, quick: bool, out: Path, sections=SECTIONS) -> dict:
    """Run the asked sections and merge the results into out/bench.json, bench.md, pareto.csv/png."""
    from flightsim.studies.bench_report import merge_and_write

    dev = resolve_device(device)
    kind = "cpu" if dev == "cpu" else "cuda"
    s = sizes(kind, quick)
    results = {"device": dev, "gpu_name": gpu_name(dev), "quick": quick, "git_commit": git_commit(),
               "cpu_count": os.cpu_count(), "date": time.strftime("%Y-%m-%d")}
    runners = {"throughput": throughput, "stages": stages, "study": study, "las": las_output, "skip": skipping,
               "pareto": pareto, "galvo": galvo, "spad": spad_frame,
               "waveform": waveform_altimeter, "scale": scale, "reduce": reduce_knobs, "survey": survey_area}
    for name in sections:  # written after each section, so an interrupted bench keeps what it measured
        started = time.perf_counter()
        results[name] = runners[name](device, s)
        results.setdefault("section_wall_s", {})[name] = time.perf_counter() - started
        results.setdefault("section_measured", {})[name] = f"{results['git_commit']} {results['date']}"
        merge_and_write(Path(out), kind, results)
    return results
