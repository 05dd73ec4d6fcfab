"""The shared error-budget framework of `flightsim budget`: each error source of an instrument alone and all of
them at once, simulated on the device (Monte Carlo through the real simulator path) and propagated to first order
in float64, side by side with their ratio; the root-sum-square of the sources against the all-sources-on run.

An instrument's budget is an :class:`InstrumentBudget`: its :class:`Source` list, how to simulate a set of sources
(:meth:`~InstrumentBudget.simulate`: the errors of one scalar quantity, e.g. the height error of every signal
photon, with the geometry the first-order model needs) and the float64 first-order model of each source
(:meth:`~InstrumentBudget.first_order`). This module does the rest once for every instrument: the statistics
(sample mean and σ with their confidence intervals), the totals, budget.json and REPORT.md.

Every source is reported as (mean, σ, RMS = √(mean² + σ²)) of the error [m]. A source's *contribution* to the
total is its RMS (role ``noise``: a random error, or a systematic one at its 1σ value) or its |mean| alone (role
``bias``: a bias of an echo whose spread other sources already carry, e.g. pile-up); sources of role ``product``
act on a derived product (e.g. gridded points) and ``alternative`` ones are another value of a source above (e.g.
a steeper slope): both stay out of the total and of the all-sources run. The total is the root-sum-square of the
contributions (independent sources), against the RMS of the run with every source on at once.
"""
from __future__ import annotations

import json
import math
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from flightsim.core.atomic import write_atomic
from flightsim.core.errors import InputError

CONFIDENCE = 0.99  # of the intervals the report and the tests use
SIGMA_FLOOR_M = 1.0e-9  # first-order σ below this: a systematic source, no σ ratio
ROLES = ("noise", "bias", "product", "alternative")


@dataclass(frozen=True)
class Source:
    """One error source of a budget."""

    name: str
    value: float  # its 1σ or its value, in ``unit``
    unit: str
    meaning: str  # what it is and where its value comes from
    role: str = "noise"  # noise, bias or product (see the module docstring)
    breaks: str = ""  # why its first-order model is expected to break ("" when it should hold)


@dataclass
class Simulated:
    """One simulated set of sources: the errors [m] of the budget's quantity and the run's geometry."""

    errors: np.ndarray  # (n,) float64 [m]
    geometry: dict = field(default_factory=dict)  # what the first-order model needs (directions, ranges, …)
    wall_s: float = 0.0


class InstrumentBudget(Protocol):
    """What an instrument's budget provides (see flightsim/studies/budget_spad.py for one)."""

    name: str  # the --instrument value
    title: str
    quantity: str  # the error the budget measures, one line
    seed: str  # the seed file the budget cites
    sources: tuple[Source, ...]
    default_shots: int  # shots per source run

    def simulate(self, names: tuple[str, ...], device: str, shots: int, seed: int) -> Simulated: ...

    def first_order(self, name: str, sim: Simulated) -> tuple[float, float]: ...

    def notes(self, numbers: dict) -> str: ...


def sigma_relative_error(n: int) -> float:
    """Expected relative error of a normal sample's σ from ``n`` values, 1/√(2(n − 1))."""
    return 1.0 / math.sqrt(2.0 * (n - 1))


class SlotMoments:
    """Per-slot float64 sums of a deviation vector and its square over Monte Carlo draws, on the device (the
    deviations readout adds to them); :meth:`moments` turns them into each slot's mean and sample σ."""

    def __init__(self, slots: int, device):
        import warp as wp

        self.sums, self.squares = (wp.zeros(slots, dtype=wp.vec3d, device=device) for _ in range(2))
        self.hits = wp.zeros(slots, dtype=wp.int32, device=device)

    def readout(self):
        """A deviations readout that adds one draw to these sums."""
        from flightsim.engine.readouts.deviations import Deviations

        return Deviations(self.sums, self.squares, self.hits)

    def moments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean (slots, 3), sample σ (slots, 3), draws that returned (slots,) float64) per slot; NaN where fewer
        than two draws returned."""
        n = self.hits.numpy().astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.sums.numpy() / n[:, None]
            var = (self.squares.numpy() - n[:, None] * mean ** 2) / (n[:, None] - 1.0)
        return mean, np.sqrt(np.maximum(var, 0.0)), n


def sigma_interval(sigma: float, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Two-sided ``confidence`` interval of a normal population's σ from a sample σ of ``n`` values (χ² with n − 1
    degrees of freedom)."""
    from scipy.stats import chi2

    k = max(int(n) - 1, 1)
    a = 1.0 - confidence
    return sigma * math.sqrt(k / chi2.ppf(1.0 - a / 2.0, k)), sigma * math.sqrt(k / chi2.ppf(a / 2.0, k))


def mean_halfwidth(sigma: float, n: int, confidence: float = CONFIDENCE) -> float:
    """Half width of the ``confidence`` interval of a sample mean of ``n`` values of spread ``sigma``."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + confidence / 2.0)) * sigma / math.sqrt(max(int(n), 1))


def statistics(errors: np.ndarray, independent: int | None = None) -> dict:
    """Sample mean, σ and RMS [m] of ``errors`` with their intervals at CONFIDENCE (from ``independent`` draws when
    the errors share fewer random draws than their number, e.g. a tilt noise drawn per pulse for all its beams)."""
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    n = int(e.size)
    if n < 2:
        return {"n": n, "mean_m": math.nan, "sigma_m": math.nan, "rms_m": math.nan, "sigma_interval_m": [math.nan] * 2,
                "mean_halfwidth_m": math.nan}
    mean, sigma = float(e.mean()), float(e.std(ddof=1))
    k = min(n, independent or n)
    return {"n": n, "independent": k, "mean_m": mean, "sigma_m": sigma, "rms_m": math.hypot(mean, sigma),
            "sigma_interval_m": list(sigma_interval(sigma, k)), "mean_halfwidth_m": mean_halfwidth(sigma, k)}


def contribution(role: str, mean: float, sigma: float) -> float:
    """A source's share of the total [m]: its RMS (noise), its |mean| (bias) or nothing (product)."""
    return {"noise": math.hypot(mean, sigma), "bias": abs(mean)}.get(role, 0.0)


def source_names(budget: InstrumentBudget, sources: str | None) -> tuple[str, ...]:
    """The budget's sources named by ``sources`` (comma-separated; None: all), checked."""
    known = tuple(s.name for s in budget.sources)
    if sources is None:
        return known
    names = tuple(n.strip() for n in sources.split(",") if n.strip())
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise InputError("--sources", sources, f"a comma-separated subset of {','.join(known)} ({budget.name})")
    return names


def fly(cfg, readout) -> tuple[object, object, list, float]:
    """(scene, tracer, every host chunk ``readout`` handed over, wall [s] of the run) of one flight of ``cfg``."""
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    chunks = []
    started = time.perf_counter()
    sim.run(readout, chunks.append)
    return scene, sim, chunks, time.perf_counter() - started


def run_source(budget: InstrumentBudget, source: Source, device: str, shots: int, seed: int) -> dict:
    """One source alone: simulated on ``device`` and propagated to first order; the row of budget.json."""
    sim = budget.simulate((source.name,), device, shots, seed)
    model_mean, model_sigma = budget.first_order(source.name, sim)
    mc = statistics(sim.errors, sim.geometry.get("independent"))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = mc["sigma_m"] / model_sigma if model_sigma > SIGMA_FLOOR_M else math.nan
    return {"source": asdict(source), "monte_carlo": mc, "wall_s": round(sim.wall_s, 3),
            "first_order": {"mean_m": model_mean, "sigma_m": model_sigma, "rms_m": math.hypot(model_mean, model_sigma)},
            "sigma_ratio": ratio,
            "mean_difference_m": mc["mean_m"] - model_mean,
            "contribution_m": {"monte_carlo": contribution(source.role, mc["mean_m"], mc["sigma_m"]),
                               "first_order": contribution(source.role, model_mean, model_sigma)}}


def run_budget(budget: InstrumentBudget, device: str = "cpu", shots: int | None = None, seed: int = 0,
               sources: str | None = None) -> dict:
    """Every source of ``budget`` alone, then all at once; the numbers of budget.json."""
    names = source_names(budget, sources)
    shots = shots or budget.default_shots
    started = time.perf_counter()
    rows = [run_source(budget, s, device, shots, seed) for s in budget.sources if s.name in names]
    together = [s.name for s in budget.sources if s.name in names and s.role in ("noise", "bias")]
    everything = statistics(budget.simulate(tuple(together), device, shots, seed).errors)
    rss = {k: math.sqrt(sum(r["contribution_m"][k] ** 2 for r in rows)) for k in ("monte_carlo", "first_order")}
    return {"instrument": budget.name, "device": device, "host": platform.node(), "shots": shots, "seed": seed,
            "quantity": budget.quantity, "confidence": CONFIDENCE, "sources": rows,
            "all_sources": {"names": together, "monte_carlo": everything,
                            "rss_of_sources_m": rss,
                            "rss_over_all_sources": rss["monte_carlo"] / everything["rms_m"],
                            "first_order_rss_over_all_sources": rss["first_order"] / everything["rms_m"]},
            "wall_s": round(time.perf_counter() - started, 2)}


def write_budget(budget: InstrumentBudget, out: Path, numbers: dict, command: str) -> None:
    """budget.json and REPORT.md of ``numbers`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "budget.json", json.dumps({"command": command, **numbers}, indent=2) + "\n")
    write_atomic(out / "REPORT.md", report(budget, numbers, command))


def _mm(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{1e3 * v:.3f}"


def _row(r: dict) -> str:
    s, mc, fo = r["source"], r["monte_carlo"], r["first_order"]
    lo, hi = mc["sigma_interval_m"]
    return (f"| {s['name']} | {s['value']:g} {s['unit']} | {s['role']} | {mc['n']:,} ({mc['independent']:,}) | "
            f"{_mm(mc['mean_m'])} ± "
            f"{_mm(mc['mean_halfwidth_m'])} | {_mm(fo['mean_m'])} | {_mm(mc['sigma_m'])} ({_mm(lo)}–{_mm(hi)}) | "
            f"{_mm(fo['sigma_m'])} | {r['sigma_ratio']:.3f} |")


def report(budget: InstrumentBudget, n: dict, command: str) -> str:
    """REPORT.md of a budget from its numbers: the sources, each alone on the device beside first order, the
    total, and the instrument's notes."""
    rows = "\n".join(_row(r) for r in n["sources"])
    meanings = "\n".join(f"- **{r['source']['name']}**: {r['source']['meaning']}"
                         + (f" *First order expected to break*: {r['source']['breaks']}" if r['source']['breaks'] else "")
                         for r in n["sources"])
    a = n["all_sources"]
    contributions = "\n".join(f"| {r['source']['name']} | {_mm(r['contribution_m']['monte_carlo'])} | "
                              f"{_mm(r['contribution_m']['first_order'])} |" for r in n["sources"])
    e = a["monte_carlo"]
    return f"""# {budget.title}: error budget

Regenerate: `{command}` (device `{n['device']}`, {n['shots']:,} shots per run, seed {n['seed']}, {n['wall_s']:.0f} s).
Seed: `../shared/seeds/{budget.seed}`. Quantity: {n['quantity']}

Each source alone, simulated through the simulator (Monte Carlo on `{n['device']}`) and propagated to first order
in float64 (NumPy), all in mm. Intervals at {100 * n['confidence']:.0f} %: the mean ± its half width, the σ's from
χ² with n − 1 degrees of freedom. Ratio = Monte Carlo σ ÷ first-order σ.

| source | value | role | n (independent) | MC mean | first-order mean | MC σ (interval) | first-order σ | σ ratio |
| --- | --- | --- | --- | --- | --- | --- | --- | --- |
{rows}

{meanings}

## Total

Contribution of each source (role noise: RMS = √(mean² + σ²); bias: |mean|; product, alternative: not in the total) [mm]:

| source | Monte Carlo | first order |
| --- | --- | --- |
{contributions}
| **root-sum-square** | **{_mm(a['rss_of_sources_m']['monte_carlo'])}** | **{_mm(a['rss_of_sources_m']['first_order'])}** |

All sources on at once ({', '.join(a['names'])}), one run of {e['n']:,} samples: mean {_mm(e['mean_m'])} mm,
σ {_mm(e['sigma_m'])} mm, RMS **{_mm(e['rms_m'])} mm**. Root-sum-square of the sources ÷ all-on RMS: Monte Carlo
{a['rss_over_all_sources']:.3f}, first order {a['first_order_rss_over_all_sources']:.3f}.

{budget.notes(n)}
"""

