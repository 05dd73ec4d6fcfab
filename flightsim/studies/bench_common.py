"""What every `flightsim bench` section shares: the sizes, the benchmark flight, timed runs and the bare ray
cast every throughput is compared with (the same scene, rays and processes), kernel times, records."""
from __future__ import annotations

import contextlib
import dataclasses
import os
import platform
import subprocess
import tempfile
import time

import numpy as np
import warp as wp

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.meshes import SceneMeshes
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.readouts.waveforms import sample_subrays
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, edge_buffer_m, flight_trajectories
from kernels import trace


DELTA = 2.314


SCALE_TRIANGLES = {"cuda": (1e4, 1e6, 1e7, 5e7), "cpu": (1e4, 1e6)}  # terrain sizes of the scale section


REDUCE_TRIANGLES = (1e6, 1e7)  # terrain sizes of the reduce section


# the reduce section's settings: (run.sum_replicas, run.slots_per_thread)
REDUCE_KNOBS = [(replicas, spt) for replicas in (64, 512, 2048) for spt in (16, 32, 64, 128)]


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


def kernel_times(run) -> dict[str, float]:
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


def two_process_record(cfg: RunConfig, sample: int, repeats: int) -> dict:
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
        return throughput_record(sim, cfg, counts, wall, hits / bare_wall, processes=2)
    finally:
        pool.close()


def throughput_record(sim: Tracer, cfg: RunConfig, counts, wall: float, raycast_rate: float, processes: int) -> dict:
    rate = counts.returns / wall
    return {
        "device": sim.device, "gpu_name": gpu_name(sim.device), "scene": cfg.scene.name,
        "triangles": int(len(sim.scene.triangles)), "array": cfg.fan.array, "processes": processes,
        "optics": cfg.run.optics, "pulses": counts.pulses, "returns": counts.returns, "wall_s": wall,
        "returns_per_s": rate, "raycast_returns_per_s": raycast_rate, "ratio": rate / raycast_rate,
        "git_commit": git_commit(),
    }


@contextlib.contextmanager
def child_bytecode():
    """Child processes started within read and write Python's bytecode in a folder of their own (removed after), as
    an installed package's users have it: in an environment with PYTHONDONTWRITEBYTECODE (the GPU machines'), every
    child would otherwise compile every module's source at its start (~1.4 s on an H100 host)."""
    saved = {name: os.environ.pop(name, None) for name in ("PYTHONPYCACHEPREFIX", "PYTHONDONTWRITEBYTECODE")}
    with tempfile.TemporaryDirectory() as folder:
        os.environ["PYTHONPYCACHEPREFIX"] = folder
        try:
            yield folder
        finally:
            os.environ.pop("PYTHONPYCACHEPREFIX", None)
            os.environ.update({name: value for name, value in saved.items() if value is not None})


def run_measured(command: list[str], stderr=subprocess.DEVNULL) -> tuple[float, int, float, subprocess.Popen]:
    """(wall [s], exit code, peak resident memory [MiB], the process) of ``command`` in a fresh process.

    The peak is the process's own: its ``VmHWM`` (the high-water mark of the address space exec gave it), read from
    /proc every 10 ms while it runs. wait4's ``ru_maxrss`` alone (the fallback without /proc) also counts the pages of
    this process at the fork, which are many once Warp has started CUDA here (2.3 GB against the 0.6 GB of the LAS
    command on an H100 host)."""
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr)
    status_file = f"/proc/{process.pid}/status"
    peak_kib = 0
    while True:
        pid, status, usage = os.wait4(process.pid, os.WNOHANG)
        if pid:
            break
        peak_kib = max(peak_kib, _high_water_kib(status_file))
        time.sleep(0.01)
    wall = time.perf_counter() - started
    process.returncode = os.waitstatus_to_exitcode(status)
    return wall, process.returncode, (peak_kib or usage.ru_maxrss) / 1024.0, process


def _high_water_kib(status_file: str) -> int:
    """VmHWM [KiB] from a /proc/<pid>/status file; 0 where it cannot be read (no /proc, the process gone)."""
    try:
        with open(status_file) as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


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
