"""`flightsim bench` section photons: the photon instruments' runs end to end, each `flightsim simulate` in a fresh
process (the SPAD lidar's MODE-A frame, ATLAS's six beams in parts of the default size and of four times that; shorter
on the CPU), with the wall, the peak memory, the stages, photons/s and the writers' times; then the writers alone on
those runs' photons (:mod:`flightsim.studies.bench_photon_writers`), in the same run."""
from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

from flightsim.core.warp_runtime import resolve_device
from flightsim.studies.bench_common import Sizes, run_measured
from flightsim.studies.bench_photon_writers import atlas_products, las_writer, writer_lines

LARGE_PARTS = {"run.host_photons": 1 << 22}  # a photon run's parts four times the default's
RUNS = {"cuda": (("spad", 0.86, {}), ("atlas", 10.0, {}), ("atlas", 10.0, LARGE_PARTS)),
        "cpu": (("spad", 0.086, {}), ("atlas", 2.0, {}), ("atlas", 2.0, LARGE_PARTS))}
"""(instrument preset, flight duration [s], settings) of each run: on the GPU the SPAD frame (43,000 pulses) and a 10 s
ATLAS pass, in parts of the default size and four times that (memory against wall); on the CPU a tenth of the frame
and a 2 s pass (--quick: a tenth of those)."""


def photon_runs(device: str, s: Sizes) -> dict:
    """The runs' records (each after an untimed short run of its instrument that fills the kernel cache), the LAS
    writer's record on the SPAD run's photons and ATLAS's products' on the ATLAS run's (parts of the default size)."""
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
        atlas = next(k for k, (name, _, settings) in enumerate(runs) if name == "atlas" and not settings)
        products = atlas_products(Path(tmp) / f"{atlas}-atlas")
    return {"runs": records, "las_writer": writer, "atlas_products": products}


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
    return lines + _writer_lines(x["runs"]) + writer_lines(x["las_writer"], x.get("atlas_products"))


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
