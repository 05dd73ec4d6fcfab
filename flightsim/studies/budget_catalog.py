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
