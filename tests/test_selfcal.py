"""Risley self-calibration: recovery of injected parameters from synthetic observations of known planes (ranges from
an independent float64 ray-plane intersection), the Jacobian σ against a Monte Carlo spread, robustness to outlier
planes, the raw observables of an engine flight against its true hits, and one-line errors for bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightsim.core.constants import ARCSEC
from flightsim.core.errors import InputError
from flightsim.instrument import risley_model
from flightsim.studies import selfcal as sc

N_TRUE = 1.5066
APEX_TRUE = risley_model.apex_for_cone(math.radians(15.0), N_TRUE)
TRUTH = np.array([N_TRUE, APEX_TRUE, 30 * ARCSEC, 60 * ARCSEC, -40 * ARCSEC, 90 * ARCSEC])
BELIEVED = np.array([N_TRUE + 1e-3, APEX_TRUE + 36 * ARCSEC, 0.0, 0.0, 0.0, 0.0])
HEIGHT = 1000.0
TILE = 60.0  # side of each synthetic plane's tile [m]
TILES = 6  # per side


def _planes(rng) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals, offsets d: n·p = d) of the tiles' planes: slopes 0–40° towards every azimuth."""
    slope = np.radians(rng.uniform(0.0, 40.0, TILES * TILES))
    azimuth = rng.uniform(0.0, 2 * np.pi, TILES * TILES)
    normal = np.stack([np.sin(slope) * np.sin(azimuth), np.sin(slope) * np.cos(azimuth), np.cos(slope)], axis=1)
    centre = (np.indices((TILES, TILES)).reshape(2, -1).T - (TILES - 1) / 2) * TILE
    heights = rng.uniform(0.0, 20.0, TILES * TILES)
    points = np.column_stack([centre, heights])
    return normal, np.einsum("ij,ij->i", normal, points)


def _poses(rng, pulses: int):
    """Two level lines 100 m apart with reciprocal headings (north, then south) at HEIGHT; (origin, R_local←sensor,
    prism-angle reading) per pulse. Sensor = body: x forward, y right, z down."""
    north = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # columns: body x, y, z in ENU
    south = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    half = pulses // 2
    along = rng.uniform(-650.0, 650.0, pulses)
    origin = np.column_stack([np.where(np.arange(pulses) < half, 50.0, -50.0), along, np.full(pulses, HEIGHT)])
    rot = np.where((np.arange(pulses) < half)[:, None, None], north, south)
    return origin, rot, rng.uniform(0.0, 2 * np.pi, pulses)


def synthetic(seed: int = 0, pulses: int = 6000, noise_m: float = 0.0, outlier_fraction: float = 0.0,
              truth: np.ndarray = TRUTH, noise_seed: int | None = None) -> tuple[sc.Observations, np.ndarray]:
    """Observations of the tiles' planes by the true instrument: (observations, true points); the noise and outliers
    drawn from ``noise_seed`` (default: the geometry's seed)."""
    rng = np.random.default_rng(seed)
    normal, offset = _planes(rng)
    origin, rot, phi = _poses(rng, pulses)
    n = 3
    fan = risley_model.trace_fan(phi + truth[2], n, 2.314e-3, truth[0], truth[1], 0.01, precision="float64")
    mount = Rotation.from_euler("ZYX", truth[5:2:-1]).as_matrix()
    start = origin[:, None] + np.einsum("pij,pbj->pbi", rot, fan.exit_points @ mount.T)
    direction = np.einsum("pij,pbj->pbi", rot, fan.directions @ mount.T)
    ground = start - (start[..., 2:] / direction[..., 2:]) * direction  # the z = 0 hit picks the tile
    cell = np.floor(ground[..., :2] / TILE + TILES / 2).astype(int)
    ok = np.all((cell >= 0) & (cell < TILES), axis=-1)
    p, b = np.nonzero(ok)
    tile = cell[p, b, 0] * TILES + cell[p, b, 1]
    s, d = start[p, b], direction[p, b]
    r = (offset[tile] - np.einsum("ij,ij->i", normal[tile], s)) / np.einsum("ij,ij->i", normal[tile], d)
    true_points = s + r[:, None] * d
    rng = rng if noise_seed is None else np.random.default_rng(noise_seed)
    r = r + rng.normal(0.0, noise_m, len(r)) if noise_m else r
    bad = rng.choice(TILES * TILES, int(round(outlier_fraction * TILES * TILES)), replace=False)
    for k, t in enumerate(bad):  # vegetation-like roughness and smooth domes on whole tiles
        on = tile == t
        dist = np.hypot(*(true_points[on, :2] - true_points[on, :2].mean(axis=0)).T)
        r[on] += rng.normal(0.0, 0.25, on.sum()) if k % 2 == 0 else -0.6 * np.clip(1 - (dist / dist.max()) ** 2, 0, 1)
    obs = sc.Observations(origin, rot, phi, p.astype(np.int64), b.astype(np.int64), r, tile.astype(np.int64), n,
                          2.314e-3, 0.01)
    return obs, true_points


def _errors(cal: sc.Calibration) -> dict[str, float]:
    """Recovered − true of the observable quantities [arcsec]."""
    return {"cone": (sc.cone_angle(cal.x) - sc.cone_angle(TRUTH)) / ARCSEC,
            "encoder_plus_yaw": (cal.x[2] + cal.x[5] - TRUTH[2] - TRUTH[5]) / ARCSEC,
            "roll": (cal.x[3] - TRUTH[3]) / ARCSEC, "pitch": (cal.x[4] - TRUTH[4]) / ARCSEC}


def test_true_parameters_reproduce_the_synthetic_truth():
    obs, true_points = synthetic(pulses=800)
    assert np.abs(sc.georeference(obs, TRUTH) - true_points).max() < 1e-6
    assert np.abs(sc.georeference(obs, BELIEVED) - true_points).max() > 0.3  # the errors move points decimetres


def test_georeferencer_keeps_the_prism_only_for_its_own_parameters():
    """One georeferencer over a sequence of parameters (the prism changed, then only the boresight, then back to
    an earlier prism) gives, each time, what a fresh evaluation of those parameters gives, to the bit."""
    obs, _ = synthetic(pulses=300)
    georeferencer = sc.Georeferencer(obs)
    moved_prism = TRUTH + np.array([1e-3, 2e-4, 0.0, 0.0, 0.0, 0.0])
    moved_mount = TRUTH + np.array([0.0, 0.0, 0.0, 3e-4, -2e-4, 1e-4])
    for x in (TRUTH, moved_prism, moved_mount, BELIEVED, TRUTH, moved_prism + moved_mount - TRUTH):
        np.testing.assert_array_equal(georeferencer(x), sc.georeference(obs, x))


def test_noise_free_recovery_is_exact():
    obs, true_points = synthetic()
    cal = sc.calibrate(obs, BELIEVED, loss="linear", stages=1)
    errors = _errors(cal)
    assert max(abs(v) for v in errors.values()) < 0.01, errors
    # noise-free, even the weakly separable n, α, δφ and yaw come back (the off-axis beams' distortion tells them apart)
    assert abs(cal.x[0] - TRUTH[0]) < 1e-7
    assert np.abs(cal.x[1:] - TRUTH[1:]).max() < 0.01 * ARCSEC
    assert np.abs(sc.georeference(obs, cal.x) - true_points).max() < 2e-3
    assert sc.pooled_rms(sc.georeference(obs, cal.x), obs.segment) < 1e-4
    c = cal.correlation  # n and α move the cone together; δφ and yaw both turn the scan about the prism axis
    assert c[0, 1] < -0.99 and c[2, 5] < -0.99
    assert abs(c[3, 4]) < 0.5


def test_jacobian_sigma_matches_the_monte_carlo_spread():
    draws, predicted = [], []
    for seed in range(10):
        obs, _ = synthetic(seed=3, pulses=3000, noise_m=0.05, noise_seed=100 + seed)  # one geometry, new noise
        cal = sc.calibrate(obs, TRUTH, loss="linear", stages=1)
        draws.append([*_errors(cal).values()])
        predicted.append([sc.combinations(cal)["cone_half_angle"][1], sc.combinations(cal)["encoder_plus_yaw"][1],
                          cal.sigma[3] / ARCSEC, cal.sigma[4] / ARCSEC])
    spread = np.std(draws, axis=0, ddof=1)
    sigma = np.mean(predicted, axis=0)
    assert np.all(sigma > 0)
    ratio = spread / sigma  # 10 draws: the sample σ is good to about ±25 % (1σ)
    assert np.all((ratio > 0.45) & (ratio < 1.8)), (spread, sigma)
    assert np.all(np.abs(np.mean(draws, axis=0)) < 3 * sigma / math.sqrt(10) + 0.01)


def test_outlier_planes_do_not_bias_the_robust_estimate():
    obs, _ = synthetic(seed=7, noise_m=0.02, outlier_fraction=0.1)
    robust = sc.calibrate(obs, BELIEVED)
    plain = sc.calibrate(obs, BELIEVED, loss="linear", stages=1)
    e_robust, e_plain = _errors(robust), _errors(plain)
    sigma = {"cone": sc.combinations(robust)["cone_half_angle"][1],
             "encoder_plus_yaw": sc.combinations(robust)["encoder_plus_yaw"][1],
             "roll": robust.sigma[3] / ARCSEC, "pitch": robust.sigma[4] / ARCSEC}
    for k, e in e_robust.items():  # stated bound: within 4σ and 1 arcsec of the truth
        assert abs(e) < 4 * sigma[k] + 1.0, (k, e, sigma[k])
    assert sum(abs(v) for v in e_robust.values()) < sum(abs(v) for v in e_plain.values())


def test_bad_input_is_one_line_error():
    obs, _ = synthetic(pulses=300)
    with pytest.raises(InputError, match="selfcal.loss"):
        sc.calibrate(obs, BELIEVED, loss="l2")
    with pytest.raises(InputError, match="selfcal.x0"):
        sc.calibrate(obs, BELIEVED[:4])
    few = obs.subset(obs.segment < 2)
    with pytest.raises(InputError, match="selfcal.segments"):
        sc.calibrate(few, BELIEVED)
    broken = obs.subset(np.arange(len(obs.range_m)))
    broken.beam = broken.beam[:-1]
    with pytest.raises(InputError, match="selfcal.beam"):
        sc.calibrate(broken, BELIEVED)
    negative = obs.subset(np.arange(len(obs.range_m)))
    negative.range_m = -negative.range_m
    with pytest.raises(InputError, match="selfcal.range_m") as err:
        sc.calibrate(negative, BELIEVED)
    assert "\n" not in str(err.value)


def test_engine_observables_reproduce_the_true_hits():
    """The raw observables of an engine flight (noise off), re-georeferenced with the injected truth, land on the
    engine's true hits (its own kernels), and with the believed values off them."""
    from flightsim.studies import selfcal_flight as sf

    cfg = sf.flight_config(500.0, 3, injected=sf.Injected(range_noise_m=0.0))
    truth, believed = sf.parameters(cfg)
    flight = sf.fly(cfg)
    index = np.arange(0, len(flight.range_m), 7)
    obs = sf.observations(flight, index)
    assert np.abs(sc.georeference(obs, truth) - flight.true_points[index]).max() < 2e-3  # float32 points and ranges
    assert np.abs(sc.georeference(obs, believed) - flight.true_points[index]).max() > 0.1


def test_cli_needs_an_output_directory(capsys):
    from flightsim.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["selfcal", "--device", "cpu"])
    assert exc.value.code == 2
    assert "--out" in capsys.readouterr().err


def test_empty_grid_is_one_line_error(tmp_path):
    from flightsim.studies.selfcal_report import run_selfcal

    with pytest.raises(InputError, match="selfcal.grid"):
        run_selfcal(tmp_path, grid={"arrays": (), "altitudes_m": (1000.0,)})


def test_georeference_agrees_across_devices(device):
    obs, true_points = synthetic(pulses=400)
    assert np.abs(sc.georeference(obs, TRUTH, device) - true_points).max() < 1e-6
    assert np.abs(sc.georeference(obs, BELIEVED, device) - sc.georeference(obs, BELIEVED, "cpu")).max() < 1e-9
