"""Where a forest ALS run's time goes: the bench's forest run (:func:`flightsim.studies.bench_forest.forest_tracer`)
as it is, without a blind stretch after a return (one detector event a return, not two), with a threshold no echo
reaches (no event, no return: the walk and the set-up alone), and with other register caps or chunk sizes; one scene
for all, each the best of three timed runs after one that compiles::

    python3 -m flightsim.studies.forest_events --device cuda
    python3 -m flightsim.studies.forest_events --device cuda --variants "as is,registers 85,chunk 4x"
"""
from __future__ import annotations

import argparse
import sys

import warp as wp

from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.studies.bench_forest import forest_config

VARIANTS = {"as is": {}, "no blind stretch": {"discrete.min_separation_m": 0.0},
            "no echo reaches the threshold": {"discrete.threshold": 1.0},
            "registers 85": {"run.max_registers": 85}, "registers 128": {"run.max_registers": 128},
            "chunk 2x": {"run.chunk_pulses": 186413}, "chunk 4x": {"run.chunk_pulses": 372827}}
"""Each variant's settings over the bench's forest run (the chunks: multiples of its default, 2²² slots of 45)."""


def forest_events(device: str, beams: float, size_m: float, variants: list[str], runs: int = 3) -> list[dict]:
    """Per variant: its beams, returns and the best wall [s] of ``runs`` timed runs (after one that compiles)."""
    scene = build_scene(forest_config(device, 3.0, beams, size_m))
    rows = []
    for name in variants:
        cfg = forest_config(device, 3.0, beams, size_m, **VARIANTS[name])
        tracer = Tracer(cfg, scene, flight_trajectories(cfg, scene))
        walls = []
        for _ in range(runs + 1):
            wp.synchronize_device(tracer.device)
            counts = tracer.run(Points(on_device=True), consume=lambda returns: None)
            walls.append(counts.wall_s)
        rows.append({"variant": name, "beams": counts.beams_fired, "returns": counts.returns,
                     "wall_s": min(walls[1:])})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--beams", type=float, default=5e7, help="beams of the run (default: the bench's 5e7)")
    parser.add_argument("--size-m", type=float, default=1000.0, help="the stand's side [m]")
    parser.add_argument("--variants", default="as is,no blind stretch,no echo reaches the threshold",
                        help="comma-separated, of: " + ", ".join(VARIANTS))
    args = parser.parse_args(argv)
    names = args.variants.split(",")
    unknown = [name for name in names if name not in VARIANTS]
    if unknown:
        print(f"forest_events: unknown variants {unknown}: the variants are {', '.join(VARIANTS)}", file=sys.stderr)
        return 2
    print("| the forest run | beams | returns | wall [ms] |\n| --- | --- | --- | --- |")
    for row in forest_events(args.device, args.beams, args.size_m, names):
        print(f"| {row['variant']} | {row['beams']:,} | {row['returns']:,} | {row['wall_s'] * 1e3:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
