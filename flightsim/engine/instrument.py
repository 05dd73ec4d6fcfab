"""The instrument a validated config composes: its parts built from their own settings."""
from __future__ import annotations

import functools

from flightsim.core import registry
from kernels.parts import Instrument as KernelInstrument


class Instrument:
    """The emitter, deflector, detector and error models of a run (the error models not in use at their
    defaults: no error)."""

    def __init__(self, cfg):
        i = cfg.instrument
        self.emitter = registry.part("emitter", i.emitter)(getattr(cfg, i.emitter))
        self.deflector = registry.part("deflector", i.deflector)(getattr(cfg, i.deflector), self.emitter)
        self.detector = registry.part("detector", i.detector)(getattr(cfg, i.detector))
        self.ranging = registry.part("errors", "ranging")(cfg.error_model("ranging"), cfg.run.seed)
        self.pose = registry.part("errors", "pose")(cfg.error_model("pose"))

    @functools.cached_property
    def kernel(self) -> KernelInstrument:
        """The kernels' key: the emitter's and the deflector's device functions and structs."""
        return KernelInstrument(self.emitter.kernel, self.deflector.kernel)

    @property
    def beams_per_pulse(self) -> int:
        return self.emitter.beams_per_pulse

    def reach_deg(self) -> float:
        """A bound on any beam's angle from the sensor axis (sizes built-in scenes), with the detector's footprint
        around it (a waveform's sub-rays) [deg]."""
        footprint = getattr(self.detector, "footprint_deg", lambda: 0.0)()
        return self.deflector.reach_deg() + footprint

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the sensor axis over the scan (culls pulses) [rad]."""
        return self.deflector.max_off_axis_rad()
