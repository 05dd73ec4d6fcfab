"""The instruments of `flightsim budget`'s shared framework (flightsim/studies/budgets.py): each one's budget by
name, and the run that writes budget.json and REPORT.md."""
from __future__ import annotations

from pathlib import Path

from flightsim.core.errors import InputError
from flightsim.studies.budgets import InstrumentBudget, run_budget, source_names, write_budget


INSTRUMENTS = ("spad", "change1", "atlas")  # the budgets of this framework (change3 and risley have their own report)


def instrument_budget(name: str) -> InstrumentBudget:
    """The budget of instrument ``name`` (one of INSTRUMENTS)."""
    if name == "spad":
        from flightsim.studies.budget_spad import BUDGET
    elif name == "change1":
        from flightsim.studies.budget_change1 import BUDGET
    elif name == "atlas":
        from flightsim.studies.budget_atlas import BUDGET
    else:
        raise InputError("--instrument", name, "change3, risley, " + ", ".join(INSTRUMENTS))
    return BUDGET


def budget_command(name: str, out: Path, device: str, shots: int | None, sources: str | None) -> str:
    """The command line that regenerates a budget."""
    extra = (f" --draws {shots}" if shots else "") + (f" --sources {sources}" if sources else "")
    return f"flightsim budget --instrument {name} --device {device}{extra} --out {out}"


def run_instrument(name: str, out: Path, device: str = "cpu", shots: int | None = None, seed: int = 0,
                   sources: str | None = None) -> dict:
    """Compute instrument ``name``'s budget and write it under ``out`` (budget.json, REPORT.md)."""
    budget = instrument_budget(name)
    source_names(budget, sources)  # checked before anything runs
    numbers = run_budget(budget, device, shots, seed, sources)
    write_budget(budget, out, numbers, budget_command(name, out, device, shots, sources))
    return numbers


def run_any(name: str, out: Path, device: str = "cpu", draws: int | None = None, columns: int | None = None,
            seed: int = 0, sources: str | None = None) -> dict:
    """`flightsim budget`: any instrument's budget into ``out`` (change3 and risley: their own reports, ``draws``
    Monte Carlo draws, default 200; the others: this framework's, ``draws`` shots per source), inputs checked first."""
    if draws is not None and not 2 <= draws <= 10_000_000:
        raise InputError("--draws", draws, "an integer in [2, 10000000]")
    if columns is not None and not 2 <= columns <= 65536:
        raise InputError("--columns", columns, "an integer in [2, 65536]")
    if sources is not None and name not in INSTRUMENTS:
        raise InputError("--sources", sources, "only with --instrument " + ", ".join(INSTRUMENTS))
    if name in INSTRUMENTS:
        return run_instrument(name, out, device, draws, seed, sources)
    from flightsim.studies.budget_report import run_budget, run_risley_budget

    if name == "risley":
        return run_risley_budget(out, device=device, draws=draws or 200, seed=seed)
    if name == "change3":
        return run_budget(out, device=device, draws=draws or 200, columns=columns, seed=seed)
    raise InputError("--instrument", name, "change3, risley, " + ", ".join(INSTRUMENTS))


def compile_budget(name: str, device: str = "cpu") -> int:
    """Compile into Warp's kernel cache (or load from it) the kernels `flightsim budget --instrument` ``name`` launches
    (``flightsim compile --for budget``): the budget run once with two draws in a scratch directory, whose kernels are a
    full run's (they depend on its error sources, not on its draws); returns the modules loaded."""
    import tempfile

    from flightsim.core.warp_runtime import loaded_modules

    with tempfile.TemporaryDirectory() as tmp:
        run_any(name, Path(tmp), device, draws=2)
    return loaded_modules()
