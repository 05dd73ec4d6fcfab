"""Host side of the two-mirror galvanometer scanner: geometry checks, structs, timing."""
from __future__ import annotations

import math

import numpy as np

from flightsim.core.config import ARCSEC, RunConfig
from flightsim.core.errors import InputError
from flightsim.instrument import galvo_model
from flightsim.instrument.risley import FSM_ONLY, RISLEY_ONLY, refuse_errors
from kernels import galvo
from trajectories import PulseTiming

MAX_FIELD_DEG = 80.0  # full field of either axis [deg]


class GalvoDeflector:
    """``[galvo]`` as built; ``[processing] b_mm, e_mm`` as believed; ``[errors]`` angle errors on the truth."""

    kernel = galvo.GALVO

    def __init__(self, cfg: RunConfig):
        self.cfg = cfg
        g = cfg.galvo
        self.half_field_rad = tuple(math.radians(f) / 2.0 for f in g.field_deg)

    def geometry(self, believed: bool = False) -> galvo_model.GalvoGeometry:
        """The float64 reference model of this scanner (truth, or as the processing believes it)."""
        g, p = self.cfg.galvo, self.cfg.processing
        b, e = (p.b_mm, p.e_mm) if believed else (g.b_mm, g.e_mm)
        return galvo_model.GalvoGeometry(b_m=b * 1e-3, e_m=e * 1e-3,
                                         channel_angles_rad=tuple(np.asarray(self.cfg.channels.angles_mrad) * 1e-3),
                                         field_deg=tuple(g.field_deg), strips=g.strips, columns=g.columns)

    def check(self) -> None:
        g, cfg = self.cfg.galvo, self.cfg
        field = tuple(g.field_deg)
        if len(field) != 2 or not all(math.isfinite(f) and 0.0 < f <= MAX_FIELD_DEG for f in field):
            raise InputError("galvo.field_deg", ",".join(map(str, field)),
                             f"two full angles (horizontal, vertical) in (0, {MAX_FIELD_DEG:g}] deg")
        if "nominal" in cfg.output.models:
            raise InputError("output.models", ",".join(cfg.output.models),
                             "exact (the rigid-array nominal model is defined for the risley deflector only)")
        if cfg.run.optics == "lut":
            raise InputError("run.optics", cfg.run.optics, "float32 or float64 (lut tabulates the risley wedge only)")
        refuse_errors(cfg, RISLEY_ONLY, "risley")
        refuse_errors(cfg, FSM_ONLY, "fsm")
        if cfg.instrument.emitter != "channels":
            raise InputError("instrument.emitter", cfg.instrument.emitter, "channels with the galvo deflector")
        for believed in (False, True):
            self._check_reflects(believed)

    def _check_reflects(self, believed: bool) -> None:
        """Every channel at every corner of the field must meet both mirrors on their fronts, within the aperture."""
        geom = self.geometry(believed)
        h, v = self.half_field_rad
        delta = np.array([-h, h, -h, h, 0.0]) / 2.0
        gamma = np.array([-v, -v, v, v, 0.0]) / 2.0
        hits = galvo_model.mirror_hits(geom, delta[:, None], gamma[:, None],
                                       np.arange(len(geom.channel_angles_rad))[None, :])
        if not hits.front.all():
            raise InputError("galvo.field_deg", ",".join(map(str, self.cfg.galvo.field_deg)),
                             "a field whose beams meet both mirrors on their reflecting sides")
        reach_mm = 1e3 * float(max(hits.off_pivot1.max(), hits.off_pivot2.max()))
        if reach_mm > self.cfg.galvo.aperture_mm:
            side = "[processing]" if believed else "[galvo]"
            raise InputError("galvo.aperture_mm", self.cfg.galvo.aperture_mm,
                             f"at least {reach_mm:.2f} mm: with the b_mm, e_mm of {side} the beams meet the mirrors "
                             f"that far from their pivots over the field")

    def timing(self) -> PulseTiming:
        g = self.cfg.galvo
        return PulseTiming(prf_hz=g.strips * g.columns / g.frame_s, rotation_hz=0.0, phase0_rad=0.0,
                           field_prefix="galvo")

    def params(self, believed: bool) -> galvo.Galvo:
        cfg, g = self.cfg, self.cfg.galvo
        s = galvo.Galvo()
        b_mm, e_mm = (cfg.processing.b_mm, cfg.processing.e_mm) if believed else (g.b_mm, g.e_mm)
        s.b, s.e, s.aperture = b_mm * 1e-3, e_mm * 1e-3, g.aperture_mm * 1e-3
        s.h_half, s.v_half = (f / 2.0 for f in self.half_field_rad)
        s.strips, s.columns = g.strips, g.columns
        e = cfg.errors
        errors = (0.0,) * 6 if believed else (e.b1_arcsec, e.b2_arcsec, e.b3_arcsec, e.c1_arcsec, e.h_noise_arcsec,
                                              e.v_noise_arcsec)
        s.b1, s.b2, s.b3, s.c1, s.sigma_h, s.sigma_v = (v * ARCSEC for v in errors)
        return s

    @property
    def believed_is_truth(self) -> bool:
        cfg, e = self.cfg, self.cfg.errors
        angles = (e.b1_arcsec, e.b2_arcsec, e.b3_arcsec, e.c1_arcsec, e.h_noise_arcsec, e.v_noise_arcsec)
        return not any(angles) and (cfg.processing.b_mm, cfg.processing.e_mm) == (cfg.galvo.b_mm, cfg.galvo.e_mm)

    def max_off_axis_rad(self, emitter) -> float:
        """Largest angle of any beam from the optical axis over the field [rad] (traced at the corners)."""
        geom = self.geometry()
        h, v = self.half_field_rad
        delta = np.array([-h, h, -h, h]) / 2.0
        gamma = np.array([-v, -v, v, v]) / 2.0
        _, direction = galvo_model.trace(geom, delta[:, None], gamma[:, None],
                                         np.arange(len(geom.channel_angles_rad))[None, :])
        return float(np.arccos(np.clip(direction[..., 2], -1.0, 1.0)).max())

    def reach_deg(self, emitter) -> float:
        return math.degrees(self.max_off_axis_rad(emitter))
