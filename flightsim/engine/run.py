"""`flightsim simulate`: one run from a config to LAS tiles, run.toml and summary.json."""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Callable

from flightsim.core.version import __version__
from flightsim.core.atomic import write_atomic
from flightsim.core.constants import MODELS
from flightsim.engine.config import RunConfig
from flightsim.engine.config_io import to_toml
from flightsim.engine.world import edge_buffer_m
from flightsim.core.errors import InputError
from flightsim.engine.world import build_scene, flight_trajectories

STAGES = ("scene", "plan", "setup", "trace", "finish")
"""Where a LAS run's time goes (summary.json ``stages_s`` [s]): reading the scene, planning the flight (height
grid, terrain following, clearance), the device set-up (BVHs, plane boundaries, output writers), tracing
with every chunk's points handed to the writers, and finishing the tiles, the COPC file and the patch raster."""

PATCH_RASTER = "patch_rms.tif"
"""Per-patch fit RMS of a LAS run over curved ground (:class:`flightsim.outputs.consumers.PatchStatistics`)."""


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
        only_temporaries = present <= {f".{name}.part" for name in ("run.toml", "summary.json", "photons.h5")}
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
    marker summary.json first, the tiles and temporaries next, and run.toml, which names the
    config of the unfinished run, last."""
    for name in ("summary.json", "photons.h5", PATCH_RASTER, *MODELS, *(f"{m}.copc.laz" for m in MODELS)):
        target = directory / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    for leftover in directory.glob(".*.part"):
        leftover.unlink()
    (directory / "run.toml").unlink(missing_ok=True)


def simulate_to_directory(cfg: RunConfig, directory: Path, overwrite: bool = False,
                          progress: Callable[[int, int], None] | None = None) -> dict:
    """Run a validated config, write its tiles, run.toml and summary.json; return the summary."""
    marks = [time.perf_counter()]
    scene = build_scene(cfg)
    buffer = edge_buffer_m(cfg) if cfg.instrument.detector == "discrete" else 0.0
    if buffer > 0.0:
        scene.prefetch_boundary_segments()  # found while the flight is planned and the BVHs built
    marks.append(time.perf_counter())
    trajectories = flight_trajectories(cfg, scene)
    marks.append(time.perf_counter())
    # Warp is loaded only for input that passed the checks above, so that bad input fails fast
    from flightsim.outputs.consumers import PatchStatistics, PlaneStatistics, patch_grid
    from flightsim.outputs.copc import write_run_copc
    from flightsim.outputs.device_las import DeviceLasOutput
    from flightsim.engine.readouts.points import Points
    from flightsim.engine.tracer import Tracer
    from flightsim.core.warp_runtime import resolve_device

    resolve_device(cfg.run.device)  # every input is checked before the output directory is touched
    patches = None if cfg.instrument.detector in ("photon", "waveform") else patch_grid(scene, cfg.scoring.patch_m)
    cfg_text = to_toml(cfg)
    prepare_output(directory, cfg_text, overwrite)
    write_atomic(directory / "run.toml", cfg_text)
    if cfg.instrument.detector == "photon":
        return _photons_to_directory(cfg, scene, trajectories, directory, cfg_text, progress)
    if cfg.instrument.detector == "waveform":
        return _waveforms_to_directory(cfg, scene, trajectories, directory, cfg_text, progress)
    simulator = Tracer(cfg, scene, trajectories, with_truth=cfg.output.position_error, edge_buffer_m=buffer)
    las = DeviceLasOutput(directory, cfg.output, simulator, buffer > 0.0, cfg.flight.start_gps_time)
    planes = PlaneStatistics(simulator, buffer) if scene.planar else None  # curved ground: patches only
    fits = PatchStatistics(simulator, patches, buffer) if patches is not None else None
    consumers = [c for c in (planes, fits, las) if c is not None]

    def consume(returns):
        for consumer in consumers:
            consumer(returns)

    marks.append(time.perf_counter())
    try:
        counts = simulator.run(Points(on_device=True), consume, progress)
        marks.append(time.perf_counter())
        tiles = las.close()
    except BaseException:
        las.abort()
        raise
    copc = write_run_copc(directory, tiles) if cfg.output.copc else None
    patch_summary = fits.write(directory / PATCH_RASTER, scene) if fits is not None else None
    marks.append(time.perf_counter())
    summary = {
        **_summary_head(cfg, simulator, counts),
        "points": {model: counts.returns for model in simulator.models},
        "tir_dropped": counts.tir_dropped,
        "misses": counts.misses,
        "wall_s": round(counts.wall_s, 4),
        "rms_m": planes.rms_m() if planes is not None else {model: None for model in simulator.models},
        **({"patches": patch_summary} if patch_summary is not None else {}),
        "stages_s": {stage: round(end - start, 3) for stage, start, end in zip(STAGES, marks, marks[1:])},
        "edge_buffer_m": buffer,
        **({"apex_angle_deg": cfg.risley.apex_angle_deg} if cfg.instrument.deflector == "risley" else {}),
        "lines": {str(k): v for k, v in counts.per_line.items()},
        "tiles": tiles,
        **({"copc": copc} if copc is not None else {}),
    }
    write_atomic(directory / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _photons_to_directory(cfg: RunConfig, scene, trajectories, directory: Path, cfg_text: str,
                          progress: Callable[[int, int], None] | None) -> dict:
    """Photon mode: every detection into photons.h5, LAS tiles in photons/ (in output.crs) and, from orbit, the
    ATL03-style atl03.h5, then summary.json."""
    from flightsim.engine.readouts.photons import Photons
    from flightsim.engine.tracer import Tracer
    from flightsim.outputs.atl03_h5 import Atl03Writer
    from flightsim.outputs.photon_las import FOLDER, PhotonLas
    from flightsim.outputs.photons_h5 import PhotonWriter

    simulator = Tracer(cfg, scene, trajectories)
    shutil.rmtree(directory / FOLDER, ignore_errors=True)  # tiles of a run being redone
    writer = PhotonWriter(directory, cfg_text, simulator.timing.prf_hz, scene.origin, scene.crs.to_wkt())
    body = cfg.flight.body if cfg.flight.platform == "orbit" else None
    las = PhotonLas(directory, cfg.output, scene, simulator.timing, simulator.instrument.emitter.beam_columns, body,
                    cfg.flight.start_gps_time)
    writers = [writer, las] + ([Atl03Writer(directory, body, cfg_text, simulator.timing.prf_hz, scene)]
                               if body is not None else [])

    def consume(chunk):
        for w in writers:
            w(chunk)

    try:
        counts = simulator.run(Photons(), consume, progress)
        names = [w.close() for w in writers]
    except BaseException:
        for w in writers:
            w.abort()
        raise
    summary = {
        **_summary_head(cfg, simulator, counts),
        "reflectance": _reflectance(cfg, scene, cfg.photon.reflectance),
        "photons": writer.count,
        "signal_photons": writer.signal,
        "photon_tiles": las.tiles,
        "wall_s": round(counts.wall_s, 4),
        "lines": {str(k): v for k, v in counts.per_line.items()},
        "files": names,
    }
    write_atomic(directory / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _waveforms_to_directory(cfg: RunConfig, scene, trajectories, directory: Path, cfg_text: str,
                            progress: Callable[[int, int], None] | None) -> dict:
    """Waveform mode: every beam's waveform, its geolocation and ranging into waveforms.h5, then summary.json."""
    from flightsim.engine.readouts.waveforms import Waveforms
    from flightsim.engine.tracer import Tracer
    from flightsim.instrument.waveform import system
    from flightsim.outputs.waveforms_h5 import WaveformWriter

    simulator = Tracer(cfg, scene, trajectories)
    taps, first_lag = simulator.instrument.detector.pulse_taps("cpu")
    tx = (taps.numpy(), first_lag * cfg.waveform.sample_interval_s)
    writer = WaveformWriter(directory, cfg_text, system(cfg.waveform), simulator.timing.prf_hz, scene, tx)
    try:
        counts = simulator.run(Waveforms(), writer, progress)
        names = writer.close()
    except BaseException:
        writer.abort()
        raise
    summary = {
        **_summary_head(cfg, simulator, counts),
        "reflectance": _reflectance(cfg, scene, cfg.waveform.reflectance),
        "waveforms": writer.shots,
        "subray_returns": counts.returns,
        "returns": int(sum(len(r) for r in writer.returns)),
        "wall_s": round(counts.wall_s, 4),
        "lines": {str(k): v for k, v in counts.per_line.items()},
        "files": names,
    }
    write_atomic(directory / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _reflectance(cfg: RunConfig, scene, value: float) -> float | str:
    """Where a photon or waveform run's reflectance came from: the scene's per-triangle albedo (a land-cover
    raster's, or the scene's own), else the run's one ``value`` (ρ, or the waveform's f)."""
    if scene.reflectance is None:
        return value
    return "per triangle (land cover)" if cfg.scene.values().get("landcover") else "per triangle (scene)"


def _summary_head(cfg: RunConfig, simulator, counts) -> dict:
    """The summary.json fields every run has: versions, scene, device, instrument and pulse counts."""
    return {
        "flightsim": __version__,
        "scene": cfg.scene.name,
        "device": simulator.device,
        "instrument": {"emitter": cfg.instrument.emitter, "deflector": cfg.instrument.deflector,
                       "detector": cfg.instrument.detector},
        "pulses": counts.pulses,
        "pulses_culled": counts.pulses_culled,
        "beams_fired": counts.beams_fired,
    }
