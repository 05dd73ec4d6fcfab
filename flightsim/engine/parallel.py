"""One run's statistics split over several CPU processes.

Warp runs a CPU launch on one thread, so a CPU run uses more cores by giving each process every
n-th chunk of pulses (:meth:`Tracer.run_statistics` ``share``) and adding the per-plane sums.
Workers are started once and keep their scene, BVH and kernels for every task they get.
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

from flightsim.engine.config import RunConfig, validate
from flightsim.engine.config_io import from_dict, to_toml
from flightsim.scoring.planes import PlaneMoments
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.tracer import RunCounts

_worker_state: dict = {}


def _simulator(cfg_toml: str):
    """This process's simulator for a config, built on first use and kept."""
    import tomllib

    from flightsim.engine.world import edge_buffer_m
    from flightsim.engine.world import build_scene, flight_trajectories
    from flightsim.engine.tracer import Tracer

    if _worker_state.get("key") != cfg_toml:
        cfg = validate(from_dict(tomllib.loads(cfg_toml)))
        scene = build_scene(cfg)
        _worker_state["key"] = cfg_toml
        _worker_state["sim"] = Tracer(cfg, scene, flight_trajectories(cfg, scene), edge_buffer_m=edge_buffer_m(cfg))
    return _worker_state["sim"]


def _share(cfg_toml: str, share: tuple[int, int]):
    moments, counts = run_statistics(_simulator(cfg_toml), share=share)
    return {m: (v.count, v.first, v.second) for m, v in moments.items()}, counts


def _warm(cfg_toml: str) -> None:
    """Build the simulator and compile its kernels (runs the first chunk only)."""
    sim = _simulator(cfg_toml)
    run_statistics(sim, share=(0, 1 << 30))


class ProcessPool:
    """Worker processes (spawned: Warp and fork do not mix) that split statistics runs."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))

    def warm(self, cfg: RunConfig) -> None:
        """Make every worker build the config's simulator (outside any timing)."""
        text = to_toml(cfg)
        list(self.pool.map(_warm, [text] * self.workers))

    def run_statistics(self, cfg: RunConfig, references) -> tuple[dict[str, PlaneMoments], RunCounts, float]:
        """(moments, counts, wall [s]) of a run split over the workers; wall is the slowest worker's
        own run time (the workers run at the same time), without the hand-over between processes."""
        text = to_toml(cfg)
        parts = list(self.pool.map(_share, [text] * self.workers, [(k, self.workers) for k in range(self.workers)]))
        wall = max(part.wall_s for _, part in parts)
        moments: dict[str, PlaneMoments] = {}
        counts = RunCounts()
        for sums, part in parts:
            for model, (count, first, second) in sums.items():
                moments.setdefault(model, PlaneMoments(references)).add_sums(count, first, second)
            for name in ("pulses", "pulses_culled", "beams_fired", "returns", "tir_dropped", "misses", "edge_excluded"):
                setattr(counts, name, getattr(counts, name) + getattr(part, name))
        counts.wall_s = wall
        return moments, counts, wall

    def close(self) -> None:
        self.pool.shutdown()
