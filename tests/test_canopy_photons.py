"""Photon counting through a turbid leaf layer (kernels/canopy_photons.py): one nadir SPAD pixel over a plane under a
homogeneous layer; the leaves' and the plane's photo-electrons per pulse and the leaves' mean depth against the
Beer–Lambert integrals of the lidar equation, done here in float64."""
from __future__ import annotations

import math

import h5py
import numpy as np
from scipy import integrate

import flightsim
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import write_canopy_npz

ORIGIN = np.array([409000.0, 3393000.0, 450.0])
BOTTOM, TOP, LAD, RHO_LEAF, RHO_GROUND = 10.0, 18.0, 0.3, 0.45, 0.5
ALTITUDE, ENERGY, PRF, DURATION = 100.0, 6e-10, 1000.0, 2.0
H, C = 6.62607015e-34, 299792458.0


def _photons(tmp_path):
    grid = np.zeros((20, 20, 20), np.float32)
    grid[:, :, int(BOTTOM):int(TOP)] = LAD
    canopy = VoxelCanopy(grid, np.array([-100.0, -100.0, 0.0]), np.array([10.0, 10.0, 1.0]),
                         leaf_reflectance=RHO_LEAF)
    path = write_canopy_npz(tmp_path / "layer.npz", canopy, "EPSG:32648", ORIGIN)
    overrides = {"instrument.deflector": "fixed", "fan.array": 1, "fixed.prf_hz": PRF, "flight.duration_s": DURATION,
                 "flight.altitude_m": ALTITUDE, "scene.name": "plane", "scene.canopy": str(path),
                 "photon.gate_m": [50.0, 150.0], "photon.noise_hz": 0.0, "photon.dead_time_s": 0.0,
                 "photon.max_events": 64, "photon.tdc_bin_s": 0.0, "photon.pulse_energy_j": ENERGY,
                 "photon.reflectance": RHO_GROUND}
    config = flightsim.load_config(instrument="spad", overrides=overrides)
    result = flightsim.simulate(config)
    with h5py.File(result.directory / "photons.h5") as f:
        return config, result.stats, f["photons/range_m"][:], f["photons/signal"][:]


def test_leaf_and_ground_photons_follow_the_lidar_equation_through_the_layer(tmp_path):
    config, stats, ranges, kind = _photons(tmp_path)
    p = config.photon
    pulses = round(DURATION * PRF) + 1
    per_lambert = (ENERGY * p.wavelength_nm * 1e-9 / (H * C) * math.pi * (p.aperture_m / 2) ** 2
                   * p.optics_transmission * p.pde / math.pi)  # photo-electrons of a white target at 1 m
    kappa, depth = 0.5 * LAD, TOP - BOTTOM  # spherical leaves at nadir
    r_top = ALTITUDE - TOP
    profile = lambda s: RHO_LEAF * per_lambert * kappa * math.exp(-kappa * s) / (r_top + s) ** 2  # noqa: E731
    n_leaf = integrate.quad(profile, 0.0, depth, epsrel=1e-12)[0]
    mean_depth = integrate.quad(lambda s: s * profile(s), 0.0, depth, epsrel=1e-12)[0] / n_leaf
    var_depth = integrate.quad(lambda s: (s - mean_depth) ** 2 * profile(s), 0.0, depth, epsrel=1e-12)[0] / n_leaf
    n_ground = RHO_GROUND * per_lambert / ALTITUDE ** 2 * math.exp(-kappa * depth)

    leaves, ground = kind == 3, kind == 1
    assert (kind == 0).sum() == 0 and leaves.sum() + ground.sum() == len(kind)
    for observed, mean in ((leaves.sum(), pulses * n_leaf), (ground.sum(), pulses * n_ground)):
        assert abs(observed - mean) < 4.0 * math.sqrt(mean), (observed, mean)
    sigma_m = 0.5 * C * math.hypot(p.pulse_fwhm_s / 2.3548200450309493, p.jitter_s)
    spread = math.sqrt(var_depth + sigma_m ** 2)
    assert abs((ranges[leaves] - r_top).mean() - mean_depth) < 4.0 * spread / math.sqrt(leaves.sum())
    assert abs(ranges[ground].mean() - ALTITUDE) < 4.0 * sigma_m / math.sqrt(ground.sum())
