"""The panoramic deflector (``instrument.deflector = "panoramic"``, ``[panoramic]``): a terrestrial laser
scanner's line mirror (vertical scan lines over a vertical field) and rotating head (azimuth), stepped at fixed
angle steps (kernels/panoramic.py), with the encoders' zero errors on the truth. Mount it on the ``tripod``
platform."""
from __future__ import annotations

import math
from dataclasses import dataclass

from flightsim.core.constants import ARCSEC
from flightsim.core.errors import InputError
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.instrument.base import footprint_buffer_m
from trajectories import PulseTiming

panoramic = lazy_module("kernels.panoramic")

MAX_SCAN_PULSES = 2 ** 31 - 1  # measurements of one scan (the kernels count them in int32)


@dataclass
class PanoramicSettings(Settings):
    """The scan pattern of a panoramic (terrestrial) scanner: vertical lines over a field of elevations, the
    head turning in azimuth between them."""

    measurement_rate_hz: float = setting(125000.0, "measurements per second inside the field (the effective "
                                         "measurement rate)", "Hz", range=(0.0, 1.0e7), lo_open=True)
    vertical_deg: tuple[float, float] = setting((-40.0, 60.0), "elevations of a line's first and last measurement "
                                                "(0 = the head's horizontal plane, up positive)", "deg",
                                                length=2, items=(-90.0, 90.0))
    vertical_step_deg: float = setting(0.04, "elevation step between measurements of a line", "deg",
                                       range=(0.0, 10.0), lo_open=True)
    azimuth_deg: tuple[float, float] = setting((0.0, 360.0), "azimuths of the first and last line, clockwise from "
                                               "the tripod's heading", "deg", length=2, items=(-360.0, 720.0))
    azimuth_step_deg: float = setting(0.04, "azimuth step between lines", "deg", range=(0.0, 10.0), lo_open=True)
    zero_arcsec: tuple[float, float] = setting((0.0, 0.0), "zero errors of the azimuth and elevation encoders on "
                                               "the truth", "arcsec", length=2, items=(-3600.0, 3600.0))

    @property
    def per_line(self) -> int:
        lo, hi = self.vertical_deg
        return int(math.floor((hi - lo) / self.vertical_step_deg + 1e-9)) + 1

    @property
    def lines(self) -> int:
        start, stop = self.azimuth_deg
        return int(math.floor((stop - start) / self.azimuth_step_deg + 1e-9)) + 1

    @property
    def scan_pulses(self) -> int:
        """Measurements of one scan (the pattern repeats after them)."""
        return self.per_line * self.lines

    @property
    def scan_s(self) -> float:
        """Duration of one scan [s]."""
        return self.scan_pulses / self.measurement_rate_hz

    def check(self, context) -> None:
        lo, hi = self.vertical_deg
        if not lo < hi:
            raise InputError("panoramic.vertical_deg", list(self.vertical_deg),
                             "[lowest, highest] elevations in [-90, 90] deg with lowest < highest")
        start, stop = self.azimuth_deg
        if not start < stop <= start + 360.0:
            raise InputError("panoramic.azimuth_deg", list(self.azimuth_deg),
                             "[start, stop] azimuths with start < stop <= start + 360 deg")
        if self.scan_pulses > MAX_SCAN_PULSES:
            raise InputError("panoramic.vertical_step_deg", self.vertical_step_deg,
                             f"steps giving at most {MAX_SCAN_PULSES} measurements per scan (these give "
                             f"{self.scan_pulses}: {self.per_line} per line × {self.lines} lines)")


@register("deflector", "panoramic")
class PanoramicDeflector:
    """``[panoramic]``: vertical lines turned in azimuth, pulses at ``measurement_rate_hz``."""

    settings = PanoramicSettings
    rigid_nominal = False

    @property
    def kernel(self):
        """The kernel side: its struct and device functions."""
        return panoramic.PANORAMIC

    def __init__(self, s: PanoramicSettings, emitter):
        self.s = s
        self.emitter = emitter

    def timing(self) -> PulseTiming:
        return PulseTiming(prf_hz=self.s.measurement_rate_hz, rotation_hz=0.0, phase0_rad=0.0,
                           field_prefix="panoramic")

    def params(self, believed: bool):
        c, out = self.s, panoramic.Panoramic()
        out.elev_lo, out.elev_step = math.radians(c.vertical_deg[0]), math.radians(c.vertical_step_deg)
        out.az_start, out.az_step = math.radians(c.azimuth_deg[0]), math.radians(c.azimuth_step_deg)
        out.per_line, out.lines = c.per_line, c.lines
        zero = (0.0, 0.0) if believed else tuple(c.zero_arcsec)
        out.zero_az, out.zero_elev = (v * ARCSEC for v in zero)
        return out

    @property
    def believed_is_truth(self) -> bool:
        return not any(self.s.zero_arcsec)

    def max_off_axis_rad(self) -> float:
        """Largest angle of any beam from the sensor axis (the head's axis, down when level) [rad]."""
        fan = getattr(self.emitter, "half_diagonal_rad", 0.0)
        return min(math.pi, math.pi / 2.0 + math.radians(self.s.vertical_deg[1]) + fan)

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint at the slant range of the widest beam (no rigid-array model)."""
        return footprint_buffer_m(altitude_m, self.max_off_axis_rad(), divergence_mrad)
