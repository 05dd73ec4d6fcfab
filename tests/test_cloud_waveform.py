"""Large-footprint waveforms from a point cloud: the float64 model and the device kernel against closed forms (a
flat ground is one pulse of σ_r at nadir, widened by σ_f tan θ off nadir; the density normalisation evens out a
doubly scanned half; rh of two Gaussian layers), and the kernel against the model over a synthetic forest."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from flightsim.core.errors import InputError
from flightsim.engine.cloud_waveforms import cloud_waveforms, prepare_cloud
from flightsim.instrument.cloud_waveform_model import (C, CloudBeam, model_waveforms, sample_heights,
                                                       synthetic_forest, waveform_metrics)
from flightsim.scenes.pointcloud import PointCloud
from flightsim.scenes.scene import parse_crs

DT = 1e-9  # GEDI's sample interval: 0.15 m of range
STEP = C * DT / 2.0


def _lattice_cloud(half: float, spacing: float, height, classes=2) -> PointCloud:
    """Points on a square lattice over ±``half`` [m] (offset half a spacing from the edges) at ``height(x, y)``."""
    axis = np.arange(-half + spacing / 2.0, half, spacing)
    x, y = (a.ravel() for a in np.meshgrid(axis, axis))
    z = np.broadcast_to(height(x, y), x.shape).astype(np.float64)
    ones = np.ones(len(x), dtype=np.uint8)
    return PointCloud(np.column_stack([x, y, z]), np.full(len(x), classes, dtype=np.uint8), ones, ones.copy(),
                      parse_crs("EPSG:32648"), np.zeros(3))


def _moments(wave: np.ndarray, ranges: np.ndarray) -> tuple[float, float, float]:
    """(∫ w dr, mean range, rms width) of a waveform [1/m] over sample ranges [m], in float64."""
    w = wave.astype(np.float64)
    energy = w.sum()
    mean = (w * ranges).sum() / energy
    return energy * STEP, mean, math.sqrt((w * (ranges - mean) ** 2).sum() / energy)


def _both(device, cloud, centres, z_top, start, samples, beam, **weights):
    model = model_waveforms(cloud, centres, z_top, start, DT, samples, beam, **weights)
    kernel = cloud_waveforms(cloud, centres, z_top, start, DT, samples, beam, device=device, **weights)
    return model, kernel


def test_flat_ground_at_nadir_is_one_pulse_of_the_pulse_width(device):
    h, z_top, start, samples = 1.2345, 30.0, 20.0, 120
    cloud = _lattice_cloud(25.0, 0.5, lambda x, y: h)
    beam = CloudBeam()
    ranges = start + np.arange(samples) * STEP
    closed = norm.pdf(ranges, loc=z_top - h, scale=beam.range_sigma_m())  # ∫ = 1 [1/m]
    model, kernel = _both(device, cloud, [[0.3, -0.7]], z_top, start, samples, beam)
    assert np.abs(model["rx"][0] - closed).max() < 1e-9 * closed.max()
    # the kernel splits a point between the two bins around it: its pulse is the sampled Gaussian interpolated
    # linearly between them, off by at most bin²/8 · max|G''| = (bin/σ)²/8 of the peak, and widened by at most
    # bin²/4 in variance (bin = one sample here)
    interpolation = (STEP / beam.range_sigma_m()) ** 2 / 8.0
    assert np.abs(kernel["rx"][0] - closed).max() < 1.05 * interpolation * closed.max()
    for wave, widening in ((model["rx"][0], 1e-9), (kernel["rx"][0], interpolation)):
        energy, mean, width = _moments(wave, ranges)
        assert energy == pytest.approx(1.0, abs=1e-5)
        assert mean == pytest.approx(z_top - h, abs=1e-4)
        assert beam.range_sigma_m() - 1e-6 < width < beam.range_sigma_m() * (1.0 + widening) + 1e-6
    assert np.array_equal(model["canopy"], np.zeros_like(model["canopy"])) and not kernel["canopy"].any()


def test_flat_ground_off_nadir_widens_by_the_footprint_across_the_slant(device):
    h, z_top, theta = 0.5, 40.0, 12.0
    cloud = _lattice_cloud(26.0, 0.25, lambda x, y: h)
    beam = CloudBeam(zenith_deg=theta, azimuth_deg=35.0, centre_z_m=h)
    start, samples = 30.0, 160
    ranges = start + np.arange(samples) * STEP
    # the cut footprint's variance along one axis: σ_f² (1 − U e^−U / (1 − e^−U)), U = cut² / 2
    u = beam.cut_sigmas ** 2 / 2.0
    across = beam.footprint_sigma_m ** 2 * (1.0 - u * math.exp(-u) / (1.0 - math.exp(-u)))
    expected = math.sqrt(beam.range_sigma_m() ** 2 + across * math.tan(math.radians(theta)) ** 2)
    model, kernel = _both(device, cloud, [[1.0, 2.0]], z_top, start, samples, beam)
    for wave in (model["rx"][0], kernel["rx"][0]):
        energy, mean, width = _moments(wave, ranges)
        assert energy == pytest.approx(1.0, abs=1e-4)
        assert mean == pytest.approx((z_top - h) / math.cos(math.radians(theta)), abs=2e-3)
        assert width == pytest.approx(expected, rel=2e-3)


def test_kernel_matches_the_float64_model_over_a_forest(device):
    cloud = synthetic_forest(60_000, 15.0, seed=3)
    rng = np.random.default_rng(7)
    centres = rng.uniform(-25.0, 25.0, (100, 2))
    z_top, start, samples = 45.0, 0.0, 400
    for beam in (CloudBeam(), CloudBeam(zenith_deg=8.0, azimuth_deg=200.0)):
        model, kernel = _both(device, cloud, centres, z_top, start, samples, beam)
        heights = sample_heights(z_top, np.full(len(centres), start), DT, samples, beam)
        ours, reference = (waveform_metrics(w["rx"], w["ground"], heights) for w in (kernel, model))
        correlation = [np.corrcoef(a, b)[0, 1] for a, b in zip(kernel["rx"], model["rx"])]
        assert min(correlation) >= 0.999
        for metric in ("rh50", "rh98", "ground_z"):
            assert np.abs(ours[metric] - reference[metric]).max() < 0.1, metric
        assert np.allclose(kernel["rx"], kernel["ground"] + kernel["canopy"], atol=1e-6)
        assert not kernel["outside"].any() and (model["near"] > 0).all()


def test_density_normalisation_evens_out_a_densely_scanned_half(device):
    # ground at 0 m where x < 0 scanned 4× as densely (0.375 m lattice) as the ground at 2 m where x > 0 (0.75 m)
    dense, sparse = (_lattice_cloud(15.0, s, lambda x, y: np.where(x < 0, 0.0, 2.0)) for s in (0.375, 0.75))
    keep = [dense.xyz[:, 0] < 0, sparse.xyz[:, 0] > 0]
    ones = np.ones(int(sum(k.sum() for k in keep)), dtype=np.uint8)
    cloud = PointCloud(np.concatenate([dense.xyz[keep[0]], sparse.xyz[keep[1]]]), np.full(len(ones), 2, np.uint8),
                       ones, ones.copy(), dense.crs, np.zeros(3))
    beam = CloudBeam(pulse_sigma_s=1.5e-9)  # 22 cm: the two heights 9 σ apart
    heights = sample_heights(10.0, 5.0, DT, 60, beam)[0]
    for normalise, low_share in ((False, 0.8), (True, 0.5)):
        for waves in _both(device, cloud, [[0.0, 0.0]], 10.0, 5.0, 60, beam, normalise=normalise):
            rx = waves["rx"][0].astype(np.float64)
            assert rx[heights < 1.0].sum() / rx.sum() == pytest.approx(low_share, abs=2e-3)


def test_rh_of_two_gaussian_layers_and_the_ground_centroid():
    heights = np.linspace(-5.0, 40.0, 4501)
    sigma = 0.955
    ground = 0.4 * norm.pdf(heights, 0.3, sigma)
    rx = ground + 0.6 * norm.pdf(heights, 20.0, sigma)
    metrics = waveform_metrics(rx[None], ground[None], heights)
    assert metrics["ground_z"][0] == pytest.approx(0.3, abs=1e-6)
    assert metrics["rh50"][0] == pytest.approx(20.0 + sigma * norm.ppf(1.0 / 6.0) - 0.3, abs=0.01)
    assert metrics["rh98"][0] == pytest.approx(20.0 + sigma * norm.ppf(0.98 / 0.6 - 0.4 / 0.6) - 0.3, abs=0.01)


def test_footprints_outside_the_cloud_are_flagged_or_refused(device):
    cloud = _lattice_cloud(20.0, 1.0, lambda x, y: 0.0)
    edge = 19.5  # the lattice's last column; 3 σ_f = 16.5 m
    centres = [[0.0, 0.0], [100.0, -80.0], [edge + 16.3, 0.0], [edge + 16.7, 0.0]]
    model, kernel = _both(device, cloud, centres, 10.0, 5.0, 40, CloudBeam())
    flags = [False, True, False, True]
    assert list(kernel["outside"]) == flags and list(model["near"] == 0) == flags
    assert not kernel["rx"][1].any()
    with pytest.raises(InputError, match=r"footprint 1 at local \(100\.00, -80\.00\)"):
        cloud_waveforms(cloud, centres, 10.0, 5.0, DT, 40, device=device, user_footprints=True)


def test_requests_out_of_range_are_refused():
    cloud = _lattice_cloud(5.0, 1.0, lambda x, y: 0.0)
    for kwargs, field in (({"samples": 0}, "samples"), ({"samples": 100_000}, "samples"), ({"dt_s": -1.0}, "dt_s"),
                          ({"centres_xy": [[0.0, np.nan]]}, "centres_xy"),
                          ({"beam": CloudBeam(zenith_deg=75.0)}, "zenith_deg"), ({"rho_ground": 0.0}, "rho_ground")):
        args = {"centres_xy": [[0.0, 0.0]], "z_top": 10.0, "window_start_m": 0.0, "dt_s": DT, "samples": 50}
        args.update(kwargs)
        with pytest.raises(InputError, match=field):
            cloud_waveforms(cloud, **args)
    with pytest.raises(InputError, match="at most .* samples"):  # beyond the device histogram, not the model's
        cloud_waveforms(cloud, [[0.0, 0.0]], 10.0, 0.0, DT, 6000)
    with pytest.raises(ValueError, match="weights"):
        cloud_waveforms(cloud, [[0.0, 0.0]], 10.0, 0.0, DT, 50, prepared=prepare_cloud(cloud, normalise=True))


def test_the_prepared_cloud_lists_each_cells_points_in_file_order(device, monkeypatch):
    """prepare_cloud's grid against a loop over the cells: every point once, in its cell of side cell_m from the
    lowest x, y (the last column and row take the highest edge), in the order the cloud holds them, its weight
    negative for a ground point (the weights signed in pieces of 1000 points on threads)."""
    from flightsim.core import process_map

    monkeypatch.setattr(process_map, "ROWS_PER_PIECE", 1000)
    monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    cloud = synthetic_forest(30_000, seed=4)
    prepared = prepare_cloud(cloud, rho_ground=0.3, rho_canopy=0.6, cell_m=3.7, device=device)
    grid, points = prepared.grid, prepared.grid.points.numpy()
    start = grid.cell_start.numpy()
    lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
    nx, ny = int((hi[0] - lo[0]) // 3.7) + 1, int((hi[1] - lo[1]) // 3.7) + 1
    assert (grid.nx, grid.ny, len(start)) == (nx, ny, nx * ny + 1) and start[-1] == len(cloud) > 1000
    column = np.minimum(np.floor((cloud.xyz[:, 0] - lo[0]) / 3.7), nx - 1)
    row = np.minimum(np.floor((cloud.xyz[:, 1] - lo[1]) / 3.7), ny - 1)
    weight = np.where(cloud.classification == 2, -0.3, 0.6).astype(np.float32)
    for cell in range(nx * ny):
        mine = np.flatnonzero((row * nx + column) == cell)  # ascending: the cloud's order
        found = points[start[cell]:start[cell + 1]]
        assert np.array_equal(found[:, :3], cloud.xyz[mine].astype(np.float32)), cell
        assert np.array_equal(found[:, 3], weight[mine]), cell
