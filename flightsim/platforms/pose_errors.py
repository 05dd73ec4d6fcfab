"""The pose error model (``instrument.errors`` holds ``"pose"``, ``[pose]``): errors of the pose the processing
believes, applied to the truth (any instrument, any platform): the residual boresight error of the mounting and
the POS (GNSS/IMU) noise of each pulse.

- ``boresight_arcsec`` (roll, pitch, yaw): the true sensor axes are the believed ones turned by these angles
  (same convention as ``instrument.boresight_deg``: yaw, then pitch, then roll);
- ``position_noise_m``: the true sensor position is the POS's plus a Gaussian of this 1σ on each local axis,
  drawn per pulse (all beams of a pulse share it);
- ``attitude_noise_arcsec``: the true sensor axes are further turned by a rotation vector with this 1σ on each
  sensor axis, drawn per pulse.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.core.constants import ARCSEC
from kernels import error_models
from trajectories import rotation


@dataclass
class PoseSettings(Settings):
    """The boresight calibration's residual error and the POS noise per pulse (all off by default)."""

    boresight_arcsec: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), "roll, pitch, yaw of the true sensor axes in the believed ones", "arcsec", length=3,
        items=(-3600.0, 3600.0))
    position_noise_m: float = setting(0.0, "POS position noise per axis and pulse, 1 sigma", "m", range=(0.0, 100.0))
    attitude_noise_arcsec: float = setting(0.0, "POS attitude noise about each sensor axis per pulse, 1 sigma",
                                           "arcsec", range=(0.0, 3600.0))


@register("errors", "pose")
class PoseErrors:
    """The pose errors of ``[pose]``; the default settings are no error at all."""

    settings = PoseSettings

    def __init__(self, s: PoseSettings | None = None):
        self.s = s or PoseSettings()

    @property
    def active(self) -> bool:
        s = self.s
        return any(s.boresight_arcsec) or s.position_noise_m > 0.0 or s.attitude_noise_arcsec > 0.0

    def mount_rotation(self) -> np.ndarray:
        """The boresight error as a float64 3×3 matrix: true sensor axes in the believed sensor frame."""
        roll, pitch, yaw = (v * ARCSEC for v in self.s.boresight_arcsec)
        return rotation.as_matrix(rotation.from_euler_zyx([yaw, pitch, roll]))

    def struct(self) -> error_models.PoseErrors:
        """The kernels' struct of the pose errors."""
        out = error_models.PoseErrors()
        out.mount = wp.mat33d(*self.mount_rotation().ravel())
        out.position_sigma = self.s.position_noise_m
        out.attitude_sigma = self.s.attitude_noise_arcsec * ARCSEC
        return out
