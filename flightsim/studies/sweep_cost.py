"""What one configuration of the seed paper's study costs in one process, set-up and host work included.

``python3 -m flightsim.studies.sweep_cost --device D [--configs N] [--duration S] [--separate-edge-grids]
[--profile]``: the study's grid (250 configurations over the calibration field), a few configurations run first
untimed (scene, BVH, kernels), then N of them timed one after another as a sweep's worker runs them
(``run_configuration``, one :class:`~flightsim.studies.sweep.SceneCache`), each flying the paper's 10 s or ``S``;
prints the mean wall per configuration [ms]. ``--separate-edge-grids`` gives each edge cap a grid of its own
(``meshes.EDGE_GRID_SPAN`` 1), as before grids were shared across caps; ``--profile`` adds cProfile's heaviest calls.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time

from flightsim.engine import meshes
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.studies.bench_common import sizes
from flightsim.studies.sweep import AXIS_KEYS, SceneCache, SweepGrid, run_configuration

GRID = dict(zip(AXIS_KEYS, sizes("cuda", quick=False).study_grid))  # the study's, as `flightsim bench` sweeps it
WARM = 5  # configurations run first, untimed


def per_configuration_s(device: str, configs: int, duration_s: float | None = None,
                        profile: bool = False) -> tuple[float, str]:
    """(mean wall per configuration [s], cProfile's report or "") over ``configs`` configurations of the grid, each
    flying ``duration_s`` (None: the study's own)."""
    base = RunConfig()
    for key, value in {"scene.name": "calibration", "run.device": device, "flight.duration_s": duration_s}.items():
        if value is not None:
            set_value(base, key, value)
    grid = SweepGrid(validate(base), [(AXIS_KEYS[column], values) for column, values in GRID.items()]).configurations()
    scenes = SceneCache(cfg for _, cfg in grid)
    for labels, cfg in grid[:WARM]:
        run_configuration(labels, cfg, scenes)
    timed = grid[WARM:WARM + configs]
    profiler = cProfile.Profile() if profile else None
    started = time.perf_counter()
    if profiler:
        profiler.enable()
    for labels, cfg in timed:
        run_configuration(labels, cfg, scenes)
    if profiler:
        profiler.disable()
    wall = (time.perf_counter() - started) / len(timed)
    report = io.StringIO()
    if profiler:
        pstats.Stats(profiler, stream=report).sort_stats("cumulative").print_stats(30)
    return wall, report.getvalue()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m flightsim.studies.sweep_cost", description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--configs", type=int, default=100, help="configurations timed (at most 245)")
    parser.add_argument("--duration", type=float, help="seconds flown per configuration (default: the study's 10)")
    parser.add_argument("--separate-edge-grids", action="store_true", help="a grid per edge cap, none shared")
    parser.add_argument("--profile", action="store_true", help="cProfile's heaviest calls too")
    args = parser.parse_args(argv)
    if args.separate_edge_grids:
        meshes.EDGE_GRID_SPAN = 1.0
    wall, report = per_configuration_s(args.device, args.configs, args.duration, args.profile)
    grids = "a grid per edge cap" if args.separate_edge_grids else "edge grids shared"
    print(f"{args.device}: {wall * 1e3:.1f} ms per configuration ({args.configs} configurations, {grids})")
    print(report, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
