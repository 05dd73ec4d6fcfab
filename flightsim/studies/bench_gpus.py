"""`flightsim bench --sections gpus`: the seed paper's study and a 100 km² survey on one GPU and on every GPU of the
machine, the same command side by side (Dask, a worker per GPU: ``--gpus``), on a machine with two or more GPUs.

Four pairs: the study as the paper flies it (10 s per configuration) and flying 6× longer (the GPUs' share of the
wall grows); the survey to LAZ and to LAS, as a user runs them (the part files under ``--out``, transient: the page
cache keeps them; ``--parts /dev/shm`` gained 0-4 s more at c8290e2, ``results/scaling.md``). Each pair's outputs are
compared (the sweep's rows but their wall times; every tile byte for byte) and what differs is recorded with the
wall times; the study also runs twice on GPU 0, to tell what differs between two runs alike. What limits the
scaling is measured in the same runs: the workers' busy time (the sum of their tasks' own wall) against the
command's, the survey's segments (tracing and LAS parts) against its merges (LAZ compression or LAS copying), and the
disk's sequential write rate probed before the surveys.
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from flightsim.core.warp_runtime import resolve_device
from flightsim.studies.bench_common import DISK_PROBE_BYTES, Sizes, gpu_name, run_measured

GPUS_SURVEY_KM = 10.0  # 100 km², the survey of issue 30
LONG_STUDY_S = "60"  # seconds flown per configuration in the study's longer variant (the default is 10)
TIMING_COLUMNS = ("wall_s",)  # the sweep's columns that may differ between two runs of the same grid


def gpu_scaling(device: str, s: Sizes) -> dict:
    """Each pair (the study as the paper flies it and flying 6× longer; the survey to LAZ and to LAS) on GPU 0 alone
    and on every GPU, and the study twice on GPU 0; a record saying why not, on fewer than two GPUs."""
    import warp as wp

    count = 0 if resolve_device(device) == "cpu" else wp.get_cuda_device_count()
    if count < 2:
        return {"gpus": count, "skipped": "needs a machine with two or more GPUs"}
    every = ",".join(map(str, range(count)))
    per_gpu = max(1, (os.cpu_count() or 1) // count)  # the survey's workers per GPU: the host's cores shared out
    runs = {"study": lambda out, gpus: sweep_run(out, ["--gpus", gpus], s.study_grid),
            f"study, {LONG_STUDY_S} s per configuration":
                lambda out, gpus: sweep_run(out, ["--gpus", gpus, "--duration", LONG_STUDY_S], s.study_grid),
            "survey to LAZ": lambda out, gpus: survey_run(out, ["--gpus", gpus], _per(per_gpu, gpus), GPUS_SURVEY_KM),
            "survey to LAS": lambda out, gpus: survey_run(out, ["--gpus", gpus], _per(per_gpu, gpus), GPUS_SURVEY_KM,
                                                          laz=False)}
    from flightsim.studies.bench_scale import idle_disk_rate

    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        folder = Path(tmp)
        _warm_up(folder / "warm", ["--gpus", every], s)
        disk = idle_disk_rate(folder / "probe", DISK_PROBE_BYTES["cuda"])
        pairs = {name: [run(folder / f"{k}-{gpus}", gpus) for gpus in ("0", every)] for k, (name, run) in
                 enumerate(runs.items())}
        repeat = runs["study"](folder / "repeat", "0")  # GPU 0 again: what differs between two runs alike
    study_repeat = {"wall_s": repeat["wall_s"], "differences": compare(pairs["study"][0]["outputs"], repeat["outputs"])}
    return {"gpus": count, "gpu_name": gpu_name("cuda:0"), "cpu_count": os.cpu_count(), "disk_write_bytes_per_s": disk,
            "study_repeat": study_repeat, "pairs": {name: _pair(runs) for name, runs in pairs.items()}}


def _per(per_gpu: int, gpus: str) -> int:
    """The workers of a survey on ``gpus``: ``per_gpu`` each."""
    return per_gpu * len(gpus.split(","))


def _pair(runs: list[dict]) -> dict:
    """A pair's record: its two runs (their outputs compared, then dropped) and the speed-up."""
    differences = compare(runs[0].pop("outputs"), runs[1].pop("outputs"))
    return {"runs": runs, "speedup": runs[0]["wall_s"] / runs[1]["wall_s"], "differences": differences}


def _warm_up(folder: Path, flags: list[str], s: Sizes) -> None:
    """A small sweep and survey with ``flags`` first, untimed: the kernels the timed runs load are in Warp's
    cache."""
    sweep_run(folder / "sweep", flags, (["500"], ["3"], s.study_grid[2][:2]))
    for laz in (True, False):
        survey_run(folder / f"survey-{laz}", flags, None, 1.0, laz)
    shutil.rmtree(folder)


def sweep_run(out: Path, flags: list[str], grid: tuple[list[str], list[str], list[str]]) -> dict:
    """``flightsim sweep`` of ``grid`` (altitudes, arrays, spacings) with ``flags`` (where it runs: ``--gpus 0``,
    ``--workers 2``, …; any other): wall, the workers' busy share, and its rows to compare (``outputs``)."""
    altitudes, arrays, spacings = grid
    command = [sys.executable, "-m", "flightsim", "sweep", "--scene", "calibration", *flags,
               "--altitudes", ",".join(altitudes), "--arrays", ",".join(arrays), "--spacings-mrad", ",".join(spacings),
               "--out", str(out)]
    wall = _run(command)
    rows = sweep_rows(out / "sweep.csv")
    busy = configurations_wall_s(out / "sweep.csv")
    workers = _workers(flags)
    return {"command": _shown(command), "workers": workers, "wall_s": wall, "rows": len(rows), "busy_s": busy,
            "busy_share": busy / (wall * workers), "outputs": rows}


def survey_run(out: Path, flags: list[str], workers: int | None, km: float, laz: bool = True) -> dict:
    """``flightsim survey`` of ``km`` × ``km`` to LAZ (else LAS) with ``flags`` (as :func:`sweep_run`'s) and
    ``workers`` workers (None: as ``flags`` say): wall, where the workers' time went, the bytes written, and a digest
    of every tile to compare (``outputs``; the tiles themselves are removed)."""
    command = [sys.executable, "-m", "flightsim", "survey", "--size-km", f"{km:g}", "--set",
               f"output.laz={str(laz).lower()}",
               *flags, *(["--workers", str(workers)] if workers else []), "--out", str(out)]
    wall = _run(command)
    summary = json.loads((out / "survey.json").read_text())
    digests = tile_digests(out)
    written = sum(f.stat().st_size for f in out.rglob("*.la[sz]"))
    shutil.rmtree(out)
    busy = [w["busy_s"] for w in summary["workers"].values()]
    return {"command": _shown(command), "workers": len(busy), "wall_s": wall, "survey_wall_s": summary["wall_s"],
            "tasks": summary["tasks"], "merges": summary["merges"], "points_written": summary["points_written"],
            "bytes": written, "points_per_s": summary["points_written"] / wall, "segments_s": summary["segments_s"],
            "merges_s": summary["merges_s"], "busy_share": sum(busy) / (summary["wall_s"] * len(busy)),
            "busiest_s": max(busy), "outputs": digests}


def _workers(flags: list[str]) -> int:
    """The workers a command with ``flags`` runs on: ``--workers N``, else one per GPU of ``--gpus``, else 1."""
    if "--workers" in flags:
        return int(flags[flags.index("--workers") + 1])
    if "--gpus" in flags:
        return len(flags[flags.index("--gpus") + 1].split(","))
    return 1


def _run(command: list[str]) -> float:
    """The wall time [s] of ``command`` in a fresh process (shown on stderr); RuntimeError with its stderr if it
    fails."""
    wall, code, _peak, process = run_measured(command, stderr=subprocess.PIPE)
    if code != 0:
        raise RuntimeError(f"{_shown(command)} failed: {process.stderr.read().decode()[-3000:]}")
    print(f"bench gpus: {wall:.1f} s {_shown(command)}", file=sys.stderr)
    return wall


def row_differences(rows: list[dict], others: list[dict]) -> dict:
    """Where two runs' sweep rows differ: ``rows`` (each's count), and per differing column the rows that differ
    and the largest absolute and relative difference (numbers) or the first pair of values (text)."""
    found: dict = {"rows": [len(rows), len(others)], "columns": {}}
    for row, other in zip(rows, others):
        for key in row:
            a, b = row[key], other.get(key)
            if a == b:
                continue
            column = found["columns"].setdefault(key, {"rows": 0, "max_abs": 0.0, "max_rel": 0.0})
            column["rows"] += 1
            try:
                x, y = float(a), float(b)
                column["max_abs"] = max(column["max_abs"], abs(x - y))
                column["max_rel"] = max(column["max_rel"], abs(x - y) / max(abs(x), abs(y)))
            except (TypeError, ValueError):
                column.setdefault("first", [a, b])
    return found


def compare(outputs, others) -> dict:
    """Where two runs' outputs differ: sweep rows (:func:`row_differences`) or tile digests (the tiles that differ)."""
    if isinstance(outputs, dict):
        return {"tiles": len(outputs), "tiles_differing": tiles_differing(outputs, others)}
    return row_differences(outputs, others)


def tiles_differing(digests: dict[str, str], others: dict[str, str]) -> list[str]:
    """The tiles two runs did not write byte for byte alike (or wrote only one of)."""
    return sorted(name for name in digests.keys() | others.keys() if digests.get(name) != others.get(name))


def _shown(command: list[str]) -> str:
    """The command as a user types it (``flightsim ...``), its output folder left out."""
    return "flightsim " + " ".join(command[3:command.index("--out")])


def configurations_wall_s(path: Path) -> float:
    """The sum of a sweep.csv's configurations' own wall times [s]: each configuration once, though it has a row per
    model, each with the configuration's wall."""
    from flightsim.studies.sweep import ROW_CORE  # the columns a configuration's rows differ in

    walls = {tuple(v for k, v in row.items() if k not in ROW_CORE): float(row["wall_s"])
             for row in csv.DictReader(io.StringIO(Path(path).read_text()))}
    return sum(walls.values())


def sweep_rows(path: Path) -> list[dict]:
    """The rows of a sweep.csv without their timing columns: what two runs of one grid must share."""
    return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS}
            for row in csv.DictReader(io.StringIO(Path(path).read_text()))]


def tile_digests(out: Path) -> dict[str, str]:
    """SHA-256 of every LAS/LAZ tile under ``out`` (by path relative to it), hashed in parallel threads."""
    files = sorted(p for p in Path(out).rglob("*") if p.suffix in (".las", ".laz") and not p.name.startswith("."))

    def digest(path: Path) -> str:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            while block := fh.read(1 << 24):
                h.update(block)
        return h.hexdigest()

    with ThreadPoolExecutor(min(16, os.cpu_count() or 1)) as pool:
        return dict(zip((p.relative_to(out).as_posix() for p in files), pool.map(digest, files)))


def markdown(r: dict) -> list[str]:
    """bench.md's lines for the section (none where it was not measured, or skipped)."""
    x = r.get("gpus")
    if not x or "skipped" in x:
        return []
    disk = x["disk_write_bytes_per_s"]
    lines = [f"### Several GPUs: one against {x['gpus']} ({x['gpu_name']} ×{x['gpus']}, {x['cpu_count']} CPU cores; "
             f"disk writes {disk / 1e6:.0f} MB/s)", "",
             "| run | command | workers | wall [s] | speed-up | workers busy | outputs against GPU 0's | notes |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, pair in x["pairs"].items():
        speedup, found = f"{pair['speedup']:.2f}×", _differences(pair["differences"])
        for k, e in enumerate(pair["runs"]):
            lines.append(f"| {name} | `{e['command'].split(' --out ')[0]}` | {e['workers']} | {e['wall_s']:.1f} | "
                         f"{speedup if k else '1'} | {e['busy_share']:.0%} | {found if k else '–'} | "
                         f"{_notes(e, disk)} |")
    repeat = x["study_repeat"]
    return lines + ["", f"The study again on GPU 0: {repeat['wall_s']:.1f} s, outputs against the first run: "
                        f"{_differences(repeat['differences'])}. Wall: the whole command in a fresh process, cluster "
                        "start included. Workers busy: the sum of the workers' task times ÷ (wall × workers). "
                        "Surveys: the host's cores shared out, the same number of workers per GPU.", ""]


def _differences(found: dict) -> str:
    """A comparison's outcome in words."""
    if "tiles" in found:
        return f"{len(found['tiles_differing'])} of {found['tiles']} tiles differ" if found["tiles_differing"] else \
            f"all {found['tiles']} tiles byte for byte"
    if not found["columns"]:
        return f"all {found['rows'][0]} rows alike"
    return "; ".join(f"{name} in {c['rows']} rows, by ≤ {c['max_abs']:.1e}" for name, c in found["columns"].items())


def _notes(e: dict, disk: float) -> str:
    """A run's own numbers: rows, or points, bytes and where the workers' time went."""
    if "rows" in e:
        return f"{e['rows']} rows"
    return (f"{e['points_written']:.3g} points, {e['bytes'] / 1e9:.2f} GB ({e['bytes'] / e['wall_s'] / disk:.3f} of "
            f"the disk's rate), {e['points_per_s']:.3g} points/s; worker time: segments {e['segments_s']:.0f} s, "
            f"merges {e['merges_s']:.0f} s")
