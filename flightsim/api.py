"""The public Python API: what notebooks and scripts call; the command line is a thin layer over it.

    import flightsim
    cfg = flightsim.load_config(instrument="change3", overrides={"scene.name": "lunar"})
    result = flightsim.simulate(cfg)          # every product of the run
    result.points["exact"]                    # laspy.LasData: the exact model's LAS points
    result.stats["rms_m"]                     # what summary.json holds
    result.write("run")                       # exactly what `flightsim simulate --out run` writes

A run always goes through the products the command line writes; without ``out`` they are written to a temporary
directory that lives as long as the result, and read on first use: ``points`` (per georeferencing model, a
``laspy.LasData`` of every tile), ``waveforms`` and ``photons`` (``xarray.Dataset`` with GEDI L1B and ATL03 names,
:mod:`flightsim.outputs.datasets`), the canopy products ``atl08`` (land segments, ATL08 names), ``l2a`` (GEDI L2A
names) and ``chm`` (``xarray.DataArray``), None where the run wrote none, ``stats`` (the summary) and, for discrete
returns, ``returns`` (each return's float64 points, ids and range, and the true hits with ``with_truth``).
"""
from __future__ import annotations

import functools
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from flightsim.core import registry
from flightsim.engine.config import RunConfig, copy_config, set_value, validate
from flightsim.engine.config_io import from_dict, load_toml, preset_config


def register_part(role: str, kind: str, part: type | None = None):
    """Register a part defined outside the package as ``kind`` of ``role`` (a class decorator:
    ``@flightsim.register_part("deflector", "palmer")``), after the built-in parts, so a kind that clashes with one
    of them (a deflector called "fan", "risley" or "scene") is refused here, with
    :class:`flightsim.core.registry.KindClash`. See :func:`flightsim.core.registry.register`."""
    from flightsim.engine.products import catalog as _products  # noqa: F401  (the built-in parts of every role)
    from flightsim.engine.readouts import catalog as _readouts  # noqa: F401

    return registry.register(role, kind, part)


def load_config(source: str | Path | Mapping | RunConfig | None = None, *, instrument: str | None = None,
                overrides: Mapping[str, Any] | None = None) -> RunConfig:
    """A validated run config.

    source: a TOML path, a dict of tables ({"flight": {"altitude_m": 700}}), a RunConfig, or None;
    it is laid over the built-in ``instrument`` (a preset: "risley", the default, "change3", "spad", "change1",
    "atlas", "gedi", "vz2000"); then each ``overrides`` item {"table.setting": value} is set. Raises InputError
    naming a bad field.
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
class Returns:
    """Every return of a discrete-return run as the tracer made it (world coordinates in float64, before the LAS
    tiles' 1 mm grid)."""

    points: dict[str, np.ndarray]  # georeferencing model -> (n, 3) world E, N, H [m]
    true_points: np.ndarray | None  # (n, 3) true hits, world [m] (with_truth)
    line: np.ndarray  # (n,) flight line id
    pulse: np.ndarray  # (n,) pulse index within its line
    beam: np.ndarray  # (n,) beam index (DOE i·n + j, or channel)
    range_m: np.ndarray  # (n,) observed one-way range [m]
    return_number: np.ndarray  # (n,) 1 = first (over a canopy a beam has several returns), uint8
    number_of_returns: np.ndarray  # (n,) returns of the beam, uint8


@dataclass
class Result:
    """The products of a run: read from ``directory`` on first use."""

    directory: Path
    stats: dict  # summary.json
    cfg: RunConfig
    returns: Returns | None = None
    counts: Any = None  # flightsim.engine.tracer.RunCounts
    scene: Any = None  # flightsim.scenes.scene.Scene
    _temporary: Any = field(default=None, repr=False)  # the TemporaryDirectory holding the products

    @functools.cached_property
    def points(self) -> dict:
        """{model: laspy.LasData} of every tile of each georeferencing model (empty for other detectors)."""
        from flightsim.outputs.datasets import las_points

        return {model: las_points(sorted((self.directory / model).glob("*.la[sz]")))
                for model in self.stats.get("points", {})}

    @functools.cached_property
    def waveforms(self):
        """xarray.Dataset of every waveform (dims shot × sample, GEDI L1B names), or None."""
        return self._file("waveforms.h5", "waveform_dataset")

    @functools.cached_property
    def photons(self):
        """xarray.Dataset of every photon (dim photon, ATL03 names), or None."""
        from flightsim.outputs.datasets import photon_dataset

        if not (self.directory / "photons.h5").is_file():
            return None
        return photon_dataset(self.directory)

    @functools.cached_property
    def atl08(self):
        """xarray.Dataset of the land segments of every beam of ``atl08.h5`` (dim segment, coordinate ``beam``, ATL08
        names, fill values as NaN), or None."""
        return self._file("atl08.h5", "atl08_dataset")

    @functools.cached_property
    def l2a(self):
        """xarray.Dataset of ``l2a.h5`` (dim shot, ``rh`` shot × percentile, GEDI L2A names), or None."""
        return self._file("l2a.h5", "l2a_dataset")

    @functools.cached_property
    def chm(self):
        """xarray.DataArray of ``chm.tif`` (canopy height [m], y × x cell centres in the scene CRS, attribute
        ``crs``), or None."""
        return self._file("chm.tif", "chm_array")

    def _file(self, name: str, reader: str):
        """The run's file ``name`` read by ``reader`` (a function of :mod:`flightsim.outputs.datasets`), or None
        when the run wrote none."""
        from flightsim.outputs import datasets

        path = self.directory / name
        return getattr(datasets, reader)(path) if path.is_file() else None

    def write(self, directory: str | Path, overwrite: bool = False) -> Path:
        """Copy the run's files into ``directory`` (what ``flightsim simulate --out`` writes); its path."""
        from flightsim.engine.run import prepare_output

        target = Path(directory)
        if target.resolve() == self.directory.resolve():
            return target
        prepare_output(target, (self.directory / "run.toml").read_text(encoding="utf-8"), overwrite)
        for item in sorted(self.directory.iterdir(), key=lambda p: p.name == "summary.json"):  # the marker last
            copy = shutil.copytree if item.is_dir() else shutil.copy2
            copy(item, target / item.name)
        return target


def simulate(cfg: RunConfig, out: str | Path | None = None, with_truth: bool = False,
             progress: Callable[[int, int], None] | None = None, overwrite: bool = False) -> Result:
    """Run a validated config and return its :class:`Result`. With ``out`` the products are written there (as
    ``flightsim simulate``), else to a temporary directory owned by the result. A discrete-return run keeps every
    return in ``Result.returns`` (with the true hits when ``with_truth``)."""
    from flightsim.engine.run import execute

    temporary = None if out is not None else tempfile.TemporaryDirectory(prefix="flightsim-")
    directory = Path(out) if out is not None else Path(temporary.name) / "run"
    keeper = _ReturnKeeper(cfg.detector_part.readouts[0] == "points")
    run = execute(cfg, directory, overwrite=overwrite, progress=progress, tap=keeper if keeper.active else None,
                  with_truth=with_truth)
    if "empty" in run.summary:
        warnings.warn(f"the run made nothing: {run.summary['empty']}", RuntimeWarning, stacklevel=2)
    return Result(directory, run.summary, cfg, keeper.returns(run.tracer, with_truth), run.counts, run.tracer.scene,
                  temporary)


class _ReturnKeeper:
    """Keeps the host copy of every return a points readout hands the product."""

    def __init__(self, active: bool):
        self.active, self.parts = active, []

    def __call__(self, tracer, returns) -> None:
        from flightsim.engine.readouts.points import host_returns

        self.parts.extend(host_returns(tracer, returns))

    def returns(self, tracer, with_truth: bool) -> Returns | None:
        if not self.active:
            return None
        parts, scene = self.parts, tracer.scene

        def join(get):
            return np.concatenate([get(p) for p in parts]) if parts else np.empty(0)

        points = {m: scene.local_to_world(join(lambda p: p.points[m]).reshape(-1, 3)) for m in tracer.models}
        truth = scene.local_to_world(join(lambda p: p.true_points).reshape(-1, 3)) if with_truth else None
        def echo(p, name):
            value = getattr(p, name)
            return np.ones(len(p), np.uint8) if value is None else value

        return Returns(points, truth, join(lambda p: np.full(len(p), p.line_id)), join(lambda p: p.pulse),
                       join(lambda p: p.beam), join(lambda p: p.range_m),
                       join(lambda p: echo(p, "return_number")).astype(np.uint8),
                       join(lambda p: echo(p, "number_of_returns")).astype(np.uint8))


def sweep(base: RunConfig, axes: Mapping[str, list], out: str | Path, overwrite: bool = False) -> Path:
    """Plane-fit RMS over the grid of ``axes`` {"table.setting": [values]} (statistics readout, no LAS);
    writes the sweep table under ``out`` (resumable) and returns its path."""
    from flightsim.studies.sweep import SweepGrid, run_sweep

    grid = SweepGrid(base, [(key, list(values)) for key, values in axes.items()])
    grid.configurations()
    return run_sweep(grid, Path(out), overwrite=overwrite)


def budget(out: str | Path, device: str = "cpu", draws: int = 200, columns: int | None = None,
           instrument: str = "change3") -> dict:
    """An instrument's error budget (``flightsim budget``): the Chang'e-3 imager's full-link budget (default), or
    with ``instrument`` spad, change1 or atlas (``draws``: shots per source) the shared framework's; returns its
    numbers."""
    from flightsim.core.errors import InputError
    from flightsim.studies.budget_catalog import INSTRUMENTS, run_instrument
    from flightsim.studies.budget_report import run_budget

    if instrument in INSTRUMENTS:
        return run_instrument(instrument, Path(out), device=device, shots=draws)
    if instrument != "change3":
        raise InputError("instrument", instrument, "change3, " + ", ".join(INSTRUMENTS))
    return run_budget(Path(out), device=device, draws=draws, columns=columns)
