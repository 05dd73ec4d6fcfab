"""The rotating-wedge (Risley) deflector (``instrument.deflector = "risley"``, ``[risley]``): one Fresnel wedge
turning at the scan rate (SPEC §4), the prism-angle encoder's errors on the truth, and the wedge the
georeferencing believes in (``believed_*``; 0 = the true value)."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.core.constants import ARCSEC
from flightsim.instrument import risley_model
from kernels import wedge
from kernels.optics import exit_fan_kernel
from trajectories import PulseTiming

FAN_DEVICE = "cpu"  # where the exit fan is traced (one float64 reference for every run device)


@dataclass
class RisleySettings(Settings):
    """The wedge prism, its scan and timing, its encoder's errors and the wedge the processing believes in."""

    prf_hz: float = setting(5000.0, "pulse repetition frequency", "Hz", range=(0.0, 1.0e7), lo_open=True)
    rotation_hz: float = setting(20.0, "prism turns per second", "Hz", range=(0.0, 1000.0))
    phase0_deg: float = setting(0.0, "prism angle at the line's first pulse", "deg", range=(-360.0, 360.0))
    cone_half_angle_deg: float = setting(15.0, "deviation of the on-axis beam (the scan cone's half angle); "
                                         "derives the apex angle when apex_angle_deg is 0", "deg",
                                         range=(0.0, 89.0), lo_open=True)
    apex_angle_deg: float = setting(0.0, "wedge apex angle α; 0 derives it from cone_half_angle_deg", "deg",
                                    range=(0.0, 89.0))
    refractive_index: float = setting(1.5066, "refractive index of the glass (BK7 at 1064 nm)", "",
                                      range=(1.0, 4.0), lo_open=True)
    thickness_mm: float = setting(10.0, "centre thickness d1", "mm", range=(0.0, 1000.0), lo_open=True)
    encoder_arcsec: float = setting(0.0, "prism-angle encoder zero error on the truth", "arcsec",
                                    range=(-3600.0, 3600.0))
    encoder_noise_arcsec: float = setting(0.0, "prism-angle noise per pulse, 1 sigma", "arcsec", range=(0.0, 3600.0))
    believed_refractive_index: float = setting(0.0, "refractive index the processing believes; 0 = the true one",
                                               "", range=(0.0, 4.0))
    believed_apex_angle_deg: float = setting(0.0, "apex angle the processing believes; 0 = the true one", "deg",
                                             range=(0.0, 89.0))
    believed_thickness_mm: float = setting(0.0, "thickness the processing believes; 0 = the true one", "mm",
                                           range=(0.0, 1000.0))

    def check(self, context) -> None:
        critical = math.degrees(math.asin(1.0 / self.refractive_index))
        if self.apex_angle_deg > 0.0 and self.apex_angle_deg >= critical:
            raise InputError("risley.apex_angle_deg", self.apex_angle_deg,
                             f"an angle below {critical:.3f} deg (total internal reflection of the on-axis beam)")
        max_cone = 90.0 - critical
        if self.apex_angle_deg == 0.0 and self.cone_half_angle_deg >= max_cone:
            raise InputError("risley.cone_half_angle_deg", self.cone_half_angle_deg,
                             f"an angle in (0, {max_cone:.3f}) deg for refractive index {self.refractive_index:g}")
        if 0.0 < self.believed_refractive_index <= 1.0:
            raise InputError("risley.believed_refractive_index", self.believed_refractive_index,
                             "0 (the true index) or a number in (1, 4]")
        n_believed = self.believed_refractive_index or self.refractive_index
        if self.believed_apex_angle_deg > 0.0 and math.sin(math.radians(self.believed_apex_angle_deg)) * n_believed >= 1.0:
            raise InputError("risley.believed_apex_angle_deg", self.believed_apex_angle_deg,
                             f"an angle below {math.degrees(math.asin(1.0 / n_believed)):.3f} deg")
        if context is not None and context.optics == "lut" and (self.encoder_arcsec or self.encoder_noise_arcsec):
            raise InputError("run.optics", "lut", "float32 or float64 with prism-encoder errors "
                                                  "(the table tabulates the error-free wedge)")

    def resolved(self) -> "RisleySettings":
        """The apex angle derived from the cone (or the cone from a given apex) and the believed wedge filled in."""
        s = super().resolved()
        if s.apex_angle_deg > 0.0:
            cone = math.degrees(risley_model.cone_for_apex(math.radians(s.apex_angle_deg), s.refractive_index))
            if abs(cone - s.cone_half_angle_deg) > 1e-9:  # keep a stated cone that the apex already implies
                s.cone_half_angle_deg = cone
        else:
            s.apex_angle_deg = math.degrees(risley_model.apex_for_cone(math.radians(s.cone_half_angle_deg),
                                                                       s.refractive_index))
        s.believed_refractive_index = s.believed_refractive_index or s.refractive_index
        s.believed_apex_angle_deg = s.believed_apex_angle_deg or s.apex_angle_deg
        s.believed_thickness_mm = s.believed_thickness_mm or s.thickness_mm
        return s


@functools.lru_cache(maxsize=256)
def turn_angles(beams: int, spacing_rad: float, refractive_index: float, apex_deg: float, thickness_mm: float,
                samples: int) -> tuple[float, float]:
    """(largest angle of an exiting sub-beam from the prism axis, largest angle between a sub-beam's true and
    rigid-array exit directions) over ``samples`` prism angles of a turn [rad], of a ``beams``×``beams`` fan of
    ``spacing_rad`` through the prism (traced in float64). Kept for a sweep's configurations, which share few fans
    (the paper's study: 25 in 250)."""
    phi = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
    fan = risley_model.trace_fan(phi, beams, spacing_rad, refractive_index, math.radians(apex_deg),
                                 thickness_mm * 1e-3, precision="float64", device=FAN_DEVICE)
    if not fan.ok.any():
        return 0.0, 0.0
    off_axis = np.arctan2(np.hypot(fan.directions[..., 0], fan.directions[..., 1]), fan.directions[..., 2])
    cross = np.linalg.norm(np.cross(fan.directions, fan.nominal), axis=-1)
    distortion = np.arctan2(cross, np.sum(fan.directions * fan.nominal, axis=-1))
    return float(off_axis[fan.ok].max()), float(distortion[fan.ok].max())


def _prism(n_glass: float, apex_deg: float, thickness_mm: float, encoder_arcsec: float = 0.0,
           encoder_noise_arcsec: float = 0.0):
    prism = wedge.Prism()
    prism.n_glass = n_glass
    prism.apex = math.radians(apex_deg)
    prism.thickness = thickness_mm * 1e-3
    prism.encoder = encoder_arcsec * ARCSEC
    prism.encoder_sigma = encoder_noise_arcsec * ARCSEC
    return prism


@register("deflector", "risley")
class RisleyDeflector:
    """The wedge of ``[risley]`` (resolved settings) turning at ``rotation_hz`` in front of a fan emitter."""

    settings = RisleySettings
    kernel = wedge.WEDGE  # the kernel side: its struct and device functions
    rigid_nominal = True  # the rigid-array (nominal) georeferencing model is defined for it

    def __init__(self, s: RisleySettings, emitter):
        self.s = s
        self.emitter = emitter

    def timing(self) -> PulseTiming:
        s = self.s
        return PulseTiming(prf_hz=s.prf_hz, rotation_hz=s.rotation_hz, phase0_rad=math.radians(s.phase0_deg),
                           field_prefix="risley")

    def params(self, believed: bool):
        s = self.s
        if believed:
            return _prism(s.believed_refractive_index, s.believed_apex_angle_deg, s.believed_thickness_mm)
        return _prism(s.refractive_index, s.apex_angle_deg, s.thickness_mm, s.encoder_arcsec, s.encoder_noise_arcsec)

    @property
    def believed_is_truth(self) -> bool:
        s = self.s
        return not (s.encoder_arcsec or s.encoder_noise_arcsec) and (
            (s.believed_refractive_index, s.believed_apex_angle_deg, s.believed_thickness_mm)
            == (s.refractive_index, s.apex_angle_deg, s.thickness_mm))

    def _fan(self, phi: np.ndarray) -> risley_model.ExitFan:
        s = self.s
        return risley_model.trace_fan(phi, self.emitter.n, self.emitter.spacing_rad, s.refractive_index,
                                      math.radians(s.apex_angle_deg), s.thickness_mm * 1e-3, precision="float64",
                                      device=FAN_DEVICE)

    def setup_kernels(self) -> list:
        """(kernel, device) of what the deflector launches while a run is set up: the float64 exit fan of its reach,
        distortion and exit table (:meth:`_fan`)."""
        return [(exit_fan_kernel(wp.float64), FAN_DEVICE)]

    def reach_deg(self) -> float:
        """A bound on any beam's angle from the sensor axis, to first order [deg]."""
        return self.s.cone_half_angle_deg + math.degrees(self.emitter.half_diagonal_rad)

    def max_off_axis_rad(self, samples: int = 72) -> float:
        """Largest angle between any exiting sub-beam and the prism axis over a prism turn [rad] (traced)."""
        return self._turn_angles(samples)[0]

    def max_distortion_rad(self, samples: int = 360) -> float:
        """Largest angle between a sub-beam's true and rigid-array exit directions over a turn [rad]."""
        return self._turn_angles(samples)[1]

    def _turn_angles(self, samples: int) -> tuple[float, float]:
        """:func:`turn_angles` of this deflector's fan and prism."""
        s = self.s
        return turn_angles(self.emitter.n, self.emitter.spacing_rad, s.refractive_index, s.apex_angle_deg,
                           s.thickness_mm, samples)

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint and the rigid-array distortion at the slant range of the
        scan cone, h / cos θ · (divergence/2 + the largest distortion angle)."""
        slant = altitude_m / math.cos(math.radians(self.s.cone_half_angle_deg))
        return slant * (0.5 * divergence_mrad * 1e-3 + self.max_distortion_rad())

    def exit_table(self, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """Exit directions (zero where the beam is reflected) and exit points [m] of every beam at ``samples`` + 1
        prism angles over a turn, float32 (the ``lut`` optics)."""
        fan = self._fan(np.linspace(0.0, 2.0 * np.pi, samples + 1))
        return ((fan.directions * fan.ok[..., None]).astype(np.float32), fan.exit_points.astype(np.float32))
