"""`flightsim survey`: a large survey over a tiled scene, split into tasks that can run anywhere.

The scene is a square grid of scene tiles of ``tile_m`` — each a copy of the calibration field
(or flat ground, for ``scene.name = "plane"``) with its own float64 origin at its centre (SPEC §2) —
flown by parallel north–south lines whose spacing is the swath width (the scan circle's diameter
2·h·tan θ) less the sidelap.

Each line is cut along track into segments of ``segment_m``. One task simulates one segment: its
pulses only (``Tracer(pulse_limits=...)``, so every pulse belongs to exactly one task), over a
scene assembled from just the tiles its beams can reach (the reach radius h·tan(θ_max + tilt + 1°)
plus the scene margin around its ground track, the local origin being the tile under the middle
of the segment). It writes its points per LAS tile into part files in a directory of its own (under
the survey's parts folder: ``out/.parts``, or a folder of its own under a ``parts`` folder such as a
RAM disk), renamed into place when complete. One merge task per (model, LAS tile) then concatenates that
tile's parts in task order (line, then segment) into the final tile, atomically, and deletes the
parts. The tiles are byte-identical whether the tasks run in this process or on any number of
Dask workers, and whether or not a worker died on the way (a task or merge run twice writes the
same bytes under names of its own).

The plan (tile grid, lines, tasks and merges) is made by :mod:`flightsim.studies.survey_plan`; this module runs it.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from copy import deepcopy
from pathlib import Path
from typing import Callable

from flightsim.core.version import __version__
from flightsim.core.constants import MODELS
from flightsim.engine.config import RunConfig, copy_config
from flightsim.engine.config_io import to_toml
from flightsim.core.errors import InputError
from flightsim.outputs.device_las import DeviceLasOutput
from flightsim.core.atomic import fsync_all, start_writeback, write_atomic
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.studies.survey_plan import SegmentTask, SurveyPlan, TileGrid

PARTS = ".parts"  # per-task part files, under the output directory unless run_survey is given a parts folder
SURVEY_FILES = ("run.toml", "survey.toml", "survey.json", PARTS)
MERGE_CHUNK_POINTS = 500_000  # points read and written at a time when merging parts


# ---------------------------------------------------------------------------------------------
# the tasks


def segment_task(cfg: RunConfig, grid: TileGrid, task: SegmentTask, parts: str) -> dict:
    """Simulate one segment into ``parts/<task>/<model>/<tile>.las``; return what it wrote.

    Idempotent: a task finished by an earlier attempt is not run again; an attempt writes into a
    directory of its own and renames it into place, so attempts never share a file.
    """
    from flightsim.engine.distributed import worker_device, worker_stats

    parts = Path(parts)
    final = parts / task.name
    cfg = worker_device(cfg)
    if not (final / "task.json").is_file():
        started = time.perf_counter()
        attempt = parts / f".{task.name}.{uuid.uuid4().hex}"
        attempt.mkdir(parents=True)
        result = _simulate_segment(cfg, grid, task, attempt)
        result["wall_s"] = time.perf_counter() - started
        (attempt / "task.json").write_text(json.dumps(result))
        try:
            os.rename(attempt, final)
        except OSError:  # another attempt finished first: its output is the same
            shutil.rmtree(attempt)
    return {**json.loads((final / "task.json").read_text()), **worker_stats(), "device": cfg.run.device}


def _simulate_segment(cfg: RunConfig, grid: TileGrid, task: SegmentTask, directory: Path) -> dict:
    scene, global_plane = grid.assemble(list(task.tiles), task.origin_tile)
    trajectory = task.line.trajectory(ground_height_m=grid.centre[2])
    simulator = Tracer(cfg, scene, [trajectory], with_truth=cfg.output.position_error,
                          pulse_limits={task.line.line_id: task.pulses})
    parts = copy_config(cfg)
    parts.output.laz = False  # parts are plain LAS; the merge writes the final format
    las = DeviceLasOutput(directory, parts.output, simulator, False, cfg.flight.start_gps_time, plane_ids=global_plane,
                          durable=False)  # parts are read once by their merge, then deleted: the page cache keeps them
    try:
        counts = simulator.run(Points(on_device=True), las)
        tiles = las.close()
    except BaseException:
        las.abort()
        raise
    stray = {t for written in tiles.values() for t in written} - set(task.las_tiles)
    if stray:
        raise RuntimeError(f"task {task.name} wrote LAS tiles outside its planned reach: {sorted(stray)}")
    return {"name": task.name, "tiles": tiles,
            "counts": {k: getattr(counts, k) for k in ("pulses", "pulses_culled", "beams_fired", "returns",
                                                       "tir_dropped", "misses")}}


def merge_task(out: str, parts: str, model: str, tile: str, compress: bool, *results: dict) -> dict:
    """Concatenate a LAS tile's parts (under ``parts``), in task order, into ``out/<model>/<tile>``; delete them.

    ``results`` are the results of the tasks that could write into the tile. Idempotent: a tile
    already merged (its parts partly deleted) is only counted.
    """
    from flightsim.engine.distributed import worker_stats

    started = time.perf_counter()
    mine = sorted((r for r in results if tile in r["tiles"].get(model, {})), key=lambda r: r["name"])
    expected = sum(r["tiles"][model][tile] for r in mine)
    if not mine:
        return {"model": model, "tile": None, "points": 0, "wall_s": 0.0, **worker_stats()}
    files = [Path(parts) / r["name"] / model / tile for r in mine]
    target = Path(out) / model / (tile[:-4] + (".laz" if compress else ".las"))
    if target.is_file() and not all(p.is_file() for p in files):
        import laspy

        with laspy.open(target) as reader:
            points = reader.header.point_count
    else:
        points = merge_tile(files, target, compress)
        for part in files:
            part.unlink(missing_ok=True)
    if points != expected:
        raise RuntimeError(f"{target}: {points} points merged, the tasks wrote {expected}")
    return {"model": model, "tile": target.name, "points": points, "wall_s": time.perf_counter() - started,
            **worker_stats()}


def merge_tile(parts: list[Path], target: Path, compress: bool) -> int:
    """Write the points of ``parts`` (LAS tiles of one tile key, same header) in order into
    ``target``, through a temporary name of its own; return the number of points. The tile's write-back is
    started, not waited for: run_survey syncs every tile once, before survey.json says the survey is done."""
    target.parent.mkdir(parents=True, exist_ok=True)
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex}.part")
    try:
        with open(temporary, "wb", buffering=0) as fh:
            points = (_compress_parts if compress else _concatenate_parts)(parts, fh)
            start_writeback(fh.fileno())
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return points


def _compress_parts(parts: list[Path], fh) -> int:
    """The parts' points, decoded and compressed by laspy into ``fh``, their chunks on every core (lazrs's parallel
    compressor writes the sequential one's bytes: each chunk is compressed on its own); the number of points."""
    import laspy

    with laspy.open(parts[0]) as first:
        header = first.header
    with laspy.open(fh, mode="w", header=header, do_compress=True, laz_backend=laspy.LazBackend.LazrsParallel,
                    closefd=False) as writer:
        for part in parts:
            with laspy.open(part) as reader:
                for points in reader.chunk_iterator(MERGE_CHUNK_POINTS):
                    writer.write_points(points)
        return writer.header.point_count


def _concatenate_parts(parts: list[Path], fh) -> int:
    """The parts' point records copied byte for byte into ``fh`` after one header for them all (the bytes laspy's
    writer makes from the same points: the first part's header with the parts' counts summed and their bounds
    joined); the number of points."""
    import laspy

    headers = []
    for part in parts:
        with laspy.open(part) as reader:
            headers.append(reader.header)
    header = _joined_header(headers, parts)
    header.write_to(fh)
    for part, h in zip(parts, headers):
        with open(part, "rb", buffering=0) as src:
            _copy_range(src.fileno(), fh.fileno(), h.offset_to_point_data, h.point_count * h.point_format.size)
    return header.point_count


def _joined_header(headers: list, parts: list[Path]):
    """The first header with the point counts of all of ``headers`` summed and their bounds joined (zeros
    without points, as laspy writes them); raises where a part's header differs from the first's in more than
    those, or keeps statistics per extra dimension (the tiles' claim none: outputs.las_format)."""
    import numpy as np

    first = headers[0]
    for part, h in zip(parts, headers):
        if (h.point_format != first.point_format or h.evlrs or not np.array_equal(h.scales, first.scales)
                or not np.array_equal(h.offsets, first.offsets) or _extra_statistics(h)):
            raise RuntimeError(f"{part}: not the header of {parts[0]} (point format, scales, offsets), or one with "
                               f"statistics of its extra dimensions")
    header = deepcopy(first)
    filled = [h for h in headers if h.point_count > 0]
    header.point_count = sum(h.point_count for h in headers)
    header.number_of_points_by_return = np.sum([h.number_of_points_by_return for h in headers], axis=0,
                                               dtype=np.uint64)
    header.mins = np.min([h.mins for h in filled], axis=0) if filled else np.zeros(3)
    header.maxs = np.max([h.maxs for h in filled], axis=0) if filled else np.zeros(3)
    return header


def _extra_statistics(header) -> bool:
    """Whether an extra dimension of ``header`` claims a minimum or maximum."""
    return any(d.min_is_relevant() or d.max_is_relevant()
               for vlr in header.vlrs.get("ExtraBytesVlr") for d in vlr.extra_bytes_structs)


def _copy_range(src: int, dst: int, offset: int, count: int) -> None:
    """Append ``count`` bytes of file descriptor ``src`` from ``offset`` to ``dst`` (in the kernel where it can)."""
    end = offset + count
    while offset < end:
        try:
            copied = os.copy_file_range(src, dst, end - offset, offset)
        except (AttributeError, OSError):  # no copy_file_range here, or not between these two files
            copied = os.write(dst, os.pread(src, min(end - offset, 1 << 24), offset))
        if copied == 0:
            raise RuntimeError(f"a part ended {end - offset} bytes before its point records")
        offset += copied


# ---------------------------------------------------------------------------------------------
# the survey


def prepare_survey_output(directory: Path, texts: dict[str, str], overwrite: bool) -> None:
    """Make ``directory`` ready: empty, new, ``overwrite``, or an unfinished survey of the same config
    (run.toml and survey.toml equal to ``texts``, no survey.json), which is redone."""
    if directory.exists() and not directory.is_dir():
        raise InputError("--out", str(directory), "a directory (this path is a file)")
    present = {p.name for p in directory.iterdir()} if directory.is_dir() else set()
    if present:
        same = all((directory / name).is_file() and (directory / name).read_text() == text
                   for name, text in texts.items())
        ours = {*SURVEY_FILES, *MODELS, *(f".{name}.part" for name in SURVEY_FILES)}
        if not (overwrite or (same and "survey.json" not in present and present <= ours)):
            raise InputError("--out", str(directory),
                             "an empty or new directory (pass --overwrite to replace the survey in it)")
        for name in ("survey.json", *MODELS, PARTS, *(f".{name}.part" for name in SURVEY_FILES), "survey.toml",
                     "run.toml"):
            target = directory / name
            if target.is_dir():
                shutil.rmtree(target)
            else:
                target.unlink(missing_ok=True)
    directory.mkdir(parents=True, exist_ok=True)


def parts_folder(out: Path, parts: Path | None) -> Path:
    """Where a survey into ``out`` keeps its part files: ``out/.parts``, or under ``parts`` (an existing folder that
    every worker reaches) a folder named after ``out``'s absolute path, so surveys sharing ``parts`` never meet."""
    if parts is None:
        return out / PARTS
    if not Path(parts).is_dir():
        raise InputError("--parts", str(parts), "an existing directory that every worker can write to")
    digest = hashlib.sha256(str(out.resolve()).encode()).hexdigest()[:16]
    return Path(parts) / f"flightsim-parts-{digest}"


def run_survey(plan: SurveyPlan, out: Path, client=None, overwrite: bool = False,
               progress: Callable[[int, int], None] | None = None, parts: Path | None = None) -> dict:
    """Run a survey planned by :func:`~flightsim.studies.survey_plan.plan_survey` into ``out`` (in this process, or
    on a Dask ``client``), its part files under ``parts`` (None: in ``out``; a RAM disk keeps them off the disk, which
    then takes each point once); write and return survey.json."""
    from flightsim.core.warp_runtime import resolve_device

    resolve_device(plan.cfg.run.device)
    out = Path(out)
    folder = parts_folder(out, parts)
    texts = {"run.toml": to_toml(plan.cfg), "survey.toml": plan.spec.to_toml()}
    prepare_survey_output(out, texts, overwrite)
    shutil.rmtree(folder, ignore_errors=True)  # an unfinished survey's parts: its tasks are run again
    for name, text in texts.items():
        write_atomic(out / name, text)
    started = time.perf_counter()
    try:
        if client is None:
            segments, merges = _run_here(plan, str(out), str(folder), progress)
        else:
            segments, merges = _run_on(client, plan, str(out), str(folder), progress)
    finally:  # what attempts that died left behind, and a failed survey's parts (not reused: a rerun redoes them)
        shutil.rmtree(folder, ignore_errors=True)
    for model in plan.cfg.output.models:
        for leftover in (out / model).glob(".*.part"):
            leftover.unlink()
    fsync_all(out / r["model"] / r["tile"] for r in merges if r["tile"])  # before survey.json: every tile on the disk
    wall = time.perf_counter() - started
    summary = _summary(plan, segments, merges, wall)
    write_atomic(out / "survey.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _run_here(plan: SurveyPlan, out: str, parts: str, progress) -> tuple[list[dict], list[dict]]:
    """Every task in order in this process, each merge as soon as the last task it needs is done."""
    waiting: dict[str, list[tuple[str, str, list[str]]]] = {}
    for (model, tile), names in plan.merges.items():
        waiting.setdefault(names[-1], []).append((model, tile, names))
    total = len(plan.tasks) + len(plan.merges)
    segments, merges = {}, []
    for task in plan.tasks:
        segments[task.name] = segment_task(plan.cfg, plan.grid, task, parts)
        for model, tile, names in waiting.get(task.name, []):
            merges.append(merge_task(out, parts, model, tile, plan.cfg.output.laz, *(segments[n] for n in names)))
        if progress:
            progress(len(segments) + len(merges), total)
    return list(segments.values()), merges


def _run_on(client, plan: SurveyPlan, out: str, parts: str, progress) -> tuple[list[dict], list[dict]]:
    """The same tasks and merges on a Dask cluster; each merge runs once the tasks it needs are done
    (merges go before waiting tasks, so parts are consumed as soon as they are complete)."""
    from flightsim.engine.distributed import run_futures

    token = uuid.uuid4().hex[:8]
    tasks = {task.name: client.submit(segment_task, plan.cfg, plan.grid, task, parts,
                                      key=f"segment-{token}-{task.name}") for task in plan.tasks}
    merges = [client.submit(merge_task, out, parts, model, tile, plan.cfg.output.laz, *(tasks[n] for n in names),
                            key=f"merge-{token}-{model}-{tile}", priority=1)
              for (model, tile), names in plan.merges.items()]
    kinds = {f.key: kind for kind, futures in (("segment", tasks.values()), ("merge", merges)) for f in futures}
    done: dict[str, list[dict]] = {"segment": [], "merge": []}
    total = len(kinds)
    for future, result in run_futures(client, [*tasks.values(), *merges]):
        done[kinds[future.key]].append(result)
        if progress:
            progress(len(done["segment"]) + len(done["merge"]), total)
    return sorted(done["segment"], key=lambda r: r["name"]), done["merge"]


def _summary(plan: SurveyPlan, segments: list[dict], merges: list[dict], wall_s: float) -> dict:
    models = plan.cfg.output.models
    counts = {k: sum(r["counts"][k] for r in segments) for k in segments[0]["counts"]} if segments else {}
    tiles = {m: dict(sorted((r["tile"], r["points"]) for r in merges if r["model"] == m and r["tile"])) for m in models}
    points = {m: sum(tiles[m].values()) for m in models}
    written = sum(points.values())
    workers: dict[str, dict] = {}
    for r in [*segments, *merges]:
        w = workers.setdefault(r["worker"], {"tasks": 0, "busy_s": 0.0, "peak_rss_mb": 0.0, "devices": [], "pids": []})
        w["tasks"] += 1
        w["busy_s"] = round(w["busy_s"] + r["wall_s"], 3)
        w["peak_rss_mb"] = round(max(w["peak_rss_mb"], r["peak_rss_mb"]), 1)
        for key, value in (("devices", r.get("device")), ("pids", r["pid"])):
            if value is not None and value not in w[key]:
                w[key].append(value)
    return {
        "flightsim": __version__,
        "scene": plan.cfg.scene.name,
        "area_km2": plan.grid.side_m ** 2 / 1e6,
        "scene_tiles": plan.grid.n ** 2,
        "tile_m": plan.grid.tile_m,
        "lines": plan.cfg.flight.lines,
        "line_spacing_m": plan.cfg.flight.line_spacing_m,
        "swath_m": plan.swath_m,
        "reach_m": plan.reach_m,
        "tasks": len(plan.tasks),
        "merges": len(plan.merges),
        "points": points,
        "points_written": written,
        **counts,
        "wall_s": round(wall_s, 3),
        "segments_s": round(sum(r["wall_s"] for r in segments), 3),  # summed over the workers (the tasks' own time)
        "merges_s": round(sum(r["wall_s"] for r in merges), 3),
        "points_per_s": round(written / wall_s) if wall_s > 0 else None,
        "workers": dict(sorted(workers.items())),
        "tiles": tiles,
    }
