"""One run from a config to its files: the scene, the flight, the tracer and the detector's product (LAS tiles,
photon or waveform files), run.toml and summary.json."""
from __future__ import annotations

import json
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from flightsim.core import registry
from flightsim.core.atomic import write_atomic
from flightsim.core.errors import InputError
from flightsim.core.version import __version__
from flightsim.engine.config import RunConfig
from flightsim.engine.config_io import to_toml
from flightsim.engine.products import catalog as _products  # noqa: F401  (registers the built-in products)
from flightsim.engine.world import build_scene, flight_trajectories, planning_kernels

STAGES = ("scene", "plan", "setup", "trace", "finish")
"""Where a run's time goes (summary.json ``stages_s`` [s]): reading the scene, planning the flight (height grid,
terrain following, clearance), the device set-up (BVHs, plane boundaries, output writers), tracing with every
chunk handed to the writers, and finishing the files (tiles, COPC, patch raster, HDF5)."""

OWN_FILES = ("run.toml", "summary.json")


def product_class(cfg: RunConfig) -> type:
    """The product a run to files writes: the one of its detector's first readout."""
    return registry.part("product", cfg.detector_part.readouts[0])


def prepare_output(directory: Path, cfg_text: str, overwrite: bool) -> None:
    """Make ``directory`` ready for a run, refusing to clobber anything that is not ours to replace.

    An existing directory is reused when it is empty, when ``overwrite`` is set, or when it holds
    an unfinished run of the very same config (no summary.json, and run.toml equal to this config
    or, for a run stopped while writing it, nothing but the temporaries of our own files): that
    run is redone.
    """
    if directory.exists() and not directory.is_dir():
        raise InputError("--out", str(directory), "a directory (this path is a file)")
    present = {p.name for p in directory.iterdir()} if directory.is_dir() else set()
    if present:
        previous = directory / "run.toml"
        same = previous.is_file() and previous.read_text(encoding="utf-8") == cfg_text
        only_temporaries = present <= {f".{name}.part" for name in (*OWN_FILES, "photons.h5")}
        unfinished_same = "summary.json" not in present and (same or only_temporaries)
        if not (overwrite or unfinished_same):
            raise InputError("--out", str(directory),
                             "an empty or new directory (pass --overwrite to replace the run in it)")
        _remove_run(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError("--out", str(directory), f"a directory that can be created ({exc.strerror or exc})") from None


def _remove_run(directory: Path) -> None:
    """Delete a run's files in an order that a kill at any moment leaves resumable: the completion
    marker summary.json first, every product's files and the temporaries next, and run.toml, which names the
    config of the unfinished run, last."""
    products = [name for part in registry.kinds("product").values() for name in part.files]
    for name in ("summary.json", *products):
        target = directory / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    for leftover in directory.glob(".*.part"):
        leftover.unlink()
    (directory / "run.toml").unlink(missing_ok=True)


@dataclass
class Run:
    """A finished run to files: its summary (summary.json), counts and tracer."""

    summary: dict
    counts: Any  # flightsim.engine.tracer.RunCounts
    tracer: Any  # flightsim.engine.tracer.Tracer


def simulate_to_directory(cfg: RunConfig, directory: Path, overwrite: bool = False,
                          progress: Callable[[int, int], None] | None = None) -> dict:
    """Run a validated config, write its product, run.toml and summary.json into ``directory``; return the summary."""
    return execute(cfg, directory, overwrite, progress).summary


def execute(cfg: RunConfig, directory: Path, overwrite: bool = False,
            progress: Callable[[int, int], None] | None = None, tap: Callable[[Any, Any], None] | None = None,
            with_truth: bool = False) -> Run:
    """:func:`simulate_to_directory`, giving the run's counts and tracer too. ``tap(tracer, item)`` also sees every
    chunk the readout hands the product; ``with_truth`` keeps the true hits (the Python API keeps the returns)."""
    marks = [time.perf_counter()]
    cfg_text = to_toml(cfg)
    tracer, product = open_run(cfg, directory, marks, lambda: prepare_output(directory, cfg_text, overwrite),
                               with_truth)
    consume = product if tap is None else (lambda item: (tap(tracer, item), product(item)))
    marks.append(time.perf_counter())
    try:
        readout = product.readout()
        tracer.compile_ahead(readout, product)
        counts = tracer.run(readout, consume, progress)
        marks.append(time.perf_counter())
        fields = product.close(counts)
    except BaseException:
        product.abort()
        raise
    marks.append(time.perf_counter())
    summary = {**summary_head(cfg, tracer, counts), **fields, "wall_s": round(counts.wall_s, 4),
               "stages_s": {stage: round(end - start, 3) for stage, start, end in zip(STAGES, marks, marks[1:])},
               "lines": {str(k): v for k, v in counts.per_line.items()}}
    if product.empty(counts):
        from flightsim.engine.diagnosis import empty_reason

        summary["empty"] = empty_reason(tracer, counts)
    write_atomic(directory / "summary.json", json.dumps(summary, indent=2) + "\n")
    return Run(summary, counts, tracer)


def open_run(cfg: RunConfig, directory: Path, marks: list[float], claim: Callable[[], None],
             with_truth: bool = False):
    """(tracer, product) of a run of ``cfg``: the scene built, the set-up kernels compiled (:func:`compile_setup`),
    the flight planned (``marks`` gets the time after each), every input checked, then ``claim()`` (which makes
    ``directory`` ready) and the product opened in ``directory`` with run.toml written."""
    from flightsim.engine.tracer import Tracer

    leaves = getattr(product_class(cfg), "reads_cloud_leaves", lambda _: True)(cfg)
    scene = build_scene(cfg, cloud_leaves=leaves)  # Warp is loaded only for a scene that passed its checks
    compile_setup(cfg, scene)
    product = product_class(cfg)(cfg, scene)
    marks.append(time.perf_counter())
    trajectories = flight_trajectories(cfg, scene)
    marks.append(time.perf_counter())
    cfg_text = to_toml(cfg)  # every input is checked before the output directory is touched
    claim()
    write_atomic(directory / "run.toml", cfg_text)
    options = {**product.tracer_options, **({"with_truth": True} if with_truth else {})}
    tracer = Tracer(cfg, scene, trajectories, **options)
    product.open(tracer, directory, cfg_text)
    return tracer, product


def compile_setup(cfg: RunConfig, scene) -> None:
    """Compile the kernels a run of ``cfg`` over ``scene`` launches while it is set up (its deflector's, its flight
    planning's, its tracer's and its product's ``setup_kernels``) at once: each device's in one parallel batch, the
    devices side by side, before the set-up would compile them one after another (a Risley run on a GPU compiles
    the exit fan on the CPU while its set-up kernels compile for the GPU)."""
    from flightsim.core.warp_runtime import compile_ahead, resolve_device
    from flightsim.engine.instrument import Instrument
    from flightsim.engine.tracer import Tracer

    run_device = resolve_device(cfg.run.device)
    instrument = Instrument(cfg)
    pairs = [*getattr(instrument.deflector, "setup_kernels", list)(), *planning_kernels(cfg, scene),
             *Tracer.setup_kernels(instrument), *getattr(product_class(cfg), "setup_kernels", lambda _: [])(cfg)]
    wanted: dict[str, list] = {}
    for kernel, device in pairs:
        wanted.setdefault(run_device if device is None else resolve_device(device), []).append(kernel)
    with ThreadPoolExecutor(max(1, len(wanted))) as pool:
        for batch in [pool.submit(compile_ahead, device, kernels) for device, kernels in wanted.items()]:
            batch.result()


def compile_kernels(configs: list[RunConfig]) -> int:
    """Compile into Warp's kernel cache every kernel that runs of ``configs`` launch, all at once and without
    flying them (scenes built, flights planned, products opened in a scratch directory); returns the modules."""
    with tempfile.TemporaryDirectory() as tmp:
        places = [Path(tmp) / str(k) for k in range(len(configs))]
        opened = [open_run(cfg, place, [], place.mkdir) for cfg, place in zip(configs, places)]
        try:
            wanted = {}
            for tracer, product in opened:
                wanted.setdefault(tracer.device, []).extend(tracer.kernels_needed(product.readout(), product))
            from flightsim.core.warp_runtime import compile_ahead

            for device, kernels in wanted.items():
                compile_ahead(device, kernels)
        finally:
            for _tracer, product in opened:
                product.abort()
    return sum(len({id(k.module) for k in kernels}) for kernels in wanted.values())


def summary_head(cfg: RunConfig, tracer, counts) -> dict:
    """The summary.json fields every run has: versions, scene, device, instrument and pulse counts."""
    return {
        "flightsim": __version__,
        "scene": cfg.scene.name,
        "device": tracer.device,
        "instrument": {"emitter": cfg.instrument.emitter, "deflector": cfg.instrument.deflector,
                       "detector": cfg.instrument.detector},
        "pulses": counts.pulses,
        "pulses_culled": counts.pulses_culled,
        "beams_fired": counts.beams_fired,
    }
