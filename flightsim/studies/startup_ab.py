"""Warm start-up of flightsim source trees side by side: `flightsim simulate` (the default scene and instrument,
1 s of flight) from each tree in turn, alternating the order every round, to its command line parsed, its first
trace launch, its first LAS tile and its exit (as the bench's start-up section times them). A machine's load comes
and goes in bursts longer than one run: only trees timed in one such session compare, and the lower quartile and
the least of each time say more than a mean.

    python3 -m flightsim.studies.startup_ab --device cuda:0 --runs 20 /path/to/old/tree /path/to/new/tree

Each tree keeps its own bytecode folder (a tree's modules are otherwise compiled again whenever the other ran last);
the kernel cache is shared and warmed by a first, untimed run of each tree."""
from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from flightsim.studies.bench_startup import _launch

TIMES = ("cli_s", "first_ray_s", "first_file_s", "exit_s")


def compare(device: str, runs: int, trees: list[Path]) -> dict[Path, list[dict]]:
    """``runs`` timed runs of each tree, alternating; {tree: its records}."""
    records: dict[Path, list[dict]] = {tree: [] for tree in trees}
    with tempfile.TemporaryDirectory() as tmp:
        place = Path(tmp)

        def launch(tree: Path) -> dict:
            bytecode = {"PYTHONPYCACHEPREFIX": str(place / f"bytecode-{trees.index(tree)}"),
                        "PYTHONDONTWRITEBYTECODE": ""}  # empty: bytecode written and read
            return _launch(device, place, "warm", bytecode, tree)

        for tree in trees:
            launch(tree)  # the bytecode and the kernel cache
        for k in range(runs):
            for tree in trees if k % 2 == 0 else trees[::-1]:
                records[tree].append(launch(tree))
    return records


def table(records: dict[Path, list[dict]]) -> str:
    """A markdown table: each tree's median, lower quartile and least of every time [s]."""
    head = "| tree | runs | " + " | ".join(f"{t} median / p25 / min [s]" for t in TIMES) + " |"
    lines = [head, "|" + " --- |" * (len(TIMES) + 2)]
    for tree, rows in records.items():
        cells = []
        for t in TIMES:
            values = [r[t] for r in rows]
            quartile = statistics.quantiles(values, n=4)[0] if len(values) > 1 else values[0]
            cells.append(f"{statistics.median(values):.3f} / {quartile:.3f} / {min(values):.3f}")
        lines.append(f"| {tree} | {len(rows)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--runs", type=int, default=12)
    parser.add_argument("trees", nargs="+", type=Path)
    args = parser.parse_args(argv)
    print(table(compare(args.device, args.runs, [t.resolve() for t in args.trees])))


if __name__ == "__main__":
    main()
