"""The discrete-return detector (``instrument.detector = "discrete"``): one return per beam, the range of its hit,
georeferenced by the models of ``[output] models`` into LAS tiles (or reduced to per-plane statistics)."""
from __future__ import annotations

from dataclasses import dataclass

from flightsim.core.registry import register
from flightsim.core.settings import Settings


@dataclass
class DiscreteSettings(Settings):
    """One return per beam (no settings of its own: its range noise is the ranging error model's)."""


@register("detector", "discrete")
class DiscreteDetector:
    """One return per beam."""

    settings = DiscreteSettings
    readouts = ("points", "statistics", "deviations")  # the engine's readouts it provides; a run to files uses the first
    output = "las"  # the [output] kind of its runs
    scored = True  # its runs are scored by plane fits ([scoring])

    def __init__(self, s: DiscreteSettings):
        self.s = s
