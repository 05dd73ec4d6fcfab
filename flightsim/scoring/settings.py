"""How a discrete-return run is scored by plane fits (SPEC §9): ``[scoring]``."""
from __future__ import annotations

from dataclasses import dataclass

from flightsim.core.settings import Settings, setting


@dataclass
class ScoringSettings(Settings):
    """Plane-fit scoring of the returns."""

    table = "scoring"

    edge_buffer_m: float = setting(-1.0, "returns this close to a plane's boundary are left out of its fit; -1 = "
                                   "automatic (the footprint and the rigid-array distortion at the altitude flown)",
                                   "m", range=(-1.0, 1000.0))
    patch_m: float = setting(0.0, "side of the square patches a LAS run fits on curved ground; 0 = 25 m on a "
                             "curved scene, none on a planar one", "m", range=(0.0, 100000.0))
