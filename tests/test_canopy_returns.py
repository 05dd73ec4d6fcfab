"""Discrete returns through a turbid canopy (kernels/canopy_returns.py): a homogeneous leaf layer over a plane, one
nadir beam (or one tilted), each return where the closed form of the leading-edge trigger puts it."""
from __future__ import annotations

import math

import numpy as np
import pytest

import flightsim
from flightsim.cli import main
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.canopy_io import write_canopy_npz

ORIGIN = np.array([409000.0, 3393000.0, 450.0])
BOTTOM, TOP = 10.0, 18.0  # the leaf layer [m above the plane]


def _layer(tmp_path, lad, leaf_angles: str = "spherical", rho_leaf: float = 0.4) -> str:
    """A leaf layer between BOTTOM and TOP over the whole scene: ``lad`` [m²/m³] in every voxel, or a sequence of one
    per 1 m voxel layer from BOTTOM up."""
    grid = np.zeros((20, 20, 20), np.float32)
    grid[:, :, int(BOTTOM):int(TOP)] = np.asarray(lad, np.float32)
    canopy = VoxelCanopy(grid, np.array([-100.0, -100.0, 0.0]), np.array([10.0, 10.0, 1.0]), leaf_angles=leaf_angles,
                         leaf_reflectance=rho_leaf)
    return str(write_canopy_npz(tmp_path / "layer.npz", canopy, "EPSG:32648", ORIGIN))


def _run(tmp_path, lad, pitch_deg: float = 0.0, device: str = "cpu", **discrete):
    overrides = {"run.device": device, "instrument.deflector": "fixed", "fan.array": 1, "flight.platform": "hover",
                 "flight.altitude_m": 100.0, "flight.duration_s": 0.3, "fixed.prf_hz": 10.0,
                 "flight.pitch_deg": pitch_deg, "output.models": ["exact"], "scene.name": "plane",
                 "scene.canopy": _layer(tmp_path, lad), **{f"discrete.{k}": v for k, v in discrete.items()}}
    return flightsim.simulate(flightsim.load_config(overrides=overrides), with_truth=True)


def _expected(lad: float, cos_theta: float, thr: float, sep: float, rho_leaf: float, rho_ground: float, k_max: int):
    """Leaf returns (depth below the layer's top along the beam) and whether the plane returns: the trigger in
    float64, with G = 1/2 (spherical leaves)."""
    kappa, path = 0.5 * lad, (TOP - BOTTOM) / cos_theta
    depths, armed = [], 0.0
    while True:
        room = rho_leaf * math.exp(-kappa * armed)  # echo still to come below `armed`, per unit interception
        if room * (1.0 - math.exp(-kappa * (path - armed))) < thr:
            break
        depth = armed - math.log(1.0 - thr / room) / kappa
        depths.append(depth)
        armed = depth + sep
        if armed >= path:
            break
    transmission = math.exp(-kappa * path)
    ground = transmission * rho_ground * cos_theta >= thr and armed <= TOP / cos_theta and len(depths) < k_max
    return depths[:k_max], ground


def _expected_layers(lads, cos_theta: float, thr: float, sep: float, rho_leaf: float, rho_ground: float,
                     k_max: int):
    """As :func:`_expected` through 1 m voxel layers of leaf area densities ``lads`` (BOTTOM up), voxel by voxel as
    the detector listens: in each voxel the echo still to come, its intercepted energy ρ_l T (1 − exp(−κ x)) with
    an exp for every piece, gathered until it reaches the threshold, and after a return what the leaves send back
    while the detector is blind added to that return's echo. Returns (depths, echoes, ground)."""
    depths, echoes, transmission, gathered, armed, count = [], [], 1.0, 0.0, 0.0, 0
    for k, lad in enumerate(reversed(lads)):
        kappa, top, bottom = 0.5 * lad, k / cos_theta, (k + 1) / cos_theta
        s = top
        while kappa > 0.0 and s < bottom:
            room = rho_leaf * transmission * math.exp(-kappa * (s - top))
            if s < armed:  # blind
                end = min(armed, bottom)
                if count <= k_max:
                    echoes[-1] += room * (1.0 - math.exp(-kappa * (end - s)))
                s = end
            elif gathered + room * (1.0 - math.exp(-kappa * (bottom - s))) < thr:
                gathered += room * (1.0 - math.exp(-kappa * (bottom - s)))
                s = bottom
            else:
                s -= math.log(1.0 - (thr - gathered) / room) / kappa
                count += 1
                if count <= k_max:
                    depths.append(s)
                    echoes.append(thr)
                gathered, armed = 0.0, s + sep
        transmission *= math.exp(-kappa * (bottom - top))
    ground = transmission * rho_ground * cos_theta >= thr and armed <= TOP / cos_theta and count < k_max
    return depths, echoes, ground


@pytest.mark.parametrize("pitch, sep", [(0.0, 2.0), (20.0, 2.0), (20.0, 0.7), (0.0, 0.0)])
def test_returns_through_uneven_layers_are_those_of_a_voxel_by_voxel_detector(tmp_path, pitch, sep, device):
    """Layers of unequal density with empty ones between them, blind stretches ending inside voxels, in empty ones
    and past the last leaves, a tilted beam splitting voxels at the columns' walls: the returns' heights and echoes
    (LAS intensity, 1/65535 of a white target) against the float64 detector that takes an exp for every piece."""
    lads = [0.35, 0.0, 0.9, 0.05, 0.0, 0.0, 0.6, 0.2]  # BOTTOM up
    thr = 0.02
    result = _run(tmp_path, lads, pitch, device, min_separation_m=sep, max_returns=15, threshold=thr)
    cos_t = math.cos(math.radians(pitch))
    depths, echoes, ground = _expected_layers(lads, cos_t, thr, sep, 0.4, flightsim.load_config().discrete.reflectance,
                                              15)
    assert len(depths) >= 3 and (sep == 0.0 or max(echoes) > 1.5 * thr)  # blind stretches that gather echo
    r = result.returns
    pulses = np.unique(r.pulse)
    n = len(depths) + int(ground)
    assert len(pulses) >= 3 and len(r.pulse) == len(pulses) * n
    want_z = [TOP - depth * cos_t for depth in depths] + ([0.0] if ground else [])
    for pulse in pulses:
        mine = np.flatnonzero(r.pulse == pulse)
        z = r.true_points[mine[np.argsort(r.return_number[mine])], 2] - ORIGIN[2]
        assert np.abs(z - want_z).max() < 2e-4, (z, want_z)
    las = result.points["exact"]
    order = np.lexsort((np.asarray(las.return_number), np.asarray(las.gps_time)))
    intensity = np.asarray(las.intensity)[order].astype(np.int64).reshape(len(pulses), n)
    assert np.abs(intensity[:, :len(depths)] - np.rint(np.minimum(echoes, 1.0) * 65535.0)).max() <= 1


@pytest.mark.parametrize("lad, pitch", [(0.25, 0.0), (0.25, 20.0), (0.6, 0.0)])
def test_returns_lie_where_the_trigger_puts_them(tmp_path, lad, pitch, device):
    result = _run(tmp_path, lad, pitch, device)
    d = flightsim.load_config().discrete
    cos_t = math.cos(math.radians(pitch))
    depths, ground = _expected(lad, cos_t, d.threshold, d.min_separation_m, 0.4, d.reflectance, d.max_returns)
    r = result.returns
    n = len(depths) + int(ground)
    pulses = np.unique(r.pulse)
    assert n >= 2 and len(pulses) >= 3 and len(r.pulse) == len(pulses) * n  # every pulse the same returns
    heights = r.true_points[:, 2] - ORIGIN[2]
    for pulse in pulses:
        mine = r.pulse == pulse
        order = np.argsort(r.return_number[mine])
        z = heights[mine][order]
        want = [TOP - depth * cos_t for depth in depths] + ([0.0] if ground else [])
        assert np.abs(z - want).max() < 2e-4, (z, want)
        assert list(r.return_number[mine][order]) == list(range(1, n + 1))
        assert set(r.number_of_returns[mine]) == {n}
    las = result.points["exact"]
    classes = np.asarray(las.classification)
    assert (classes == 2).sum() == len(pulses) * int(ground) and (classes == 5).sum() == len(pulses) * len(depths)
    assert np.array_equal(np.sort(np.asarray(las.return_number)), np.sort(r.return_number))
    assert result.stats["leaf_returns"] == len(pulses) * len(depths)
    assert result.stats["beams_returned"] == len(pulses) and result.stats["dark"] == 0


def test_without_a_blind_stretch_a_tiny_threshold_keeps_the_first_max_returns(tmp_path):
    """No blind stretch and a threshold of 1e-4: the leaves could trigger ρ_l / threshold = 4000 returns a beam; the
    first 15 are kept, each where the echo gathered since the last one reaches the threshold (closed form in float64),
    and the detector stops listening there (the surface's return is not kept either)."""
    thr, lad = 1e-4, 0.6
    result = _run(tmp_path, lad, min_separation_m=0.0, max_returns=15, threshold=thr)
    r = result.returns
    kappa = 0.5 * lad
    want = [TOP + math.log(1.0 - k * thr / 0.4) / kappa for k in range(1, 16)]  # heights above the plane
    for pulse in np.unique(r.pulse):
        mine = np.flatnonzero(r.pulse == pulse)
        z = r.true_points[mine[np.argsort(r.return_number[mine])], 2] - ORIGIN[2]
        assert len(z) == 15 and np.abs(z - want).max() < 2e-4, (z, want)
    assert (np.asarray(result.points["exact"].classification) == 5).all()


def test_a_dense_layer_hides_the_ground_and_max_returns_keeps_the_first(tmp_path):
    d = flightsim.load_config().discrete
    depths, ground = _expected(0.6, 1.0, d.threshold, d.min_separation_m, 0.4, d.reflectance, d.max_returns)
    assert not ground and len(depths) == 2  # the plane's echo, 0.3 e^-2.4, is below the threshold
    dense = _run(tmp_path, 0.6).returns
    assert set(dense.number_of_returns) == {2} and (dense.true_points[:, 2] - ORIGIN[2] > BOTTOM).all()
    kept = _run(tmp_path, 0.25, max_returns=2)  # two leaf returns and the plane's: the first two kept
    assert set(kept.returns.number_of_returns) == {2}
    assert (np.asarray(kept.points["exact"].classification) == 5).all()


def test_leaf_echoes_below_the_threshold_make_nothing_and_say_why(tmp_path, capsys):
    layer = _layer(tmp_path, 2.0)
    args = ["simulate", "--set", "instrument.deflector=fixed", "--set", "fan.array=1", "--set", "flight.platform=hover",
            "--altitude", "100", "--duration", "0.3", "--set", "fixed.prf_hz=10", "--models", "exact",
            "--scene", "plane", "--set", f"scene.canopy={layer}", "--set", "discrete.threshold=0.9",
            "--out", str(tmp_path / "out")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "discrete.threshold" in err and len(err.strip().splitlines()) == 1
