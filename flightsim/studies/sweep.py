"""`flightsim sweep`: plane-fit RMS over a cartesian grid of configurations (the seed paper's study).

A sweep asks only for RMS, so every configuration runs in statistics mode: the kernels reduce
the returns to per-plane moments on the device, no LAS is written and no per-point array is
kept. Scenes and their BVHs are built once per distinct scene and shared by all configurations.

Resumable: each finished configuration writes its rows to ``DIR/rows/<key>.json`` atomically and
``sweep.csv`` / ``planes.csv`` are regenerated from the finished rows (every few seconds while the
sweep runs, and when it ends, also by an error), so a crash loses at most the configurations in
flight and a rerun skips what is done, never duplicating a row.

Given a Dask client, the configurations run as tasks on its workers (:mod:`flightsim.engine.distributed`)
and the client records each one's rows as it finishes, exactly as the serial loop does.
"""
from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from flightsim.engine.config import RunConfig, canonical_key, config_dict, copy_config, get_value, set_value, validate
from flightsim.engine.config_io import to_toml
from flightsim.engine.distributed import run_batches, worker_device
from flightsim.engine.world import edge_buffer_m
from flightsim.core.errors import InputError
from flightsim.core.atomic import save_figure, write_atomic

SPEC_COLUMNS = ["altitude_m", "array", "spacing_mrad"]
AXIS_KEYS = {"altitude_m": "flight.altitude_m", "array": "fan.array", "spacing_mrad": "fan.spacing_mrad"}
ROW_CORE = ["model", "rms_m", "points"]  # the SPEC's columns after the axes
ROW_MORE = ["returns", "planes", "edge_buffer_m", "wall_s"]
PLANE_TAIL = ["model", "plane_id", "kind", "n", "rms_m", "pitch_deg", "azimuth_deg"]
TABLES_INTERVAL_S = 2.0  # sweep.csv is regenerated at most this often while a sweep runs [s]; planes.csv (the
# paper's study: 23,500 rows, ~0.4 s to write on an H100 host) once its rows are all in, or the sweep stops


@dataclass
class SweepGrid:
    """A base config and the axes swept over it: (dotted config key, values) in order."""

    base: RunConfig
    axes: list[tuple[str, list]]
    _made: tuple[str, list] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.axes = [(canonical_key(key), list(values)) for key, values in self.axes]

    @property
    def columns(self) -> list[str]:
        """Column names of the axes: the SPEC's three, then any other swept setting."""
        return SPEC_COLUMNS + self.extra_columns

    @property
    def extra_columns(self) -> list[str]:
        return [key for key, _ in self.axes if key not in AXIS_KEYS.values()]

    def configurations(self) -> list[tuple[dict, RunConfig]]:
        """Every (axis values, validated config) of the grid, the first axis varying slowest (made and checked once:
        a grid of 250 configurations takes ~0.3 s; the list is the caller's, its configs shared)."""
        identity = self._identity()
        if self._made is None or self._made[0] != identity:
            self._made = (identity, self._make())
        return list(self._made[1])

    def _identity(self) -> str:
        """What the configurations are made from: the base config and the axes (either may be changed)."""
        return json.dumps({"axes": self.axes, "base": config_dict(self.base)}, sort_keys=True, default=str)

    def _make(self) -> list[tuple[dict, RunConfig]]:
        out = []
        keys = [key for key, _ in self.axes]
        for values in itertools.product(*(values for _, values in self.axes)):
            cfg = copy_config(self.base)
            for key, value in zip(keys, values):
                set_value(cfg, key, value)
            cfg = validate(cfg)
            out.append((self._labels(cfg), cfg))
        return out

    def _labels(self, cfg: RunConfig) -> dict:
        labels = {column: get_value(cfg, AXIS_KEYS[column]) for column in SPEC_COLUMNS}
        for column in self.columns[len(SPEC_COLUMNS):]:
            labels[column] = get_value(cfg, column)
        return labels


def config_key(cfg: RunConfig) -> str:
    """Stable identity of a configuration: a hash of its resolved TOML."""
    return hashlib.sha256(to_toml(cfg).encode()).hexdigest()[:20]


def parse_axis(flag: str, text: str) -> list[str]:
    """Comma-separated values of a sweep flag; an empty item is an error."""
    values = [v.strip() for v in str(text).split(",")]
    if not values or any(not v for v in values):
        raise InputError(flag, text, "a comma-separated list of values, e.g. 500,1000,1500")
    return values


# ---------------------------------------------------------------------------------------------
# one configuration


class SceneCache:
    """Scenes and their device BVHs, built once per distinct scene of a sweep.

    Each scene's ground is as wide as the widest flight of ``configs`` needs (``extent``, by scene
    key), so that every configuration of a sweep flies over the same scene. A worker process of a
    distributed sweep keeps one cache for all its tasks and is given the extents with each task.
    """

    def __init__(self, configs: Iterable[RunConfig] = ()):
        from flightsim.engine.world import scene_half_extent

        self.extent: dict[str, float] = {}
        for cfg in configs:
            key = self.scene_key(cfg)
            self.extent[key] = max(self.extent.get(key, 0.0), scene_half_extent(cfg))
        self.built: dict[tuple[str, float | None, str], tuple] = {}

    @staticmethod
    def scene_key(cfg: RunConfig) -> str:
        """Identity of a config's scene (its ``scene`` section)."""
        return json.dumps(cfg.scene.values(), sort_keys=True)

    def get(self, cfg: RunConfig, device: str):
        """(Scene, SceneMeshes) for a config's scene on ``device``."""
        from flightsim.engine.world import build_scene
        from flightsim.engine.meshes import SceneMeshes

        scene_key = self.scene_key(cfg)
        key = (scene_key, self.extent.get(scene_key), device)
        if key not in self.built:
            scene = build_scene(cfg, key[1])
            self.built[key] = (scene, SceneMeshes(scene, device))
        return self.built[key]


def configuration_tracer(cfg: RunConfig, scenes: SceneCache):
    """The tracer of one configuration in statistics mode, over its scene from ``scenes``, with the automatic edge
    buffer (:func:`flightsim.engine.world.edge_buffer_m`)."""
    from flightsim.engine.world import flight_trajectories
    from flightsim.engine.tracer import Tracer
    from flightsim.core.warp_runtime import resolve_device

    scene, meshes = scenes.get(cfg, resolve_device(cfg.run.device))
    return Tracer(cfg, scene, flight_trajectories(cfg, scene), edge_buffer_m=edge_buffer_m(cfg), meshes=meshes)


def compile_configuration(cfg: RunConfig) -> int:
    """Compile into Warp's kernel cache (or load from it) every kernel a sweep configuration of ``cfg`` launches,
    without flying it (``flightsim compile --for sweep``); returns the modules."""
    from flightsim.core.warp_runtime import compile_ahead
    from flightsim.engine.readouts.statistics import Statistics

    tracer = configuration_tracer(cfg, SceneCache([cfg]))
    kernels = tracer.kernels_needed(Statistics())
    compile_ahead(tracer.device, kernels)
    return len({id(k.module) for k in kernels})


def run_configuration(labels: dict, cfg: RunConfig, scenes: SceneCache) -> dict:
    """Simulate one configuration in statistics mode; return its sweep and plane rows."""
    from flightsim.scoring.planes import pooled_rms
    from flightsim.engine.readouts.statistics import run_statistics

    started = time.perf_counter()
    simulator = configuration_tracer(cfg, scenes)
    scene, buffer = simulator.scene, simulator.edge_buffer_m
    moments, counts = run_statistics(simulator)
    wall = time.perf_counter() - started
    rows, planes = [], []
    for model, m in moments.items():
        fits = m.fits()
        used = sum(f.n for f in fits)
        rms = pooled_rms(fits)
        rows.append({**labels, "model": model, "rms_m": rms if used else "", "points": used,
                     "returns": counts.returns, "planes": len(fits), "edge_buffer_m": buffer, "wall_s": wall})
        for f in fits:
            planes.append({**labels, "model": model, "plane_id": f.plane_id, "kind": scene.planes[f.plane_id].kind,
                           "n": f.n, "rms_m": f.rms_m, "pitch_deg": f.pitch_deg, "azimuth_deg": f.azimuth_deg})
    return {"rows": rows, "planes": planes}


_scenes: SceneCache | None = None  # a worker process's scenes, kept across the tasks it runs


def configuration_task(items: list[tuple[dict, RunConfig]], extents: dict[str, float]) -> list[dict]:
    """Worker side: run a batch of sweep configurations on this worker's device with this process's scenes,
    built as wide as the sweep's ``extents`` (:class:`SceneCache`) so that they equal the serial path's."""
    global _scenes
    if _scenes is None:
        _scenes = SceneCache()
    _scenes.extent.update(extents)
    return [run_configuration(labels, worker_device(cfg), _scenes) for labels, cfg in items]


# ---------------------------------------------------------------------------------------------
# the sweep directory


class SweepDirectory:
    """Finished rows of a sweep on disk, and the tables made from them."""

    def __init__(self, path: Path, description: str, overwrite: bool = False):
        """Open ``path`` for the sweep described by ``description`` (its sweep.json text).

        A directory is reused when it is new or empty, holds this same sweep (resume), or when
        ``overwrite`` is given; one holding other files or another sweep is refused.
        """
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise InputError("--out", str(self.path), "a directory (this path is a file)")
        ours = {"rows", "sweep.csv", "planes.csv", "sweep.json"}
        if self.path.is_dir():
            for leftover in self.path.glob(".*.part"):  # temporaries of a killed run
                leftover.unlink()
            present = {p.name for p in self.path.iterdir() if not p.name.endswith(".png")}
            previous = self.path / "sweep.json"
            other_sweep = previous.is_file() and previous.read_text(encoding="utf-8") != description
            if overwrite:
                for name in present & ours:
                    target = self.path / name
                    shutil.rmtree(target) if target.is_dir() else target.unlink()
            elif present - ours or other_sweep:
                raise InputError("--out", str(self.path),
                                 "a new directory, or one holding this sweep to resume (pass --overwrite to replace it)")
        try:
            (self.path / "rows").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError("--out", str(self.path), f"a directory that can be created ({exc.strerror})") from None
        write_atomic(self.path / "sweep.json", description)
        self._results: dict[Path, dict] = {}  # finished rows read or recorded by this process
        self._files: dict[int, tuple[RunConfig, Path]] = {}  # row_file's, by config object

    def row_file(self, cfg: RunConfig) -> Path:
        """The file of a configuration's rows, named by :func:`config_key` (a hash of its TOML: ~1 ms, asked for five
        times a configuration, so kept per config object; the sweep's configs are not changed once made)."""
        made = self._files.get(id(cfg))
        if made is None or made[0] is not cfg:
            made = self._files[id(cfg)] = (cfg, self.path / "rows" / f"{config_key(cfg)}.json")
        return made[1]

    def done(self, cfg: RunConfig) -> bool:
        return self.row_file(cfg).is_file()

    def record(self, cfg: RunConfig, result: dict) -> None:
        path = self.row_file(cfg)
        write_atomic(path, json.dumps(result))
        self._results[path] = json.loads(json.dumps(result))  # as a reader of the file would see it

    def _result(self, path: Path) -> dict:
        if path not in self._results:
            self._results[path] = json.loads(path.read_text())
        return self._results[path]

    def write_tables(self, grid: SweepGrid, configs: list[tuple[dict, RunConfig]], planes: bool = True) -> None:
        """Regenerate sweep.csv (and planes.csv, unless ``planes`` is False) from the finished rows, in grid order."""
        rows, plane_rows = [], []
        for _, cfg in configs:
            path = self.row_file(cfg)
            if path.is_file():
                result = self._result(path)
                rows += result["rows"]
                plane_rows += result["planes"]
        write_atomic(self.path / "sweep.csv", _csv(SPEC_COLUMNS + ROW_CORE + grid.extra_columns + ROW_MORE, rows))
        if planes:
            write_atomic(self.path / "planes.csv", _csv(grid.columns + PLANE_TAIL, plane_rows))


def _csv(columns: list[str], rows: list[dict]) -> str:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row.get(k, "")) for k in columns})
    return text.getvalue()


def _cell(value):
    return repr(value) if isinstance(value, float) else value


def run_sweep(grid: SweepGrid, out: Path, overwrite: bool = False,
              progress: Callable[[int, int], None] | None = None, client=None, batch: int = 1) -> Path:
    """Run every unfinished configuration of the grid; return the path of sweep.csv.

    Serially in this process by default; with a Dask ``client`` (and more than one configuration
    to run) as tasks of ``batch`` configurations each on its workers, recording each finished
    configuration as its result streams back.
    """
    configs = grid.configurations()
    description = json.dumps({"axes": grid.axes, "base": config_dict(grid.base)}, indent=2, default=str)
    directory = SweepDirectory(out, description, overwrite)
    scenes = SceneCache(cfg for _, cfg in configs)
    todo = [(labels, cfg) for labels, cfg in configs if not directory.done(cfg)]
    last_tables = time.perf_counter()
    try:
        for k, (cfg, result) in enumerate(_results(todo, scenes, client, batch)):
            directory.record(cfg, result)
            if time.perf_counter() - last_tables >= TABLES_INTERVAL_S:
                directory.write_tables(grid, configs, planes=False)
                last_tables = time.perf_counter()
            if progress:
                progress(k + 1, len(todo))
    finally:
        directory.write_tables(grid, configs)
    return directory.path / "sweep.csv"


def _results(todo: list[tuple[dict, RunConfig]], scenes: SceneCache, client, batch: int):
    """(config, result) of each configuration to run, as each finishes."""
    if client is None or len(todo) <= 1:
        for labels, cfg in todo:
            yield cfg, run_configuration(labels, cfg, scenes)
    else:
        for (_labels, cfg), result in run_batches(client, configuration_task, todo, scenes.extent, batch=batch,
                                                  name="configurations"):
            yield cfg, result


def plot_sweep(sweep_csv: Path, out_dir: Path) -> list[Path]:
    """One PNG per swept axis: RMS against that axis for each model, the other axes at their first value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(sweep_csv, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["rms_m"]]
    if not rows:
        return []
    axes = [c for c in rows[0] if c not in ROW_CORE + ROW_MORE]
    varying = [c for c in axes if len({r[c] for r in rows}) > 1]
    paths = []
    for column in varying:
        fixed = {c: rows[0][c] for c in axes if c != column}
        fig, ax = plt.subplots(figsize=(6, 4))
        for model in sorted({r["model"] for r in rows}):
            sel = [r for r in rows if r["model"] == model and all(r[c] == v for c, v in fixed.items())]
            sel.sort(key=lambda r: float(r[column]))
            ax.plot([float(r[column]) for r in sel], [float(r["rms_m"]) for r in sel], "o-", label=model)
        ax.set_xlabel(column)
        ax.set_ylabel("plane-fit RMS [m]")
        ax.set_title(f"RMS vs {column} ({', '.join(f'{c}={v}' for c, v in fixed.items())})", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend()
        path = Path(out_dir) / f"rms_vs_{column.replace('.', '_')}.png"
        fig.tight_layout()
        save_figure(fig, path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths
