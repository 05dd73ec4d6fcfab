"""Host side of the rotating-wedge (Risley) deflector: prism structs, timing, reach."""
from __future__ import annotations

import math

from flightsim.core.config import ARCSEC, RunConfig
from flightsim.core.errors import InputError
from kernels import wedge
from trajectories import PulseTiming

GALVO_ONLY = ("b1_arcsec", "b2_arcsec", "b3_arcsec", "c1_arcsec", "h_noise_arcsec", "v_noise_arcsec")
RISLEY_ONLY = ("encoder_arcsec", "encoder_noise_arcsec")
FSM_ONLY = ("fsm_zero_arcsec", "fsm_noise_arcsec")


def refuse_errors(cfg: RunConfig, names: tuple[str, ...], owner: str) -> None:
    """InputError for the first of ``errors.<names>`` that is set: they belong to deflector ``owner``."""
    for name in names:
        value = getattr(cfg.errors, name)
        if any(value) if isinstance(value, tuple) else value != 0.0:
            raise InputError(f"errors.{name}", value, f"0 unless instrument.deflector = {owner}")


def _prism(n_glass: float, apex_deg: float, thickness_mm: float, encoder_arcsec: float = 0.0,
           encoder_noise_arcsec: float = 0.0) -> wedge.Prism:
    prism = wedge.Prism()
    prism.n_glass = n_glass
    prism.apex = math.radians(apex_deg)
    prism.thickness = thickness_mm * 1e-3
    prism.encoder = encoder_arcsec * ARCSEC
    prism.encoder_sigma = encoder_noise_arcsec * ARCSEC
    return prism


class RisleyDeflector:
    """The wedge of ``[sensor]`` turning at ``sensor.rotation_hz``; the processing believes ``[processing]``."""

    kernel = wedge.WEDGE

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg

    def check(self) -> None:
        """The wedge's optics are checked in config._check_optics; the galvo's error sources do not apply,
        and the exit-ray table (run.optics = lut) tabulates the wedge without encoder errors."""
        refuse_errors(self.cfg, GALVO_ONLY, "galvo")
        refuse_errors(self.cfg, FSM_ONLY, "fsm")
        e = self.cfg.errors
        if self.cfg.run.optics == "lut" and (e.encoder_arcsec or e.encoder_noise_arcsec):
            raise InputError("run.optics", "lut", "float32 or float64 with prism-encoder errors "
                                                  "(the table tabulates the error-free wedge)")

    def timing(self) -> PulseTiming:
        s = self.cfg.sensor
        return PulseTiming(prf_hz=s.prf_hz, rotation_hz=s.rotation_hz, phase0_rad=math.radians(s.phase0_deg),
                           field_prefix="sensor")

    def params(self, believed: bool) -> wedge.Prism:
        if believed:
            p = self.cfg.processing
            return _prism(p.refractive_index, p.apex_angle_deg, p.thickness_mm)
        s, e = self.cfg.sensor, self.cfg.errors
        return _prism(s.refractive_index, s.apex_angle_deg, s.thickness_mm, e.encoder_arcsec, e.encoder_noise_arcsec)

    @property
    def believed_is_truth(self) -> bool:
        s, p, e = self.cfg.sensor, self.cfg.processing, self.cfg.errors
        return not (e.encoder_arcsec or e.encoder_noise_arcsec) and (p.refractive_index, p.apex_angle_deg, p.thickness_mm) == (s.refractive_index, s.apex_angle_deg,
                                                                          s.thickness_mm)

    def reach_deg(self, emitter) -> float:
        """A bound on any beam's angle from the sensor axis, to first order [deg]."""
        return self.cfg.sensor.cone_half_angle_deg + math.degrees(emitter.half_diagonal_rad)

    def max_off_axis_rad(self, emitter) -> float:
        """Largest exit angle of the fan over a prism turn [rad] (traced)."""
        from flightsim.engine.coverage import max_off_axis_rad

        return max_off_axis_rad(self.cfg)
