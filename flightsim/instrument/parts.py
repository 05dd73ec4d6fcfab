"""The registry of instrument parts and the composed instrument a run uses.

A new kind of part is one kernel module (``kernels/<kind>.py``: its ``@wp.struct`` and
``@wp.func``s) plus one host class here: ``check()`` (raise InputError naming the field),
``params(...)`` (fill the struct) and what the pipeline asks of that kind of part.
"""
from __future__ import annotations

import functools

from flightsim.core.config import RunConfig
from flightsim.instrument.emitters import ChannelEmitter, FanEmitter
from flightsim.instrument.fixed import FixedDeflector
from flightsim.instrument.fsm import FsmDeflector
from flightsim.instrument.galvo import GalvoDeflector
from flightsim.instrument.photon import DiscreteDetector, PhotonDetector
from flightsim.instrument.risley import RisleyDeflector
from flightsim.instrument.waveform import WaveformDetector
from kernels.parts import Instrument

EMITTERS = {"fan": FanEmitter, "channels": ChannelEmitter}
DEFLECTORS = {"risley": RisleyDeflector, "galvo": GalvoDeflector, "fsm": FsmDeflector, "fixed": FixedDeflector}
DETECTORS = {"discrete": DiscreteDetector, "photon": PhotonDetector, "waveform": WaveformDetector}


class HostInstrument:
    """The parts a config chooses, validated: what the simulator needs of them."""

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg
        self.emitter = EMITTERS[cfg.instrument.emitter](cfg)
        self.deflector = DEFLECTORS[cfg.instrument.deflector](cfg)
        self.detector = DETECTORS[cfg.instrument.detector](cfg)

    def check(self) -> None:
        self.emitter.check()
        self.deflector.check()
        self.detector.check()

    @functools.cached_property
    def kernel(self) -> Instrument:
        """The kernels' key: the emitter's and the deflector's device functions and structs."""
        return Instrument(self.emitter.kernel, self.deflector.kernel)

    @property
    def beams_per_pulse(self) -> int:
        return self.emitter.beams_per_pulse

    def reach_deg(self) -> float:
        """A bound on any beam's angle from the sensor axis (sizes built-in scenes), with the waveform
        detector's footprint around it [deg]."""
        footprint = getattr(self.detector, "footprint_deg", lambda: 0.0)()
        return self.deflector.reach_deg(self.emitter) + footprint

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the sensor axis over the scan (culls pulses) [rad]."""
        return self.deflector.max_off_axis_rad(self.emitter)
