"""Full waveforms through a turbid leaf layer (kernels/waveform.py leaf_echo): a homogeneous layer of leaf area index
L over a plane, the beam at nadir or 20° off, spherical or planophile leaves. The plane's echo is the open plane's
times exp(−G L / cos θ); the leaves' echo and its mean height are integrals of the Beer–Lambert profile, done
here in float64 by quadrature."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

import flightsim
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import write_canopy_npz
from flightsim.scenes.leaf_angles import g_function

ORIGIN = np.array([409000.0, 3393000.0, 450.0])
BOTTOM, TOP, LAD, RHO_LEAF, F_GROUND = 10.0, 18.0, 0.3, 0.45, 0.1  # layer [m], [m²/m³], albedo, ground BRDF [1/sr]
ALTITUDE = 100.0


def _waveforms(tmp_path, pitch_deg: float, leaf_angles: str | None):
    overrides = {"instrument.deflector": "fixed", "fixed.prf_hz": 10.0, "flight.duration_s": 0.1,
                 "flight.altitude_m": ALTITUDE, "flight.pitch_deg": pitch_deg, "scene.name": "plane",
                 "waveform.pulse_fwhm_s": 4e-9, "waveform.sample_interval_s": 2.5e-10, "waveform.samples": 2048,
                 "waveform.n_rings": 6, "waveform.n_sectors": 12, "waveform.reflectance": F_GROUND}
    if leaf_angles is not None:
        grid = np.zeros((20, 20, 20), np.float32)
        grid[:, :, int(BOTTOM):int(TOP)] = LAD
        canopy = VoxelCanopy(grid, np.array([-100.0, -100.0, 0.0]), np.array([10.0, 10.0, 1.0]),
                             leaf_angles=leaf_angles, leaf_reflectance=RHO_LEAF)
        overrides["scene.canopy"] = str(write_canopy_npz(tmp_path / f"{leaf_angles}.npz", canopy, "EPSG:32648", ORIGIN))
    config = flightsim.load_config(instrument="change1", overrides=overrides)
    ds = flightsim.simulate(config).waveforms
    rx = ds["rxwaveform"].values.astype(np.float64)
    n = rx.shape[1]
    heights = (ds["elevation_bin0"].values[:, None] + (ds["elevation_lastbin"].values - ds["elevation_bin0"].values)[:, None]
               * np.arange(n) / (n - 1)) - ORIGIN[2]
    return rx, heights


def _parts(rx, heights):
    """(ground energy, leaf energy, leaf centroid height − ground centroid height), summed over the shots."""
    ground, leaves = heights < 0.5 * BOTTOM, heights >= 0.5 * BOTTOM
    e_g, e_l = (rx * ground).sum(), (rx * leaves).sum()
    if e_l == 0.0:  # the open plane
        return e_g, e_l, None
    return e_g, e_l, (rx * leaves * heights).sum() / e_l - (rx * ground * heights).sum() / e_g


@pytest.mark.parametrize("pitch, leaves", [(0.0, "spherical"), (0.0, "planophile"), (20.0, "spherical"),
                                           (20.0, "planophile")])
def test_ground_and_leaf_echoes_are_the_beer_lambert_integrals(tmp_path, pitch, leaves):
    mu = math.cos(math.radians(pitch))
    g = float(g_function(leaves, np.array([mu]))[0])
    kappa = g * LAD  # extinction along the beam [1/m]
    open_rx, open_h = _waveforms(tmp_path, pitch, None)
    rx, h = _waveforms(tmp_path, pitch, leaves)
    e_open, nothing, _ = _parts(open_rx, open_h)
    assert nothing == 0.0
    e_g, e_l, centroid = _parts(rx, h)
    # G on the device is its 257-entry table (within 1e-5 of the integral): τ's relative error is below 4e-5
    assert e_g / e_open == pytest.approx(math.exp(-g * LAD * (TOP - BOTTOM) / mu), rel=1e-4)

    # along the beam: slant distance s into the layer from its top; range r(s); the open plane at r_g
    r_g = ALTITUDE / mu
    r_top = (ALTITUDE - TOP) / mu
    depth = (TOP - BOTTOM) / mu
    echo = lambda s: RHO_LEAF * kappa * math.exp(-kappa * s) / (r_top + s) ** 2  # noqa: E731
    leaf_energy = integrate.quad(echo, 0.0, depth, epsabs=0.0, epsrel=1e-12)[0]
    mean_depth = integrate.quad(lambda s: s * echo(s), 0.0, depth, epsabs=0.0, epsrel=1e-12)[0] / leaf_energy
    open_energy = math.pi * F_GROUND * mu / r_g ** 2  # π f cos θ_i / r² of the open plane
    assert e_l / e_open == pytest.approx(leaf_energy / open_energy, rel=2e-3)
    assert centroid == pytest.approx(TOP - mean_depth * mu, abs=0.01)
