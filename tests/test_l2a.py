"""GEDI L2A-like metrics (flightsim.outputs.l2a) against closed forms of Gaussian waveforms.

A waveform of Gaussian modes sampled every dt: the energy of a mode of amplitude A and σ s [samples] above
sample x is A·s·√(2π)·Φ((x − μ)/s) counted from below, so rh_k comes from scipy.special.ndtri (one mode) or
brentq on a sum of ndtr (the signal window cut by the thresholds). The smoothed mode (a Gaussian convolved
with the smoothing Gaussian of σ_k) has σ_s = √(s² + σ_k²) and peak A·s/σ_s, so it crosses a threshold T at
σ_s·√(2 ln(A·s/(σ_s·T))) from its centre. Heights: one sample is Δz = c·dt/2 (nadir).
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import brentq
from scipy.special import ndtr, ndtri

from flightsim.core.errors import InputError
from flightsim.outputs.l2a import FILL, L2ASettings, l2a_metrics, truth_rh
from flightsim.outputs.l2a_h5 import write_l2a

C = 299_792_458.0
DT, N, PULSE_S = 0.5e-9, 1000, 6e-9
SIG = PULSE_S / DT  # pulse σ [samples] = 12
DZ = C * DT / 2.0  # [m per sample]
TOP = 100.0  # elevation of bin0 [m]
I = np.arange(N, dtype=np.float64)
GROUND, CANOPY = (700.0, 1.0, SIG), (420.0, 0.4, 2.0 * SIG)  # (centre [samples], amplitude, σ [samples])


def _wave(*modes) -> np.ndarray:
    return sum(a * np.exp(-0.5 * ((I - mu) / s) ** 2) for mu, a, s in modes)


def _run(rx, noise=None, settings=None, lat=(10.0, 10.001), lon=(20.0, 20.002)):
    s = len(rx)
    z0 = np.full(s, TOP)
    return l2a_metrics(rx, DT, z0, z0 - (N - 1) * DZ, np.full(s, lat[0]), np.full(s, lon[0]),
                       np.full(s, lat[1]), np.full(s, lon[1]), PULSE_S, noise=noise, settings=settings)


def _energy(mode) -> float:
    mu, a, s = mode
    return a * s * np.sqrt(2.0 * np.pi)


def _below(x, modes) -> float:
    """Energy of the modes at samples >= x (below the elevation of sample x) [amplitude · samples]."""
    return sum(_energy(m) * ndtr((m[0] - x) / m[2]) for m in modes)


def _density(x, modes) -> float:
    return sum(a * np.exp(-0.5 * ((x - mu) / s) ** 2) for mu, a, s in modes)


def _crossing(mode, threshold) -> float:
    """Distance [samples] from a mode's centre to where its smoothed form falls to ``threshold``."""
    _, a, s = mode
    ss = np.hypot(s, SIG)
    return ss * np.sqrt(2.0 * np.log(a * s / ss / threshold))


def test_two_noise_free_modes_give_closed_form_rh_and_the_exact_ground():
    out = _run(_wave(GROUND, CANOPY)[None, :], noise=(0.0, 0.0))
    ground = TOP - GROUND[0] * DZ
    assert abs(out["elev_lowestmode"][0] - ground) < 0.01
    assert out["num_detectedmodes"][0] == 2 and out["quality_flag"][0] == 1
    np.testing.assert_allclose(out["lat_lowestmode"], 10.0 + 0.001 * GROUND[0] / (N - 1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(out["lon_lowestmode"], 20.0 + 0.002 * GROUND[0] / (N - 1), rtol=0, atol=1e-9)
    w = _energy(GROUND) / (_energy(GROUND) + _energy(CANOPY))  # the ground's share: 0.556, no k hits it
    for k in range(1, 100):
        p = k / 100.0
        if p < w:  # inside the ground mode
            expected = GROUND[2] * ndtri(p / w)
        else:
            expected = GROUND[0] - CANOPY[0] + CANOPY[2] * ndtri((p - w) / (1.0 - w))
        # the cumulative energy is summed in trapezoids (off by at most max|f'|/12, f the normalised energy
        # density per sample) and linear between samples (max|f'|/8 more): a shift of (1/8 + 1/12)·max|f'|/f
        # samples at the level's density f
        x = GROUND[0] - expected
        f = _density(x, [GROUND, CANOPY]) / (_energy(GROUND) + _energy(CANOPY))
        slope = max(a / s for _, a, s in (GROUND, CANOPY)) * np.exp(-0.5) / (_energy(GROUND) + _energy(CANOPY))
        assert abs(out["rh"][0, k] - expected * DZ) <= (1 / 8 + 1 / 12) * slope / f * DZ + 1e-4, k


def test_noisy_waveforms_rh50_and_rh98_within_the_noise_tolerance():
    """Noise σ_n on each sample and the noise mean estimated from 2 × 64 end samples. The energy fraction F at
    a level moves by δC/T (white noise over the window's n samples: σ_n·√n / T) and by the mean's error
    (σ_n/√128 on each of n samples: σ_n/√128 · n / T); a shift δF moves the level by δF/f samples (f the
    normalised density there); the ground centre's error is σ_n/A·√(2s/√π) samples (Fisher information of a
    Gaussian's centre). The window is cut where the smoothed modes cross 3σ_n (start) and 6σ_n (end)."""
    sigma_n, shots = 0.005, 300
    rng = np.random.default_rng(5)
    out = _run(_wave(GROUND, CANOPY)[None, :] + rng.normal(0.0, sigma_n, (shots, N)))
    modes = [GROUND, CANOPY]
    top = np.ceil(CANOPY[0] - _crossing(CANOPY, 3 * sigma_n))
    bottom = np.floor(GROUND[0] + _crossing(GROUND, 6 * sigma_n))
    total, n = _below(top, modes) - _below(bottom, modes), bottom - top + 1
    sigma_f = np.hypot(sigma_n * np.sqrt(n) / total, sigma_n / np.sqrt(127) * n / total)
    sigma_ground = sigma_n / GROUND[1] * np.sqrt(2 * GROUND[2] / np.sqrt(np.pi))
    for k in (50, 98):
        x = brentq(lambda x: _below(x, modes) - _below(bottom, modes) - k / 100 * total, top, bottom)
        tolerance = 5.0 * np.hypot(sigma_f / (_density(x, modes) / total), sigma_ground) * DZ
        error = out["rh"][:, k] - (GROUND[0] - x) * DZ
        assert np.abs(error).max() < tolerance, (k, np.abs(error).max(), tolerance)
        assert abs(error.mean()) < tolerance / np.sqrt(shots), (k, error.mean())
    assert (out["num_detectedmodes"] == 2).all()


def test_a_ground_only_waveform_spans_its_threshold_crossings():
    """One mode of the pulse's σ (flat ground), noise-free but with a known σ_n: rh100 is the smoothed echo's
    front crossing above the centre, Δz·σ_s·√(2 ln(A_s/(3σ_n))) with σ_s = √2·σ_pulse, A_s = A/√2 (3.1 pulse
    σ here), rh0 the back crossing below, and rh50 the centre itself."""
    sigma_n, mode = 0.02, (600.3, 1.0, SIG)
    out = _run(_wave(mode)[None, :], noise=(0.0, sigma_n))
    assert abs(out["elev_lowestmode"][0] - (TOP - mode[0] * DZ)) < 0.01
    assert abs(out["rh"][0, 100] - _crossing(mode, 3 * sigma_n) * DZ) < 0.005
    assert abs(out["rh"][0, 0] + _crossing(mode, 6 * sigma_n) * DZ) < 0.005
    assert abs(out["rh"][0, 50]) < 0.005
    assert out["elev_highestreturn"][0] == pytest.approx(out["elev_lowestmode"][0] + out["rh"][0, 100], abs=1e-9)
    assert out["energy_total"][0] == pytest.approx(_energy(mode) * DT, rel=1e-9)


@pytest.mark.parametrize("sigma_n, flag", [(0.02, 1), (0.06, 0)])
def test_sensitivity_follows_hancock_and_sets_the_quality_flag(sigma_n, flag):
    """1 − (n_N + n_S)·σ_n·√(2π)·σ_eff / E with n_N = Φ⁻¹(1 − 0.05·0.15/30), n_S = Φ⁻¹(0.9) and
    σ_eff = √(σ_p² + (2·5.5 m·tan 2°/c/dt)²) samples (Hancock et al. 2019, as the GEDI simulator codes it)."""
    mode = (600.0, 1.0, SIG)
    out = _run(_wave(mode)[None, :], noise=(0.0, sigma_n))
    width = np.hypot(SIG, 2 * 5.5 * np.tan(np.radians(2.0)) / C / DT)
    expected = 1 - (ndtri(1 - 0.05 * 0.15 / 30) + ndtri(0.9)) * sigma_n * np.sqrt(2 * np.pi) * width / _energy(mode)
    assert out["sensitivity"][0] == pytest.approx(expected, abs=1e-9)
    assert out["quality_flag"][0] == flag == int(expected >= 0.9)


def test_a_waveform_without_signal_is_flagged_and_filled():
    out = _run(np.zeros((2, N)), noise=(0.0, 0.01))
    assert (out["quality_flag"] == 0).all() and (out["num_detectedmodes"] == 0).all()
    for name in ("elev_lowestmode", "elev_highestreturn", "lat_lowestmode", "lon_lowestmode"):
        assert (out[name] == FILL).all()
    assert (out["rh"] == FILL).all() and out["rh"].shape == (2, 101)
    assert not any(np.isnan(v).any() for v in out.values())


def test_rh_of_windows_apart_equals_a_row_by_row_reference():
    """rh of seven waveforms whose signal windows lie apart (one a single pair of samples; one a single sample and
    one not found: FILL) against a row by row float64 reference: trapezoids from the window's bottom up, the first
    sample at which the share reaches k % interpolated linearly, elevations linear from bin0 to the last bin."""
    from flightsim.outputs.l2a import _rh

    rng = np.random.default_rng(8)
    y = _wave((300.0, 1.0, 30.0), (650.0, 0.7, 60.0))[None, :] * rng.uniform(0.5, 1.5, (7, 1))
    start = np.array([250.3, 280.6, 500.0, 640.2, 640.2, 10.0, 641.0])
    end = np.array([350.7, 300.2, 900.9, 642.5, 660.0, 990.0, 641.0])
    found = np.array([True, True, True, True, True, False, True])
    bin0, lastbin = np.linspace(50.0, 60.0, 7), np.linspace(-100.0, -90.0, 7)
    ground = np.linspace(-20.0, -10.0, 7)
    got = _rh(y, bin0, lastbin, start, end, ground, found)
    assert (got[5:] == FILL).all()
    for i in range(5):
        k = np.arange(int(np.ceil(start[i])), int(np.floor(end[i])) + 1)
        energy = np.concatenate([[0.0], np.cumsum(0.5 * (y[i, k[1:]] + y[i, k[:-1]])[::-1])])  # from the bottom up
        samples = k[::-1].astype(np.float64)
        levels = np.arange(1, 100) / 100
        at = np.interp(levels, energy / energy[-1], samples)
        expected = np.concatenate([[end[i]], at, [start[i]]])
        elevation = bin0[i] + (lastbin[i] - bin0[i]) * expected / (N - 1)
        np.testing.assert_allclose(got[i], elevation - ground[i], rtol=0.0, atol=1e-9)


def test_a_shots_rh_is_the_same_wherever_it_lies_in_its_batch():
    """A waveform whose energy share from the bottom comes 3e-12 short of rh50's level, alone and as the last of
    30,001 rows (the others without a signal): the same heights bit for bit, and rh50 the exact one, 6e-12 of a
    sample above the middle sample (a search of every row's shares at once, each row's index added to them, lost
    that difference far down a batch)."""
    from flightsim.outputs.l2a import _rh

    d = 3e-12
    y = np.array([0.0, 0.5 + 2.0 * d, 0.5, 0.5 - 2.0 * d, 0.0])  # trapezoids of 0.5 + d and, below, 0.5 - d
    rows = 30_001
    batch = np.zeros((rows, len(y)))
    batch[-1] = y
    found = np.zeros(rows, dtype=bool)
    found[-1] = True
    bin0, lastbin, ground = np.full(rows, 4.0), np.zeros(rows), np.zeros(rows)  # 1 m a sample, sample 4 at 0 m
    start, end = np.full(rows, 1.0), np.full(rows, 3.0)
    far = _rh(batch, bin0, lastbin, start, end, ground, found)[-1]
    alone = _rh(y[None, :], bin0[:1], lastbin[:1], start[:1], end[:1], ground[:1], found[-1:])[0]
    np.testing.assert_array_equal(far, alone)
    share = (0.5 - d) / ((0.5 - d) + (0.5 + d))  # at sample 2; 1 at sample 1
    np.testing.assert_allclose(alone[50], 4.0 - (2.0 - (0.5 - share) / (1.0 - share)), rtol=0.0, atol=1e-14)
    assert alone[50] - 2.0 > 5e-12


def test_truth_rh_of_a_noise_free_profile_is_measured_from_the_true_ground():
    ground = TOP - 710.0 * DZ  # 10 samples below the ground mode's centre
    rh = truth_rh(_wave(GROUND)[None, :], [TOP], [TOP - (N - 1) * DZ], [ground])
    for k in (2, 25, 50, 75, 98):
        expected = (710.0 - GROUND[0] + GROUND[2] * ndtri(k / 100)) * DZ
        assert abs(rh[0, k] - expected) < 0.005, k
    assert (truth_rh(np.zeros((1, N)), [TOP], [TOP - 1], [0.0]) == FILL).all()


def test_truth_rh_in_pieces_on_threads_is_each_profile_alone(monkeypatch):
    """truth_rh works on pieces of TRUTH_PIECE_ROWS profiles on threads: 41 profiles of one or two modes at many
    depths and widths (windows of every extent, two without energy) in pieces of three rows give each profile's rh
    alone, bit for bit."""
    import flightsim.outputs.l2a as l2a

    rng = np.random.default_rng(9)
    modes = [[(rng.uniform(50.0, 950.0), rng.uniform(0.2, 1.0), rng.uniform(2.0, 40.0))
              for _ in range(rng.integers(1, 3))] for _ in range(41)]
    profiles = np.array([_wave(*m) for m in modes])
    profiles[profiles < 1e-3] = 0.0  # windows ending where the modes fall below a floor, not at the profile's ends
    profiles[[7, 30]] = 0.0
    bin0 = TOP + rng.uniform(-20.0, 20.0, 41)
    lastbin, ground = bin0 - (N - 1) * DZ, bin0 - rng.uniform(50.0, 140.0, 41)
    alone = np.array([truth_rh(profiles[i:i + 1], bin0[i:i + 1], lastbin[i:i + 1], ground[i:i + 1])[0]
                      for i in range(41)])
    monkeypatch.setattr(l2a, "TRUTH_PIECE_ROWS", 3)
    monkeypatch.setattr("flightsim.core.process_map.usable_cores", lambda: 4)
    np.testing.assert_array_equal(truth_rh(profiles, bin0, lastbin, ground), alone)
    assert (alone[[7, 30]] == FILL).all() and (alone[:7] != FILL).all()


@pytest.mark.parametrize("change, field", [
    ({"rx": np.zeros(N)}, "rx"),
    ({"rx": np.full((1, N), np.nan)}, "rx"),
    ({"dt_s": 0.0}, "dt_s"),
    ({"pulse_sigma_s": np.nan}, "pulse_sigma_s"),
    ({"elevation_bin0": np.zeros(2)}, "elevation_bin0"),
    ({"elevation_lastbin": [TOP + 1.0]}, "elevation_lastbin"),
    ({"latitude_bin0": [np.inf]}, "latitude_bin0"),
    ({"noise": (0.0, -1.0)}, "noise σ"),
    ({"settings": L2ASettings(front_threshold=-1.0)}, "l2a.front_threshold"),
    ({"rx": np.zeros((1, 100))}, "rx"),  # too short for 2 × 64 noise samples
])
def test_bad_input_is_refused_by_name(change, field):
    args = dict(rx=np.zeros((1, N)), dt_s=DT, elevation_bin0=[TOP], elevation_lastbin=[TOP - 50.0],
                latitude_bin0=[0.0], longitude_bin0=[0.0], latitude_lastbin=[0.0], longitude_lastbin=[0.0],
                pulse_sigma_s=PULSE_S)
    args.update(change)
    with pytest.raises(InputError, match=f"invalid {field}"):
        l2a_metrics(**args)


def test_truth_rh_refuses_negative_energy():
    with pytest.raises(InputError, match="invalid profile"):
        truth_rh(-np.ones((1, N)), [TOP], [0.0], [0.0])


# --- l2a.h5 --------------------------------------------------------------------------------------

# Names of GEDI L2A's BEAMxxxx datasets (GEDI L2A data dictionary, as listed by readers of the product:
# rGEDI's getLevel2AM, SlideRule's gedi02a fields, Earth Engine's LARSE/GEDI/GEDI02_A_002 properties).
GEDI_L2A_NAMES = {"shot_number", "beam", "delta_time", "rh", "elev_lowestmode", "elev_highestreturn",
                  "lat_lowestmode", "lon_lowestmode", "lat_highestreturn", "lon_highestreturn",
                  "num_detectedmodes", "sensitivity", "quality_flag", "energy_total"}


def _beam(shots: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    out = _run(_wave(GROUND, CANOPY)[None, :] + rng.normal(0.0, 0.005, (shots, N)))
    out.update(shot_number=(np.uint64(3) << np.uint64(32)) + np.arange(shots, dtype=np.uint64),
               delta_time=1000.0 + 0.02 * np.arange(shots), pulse_sigma_s=PULSE_S, rho_ground=0.4)
    return out


def test_l2a_h5_round_trips_with_gedi_names_and_types(tmp_path):
    beams = {0: _beam(3, 1), 5: _beam(2, 2)}
    truth = {5: {"elev_ground": np.full(2, 47.5), "rh": np.tile(np.arange(101.0) / 10, (2, 1))}}
    path = write_l2a(tmp_path / "l2a.h5", beams, truth, {"config_toml": "x = 1"})
    with h5py.File(path) as f:
        assert sorted(f) == ["BEAM0000", "BEAM0005"] and f.attrs["config_toml"] == "x = 1"
        for b, name in ((0, "BEAM0000"), (5, "BEAM0005")):
            g = f[name]
            assert {k for k in g if k != "truth"} == GEDI_L2A_NAMES
            assert g.attrs["pulse_sigma_s"] == PULSE_S and g.attrs["rho_ground"] == 0.4
            assert (g["beam"][()] == b).all() and g["beam"].dtype == np.uint16
            assert g["shot_number"].dtype == np.uint64 and g["rh"].dtype == np.float32
            assert g["quality_flag"].dtype == np.uint8 and g["num_detectedmodes"].dtype == np.uint8
            np.testing.assert_array_equal(g["shot_number"][()], beams[b]["shot_number"])
            np.testing.assert_array_equal(g["elev_lowestmode"][()], beams[b]["elev_lowestmode"])
            np.testing.assert_array_equal(g["rh"][()], beams[b]["rh"].astype(np.float32))
            assert g["rh"].attrs["units"] == "m"
        assert "truth" not in f["BEAM0000"]
        np.testing.assert_array_equal(f["BEAM0005/truth/rh"][()], truth[5]["rh"].astype(np.float32))
        np.testing.assert_array_equal(f["BEAM0005/truth/elev_ground"][()], 47.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l2a.h5"]


@pytest.mark.parametrize("beams, truth, field", [
    ({0: {"shot_number": np.zeros(1, np.uint64)}}, None, r"beams\[0\].delta_time"),
    ({-1: {}}, None, "beams"),
    ({0: {"colour": 1}}, None, r"beams\[0\]"),
    ({}, None, "beams"),
    (None, {7: {}}, "truth"),
    (None, {0: {"elev_ground": np.zeros(3)}}, r"truth\[0\].rh"),
    (None, {0: {"elev_ground": np.zeros(3), "rh": np.zeros((3, 100))}}, r"truth\[0\].rh"),
])
def test_l2a_h5_refuses_bad_input_and_writes_nothing(tmp_path, beams, truth, field):
    with pytest.raises(InputError, match=f"invalid {field}"):
        write_l2a(tmp_path / "l2a.h5", {0: _beam(3, 1)} if beams is None else beams, truth)
    assert list(tmp_path.iterdir()) == []


def test_l2a_h5_refuses_nan_and_a_fractional_shot_number(tmp_path):
    beam = _beam(2, 3)
    beam["sensitivity"] = np.array([0.95, np.nan])
    with pytest.raises(InputError, match=r"invalid beams\[1\].sensitivity"):
        write_l2a(tmp_path / "l2a.h5", {1: beam})
    beam = _beam(2, 3)
    beam["shot_number"] = np.array([1.5, 2.0])
    with pytest.raises(InputError, match=r"invalid beams\[1\].shot_number"):
        write_l2a(tmp_path / "l2a.h5", {1: beam})
    assert list(tmp_path.iterdir()) == []


def test_the_fits_gaussians_and_their_jacobian_whatever_order_they_are_asked_in():
    """The lowest-mode fit's model (two Gaussians, three waveforms of 300, 260 and 200 samples padded to 300)
    against float64 sums written out, zero beyond each window, and its Jacobian against central differences: asked
    at new parameters, again at the same, at some of the last residual's rows, and back (the kept terms never
    stale)."""
    from flightsim.outputs.l2a import _Gaussians

    x = np.arange(100.0, 400.0)[None, :] + np.array([[0.0], [30.0], [-50.0]])
    inside = np.arange(300)[None, :] < np.array([[300], [260], [200]])
    target = np.where(inside, np.linspace(0.0, 1.0, 300), 0.0)
    model = _Gaussians(x, inside, target)
    first = np.array([[2.0, 0.5, 180.0, 260.0, 6.0, 11.0], [1.0, 0.2, 200.0, 230.0, 5.0, 7.0],
                      [0.3, 0.9, 120.0, 150.0, 9.0, 4.0]])
    second = first * np.array([0.75, 1.4, 0.97, 1.04, 0.8, 1.2])

    def expected(p, rows):
        a, c, w = p[:, :2, None], p[:, 2:4, None], p[:, 4:, None]
        return np.where(inside[rows], (a * np.exp(-0.5 * ((x[rows][:, None, :] - c) / w) ** 2)).sum(axis=1)
                        - target[rows], 0.0)

    everyone, some = np.arange(3), np.array([0, 2])
    for p, rows, jacobian_rows in ((first, everyone, everyone), (second, everyone, everyone),
                                   (second, everyone, some), (first[some], some, some), (first, everyone, some)):
        assert np.allclose(model.residual(p, rows), expected(p, rows), rtol=0.0, atol=1e-14)
        at = p[np.searchsorted(rows, jacobian_rows)]
        jacobian, h = model.jacobian(at, jacobian_rows), 1e-6
        assert jacobian.shape == (len(jacobian_rows), 6, 300)
        for k in range(6):
            step = np.eye(6)[k] * h
            numeric = (expected(at + step, jacobian_rows) - expected(at - step, jacobian_rows)) / (2 * h)
            assert np.allclose(jacobian[:, k], numeric, rtol=0.0, atol=1e-7), k
            assert (jacobian[:, k][~inside[jacobian_rows]] == 0.0).all()


@pytest.mark.parametrize("scale", [1e-30, 1e-12, 1e12, 1e30])
def test_waveforms_in_any_units_give_the_same_metrics(scale):
    """Stress: 50 noisy two-mode waveforms multiplied by 1e-30 … 1e30 (any power unit): finite metrics, the same mode
    counts and flags, the lowest modes and rh within 1e-3 m of the unscaled waveforms' (the thresholds scale with
    the noise; the fit's stopping tests are relative to the cost and to ‖x‖, which its amplitudes join: a step
    below 1e-8·‖x‖ stops it, 1e-4 m here at most)."""
    rng = np.random.default_rng(3)
    rx = _wave(GROUND, CANOPY)[None, :] * rng.uniform(0.5, 2.0, (50, 1)) + rng.normal(0.0, 0.01, (50, N))
    base, out = _run(rx), _run(rx * scale)
    assert all(np.isfinite(v).all() for v in out.values())
    for name in ("num_detectedmodes", "quality_flag"):
        np.testing.assert_array_equal(out[name], base[name])
    np.testing.assert_allclose(out["elev_lowestmode"], base["elev_lowestmode"], rtol=0.0, atol=1e-3)
    np.testing.assert_allclose(out["rh"], base["rh"], rtol=0.0, atol=1e-3)
    np.testing.assert_allclose(out["energy_total"], base["energy_total"] * scale, rtol=1e-12)


def test_the_lowest_modes_equal_scipys_fit_of_each_waveform():
    """The batched fit against SciPy's least_squares run on each waveform alone (the fit's window, start and
    bounds as the module docstring gives them): 200 noisy waveforms of one, two and three modes, ground and
    canopy moved about; every lowest mode within 1e-6 samples of SciPy's (a fit stops within its tolerances)."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(21)
    shots, sigma_n = 200, 0.01
    ground = 700.0 + rng.uniform(-30.0, 30.0, shots)
    canopy = ground - rng.uniform(60.0, 300.0, shots)
    rx = (_wave() + np.array([_wave((g, 1.0, SIG), (c, a, 1.6 * SIG), (c - 60.0, b, SIG))
                              for g, c, a, b in zip(ground, canopy, rng.uniform(0.0, 0.5, shots),
                                                    rng.choice([0.0, 0.3], shots))])
          + rng.normal(0.0, sigma_n, (shots, N)))
    out = _run(rx, noise=(0.0, sigma_n))
    smooth = gaussian_filter1d(rx, SIG, axis=1, mode="nearest")
    front, back = 3.0 * sigma_n, 6.0 * sigma_n
    counts = []
    for i in range(shots):
        above = np.flatnonzero(smooth[i] > front)
        start = above[0] - (smooth[i, above[0]] - front) / (smooth[i, above[0]] - smooth[i, above[0] - 1])
        last = np.flatnonzero(smooth[i] > back)[-1]
        end = last + (smooth[i, last] - back) / (smooth[i, last] - smooth[i, last + 1])
        d = np.diff(smooth[i])
        peaks = np.flatnonzero((d[:-1] > 0) & (d[1:] <= 0)) + 1
        peaks = peaks[(smooth[i, peaks] > front) & (peaks >= np.floor(start)) & (peaks <= np.ceil(end))]
        left, mid, right = smooth[i, peaks - 1], smooth[i, peaks], smooth[i, peaks + 1]
        modes = peaks + np.clip(0.5 * (left - right) / (left - 2 * mid + right), -0.5, 0.5)
        a, b, m = int(np.floor(start - 3 * SIG)), int(np.ceil(end + 3 * SIG)) + 1, len(modes)
        x = np.arange(a, b, dtype=np.float64)
        p0 = np.concatenate([np.maximum(rx[i, np.rint(modes).astype(int)], front), modes, np.full(m, SIG)])
        lower = np.concatenate([np.zeros(m), np.full(m, float(a)), np.full(m, 0.5 * SIG)])
        upper = np.concatenate([np.full(m, np.inf), np.full(m, b - 1.0), np.full(m, float(b - a))])

        def residual(p):
            return (p[:m, None] * np.exp(-0.5 * ((x - p[m:2 * m, None]) / p[2 * m:, None]) ** 2)).sum(0) - rx[i, a:b]

        def jacobian(p):
            u = (x - p[m:2 * m, None]) / p[2 * m:, None]
            e = np.exp(-0.5 * u * u)
            return np.concatenate([e, p[:m, None] * e * u / p[2 * m:, None],
                                   p[:m, None] * e * u * u / p[2 * m:, None]]).T

        fit = least_squares(residual, np.clip(p0, lower, upper), jac=jacobian, bounds=(lower, upper), x_scale="jac")
        amp, centre, width = np.split(fit.x, 3)
        seen = amp * width / np.hypot(width, SIG) > front
        expected = centre[seen].max() if seen.any() else modes[-1]
        assert abs(out["elev_lowestmode"][i] - (TOP - expected * DZ)) < 1e-6 * DZ, i
        counts.append(m)
    assert set(counts) == {1, 2, 3}, np.bincount(counts)
