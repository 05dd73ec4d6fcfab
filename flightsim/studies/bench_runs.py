"""`flightsim bench` sections of the pipeline's throughput against bare ray casting: the airborne instrument over the
calibration field (and where its time goes), the seed paper's study, the galvo imager, a SPAD frame and the waveform
altimeter."""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import warp as wp

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.config import set_value, validate
from flightsim.engine.readouts.photons import Photons
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.readouts.waveforms import Waveforms
from flightsim.studies.bench_common import (bare_raycast, gpu_name, kernel_name, kernel_times, simulator, Sizes,
                                            throughput_record, timed_statistics, two_process_record, workload)


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
        records.append(throughput_record(sim, cfg, counts, wall, hits / bare_wall, processes=1))
        if sim.device_kind == "cpu":
            records.append(two_process_record(cfg, sample, repeats))
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
        record = throughput_record(sim, cfg, counts, wall, hits / bare_wall, processes=1)
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
    from flightsim.studies.spad import PAPER, frame_config, frame_simulator, grid_bins, photon_frame, simulate_frame
    from flightsim.studies.spad_traffic import key_bits, traffic_record

    frame_pulses = PAPER["mode_a"]["pulses"]
    pulses = frame_pulses if resolve_device(device) != "cpu" else frame_pulses // (1000 if s.quick else 100)
    _, sim = frame_simulator(frame_config(100.0, "A", device, pulses))
    frame = photon_frame(sim, PAPER["mode_a"]["grid"])  # one frame's memory, reused frame after frame
    simulate_frame(sim, frame)
    runs = [simulate_frame(sim, frame) for _ in range(3)]
    counts, points, wall = min(runs, key=lambda r: r[2])
    photons_only = min(_into_frame(sim, frame) for _ in range(2))
    sample = min(counts.beams_fired, 1 << 24)
    repeats = max(1, round(counts.beams_fired / sample))
    bare_wall, _ = bare_raycast(sim, sample, repeats)
    beams_per_s, bare_per_s = counts.beams_fired / wall, sample * repeats / bare_wall
    frame_wall = wall * frame_pulses / counts.pulses
    return {"pulses": counts.pulses, "frame_pulses": frame_pulses, "beams": counts.beams_fired,
            "photons": counts.returns, "points": len(points.points), "wall_s": wall,
            "trace_and_photons_s": photons_only, "frame_wall_s": frame_wall,
            "instrument_frame_s": PAPER["mode_a"]["frame_s"], "faster_than_instrument": PAPER["mode_a"]["frame_s"] / frame_wall,
            "beams_per_s": beams_per_s, "raycast_rays_per_s": bare_per_s, "ratio": beams_per_s / bare_per_s,
            "traffic": traffic_record(counts.beams_fired, counts.returns, frame.cells ** 2,
                                      key_bits(frame.cells ** 2, sim.cfg.photon.gate_m[1] - sim.cfg.photon.gate_m[0],
                                               grid_bins(sim.cfg)[0]), wall, device)}


def _into_frame(sim, frame) -> float:
    """Wall [s] of a frame's trace and photons into ``frame``, not gridded."""
    frame.reset()
    return sim.run(Photons(frame=frame)).wall_s


def waveform_altimeter(device: str, s: Sizes) -> list[dict]:
    """The waveform altimeter (the change1 preset: 7200 sub-rays per shot, 32,768 samples of 0.01 ns) over
    the flat and the 0.20-slope footprints, shots fired at 1 kHz: sub-ray returns/s with the waveform
    accumulation on the device (pilot ray, deposit, convolution with the pulse; nothing to the host),
    against the bare ray cast of the same sub-rays. Best of two after a run that compiles. On a GPU the slope
    also at the flat's 20,000 shots: its 500 are one chunk of ~2 ms, whose launches and waits weigh as much as
    its work."""
    from flightsim.studies.waveform import waveform_config

    cuda = resolve_device(device) != "cpu"
    records = []
    cases = (("flat", 20000), ("slope", 500), ("slope", 20000)) if cuda else (("flat", 20), ("slope", 4))
    for scene, shots in cases:
        cfg = waveform_config(scene, device, **{"fixed.prf_hz": 1000.0, "flight.duration_s": (shots - 0.5) / 1000.0})
        sim = simulator(cfg)
        sim.run(Waveforms(on_device=True), lambda found: None)
        counts = min((sim.run(Waveforms(on_device=True), lambda found: None) for _ in range(2)), key=lambda c: c.wall_s)
        kernels = kernel_times(lambda: sim.run(Waveforms(on_device=True), lambda found: None)) if cuda else {}
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


def study(device: str, s: Sizes) -> dict:
    """Wall time of the seed paper's grid over the calibration field in a fresh process, from an empty kernel cache
    (seeded with the prebuilt kernels; whatever they lack compiled in the run), after an untimed sweep of one
    configuration has written the modules' bytecode (as an installed package has it)."""
    altitudes, arrays, spacings = s.study_grid
    with tempfile.TemporaryDirectory() as tmp:
        def sweep(grid: tuple[list[str], list[str], list[str]], name: str) -> tuple[list[str], float]:
            env = dict(os.environ, WARP_CACHE_PATH=str(Path(tmp) / f"kernels-{name}"))
            command = [sys.executable, "-m", "flightsim", "sweep", "--scene", "calibration", "--device", device,
                       *(f"--{flag}={','.join(values)}" for flag, values in zip(("altitudes", "arrays",
                                                                                  "spacings-mrad"), grid)),
                       "--out", str(Path(tmp) / name)]
            started = time.perf_counter()
            done = subprocess.run(command, env=env, capture_output=True, text=True)
            wall = time.perf_counter() - started
            if done.returncode != 0:
                raise RuntimeError(f"study sweep failed: {' '.join(command)}\n{done.stderr[-4000:]}")
            return command, wall

        sweep(([altitudes[0]], [arrays[0]], [spacings[0]]), "bytecode")
        command, wall = sweep((altitudes, arrays, spacings), "sweep")
        rows = (Path(tmp) / "sweep" / "sweep.csv").read_text().splitlines()[1:]
    configs = len(altitudes) * len(arrays) * len(spacings)
    return {"device": resolve_device(device), "gpu_name": gpu_name(resolve_device(device)), "configurations": configs,
            "rows": len(rows), "wall_s": wall, "kernel_compile_included": True, "command": " ".join(command[1:])}
