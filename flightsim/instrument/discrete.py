"""The discrete-return detector (``instrument.detector = "discrete"``): one return per beam, the range of its hit,
georeferenced by the models of ``[output] models`` into LAS tiles (or reduced to per-plane statistics); over a
scene with a canopy, up to ``max_returns`` per beam: the leaves' and the surface's under them."""
from __future__ import annotations

from dataclasses import dataclass

from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting


@dataclass
class DiscreteSettings(Settings):
    """One return per beam; through a canopy (``scene.canopy``, a forest) the leaves' returns too, each where its
    echo reaches the threshold (kernels/canopy_returns.py). The range noise is the ranging error model's."""

    max_returns: int = setting(5, "returns kept per beam through a canopy, the first ones (LAS allows 15)",
                               "returns", range=(1, 15))
    min_separation_m: float = setting(2.0, "the detector's blind stretch after a return, through a canopy", "m",
                                      range=(0.0, 100.0))
    threshold: float = setting(0.05, "echo a return needs through a canopy, in units of a white Lambertian "
                               "target filling the footprint at normal incidence", "", range=(0.0, 1.0),
                               lo_open=True)
    reflectance: float = setting(0.3, "Lambertian albedo of surfaces under a canopy where the scene has none per "
                                 "triangle (scene.landcover)", "", range=(0.0, 1.0), lo_open=True)


@register("detector", "discrete")
class DiscreteDetector:
    """One return per beam."""

    settings = DiscreteSettings
    readouts = ("points", "statistics", "deviations")  # the engine's readouts it provides; a run to files uses the first
    output = "las"  # the [output] kind of its runs
    scored = True  # its runs are scored by plane fits ([scoring])

    def __init__(self, s: DiscreteSettings):
        self.s = s
