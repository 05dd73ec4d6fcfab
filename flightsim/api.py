"""The public Python API: what notebooks and scripts call; the command line is a thin layer over it.

    import flightsim
    cfg = flightsim.load_config(instrument="change3", overrides={"scene.name": "lunar"})
    result = flightsim.simulate(cfg)          # points in memory
    result.points["exact"]                    # (n, 3) world coordinates [m]
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from flightsim.engine.config import RunConfig, copy_config, set_value, validate
from flightsim.engine.config_io import from_dict, load_toml, preset_config


def load_config(source: str | Path | Mapping | RunConfig | None = None, *, instrument: str | None = None,
                overrides: Mapping[str, Any] | None = None) -> RunConfig:
    """A validated run config.

    source: a TOML path, a dict of tables ({"flight": {"altitude_m": 700}}), a RunConfig, or None;
    it is laid over the built-in ``instrument`` ("risley", the default, or "change3"); then each
    ``overrides`` item {"section.field": value} is set. Raises InputError naming a bad field.
    """
    base = preset_config(instrument or "risley")
    if isinstance(source, RunConfig):
        cfg = copy_config(source)
    elif isinstance(source, Mapping):
        cfg = from_dict(dict(source), base)
    elif source is not None:
        cfg = load_toml(source, base)
    else:
        cfg = base
    for key, value in (overrides or {}).items():
        set_value(cfg, key, value)
    return validate(cfg)


@dataclass
class SimulationResult:
    """The returns of a run, in memory (world coordinates in float64)."""

    points: dict[str, np.ndarray]  # georeferencing model -> (n, 3) world E, N, H [m]
    true_points: np.ndarray | None  # (n, 3) true hits, world [m] (with_truth)
    line: np.ndarray  # (n,) flight line id
    pulse: np.ndarray  # (n,) pulse index within its line
    beam: np.ndarray  # (n,) beam index (DOE i·n + j, or channel)
    range_m: np.ndarray  # (n,) observed one-way range [m]
    counts: Any  # flightsim.engine.tracer.RunCounts
    scene: Any  # flightsim.scenes.scene.Scene


def simulate(cfg: RunConfig, out: str | Path | None = None, with_truth: bool = False,
             progress: Callable[[int, int], None] | None = None, overwrite: bool = False):
    """Run a validated config. With ``out``: write LAS tiles, run.toml and summary.json there and return
    the summary (as ``flightsim simulate``); without: return a :class:`SimulationResult`."""
    if out is not None:
        from flightsim.engine.run import simulate_to_directory

        return simulate_to_directory(cfg, Path(out), overwrite=overwrite, progress=progress)
    from flightsim.engine.readouts.points import Points
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene), with_truth=with_truth)
    parts = []
    counts = sim.run(Points(), parts.append, progress)
    join = (lambda get: np.concatenate([get(p) for p in parts]) if parts else np.empty(0))
    points = {m: scene.local_to_world(join(lambda p: p.points[m]).reshape(-1, 3)) for m in sim.models}
    truth = scene.local_to_world(join(lambda p: p.true_points).reshape(-1, 3)) if with_truth else None
    return SimulationResult(points, truth, join(lambda p: np.full(len(p), p.line_id)), join(lambda p: p.pulse),
                            join(lambda p: p.beam), join(lambda p: p.range_m), counts, scene)


def sweep(base: RunConfig, axes: Mapping[str, list], out: str | Path, overwrite: bool = False) -> Path:
    """Plane-fit RMS over the grid of ``axes`` {"section.field": [values]} (statistics mode, no LAS);
    writes the sweep table under ``out`` (resumable) and returns its path."""
    from flightsim.studies.sweep import SweepGrid, run_sweep

    grid = SweepGrid(base, [(key, list(values)) for key, values in axes.items()])
    grid.configurations()
    return run_sweep(grid, Path(out), overwrite=overwrite)


def budget(out: str | Path, device: str = "cpu", draws: int = 200, columns: int | None = None) -> dict:
    """The Chang'e-3 imager's full-link error budget (``flightsim budget``); returns its numbers."""
    from flightsim.studies.budget_report import run_budget

    return run_budget(Path(out), device=device, draws=draws, columns=columns)
