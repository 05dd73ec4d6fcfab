"""`flightsim bench`: measured speed, the cost in accuracy of every speed knob, and what skipping saves.

Every number is measured in the run that reports it. Throughput records compare the end-to-end
pipeline with the bare ray cast it makes (:func:`kernels.mesh_cast.closest_hit`, nothing else) on the same scene,
the same rays and the same number of processes, so the ratio holds however busy the machine is. Results merge into DIR/bench.json
(one entry per device kind) and DIR/bench.md; the knob study goes to DIR/pareto.csv and .png.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from flightsim.core.warp_runtime import resolve_device
from flightsim.studies.bench_common import child_bytecode, git_commit, gpu_name, sizes
from flightsim.studies.bench_forest import forest
from flightsim.studies.bench_gpus import gpu_scaling
from flightsim.studies.bench_photon_runs import photon_runs
from flightsim.studies.bench_runs import galvo, spad_frame, stages, study, throughput, waveform_altimeter
from flightsim.studies.bench_savings import pareto, skipping
from flightsim.studies.bench_startup import startup
from flightsim.studies.bench_scale import las_output, reduce_knobs, scale, survey_area
from flightsim.studies.waveform_processing import ranging_bench

SECTIONS = ("throughput", "stages", "study", "las", "skip", "pareto", "galvo", "spad", "waveform", "scale",
            "reduce", "survey", "forest", "startup", "ranging", "gpus", "photons")


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
               "waveform": waveform_altimeter, "scale": scale, "reduce": reduce_knobs, "survey": survey_area,
               "forest": forest, "startup": startup, "ranging": ranging_bench, "gpus": gpu_scaling,
               "photons": photon_runs}
    machine = results["gpu_name"] if kind == "cuda" else f"{results['cpu_count']} CPU cores"
    with child_bytecode():  # the sections' commands start as an installed package's would
        for name in sections:  # written after each section, so an interrupted bench keeps what it measured
            started = time.perf_counter()
            results[name] = runners[name](device, s)
            results.setdefault("section_wall_s", {})[name] = time.perf_counter() - started
            results.setdefault("section_measured", {})[name] = f"{results['git_commit']} {results['date']} on {machine}"
            merge_and_write(Path(out), kind, results)
    return results

