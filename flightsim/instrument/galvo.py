"""The two-mirror galvanometer scanner (``instrument.deflector = "galvo"``, ``[galvo]``): its mirrors and raster
(kernels/galvo.py), the angle errors of the seed paper's §2 on the truth, and the mirror separations the
georeferencing believes in (``believed_*``; 0 = the true value)."""
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
from flightsim.instrument import galvo_model
from trajectories import PulseTiming

galvo = lazy_module("kernels.galvo")

MAX_FIELD_DEG = 80.0  # full field of either axis [deg]
ANGLE_ERRORS = ("b1_arcsec", "b2_arcsec", "b3_arcsec", "c1_arcsec", "h_noise_arcsec", "v_noise_arcsec")


def _arcsec(doc: str, noise: bool = False):
    return setting(0.0, doc, "arcsec", range=(0.0 if noise else -3600.0, 3600.0))


@dataclass
class GalvoSettings(Settings):
    """The two galvanometer mirrors, their raster, their angle errors and the mirrors the processing believes in."""

    b_mm: float = setting(50.0, "source to mirror 1", "mm", range=(0.0, 1000.0), lo_open=True)
    e_mm: float = setting(20.0, "mirror 1 to mirror 2", "mm", range=(0.0, 1000.0), lo_open=True)
    aperture_mm: float = setting(15.0, "half size of each mirror", "mm", range=(0.0, 1000.0), lo_open=True)
    field_deg: tuple[float, float] = setting((30.0, 30.0), "full field of the central ray: horizontal, vertical",
                                             "deg", length=2)
    strips: int = setting(17, "horizontal strips per frame", "strips", range=(1, 4096))
    columns: int = setting(256, "pulses per strip", "pulses", range=(1, 65536))
    frame_s: float = setting(0.1, "time per frame", "s", range=(0.0, 3600.0), lo_open=True)
    b1_arcsec: float = _arcsec("horizontal encoder zero error on the truth")
    b2_arcsec: float = _arcsec("collimation-axis error on the truth")
    b3_arcsec: float = _arcsec("horizontal-axis error on the truth")
    c1_arcsec: float = _arcsec("vertical encoder zero error on the truth")
    h_noise_arcsec: float = _arcsec("horizontal mirror angle noise per pulse, 1 sigma", noise=True)
    v_noise_arcsec: float = _arcsec("vertical mirror angle noise per pulse, 1 sigma", noise=True)
    believed_b_mm: float = setting(0.0, "source to mirror 1 as the processing believes; 0 = the true one", "mm",
                                   range=(0.0, 1000.0))
    believed_e_mm: float = setting(0.0, "mirror 1 to mirror 2 as the processing believes; 0 = the true one", "mm",
                                   range=(0.0, 1000.0))

    def check(self, context) -> None:
        if not all(0.0 < f <= MAX_FIELD_DEG for f in self.field_deg):
            raise InputError("galvo.field_deg", ",".join(map(str, self.field_deg)),
                             f"two full angles (horizontal, vertical) in (0, {MAX_FIELD_DEG:g}] deg")
        if context is None:
            return
        if context.emitter != "channels":
            raise InputError("instrument.emitter", context.emitter, "channels with the galvo deflector")
        if "nominal" in context.models:
            raise InputError("output.models", ",".join(context.models),
                             "exact (the rigid-array nominal model is defined for the risley deflector only)")
        if context.optics == "lut":
            raise InputError("run.optics", context.optics, "float32 or float64 (lut tabulates the risley wedge only)")
        angles = tuple(context.settings("channels").angles_mrad)
        resolved = self.resolved()
        for believed in (False, True):
            _check_reflects(resolved, angles, believed)

    def resolved(self) -> "GalvoSettings":
        s = super().resolved()
        s.believed_b_mm = s.believed_b_mm or s.b_mm
        s.believed_e_mm = s.believed_e_mm or s.e_mm
        return s


def geometry(s: GalvoSettings, channel_angles_mrad, believed: bool = False) -> galvo_model.GalvoGeometry:
    """The float64 reference model of the scanner (truth, or as the processing believes it)."""
    b, e = (s.believed_b_mm, s.believed_e_mm) if believed else (s.b_mm, s.e_mm)
    return galvo_model.GalvoGeometry(b_m=b * 1e-3, e_m=e * 1e-3,
                                     channel_angles_rad=tuple(np.asarray(channel_angles_mrad) * 1e-3),
                                     field_deg=tuple(s.field_deg), strips=s.strips, columns=s.columns)


def _half_field_rad(s: GalvoSettings) -> tuple[float, float]:
    return tuple(math.radians(f) / 2.0 for f in s.field_deg)


def _check_reflects(s: GalvoSettings, angles_mrad, believed: bool) -> None:
    """Every channel at every corner of the field must meet both mirrors on their fronts, within the aperture."""
    geom = geometry(s, angles_mrad, believed)
    h, v = _half_field_rad(s)
    delta = np.array([-h, h, -h, h, 0.0]) / 2.0
    gamma = np.array([-v, -v, v, v, 0.0]) / 2.0
    hits = galvo_model.mirror_hits(geom, delta[:, None], gamma[:, None], np.arange(len(angles_mrad))[None, :])
    if not hits.front.all():
        raise InputError("galvo.field_deg", ",".join(map(str, s.field_deg)),
                         "a field whose beams meet both mirrors on their reflecting sides")
    reach_mm = 1e3 * float(max(hits.off_pivot1.max(), hits.off_pivot2.max()))
    if reach_mm > s.aperture_mm:
        side = "believed_b_mm, believed_e_mm" if believed else "b_mm, e_mm"
        raise InputError("galvo.aperture_mm", s.aperture_mm,
                         f"at least {reach_mm:.2f} mm: with the {side} of [galvo] the beams meet the mirrors "
                         f"that far from their pivots over the field")


@register("deflector", "galvo")
class GalvoDeflector:
    """``[galvo]`` (resolved settings) in front of a channel emitter."""

    settings = GalvoSettings
    rigid_nominal = False

    @property
    def kernel(self):
        """The kernel side: its struct and device functions."""
        return galvo.GALVO

    def __init__(self, s: GalvoSettings, emitter):
        self.s = s
        self.emitter = emitter
        self.half_field_rad = _half_field_rad(s)

    def geometry(self, believed: bool = False) -> galvo_model.GalvoGeometry:
        """The float64 reference model of this scanner (truth, or as the processing believes it)."""
        return geometry(self.s, self.emitter.angles_mrad, believed)

    def timing(self) -> PulseTiming:
        s = self.s
        return PulseTiming(prf_hz=s.strips * s.columns / s.frame_s, rotation_hz=0.0, phase0_rad=0.0,
                           field_prefix="galvo")

    def params(self, believed: bool):
        s, out = self.s, galvo.Galvo()
        b_mm, e_mm = (s.believed_b_mm, s.believed_e_mm) if believed else (s.b_mm, s.e_mm)
        out.b, out.e, out.aperture = b_mm * 1e-3, e_mm * 1e-3, s.aperture_mm * 1e-3
        out.h_half, out.v_half = (f / 2.0 for f in self.half_field_rad)
        out.strips, out.columns = s.strips, s.columns
        errors = (0.0,) * 6 if believed else tuple(getattr(s, name) for name in ANGLE_ERRORS)
        out.b1, out.b2, out.b3, out.c1, out.sigma_h, out.sigma_v = (v * ARCSEC for v in errors)
        return out

    @property
    def believed_is_truth(self) -> bool:
        s = self.s
        return not any(getattr(s, name) for name in ANGLE_ERRORS) and (s.believed_b_mm, s.believed_e_mm) == (
            s.b_mm, s.e_mm)

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the optical axis over the field [rad] (traced at the corners)."""
        geom = self.geometry()
        h, v = self.half_field_rad
        delta = np.array([-h, h, -h, h]) / 2.0
        gamma = np.array([-v, -v, v, v]) / 2.0
        _, direction = galvo_model.trace(geom, delta[:, None], gamma[:, None],
                                         np.arange(len(geom.channel_angles_rad))[None, :])
        return float(np.arccos(np.clip(direction[..., 2], -1.0, 1.0)).max())

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint at the slant range of the widest beam (no rigid-array model)."""
        return footprint_buffer_m(altitude_m, self.max_off_axis_rad(), divergence_mrad)
