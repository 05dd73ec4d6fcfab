"""The fast-steering-mirror deflector (``instrument.deflector = "fsm"``, ``[fsm]``): a 45° mirror and a large
two-axis fast steering mirror in front of a fan emitter, scanned in MODE-A sweeps or a MODE-B step grid
(kernels/fsm.py), with the FSM's encoder zero errors and tilt noise on the truth."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.instrument.base import footprint_buffer_m
from flightsim.core.constants import ARCSEC
from flightsim.instrument import fsm_model
from trajectories import PulseTiming

fsm = lazy_module("kernels.fsm")

MAX_SPAN_MRAD = 200.0  # full tilt span of either axis
MODES = ("A", "B")


@dataclass
class FsmSettings(Settings):
    """The FSM path, its scan pattern and timing, and its errors on the truth."""

    b2_mm: float = setting(30.0, "grating to the 45° mirror", "mm", range=(0.0, 1000.0), lo_open=True)
    d_mm: float = setting(40.0, "45° mirror to the FSM", "mm", range=(0.0, 1000.0), lo_open=True)
    aperture_mm: float = setting(25.0, "half size of each mirror", "mm", range=(0.0, 1000.0), lo_open=True)
    mode: str = setting("A", "A: triangle-wave sweeps in x, steps in y (sub-pixel interleave); B: a steps × steps grid",
                        choices=MODES)
    span_mrad: tuple[float, float] = setting((2.62, 1.80), "full FSM tilt span of the pattern (θx, θy)", "mrad",
                                             length=2, items=(0.0, MAX_SPAN_MRAD))
    lines: int = setting(40, "MODE-A sweeps per frame, MODE-B steps per axis", "lines", range=(1, 65536))
    frame_s: float = setting(0.86, "time per frame", "s", range=(0.0, 3600.0), lo_open=True)
    prf_hz: float = setting(50000.0, "pulse repetition frequency", "Hz", range=(0.0, 1.0e7), lo_open=True)
    zero_arcsec: tuple[float, float] = setting((0.0, 0.0), "FSM encoder zero errors of θx, θy on the truth", "arcsec",
                                               length=2, items=(-3600.0, 3600.0))
    noise_arcsec: float = setting(0.0, "FSM tilt noise per axis and pulse, 1 sigma", "arcsec", range=(0.0, 3600.0))

    @property
    def frame_pulses(self) -> int:
        return int(round(self.frame_s * self.prf_hz))

    def check(self, context) -> None:
        positions = self.lines if self.mode == "A" else self.lines * self.lines
        if self.frame_pulses < 2 * positions:
            raise InputError("fsm.prf_hz", self.prf_hz, f"at least {2 * positions / self.frame_s:g} Hz: a frame of "
                             f"{self.frame_s:g} s needs 2 pulses for each of its {positions} sweeps or steps")
        if context is None:
            return
        if context.emitter != "fan":
            raise InputError("instrument.emitter", context.emitter,
                             "fan (the Dammann grating's N×N array) with the fsm deflector")
        if "nominal" in context.models:
            raise InputError("output.models", ",".join(context.models),
                             "exact (the rigid-array nominal model is defined for the risley deflector only)")
        if context.optics == "lut":
            raise InputError("run.optics", context.optics, "float32 or float64 (lut tabulates the risley wedge only)")
        from flightsim.instrument.fan import FanEmitter

        reach_mm = 1e3 * max(_mirror_offsets(self, FanEmitter(context.settings("fan"))))
        if reach_mm > self.aperture_mm:
            raise InputError("fsm.aperture_mm", self.aperture_mm,
                             f"at least {reach_mm:.2f} mm: the fan meets the mirrors that far from their centres")


def geometry(s: FsmSettings) -> fsm_model.FsmGeometry:
    return fsm_model.FsmGeometry(s.b2_mm * 1e-3, s.d_mm * 1e-3, s.mode, tuple(v * 1e-3 for v in s.span_mrad),
                                 s.lines, s.frame_pulses)


def _corners(s: FsmSettings, emitter):
    """(θx, θy) at the pattern's corners and the fan's beams (emitter frame)."""
    sx, sy = (v * 1e-3 / 2.0 for v in s.span_mrad)
    tx = np.array([-sx, sx, -sx, sx, 0.0])[:, None]
    ty = np.array([-sy, -sy, sy, sy, 0.0])[:, None]
    return tx, ty, emitter.directions()[None, :, :]


def _mirror_offsets(s: FsmSettings, emitter) -> tuple[float, float]:
    """Farthest the fan meets the 45° mirror and the FSM from their centres over the pattern [m]."""
    _, _, (off1, off2) = fsm_model.trace(geometry(s), *_corners(s, emitter))
    return float(off1.max()), float(off2.max())


@register("deflector", "fsm")
class FsmDeflector:
    """``[fsm]`` as built and scanned, in front of a fan emitter."""

    settings = FsmSettings
    rigid_nominal = False

    @property
    def kernel(self):
        """The kernel side: its struct and device functions."""
        return fsm.FSM

    def __init__(self, s: FsmSettings, emitter):
        self.s = s
        self.emitter = emitter


    @property
    def frame_pulses(self) -> int:
        return self.s.frame_pulses

    def geometry(self) -> fsm_model.FsmGeometry:
        return geometry(self.s)

    def timing(self) -> PulseTiming:
        return PulseTiming(prf_hz=self.s.prf_hz, rotation_hz=0.0, phase0_rad=0.0, field_prefix="fsm")

    def params(self, believed: bool):
        c, out = self.s, fsm.Fsm()
        out.b2, out.d, out.aperture = c.b2_mm * 1e-3, c.d_mm * 1e-3, c.aperture_mm * 1e-3
        out.mode = fsm.MODE_A if c.mode == "A" else fsm.MODE_B
        out.span_x, out.span_y = (v * 1e-3 for v in c.span_mrad)
        out.frame_pulses, out.lines = self.frame_pulses, c.lines
        zero = (0.0, 0.0) if believed else tuple(c.zero_arcsec)
        out.zero_x, out.zero_y = (v * ARCSEC for v in zero)
        out.sigma = 0.0 if believed else c.noise_arcsec * ARCSEC
        return out

    @property
    def believed_is_truth(self) -> bool:
        return not any(self.s.zero_arcsec) and self.s.noise_arcsec == 0.0

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the sensor axis over the pattern's corners [rad]."""
        _, direction, _ = fsm_model.trace(self.geometry(), *_corners(self.s, self.emitter))
        return float(np.arccos(np.clip(direction[..., 2], -1.0, 1.0)).max())

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint at the slant range of the widest beam (no rigid-array model)."""
        return footprint_buffer_m(altitude_m, self.max_off_axis_rad(), divergence_mrad)
