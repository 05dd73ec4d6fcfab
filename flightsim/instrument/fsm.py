"""Host side of the fast-steering-mirror deflector: checks, structs, timing, reach."""
from __future__ import annotations

import math

import numpy as np

from flightsim.core.config import ARCSEC, RunConfig
from flightsim.core.errors import InputError
from flightsim.instrument import fsm_model
from flightsim.instrument.risley import GALVO_ONLY, RISLEY_ONLY, refuse_errors
from kernels import fsm
from trajectories import PulseTiming

MAX_SPAN_MRAD = 200.0  # full tilt span of either axis
MODES = {"A": fsm.MODE_A, "B": fsm.MODE_B}


class FsmDeflector:
    """``[fsm]`` as built and scanned; ``[errors] fsm_zero_arcsec, fsm_noise_arcsec`` on the truth."""

    kernel = fsm.FSM

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg

    @property
    def frame_pulses(self) -> int:
        c = self.cfg.fsm
        return int(round(c.frame_s * c.prf_hz))

    def geometry(self) -> fsm_model.FsmGeometry:
        c = self.cfg.fsm
        return fsm_model.FsmGeometry(c.b2_mm * 1e-3, c.d_mm * 1e-3, c.mode, tuple(v * 1e-3 for v in c.span_mrad),
                                     c.lines, self.frame_pulses)

    def check(self) -> None:
        c, cfg = self.cfg.fsm, self.cfg
        refuse_errors(cfg, GALVO_ONLY, "galvo")
        refuse_errors(cfg, RISLEY_ONLY, "risley")
        if c.mode not in MODES:
            raise InputError("fsm.mode", c.mode, "A (sweeps, sub-pixel interleave) or B (step grid)")
        span = tuple(c.span_mrad)
        if len(span) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= MAX_SPAN_MRAD
                                     for v in span):
            raise InputError("fsm.span_mrad", ",".join(map(str, span)), f"two spans (θx, θy) in [0, {MAX_SPAN_MRAD:g}] mrad")
        zero = tuple(cfg.errors.fsm_zero_arcsec)
        if len(zero) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) and abs(v) <= 3600.0 for v in zero):
            raise InputError("errors.fsm_zero_arcsec", ",".join(map(str, zero)), "two angles within ±3600 arcsec")
        positions = c.lines if c.mode == "A" else c.lines * c.lines
        if self.frame_pulses < 2 * positions:
            raise InputError("fsm.prf_hz", c.prf_hz, f"at least {2 * positions / c.frame_s:g} Hz: a frame of "
                             f"{c.frame_s:g} s needs 2 pulses for each of its {positions} sweeps or steps")
        if cfg.instrument.emitter != "fan":
            raise InputError("instrument.emitter", cfg.instrument.emitter, "fan (the Dammann grating's N×N array) "
                                                                           "with the fsm deflector")
        if "nominal" in cfg.output.models:
            raise InputError("output.models", ",".join(cfg.output.models), "exact (the rigid-array nominal model is "
                                                                           "defined for the risley deflector only)")
        if cfg.run.optics == "lut":
            raise InputError("run.optics", cfg.run.optics, "float32 or float64 (lut tabulates the risley wedge only)")
        self._check_apertures()

    def _corners(self):
        """(θx, θy) at the pattern's corners and the fan's corner beams (emitter frame)."""
        from flightsim.instrument.emitters import FanEmitter

        sx, sy = (v * 1e-3 / 2.0 for v in self.cfg.fsm.span_mrad)
        tx = np.array([-sx, sx, -sx, sx, 0.0])[:, None]
        ty = np.array([-sy, -sy, sy, sy, 0.0])[:, None]
        beams = FanEmitter(self.cfg).directions()
        return tx, ty, beams[None, :, :]

    def _check_apertures(self) -> None:
        tx, ty, beams = self._corners()
        _, _, (off1, off2) = fsm_model.trace(self.geometry(), tx, ty, beams)
        reach_mm = 1e3 * float(max(off1.max(), off2.max()))
        if reach_mm > self.cfg.fsm.aperture_mm:
            raise InputError("fsm.aperture_mm", self.cfg.fsm.aperture_mm,
                             f"at least {reach_mm:.2f} mm: the fan meets the mirrors that far from their centres")

    def timing(self) -> PulseTiming:
        return PulseTiming(prf_hz=self.cfg.fsm.prf_hz, rotation_hz=0.0, phase0_rad=0.0, field_prefix="fsm")

    def params(self, believed: bool) -> fsm.Fsm:
        c = self.cfg.fsm
        s = fsm.Fsm()
        s.b2, s.d, s.aperture = c.b2_mm * 1e-3, c.d_mm * 1e-3, c.aperture_mm * 1e-3
        s.mode = MODES[c.mode]
        s.span_x, s.span_y = (v * 1e-3 for v in c.span_mrad)
        s.frame_pulses, s.lines = self.frame_pulses, c.lines
        e = self.cfg.errors
        zero = (0.0, 0.0) if believed else tuple(e.fsm_zero_arcsec)
        s.zero_x, s.zero_y = (v * ARCSEC for v in zero)
        s.sigma = 0.0 if believed else e.fsm_noise_arcsec * ARCSEC
        return s

    @property
    def believed_is_truth(self) -> bool:
        e = self.cfg.errors
        return not any(e.fsm_zero_arcsec) and e.fsm_noise_arcsec == 0.0

    def max_off_axis_rad(self, emitter) -> float:
        """Largest angle of any beam from the sensor axis over the pattern's corners [rad]."""
        tx, ty, beams = self._corners()
        _, direction, _ = fsm_model.trace(self.geometry(), tx, ty, beams)
        return float(np.arccos(np.clip(direction[..., 2], -1.0, 1.0)).max())

    def reach_deg(self, emitter) -> float:
        return math.degrees(self.max_off_axis_rad(emitter))
