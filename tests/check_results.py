#!/usr/bin/env python3
"""Whether the committed results are what the code writes now: each report under ``results/`` names the command
that regenerates it (its line ``Regenerate: `flightsim ...```); this script runs those commands into a temporary
folder and compares what they write with the committed files, the way ``pin_products.py`` compares products
(JSON without its volatile keys, CSV rows, HDF5 datasets, LAS bytes; figures not compared). Markdown reports are
compared without their ``Regenerate:`` line and with their timings masked (``TIMING``). Run as a script, the commands
run in this process's environment as it was before ``pin_products`` imported ``same_bits`` (whose NumPy and OpenBLAS
kernels round differently from a user's run, which wrote the results); under the test suite, whose conftest sets
them first, in the suite's.

Each command's numbers are summed up as: equal; differing only in round-off (every differing number within
``--rel`` of the committed one); or differing (the first lines of the differences). Commands for a GPU
(``--device cuda``, unless ``--gpu``) and the benchmark (its timings) are listed, not run.

    python3 tests/check_results.py                      # every report (~50 min on 2 cores: spad's 16, tls 22)
    python3 tests/check_results.py --only spaceborne    # reports whose path holds the text
    python3 tests/check_results.py --out results/freshness.md
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

USER_ENV = dict(os.environ)  # the commands run as a user runs them: without what same_bits (below) sets
sys.path.insert(0, str(Path(__file__).resolve().parent))
import pin_products  # noqa: E402  (the same digests as the product pins)

ROOT = Path(__file__).resolve().parent.parent
REGENERATE = re.compile(r"^Regenerate: `(flightsim [^`]+)`", re.MULTILINE)
IGNORED_KEYS = {"command", "device_s", "numpy_s"}  # the echo of the command line (it names the output folder); timings
GPU = "--device cuda"
NOT_RUN = {GPU: "needs a GPU (--gpu runs it)", "flightsim bench": "timings, compared only as ratios in one run"}


def commands(only: str | None) -> list[tuple[Path, str]]:
    """(report, command) of every report under results/ that names its command."""
    found = []
    for report in sorted((ROOT / "results").rglob("*.md")):
        match = REGENERATE.search(report.read_text(encoding="utf-8"))
        if match and (only is None or only in str(report.relative_to(ROOT))):
            found.append((report, match.group(1)))
    return found


def _redirected(command: str, out: Path) -> tuple[list[str], Path]:
    """The command's arguments with its ``--out DIR`` pointed at ``out``, and the committed DIR."""
    args = shlex.split(command)[1:]
    at = args.index("--out")
    committed = ROOT / args[at + 1]
    args[at + 1] = str(out)
    return args, committed


TIMING = re.compile(r"\d[\d.,]*(?:e[+-]?\d+)? (?:s\b|[\w-]+/s\b)")  # "3.84 s", "2,067 draws/s"


def _report_text(path: Path) -> str:
    """A report's text without its Regenerate line and with its timings ("3.84 s", "2067 draws/s") masked."""
    return "\n".join(TIMING.sub("#", line) for line in path.read_text(encoding="utf-8").splitlines()
                     if not line.startswith("Regenerate:"))


def _numbers(a, b, path: str, out: dict) -> None:
    """Walk two digests side by side: the largest relative difference of their numbers, and the paths where
    anything else differs (a key, a string, a length)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in (k for k in a if k not in IGNORED_KEYS):
            if key in b:
                _numbers(a[key], b[key], f"{path}/{key}", out)
            else:
                out["other"].append(f"{path}/{key}: missing now")
        return
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            _numbers(x, y, f"{path}[{i}]", out)
        return
    x, y = _as_number(a), _as_number(b)
    if x is not None and y is not None:
        if x != y and not (math.isnan(x) and math.isnan(y)):
            rel = abs(x - y) / max(abs(x), abs(y))
            out["numbers"] += 1
            if rel > out["max_rel"]:
                out["max_rel"], out["worst"] = rel, f"{path}: {a} -> {b}"
        return
    if json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
        out["other"].append(f"{path}: {pin_products._short(a, 80)} -> {pin_products._short(b, 80)}")


def _as_number(value) -> float | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _shown(folder: Path) -> str:
    """A folder as a report names it: relative to the repository where it lies in it."""
    return str(folder.relative_to(ROOT)) if folder.is_relative_to(ROOT) else str(folder)


def _first_difference(rel: str, then: list[str], now: list[str]) -> str:
    """The report's name, its count of differing lines and the first of them, as committed and as written now."""
    pairs = [(a, b) for a, b in zip(then, now) if a != b] + [("", b) for b in now[len(then):]]
    pairs += [(a, "") for a in then[len(now):]]
    return f"{rel}: {len(pairs)} lines, the first `{pairs[0][0][:80]}` -> `{pairs[0][1][:80]}`"


TIME_KEYS = frozenset(k for k in pin_products.VOLATILE_KEYS  # durations: "wall_s", "scan_s", … (not "draws_per_s")
                      if k.endswith("_s") and not k.endswith("per_s"))


def _seconds(value, timed: bool = False) -> float:
    """The sum of the numbers under a JSON value's timing keys (``TIME_KEYS``, at any depth) [s]."""
    if isinstance(value, dict):
        return sum(_seconds(v, timed or k in TIME_KEYS) for k, v in value.items())
    if isinstance(value, list):
        return sum(_seconds(v, timed) for v in value)
    return float(value) if timed and isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0


def compare(committed: Path, written: Path) -> dict:
    """Differences of the files the command wrote that are committed too, and the JSON files' timings summed
    (``seconds``: committed, now)."""
    out = {"files": 0, "numbers": 0, "max_rel": 0.0, "worst": "", "other": [], "reports": [], "seconds": [0.0, 0.0]}
    for path in sorted(p for p in written.rglob("*") if p.is_file()):
        rel = str(path.relative_to(written))
        mine = committed / rel
        if not mine.is_file() or pin_products._matches(rel, pin_products.SKIP):
            continue
        out["files"] += 1
        if path.suffix == ".md":
            now, then = _report_text(path).replace(str(written), _shown(committed)), _report_text(mine)
            if now != then:
                out["reports"].append(_first_difference(rel, then.splitlines(), now.splitlines()))
            continue
        if path.suffix == ".json":
            for i, file in enumerate((mine, path)):
                out["seconds"][i] += _seconds(json.loads(file.read_text(encoding="utf-8")))
        _numbers(pin_products.digest_file(mine, rel, committed), pin_products.digest_file(path, rel, written),
                 rel, out)
    return out


def rerun(command: str) -> dict:
    """Run a report's command into a temporary folder: its time [s], exit status, error output and the
    differences (:func:`compare`) of what it wrote from the committed files."""
    with tempfile.TemporaryDirectory() as tmp:
        args, committed = _redirected(command, Path(tmp) / "out")
        start = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "flightsim", *args], cwd=ROOT, capture_output=True, text=True,
                             env=USER_ENV)
        seconds = time.perf_counter() - start
        d = compare(committed, Path(tmp) / "out") if run.returncode == 0 else {}
    return {"run_s": seconds, "returncode": run.returncode, "stderr": run.stderr, **d}


def check(report: Path, command: str, rel_tol: float, gpu: bool) -> str:
    """One table row: the report, its command, the run's time, its timings against the committed ones and what
    differs."""
    name = str(report.relative_to(ROOT))
    reason = next((why for text, why in NOT_RUN.items() if text in command and not (gpu and text == GPU)), None)
    if reason:
        return f"| {name} | `{command}` | - | - | not run: {reason} |"
    d = rerun(command)
    then, now = d.get("seconds", (0.0, 0.0))
    head = f"| {name} | `{command}` | {d['run_s']:.0f} | {f'{now / then:.2f}' if then > 0 else '-'} |"
    if d["returncode"] != 0:
        return f"{head} failed (exit {d['returncode']}): {d['stderr'][-200:]} |"
    if d["other"] or d["reports"] or d["max_rel"] > rel_tol:
        state = f"**differs**: {d['numbers']} numbers (largest relative {d['max_rel']:.1e}, {d['worst']})"
        state += "".join(f"; {line}" for line in d["other"][:3])
        state += f"; {len(d['other'])} other values" if len(d["other"]) > 3 else ""
        state += "".join(f"; report {r}" for r in d["reports"])
    elif d["numbers"]:
        state = f"round-off: {d['numbers']} numbers within {d['max_rel']:.1e}"
    else:
        state = "equal"
    return f"{head} {state} ({d['files']} files) |"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="only reports whose path holds this text")
    parser.add_argument("--rel", type=float, default=1e-9, help="round-off: the largest relative difference")
    parser.add_argument("--gpu", action="store_true", help="run the commands for a GPU too")
    parser.add_argument("--out", type=Path, help="also write the table to this Markdown file")
    a = parser.parse_args(argv)
    rows = ["| report | command | run [s] | its timings ÷ the committed | against the committed files |",
            "| --- | --- | --- | --- | --- |"]
    for report, command in commands(a.only):
        rows.append(check(report, command, a.rel, a.gpu))
        print(rows[-1], flush=True)
    if a.out:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        a.out.write_text(f"# The committed results against a rerun of their commands\n\n`python3 tests/check_results.py"
                         f"{' --only ' + a.only if a.only else ''}` at {head.stdout.strip()}, this machine.\n\n"
                         + "\n".join(rows) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
