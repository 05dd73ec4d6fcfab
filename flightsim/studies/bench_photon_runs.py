"""`flightsim bench` section photons: the photon instruments' runs end to end, each `flightsim simulate` in a fresh
process (the SPAD lidar's MODE-A frame, ATLAS's six beams in parts of the default size and of four times that; shorter
on the CPU), with the wall, the peak memory, the stages, photons/s and the writers' times; and the photon LAS writer
on the SPAD run's photons (read back from its photons.h5, in the run's parts of whole pulses) on one thread and on the
threads a run off orbit gives it, in the same run."""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flightsim.core.warp_runtime import resolve_device
from flightsim.studies.bench_common import Sizes, run_measured

LARGE_PARTS = {"run.host_photons": 1 << 22}  # a photon run's parts four times the default's
RUNS = {"cuda": (("spad", 0.86, {}), ("atlas", 10.0, {}), ("atlas", 10.0, LARGE_PARTS)),
        "cpu": (("spad", 0.086, {}), ("atlas", 2.0, {}), ("atlas", 2.0, LARGE_PARTS))}
"""(instrument preset, flight duration [s], settings) of each run: on the GPU the SPAD frame (43,000 pulses) and a 10 s
ATLAS pass, in parts of the default size and four times that (memory against wall); on the CPU a tenth of the frame
and a 2 s pass (--quick: a tenth of those)."""


def photon_runs(device: str, s: Sizes) -> dict:
    """The runs' records (each after an untimed short run of its instrument that fills the kernel cache) and the
    LAS writer's record on the SPAD run's photons."""
    device = resolve_device(device)
    runs = RUNS["cpu" if device == "cpu" else "cuda"]
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        records = []
        for k, (instrument, duration, settings) in enumerate(runs):
            duration = duration / 10 if s.quick else duration
            if instrument not in [run[0] for run in runs[:k]]:
                _simulate(device, instrument, duration / 100, Path(tmp) / f"warm-{instrument}")
            records.append(_simulate(device, instrument, duration, Path(tmp) / f"{k}-{instrument}", settings))
        writer = las_writer(Path(tmp) / "0-spad")
    return {"runs": records, "las_writer": writer}


def _simulate(device: str, instrument: str, duration: float, out: Path, settings: dict | None = None) -> dict:
    """Wall, peak memory, photons, stages and writers' times of `flightsim simulate --instrument ... --duration ...
    [--set key=value ...]` into ``out``."""
    sets = [arg for key, value in (settings or {}).items() for arg in ("--set", f"{key}={value}")]
    command = [sys.executable, "-m", "flightsim", "simulate", "--instrument", instrument, "--duration",
               f"{duration:g}", "--device", device, *sets, "--out", str(out)]
    wall, code, peak_mib, _ = run_measured(command)
    if code != 0:
        raise RuntimeError(f"photon benchmark run failed: {' '.join(command)}")
    summary = json.loads((out / "summary.json").read_text())
    label = ", ".join([instrument, *(f"{key}={value}" for key, value in (settings or {}).items())])
    return {"instrument": instrument, "label": label, "duration_s": duration, "device": device,
            "photons": summary["photons"], "wall_s": wall, "photons_per_s": summary["photons"] / wall,
            "peak_rss_mib": peak_mib,
            "stages_s": summary["stages_s"], "writers_s": summary["writers_s"],
            "command": " ".join(["flightsim", *command[3:-2]])}


def las_writer(run: Path, threads: int | None = None) -> dict:
    """Photons/s of the photon LAS writer (``photons/`` of the run in ``run``, written again elsewhere) on one thread
    and on ``threads`` (None: ``thread_count(LAS_THREADS)``, as a run off orbit has), the two in turn, best of two each
    (the photons' beam directions taken as nadir: photons.h5 keeps none; the scan angle costs the same)."""
    from flightsim.core.background import Background
    from flightsim.core.process_map import thread_count
    from flightsim.engine.config import validate
    from flightsim.engine.config_io import load_toml, preset_config
    from flightsim.engine.instrument import Instrument
    from flightsim.engine.products.photons import LAS_THREADS
    from flightsim.engine.world import build_scene
    from flightsim.outputs.photon_las import PhotonLas

    cfg = validate(load_toml(run / "run.toml", preset_config("spad")))
    scene, instrument = build_scene(cfg), Instrument(cfg)
    timing = instrument.deflector.timing()
    parts = _parts(run / "photons.h5", scene.origin, timing.prf_hz, cfg.run.host_photons)
    photons, threads = sum(len(part) for part in parts), threads or thread_count(LAS_THREADS)
    walls = {1: [], threads: []}
    for _ in range(2):
        for count in walls:
            with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as out:
                writer = Background(PhotonLas(Path(out), cfg.output, scene, timing, instrument.emitter.beam_columns,
                                              None, cfg.flight.start_gps_time), "bench-las", threads=count)
                started = time.perf_counter()
                for part in parts:
                    writer(part)
                writer.close()
                walls[count].append(time.perf_counter() - started)
    one, many = min(walls[1]), min(walls[threads])
    return {"photons": photons, "parts": len(parts), "threads": threads, "one_thread_s": one, "threads_s": many,
            "one_thread_photons_per_s": photons / one, "threads_photons_per_s": photons / many, "speedup": one / many}


def _parts(path: Path, origin, prf_hz: float, most: int) -> list:
    """The photons of photons.h5 at ``path`` (a run of one flight line, as the SPAD frame is) as PhotonChunks (local to
    the scene ``origin`` [m]) in the parts the run hands its writers (whole pulses, at most ``most``: its
    ``run.host_photons``)."""
    import h5py

    from flightsim.engine.readouts.photons import PhotonChunk, pulse_parts

    with h5py.File(path) as f:
        c = {name: f["photons"][name][:] for name in ("line_id", "pulse", "pixel", "time_of_flight_s", "signal",
                                                      "delta_time", "x", "y", "z")}
    points = np.column_stack([c["x"], c["y"], c["z"]]) - np.asarray(origin, dtype=np.float64)
    nadir = np.tile(np.float32([0.0, 0.0, -1.0]), (len(points), 1))
    start = float(c["delta_time"][0]) - float(c["pulse"][0]) / prf_hz  # the line's pulse 0 [s]
    return [PhotonChunk(int(c["line_id"][a]), start, c["pulse"][a:b], c["pixel"][a:b], c["time_of_flight_s"][a:b],
                        c["signal"][a:b] > 0, c["signal"][a:b].astype(np.int8), points[a:b], nadir[a:b])
            for a, b in pulse_parts(c["pulse"], most)]


def markdown(r: dict) -> list[str]:
    """bench.md's lines of the section."""
    if "photons" not in r:
        return []
    x = r["photons"]
    lines = ["### Photon runs end to end (`flightsim simulate`, a fresh process each)", "",
             "| command | photons | wall [s] | photons/s | peak RSS [MiB] | setup [s] | trace [s] | finish [s] |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| `{run['command']}` | {run['photons']:.3g} | {run['wall_s']:.2f} | {run['photons_per_s']:.3g} | "
              f"{run['peak_rss_mib']:.0f} | {run['stages_s']['setup']:.2f} | {run['stages_s']['trace']:.2f} | "
              f"{run['stages_s']['finish']:.2f} |" for run in x["runs"]]
    lines += _writer_lines(x["runs"])
    w = x["las_writer"]
    parts = f"{w['parts']} part" + ("s" if w["parts"] != 1 else "")
    return lines + ["", f"The photon LAS writer alone on the SPAD run's {w['photons']:.3g} photons ({parts}): "
                        f"{w['one_thread_photons_per_s']:.3g} photons/s on one thread, "
                        f"{w['threads_photons_per_s']:.3g} on {w['threads']} ({w['speedup']:.2f}×, best of two each "
                        "in turn; the tiles as a run off orbit makes them).", ""]


def _writer_lines(runs: list[dict]) -> list[str]:
    """Each run's writers (summary.json ``writers_s``), where the records have them."""
    rows = [f"| {run.get('label', run['instrument'])} | {name} | {t['busy']:.2f} | {t['cpu']:.2f} | {t['prepare']:.2f} | "
            f"{t['held_back']:.2f} | {t['close']:.2f} |"
            for run in runs for name, t in run.get("writers_s", {}).items()]
    if not rows:
        return []
    return ["", "Their writers (summary.json `writers_s`, each on a thread of its own): its calls' wall and that "
            "thread's CPU time, a staged writer's preparing threads, the trace's waits for it, its close.", "",
            "| run | file | busy [s] | CPU [s] | prepare [s] | held the trace back [s] | close [s] |",
            "| --- | --- | --- | --- | --- | --- | --- |", *rows]
