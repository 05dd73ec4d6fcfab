"""`flightsim bench` section startup: seconds from launching `flightsim simulate` (the default scene and
instrument, 1 s of flight) to its command line parsed, to the first trace launch and to the first LAS tile on
disk, with an empty Warp kernel cache (cold: every module compiled), again with the cache it left (warm), and
after `flightsim compile` filled an empty cache ahead of the run; and what `flightsim compile --all` takes. Every
process reads Python's bytecode, as an installed package's are (written by a first, untimed run into a bytecode
folder of the section's own: an environment with PYTHONDONTWRITEBYTECODE, or packages installed without their
bytecode, would otherwise compile every module's source at every start)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flightsim.core.warp_runtime import resolve_device
from flightsim.studies.bench_common import Sizes, child_bytecode


def startup(device: str, s: Sizes) -> list[dict]:
    """One record per cache state: cold (an empty Warp kernel cache: the prebuilt kernels seeded into it), cold with
    nothing prebuilt (every module compiled), warm (the cache the first cold run left), and after `flightsim compile`
    of the same flags (``compile_s``) in another empty cache with nothing prebuilt; the last record times
    `flightsim compile --all` (every built-in instrument) in an empty cache with nothing prebuilt. A run record
    holds the medians of REPEATS runs."""
    device = resolve_device(device)
    with child_bytecode(), tempfile.TemporaryDirectory() as prime:  # the children's bytecode (this process: its own)
        _launch(device, Path(prime), "bytecode")
        return _records(device)


REPEATS = 3  # runs per cache state (each cold one in a cache of its own); the record holds their medians


def _records(device: str) -> list[dict]:
    """The records of :func:`startup`."""
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryDirectory() as ahead:
        colds = [Path(tmp) / f"cold{k}" for k in range(REPEATS)]
        records = [_median(device, colds, "cold")]
        records.append(_median(device, [Path(tmp) / f"bare{k}" for k in range(REPEATS)], "cold, nothing prebuilt",
                               NOT_PREBUILT))
        records.append(_median(device, colds[:1] * REPEATS, "warm"))
        compiled = _compile(device, Path(ahead), [])
        records.append({**_median(device, [Path(ahead)] * REPEATS, "compiled ahead", NOT_PREBUILT),
                        "compile_s": compiled})
    with tempfile.TemporaryDirectory() as every:
        records.append({"cache": "compile --all", "device": device, "compile_s": _compile(device, Path(every),
                                                                                        ["--all"])})
    return records


def _median(device: str, folders: list[Path], state: str, env_more: dict | None = None) -> dict:
    """One run in each of ``folders`` (its kernel cache and output there): the first run's record with the median
    of every time over the runs, and their count."""
    runs = [_launch(device, folder, state, env_more) for folder in folders]
    times = {key: float(np.median([r[key] for r in runs])) for key in ("cli_s", "first_ray_s", "exit_s")}
    files = [r["first_file_s"] for r in runs if r["first_file_s"] is not None]
    return {**runs[0], **times, "first_file_s": float(np.median(files)) if files else None, "runs": len(runs),
            "modules_compiled": max(r["modules_compiled"] for r in runs)}


NOT_PREBUILT = {"FLIGHTSIM_PREBUILT": "0"}  # Warp's kernel cache left as it is: every module compiled


def _compile(device: str, tmp: Path, flags: list[str]) -> float:
    """Seconds `flightsim compile` takes in the kernel cache under ``tmp``."""
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp / "kernels"), FLIGHTSIM_CACHE=str(tmp / "scenes"), **NOT_PREBUILT)
    command = [sys.executable, "-m", "flightsim", "compile", "--device", device, *flags]
    started = time.time()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"compile failed: {' '.join(command)}\n{done.stderr[-4000:]}")
    return time.time() - started


def _launch(device: str, tmp: Path, state: str, env_more: dict | None = None, tree: Path | None = None) -> dict:
    """One timed `flightsim simulate` in a fresh process, its kernel cache and output under ``tmp``; ``tree``: a
    source tree of flightsim to run instead of the installed one."""
    tag = state.replace(" ", "-").replace(",", "")
    tmp.mkdir(parents=True, exist_ok=True)
    out, timeline = tmp / f"run-{tag}", tmp / f"timeline-{tag}.txt"
    shutil.rmtree(out, ignore_errors=True)
    kernels = tmp / "kernels"
    env = dict(os.environ, WARP_CACHE_PATH=str(kernels), FLIGHTSIM_CACHE=str(tmp / "scenes"),
               FLIGHTSIM_TIMELINE=str(timeline), **(env_more or {}))
    if tree is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree), *filter(None, [os.environ.get("PYTHONPATH")])])
    command = [sys.executable, "-m", "flightsim", "simulate", "--device", device, "--duration", "1",
               "--out", str(out)]
    modules_before = _modules(kernels)
    started = time.time()
    done = subprocess.run(command, env=env, capture_output=True, text=True, cwd=tree)
    ended = time.time()
    if done.returncode != 0:
        raise RuntimeError(f"start-up run failed: {' '.join(command)}\n{done.stderr[-4000:]}")
    events = dict(line.split() for line in timeline.read_text().splitlines())
    tiles = list(out.rglob("*.las"))
    return {"cache": state, "device": device, "command": "flightsim " + " ".join(command[3:-1]),
            "cli_s": float(events["cli"]) - started, "first_ray_s": float(events["first_ray"]) - started,
            "first_file_s": min(t.stat().st_mtime for t in tiles) - started if tiles else None,
            "exit_s": ended - started, "bytecode": True,
            "modules_compiled": _modules(kernels) - modules_before}


def _modules(cache: Path) -> int:
    """Modules compiled into a Warp kernel cache (a module Warp compiles leaves its generated source beside its
    binary; a prebuilt one has none)."""
    return sum(1 for folder in cache.glob("*/wp_*") if any(folder.glob("*.cpp")) or any(folder.glob("*.cu")))
