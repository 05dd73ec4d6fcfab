"""Errors of the pose the processing believes, applied to the truth (any instrument, any platform):
the residual boresight error of the mounting and the POS (GNSS/IMU) noise of each pulse.

- ``errors.boresight_arcsec`` (roll, pitch, yaw): the true sensor axes are the believed ones turned
  by these angles (same convention as ``sensor.boresight_deg``: yaw, then pitch, then roll);
- ``errors.position_noise_m``: the true sensor position is the POS's plus a Gaussian of this 1σ on
  each local axis, drawn per pulse (all beams of a pulse share it);
- ``errors.attitude_noise_arcsec``: the true sensor axes are further turned by a rotation vector with
  this 1σ on each sensor axis, drawn per pulse.
"""
from __future__ import annotations

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from flightsim.core.config import ARCSEC, RunConfig
from kernels import trace


def has_pose_errors(cfg: RunConfig) -> bool:
    e = cfg.errors
    return any(e.boresight_arcsec) or e.position_noise_m > 0.0 or e.attitude_noise_arcsec > 0.0


def mount_rotation(cfg: RunConfig) -> np.ndarray:
    """The boresight error as a float64 3×3 matrix: true sensor axes in the believed sensor frame."""
    roll, pitch, yaw = (v * ARCSEC for v in cfg.errors.boresight_arcsec)
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def pose_errors(cfg: RunConfig) -> trace.PoseErrors:
    """The kernels' struct of the pose errors of ``cfg``."""
    s = trace.PoseErrors()
    s.mount = wp.mat33d(*mount_rotation(cfg).ravel())
    s.position_sigma = cfg.errors.position_noise_m
    s.attitude_sigma = cfg.errors.attitude_noise_arcsec * ARCSEC
    return s
