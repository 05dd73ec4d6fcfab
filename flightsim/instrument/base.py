"""What the engine asks of each kind of instrument part (the protocols a new part implements), and helpers parts
share.

A part is one module: a :class:`~flightsim.core.settings.Settings` dataclass (its table in the config) and a
host class registered with :func:`flightsim.core.registry.register`. The host class is built from its own
settings only (a deflector also gets its emitter), never from the run config. Kernel-side, an emitter or a
deflector is a :class:`kernels.parts.Emitter` / :class:`kernels.parts.Deflector` of ``@wp.func`` s and a
``@wp.struct``; the trace kernels are built for the parts a run uses.
"""
from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np

from trajectories import PulseTiming

MAX_SLANT_RAD = math.radians(80.0)  # the widest beam the automatic edge buffer is sized for


class Emitter(Protocol):
    """The beams of one pulse. ``kernel``: a :class:`kernels.parts.Emitter`."""

    kernel: Any
    beams_per_pulse: int
    half_diagonal_rad: float  # largest angle of a beam from the emitter's axis, to first order [rad]
    divergence_mrad: float  # full divergence of each beam [mrad]
    beam_columns: int  # beam b is written to LAS as row b // beam_columns, column b % beam_columns

    def directions(self) -> np.ndarray:
        """(beams, 3) unit directions in the emitter frame (+z the axis), float64."""

    def params(self, device: str) -> Any:
        """The kernel struct of the emitter's parameters."""


class Deflector(Protocol):
    """What turns the beams into the scan. ``kernel``: a :class:`kernels.parts.Deflector`; ``rigid_nominal``: whether
    the rigid-array (nominal) georeferencing model is defined for it."""

    kernel: Any
    rigid_nominal: bool
    believed_is_truth: bool  # the processing's deflector is the true one (the traced ray is reused)

    def timing(self) -> PulseTiming:
        """Pulse times and scan phase."""

    def params(self, believed: bool) -> Any:
        """The kernel struct of the true deflector, or of the one the processing believes in."""

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the sensor axis over the scan [rad] (culls pulses)."""

    def reach_deg(self) -> float:
        """A bound on any beam's angle from the sensor axis [deg] (sizes built-in scenes)."""

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer of plane scoring at ``altitude_m`` [m]."""


class Detector(Protocol):
    """What a beam that hits becomes: ``readouts`` names the engine readouts it provides (the first is the one a run
    to files uses), ``output`` the [output] kind of its runs (None: no settings), ``scored`` whether its runs are
    scored by plane fits ([scoring])."""

    readouts: tuple[str, ...]
    output: str | None
    scored: bool


def footprint_buffer_m(altitude_m: float, off_axis_rad: float, divergence_mrad: float) -> float:
    """Edge buffer of a deflector without a rigid-array model [m]: the footprint's half width at the slant range of
    its widest beam (at most MAX_SLANT_RAD from nadir)."""
    slant = altitude_m / math.cos(min(off_axis_rad, MAX_SLANT_RAD))
    return slant * 0.5 * divergence_mrad * 1e-3
