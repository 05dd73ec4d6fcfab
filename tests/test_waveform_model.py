"""The float64 large-footprint echo model against closed forms and the patent's stated numbers.

Closed forms used (R = Hα the footprint edge, profile e^(−2ρ²/R²) truncated at R, u = 2ρ²/R² ∈ [0, 2]
with density ∝ e^(−u)):
- E[u] = (1 − 3e⁻²)/(1 − e⁻²), so E[ρ²] = (R²/2)·E[u] and, by symmetry, σ_x² = E[x²] = (R²/4)·E[u]
  (σ_x = 24.865 m against 30 m untruncated).
- A ground point at ρ lies √(H² + ρ²) − H = ρ²/2H − O(ρ⁴/H³) farther than nadir (H(1/cos φ − 1) with
  tan φ = ρ/H), so the footprint's mean extra range is Δ = E[ρ²]/2H = Hα²(1 − 3e⁻²)/(4(1 − e⁻²))
  = 3.0914 mm (20.62 ps of two-way delay).
- Over the plane z = s·x the range is H − s·x + O(s²x²/H): the delays' RMS is 2sσ_x/c.
- The disc ρ ≤ R holds 1 − e⁻² of an untruncated Gaussian beam (all of the pulse by the patent's eq. 7).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import quad

from flightsim.core.errors import InputError
from flightsim.instrument import waveform_model as wm
from flightsim.instrument.waveform_surfaces import BumpSurface, PlaneSurface

C = 299_792_458.0
H, ALPHA, TAU, P_MAX = 200e3, 3e-4, 7e-9, 0.05  # the patent's embodiment
R = H * ALPHA  # 60 m
SIGMA_P = TAU / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # 2.9726 ns
E2 = math.exp(-2.0)
MEAN_U = (1.0 - 3.0 * E2) / (1.0 - E2)
DELTA_M = H * ALPHA ** 2 * MEAN_U / 4.0
SIGMA_X_M = 0.5 * R * math.sqrt(MEAN_U)
SYSTEM = wm.WaveformSystem()


def _echo(system: wm.WaveformSystem, surface):
    rets = wm.sample_returns(system, wm.footprint(system), surface)
    times = wm.time_base(system, rets)
    return rets, times, wm.echo_analytic(system, rets, times)


def test_pulse_is_the_patent_gaussian():
    t = np.arange(-20e-9, 30e-9, 1e-12)
    p = wm.pulse_power_w(SYSTEM, t)
    m = wm.pulse_moments(SYSTEM)
    assert wm.pulse_power_w(SYSTEM, 0.0) == pytest.approx(0.5 * P_MAX, rel=1e-14, abs=0)  # t = 0: leading half power
    assert wm.pulse_power_w(SYSTEM, TAU) == pytest.approx(0.5 * P_MAX, rel=1e-14, abs=0)
    energy = math.sqrt(math.pi) * TAU * P_MAX / (2.0 * math.sqrt(math.log(2.0)))  # eq. 3's A
    assert m.energy_j == pytest.approx(energy, rel=1e-14, abs=0)
    assert m.energy_j == pytest.approx(np.sum(p) * 1e-12, rel=1e-9, abs=0)
    assert m.energy_j == pytest.approx(3.7255e-10, rel=1e-4, abs=0)
    assert m.mean_s == pytest.approx(np.sum(t * p) / np.sum(p), rel=1e-9, abs=0) == 3.5e-9
    assert m.rms_width_s == pytest.approx(SIGMA_P, rel=1e-14, abs=0)
    assert m.rms_width_s == pytest.approx(2.97263e-9, rel=1e-5, abs=0)
    assert wm.fwhm_s(t, p) == pytest.approx(TAU, rel=1e-6, abs=0)


def test_patent_grid_has_7200_cells_out_to_the_edge():
    fp = wm.footprint(SYSTEM)
    rho = np.hypot(fp.x_m, fp.y_m)
    assert fp.weight.size == 7200
    assert np.unique(rho.round(9)).tolist() == pytest.approx([(m - 0.5) * R / 60 for m in range(1, 61)])  # eq. 15
    assert fp.weight.sum() == pytest.approx(1.0, rel=1e-13, abs=0)  # eq. 7: the disc carries the whole pulse
    ring = np.exp(-2.0 * (np.arange(60) / 60) ** 2) - np.exp(-2.0 * (np.arange(1, 61) / 60) ** 2)  # ∫ over annuli
    assert fp.weight.reshape(60, 120)[:, 0] == pytest.approx(ring / 120 / (1.0 - E2), rel=1e-12, abs=0)
    tan_off_nadir = np.hypot(fp.direction[:, 0], fp.direction[:, 1]) / -fp.direction[:, 2]
    assert tan_off_nadir == pytest.approx(rho / H, rel=1e-12, abs=0)  # tan φ = ρ/H (eq. 6)
    even = wm.footprint(dataclasses.replace(SYSTEM, scheme="equal_energy"))
    assert np.ptp(even.weight) < 1e-15 and np.hypot(even.x_m, even.y_m).max() < R


def test_flat_echo_is_the_pulse_delayed_by_the_footprint_mean_range():
    rets, times, echo = _echo(SYSTEM, PlaneSurface(0.0))
    m = wm.measure(SYSTEM, times, echo)
    assert m.fwhm_s == pytest.approx(TAU, rel=1e-3, abs=0)
    assert m.rms_width_s == pytest.approx(SIGMA_P, rel=1e-4, abs=0)
    delay = 2.0 * (H + DELTA_M) / C  # 2H/c plus the footprint's own spread: 20.62 ps
    assert m.centroid_s - 0.5 * TAU == pytest.approx(delay, abs=1e-14)  # 0.01 ps
    assert m.half_power_s == pytest.approx(delay, abs=1e-13)
    assert m.centroid_range_m - H == pytest.approx(DELTA_M, rel=1e-4, abs=0)
    assert DELTA_M == pytest.approx(3.0914e-3, rel=1e-4, abs=0)
    assert np.max(rets.range_m) - H == pytest.approx(R ** 2 / (2 * H) * (59.5 / 60) ** 2, rel=1e-6, abs=0)  # edge ring


def test_slope_widens_the_echo_by_the_across_slope_extent():
    s = wm.PATENT_SLOPE
    for system in (SYSTEM, wm.PATENT):
        _, times, echo = _echo(system, PlaneSurface(s))
        expected = math.sqrt(SIGMA_P ** 2 + (2.0 * s * SIGMA_X_M / C) ** 2)  # 33.31 ns
        assert wm.rms_width_s(times, echo) == pytest.approx(expected, rel=1e-3, abs=0)
        assert wm.rms_width_s(times, echo) != pytest.approx(math.sqrt(SIGMA_P ** 2 + (2 * s * 0.5 * R / C) ** 2),
                                                            rel=0.1, abs=0)  # the untruncated σ_x = R/2 is far off


@pytest.mark.parametrize("scheme, rel", [("polar", 1e-11), ("equal_energy", 1e-11), ("polar_midpoint", 2e-4)])
def test_received_power_is_the_lidar_equation_over_the_footprint(scheme, rel):
    parts = dict(aperture_m=0.14, transmitter_efficiency=0.8, receiver_efficiency=0.6,
                 atmosphere_transmission=0.9, reflectance=0.12 / math.pi, scheme=scheme)
    lidar = math.pi * 0.12 / math.pi * 0.9 ** 2 * 0.14 ** 2 * 0.8 * 0.6 / (4.0 * H ** 2)  # eq. 1, P_r / P_s at H
    obliquity = 1.0 - 1.5 * (0.5 * R ** 2 * MEAN_U) / H ** 2  # E[cos θ_i · H²/r²] = E[(1 + ρ²/H²)^(−3/2)]
    for all_energy, inside in ((True, 1.0), (False, 1.0 - E2)):
        system = wm.WaveformSystem(footprint_holds_all_energy=all_energy, **parts)
        rets, times, echo = _echo(system, PlaneSurface(0.0))
        assert np.sum(rets.gain) * P_MAX == pytest.approx(lidar * inside * obliquity * P_MAX, rel=rel, abs=0)
        assert np.sum(echo) * system.sample_interval_s == pytest.approx(
            np.sum(rets.gain) * wm.pulse_energy_j(system), rel=1e-9, abs=0)  # the echo holds each sample's pulse energy


@pytest.mark.parametrize("surface", [PlaneSurface(0.0), BumpSurface()], ids=["flat", "bump"])
def test_binned_path_converges_to_the_analytic_echo_as_dt_shrinks(surface):
    errors = {"linear": [], "nearest": []}
    dts = (4e-11, 2e-11, 1e-11, 5e-12)
    for dt in dts:
        system = wm.WaveformSystem(n_rings=30, n_sectors=60, sample_interval_s=dt)
        rets = wm.sample_returns(system, wm.footprint(system), surface)
        times = wm.time_base(system, rets)
        exact = wm.echo_analytic(system, rets, times)
        scale = np.sum(rets.gain) * P_MAX
        for binning, found in errors.items():
            found.append(np.max(np.abs(wm.echo_binned(system, rets, times, binning) - exact)) / scale)
        # Bounds: a delay moved by ≤ dt/2 changes P by ≤ max|P'|·dt/2 = P_max e^(−½) dt/2σ; linear binning
        # interpolates P between bins, off by ≤ max|P''| dt²/8 = P_max dt²/8σ².
        assert errors["nearest"][-1] <= math.exp(-0.5) * dt / (2.0 * SIGMA_P)
        assert errors["linear"][-1] <= dt ** 2 / (8.0 * SIGMA_P ** 2)
    order = np.log2(np.array(errors["linear"][:-1]) / np.array(errors["linear"][1:]))
    assert np.all(order > 1.7) and np.mean(order) == pytest.approx(2.0, abs=0.25)  # observed: second order


def test_flat_centroid_converges_in_rings_at_second_order():
    errors = []
    for rings in (8, 16, 32, 64):
        system = wm.WaveformSystem(n_rings=rings, n_sectors=8, sample_interval_s=1e-10)
        _, times, echo = _echo(system, PlaneSurface(0.0))
        errors.append(wm.measure(system, times, echo).centroid_range_m - H - DELTA_M)
    order = np.log2(np.abs(np.array(errors[:-1]) / np.array(errors[1:])))
    assert order == pytest.approx([2.0, 2.0, 2.0], abs=0.05)  # ring midpoints: Δρ²/12 bias in E[ρ²]
    system = wm.WaveformSystem(n_rings=8, n_sectors=8, scheme="equal_energy", sample_interval_s=1e-10)
    _, times, echo = _echo(system, PlaneSurface(0.0))
    assert wm.measure(system, times, echo).centroid_range_m - H == pytest.approx(DELTA_M, abs=1e-9)  # RMS radii


def test_slope_echo_converges_as_rings_and_sectors_grow():
    def echo(rings, times=None):
        system = wm.WaveformSystem(n_rings=rings, n_sectors=2 * rings, sample_interval_s=1e-10)
        rets = wm.sample_returns(system, wm.footprint(system), PlaneSurface(wm.PATENT_SLOPE))
        times = wm.time_base(system, rets) if times is None else times
        return times, wm.echo_analytic(system, rets, times)

    times, reference = echo(256)
    errors = np.array([np.max(np.abs(echo(m, times)[1] - reference)) for m in (32, 64, 128)]) / reference.max()
    assert errors[0] < 1e-2 and np.all(np.diff(errors) < 0)
    assert np.log2(errors[0] / errors[-1]) / 2 > 2.0  # observed ≈ 2.9 (against a 256 × 512 grid)


def test_bump_is_met_on_its_surface_and_its_truth():
    bump = BumpSurface()
    fp = wm.footprint(SYSTEM)
    rets = wm.sample_returns(SYSTEM, fp, bump)
    x, y, z = rets.point_m.T
    assert np.max(np.abs(z - bump.height(x, y))) < 1e-10  # one Newton step leaves 3e-10 m, two reach rounding
    on_ray = np.array([0.0, 0.0, H]) + rets.range_m[:, None] * fp.direction
    assert np.max(np.abs(on_ray - rets.point_m)) < 1e-9
    assert wm.nadir_range_m(SYSTEM, bump) == H - 5.0
    num = quad(lambda r: 2.5 * (1 + math.cos(math.pi * r / 20.0)) * math.exp(-2 * r * r / R ** 2) * r, 0, 20.0)[0]
    den = quad(lambda r: math.exp(-2 * r * r / R ** 2) * r, 0, R)[0]
    assert wm.mean_height_m(fp, rets) == pytest.approx(num / den, rel=1e-3, abs=0)
    top = np.argmin(np.hypot(x, y))
    assert rets.cos_incidence[top] == pytest.approx(1.0, abs=1e-3)


def test_decomposition_recovers_gaussians():
    t = np.arange(0.0, 80e-9, 1e-11)
    truth = [(10e-9, 3e-13, 3e-9), (40e-9, 1e-13, 5e-9)]
    echo = sum(a * np.exp(-0.5 * ((t - t0) / s) ** 2) for t0, a, s in truth)
    found = wm.decompose(SYSTEM, t, echo)
    assert [(g.time_s, g.amplitude_w, g.sigma_s) for g in found] == [pytest.approx(g, rel=1e-6, abs=0) for g in truth]
    _, times, flat = _echo(SYSTEM, PlaneSurface(0.0))
    (only,) = wm.decompose(SYSTEM, times, flat)
    assert only.sigma_s == pytest.approx(SIGMA_P, rel=1e-4, abs=0)
    assert only.time_s == pytest.approx(0.5 * TAU + 2.0 * (H + DELTA_M) / C, abs=1e-14)


def test_patent_figures():
    fig = wm.patent_figures()
    flat, slope, bump = fig["flat"], fig["slope"], fig["bump"]
    assert flat["fwhm_s"] == pytest.approx(TAU, rel=1e-3, abs=0)
    assert flat["first_return_s"] == pytest.approx(2.0 * math.hypot(H, R / 120) / C, abs=1e-17)  # inner ring
    assert flat["last_return_s"] == pytest.approx(2.0 * (H + (59.5 / 60) ** 2 * R ** 2 / (2 * H)) / C, abs=1e-15)
    assert flat["window_s"] == pytest.approx((flat["first_return_s"] - TAU, flat["last_return_s"] + TAU), abs=1e-18)
    assert flat["range_error_m"] == pytest.approx(DELTA_M, abs=2e-5)
    top = 59.5 * math.cos(math.pi / 120)  # outer ring, first sector's mid-angle: the highest cell (eq. 15)
    assert slope["first_return_s"] == pytest.approx(2.0 * math.hypot(59.5, H - 0.2 * top) / C, abs=1e-17)  # eq. 10
    assert slope["rms_width_s"] == pytest.approx(math.sqrt(SIGMA_P ** 2 + (0.4 * SIGMA_X_M / C) ** 2), rel=1e-3, abs=0)
    assert slope["range_error_m"] < -1.0  # the uphill side's earlier returns pull the half-power point
    assert bump["nadir_range_m"] == H - 5.0 and bump["first_return_s"] > 2.0 * (H - 5.0) / C
    assert 0.0 < bump["mean_height_m"] < 5.0


@pytest.mark.parametrize("field, value", [
    ("altitude_m", 0.0), ("altitude_m", math.inf), ("half_divergence_rad", 0.0), ("half_divergence_rad", -3e-4),
    ("pulse_fwhm_s", 0.0), ("peak_power_w", math.nan), ("sample_interval_s", 8e-9), ("n_rings", 0),
    ("n_sectors", 0), ("n_rings", 2.5), ("receiver_efficiency", 1.5), ("scheme", "hex"), ("geometry", "slant"),
])
def test_bad_input_names_its_field(field, value):
    with pytest.raises(InputError) as err:
        wm.WaveformSystem(**{field: value})
    assert err.value.field == f"waveform.{field}"


@pytest.mark.parametrize("make, field", [
    (lambda: BumpSurface(radius_m=0.0), "surface.radius_m"), (lambda: PlaneSurface(math.nan), "surface.slope"),
    (lambda: wm.echo_binned(SYSTEM, None, np.zeros(3), "cubic"), "waveform.binning"),
])
def test_bad_surface_or_binning_names_its_field(make, field):
    with pytest.raises(InputError) as err:
        make()
    assert err.value.field == field


def _noisy_gaussian(seed: int, background: float = 0.05, noise: float = 0.01, sd: float = 6.37, n: int = 3000):
    """A unit Gaussian echo (σ ``sd`` samples of 1 ns, centred at sample 1234.3) on a background, with white
    Gaussian noise of ``noise`` of its peak: (times [s], waveform [W], centre [s], σ [s])."""
    rng = np.random.default_rng(seed)
    i = np.arange(n, dtype=np.float64)
    times = 2.8e-3 + 1e-9 * i
    echo = np.exp(-0.5 * ((i - 1234.3) / sd) ** 2) + background + rng.normal(0.0, noise, n)
    return times, echo, times[0] + 1234.3e-9, sd * 1e-9


def test_window_noise_is_the_ends_mean_and_sigma_and_a_floor_noise_crosses_in_one_window_of_a_hundred():
    rows = np.stack([_noisy_gaussian(seed)[1] for seed in range(400)])
    mean, floor = wm.window_noise(rows)
    ends = np.concatenate([rows[:, :64], rows[:, -64:]], axis=1)
    np.testing.assert_allclose(mean, ends.mean(axis=1), rtol=1e-15)
    k = 4.504062242  # Φ⁻¹(1 − 0.01/3000): ½·erfc(k/√2) = 3.3333e-6, solved by bisection in float64
    np.testing.assert_allclose(floor, k * ends.std(axis=1, ddof=1), rtol=1e-9)
    assert abs(mean.mean() - 0.05) < 0.01 * 4 / math.sqrt(128 * 400)  # the background, within 4 standard errors
    noise_only = rows[:, 2000:] - mean[:, None]  # 1000 samples far from the echo
    assert np.mean((noise_only > floor[:, None]).any(axis=1)) < 0.02  # 1000/3000 of 1 %, with room


@pytest.mark.parametrize("seed", range(5))
def test_a_noisy_echos_measures_are_its_own_above_the_noise_floor(seed):
    """Over the whole 3000-sample window the background and the noise outweigh the echo (its centroid is pulled
    metres away, its second moment may come out negative); above the floor, the centroid is the echo's centre and
    the RMS width that of a Gaussian truncated where it meets the floor: σ·√(1 − 2aφ(a)/(2Φ(a) − 1)),
    a = √(2 ln(peak / floor))."""
    from scipy.stats import norm

    times, echo, centre, sd = _noisy_gaussian(seed)
    noise = wm.window_noise(echo[None, :])
    mean, floor = float(noise[0][0]), float(noise[1][0])
    m = wm.measure(SYSTEM, times, echo, (mean, floor))
    assert abs(m.centroid_s - centre) < 0.04 * sd  # the noise's share of the centroid: ~0.005 σ rms
    assert abs(m.peak_s - centre) < 0.1 * sd
    a = math.sqrt(2.0 * math.log(1.0 / floor))
    truncated = sd * math.sqrt(1.0 - 2.0 * a * norm.pdf(a) / (2.0 * norm.cdf(a) - 1.0))
    assert m.rms_width_s == pytest.approx(truncated, rel=0.03)
    assert m.fwhm_s == pytest.approx(wm.FWHM_PER_SIGMA * sd, rel=0.03)
    whole = wm.measure(SYSTEM, times, echo)
    assert abs(whole.centroid_s - centre) > 10 * sd  # what the whole window gives
    assert math.isnan(whole.rms_width_s) or whole.rms_width_s > 10 * sd


def test_rms_width_is_nan_without_a_warning_where_the_moment_is_negative():
    """Samples that weigh negative (noise below its mean) can make Σ (t − t̄)² P / Σ P negative (weights −1, 3, −1
    at −1, 0, 1: −2): its root NaN, as the device's measures give it, and no RuntimeWarning; a positive moment's root
    as before (weights 1, 1 at ±1: 1)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(wm.rms_width_s(np.array([-1.0, 0.0, 1.0]), np.array([-1.0, 3.0, -1.0])))
        assert wm.rms_width_s(np.array([-1.0, 1.0]), np.array([1.0, 1.0])) == 1.0


def test_windows_of_noise_alone_have_no_measures():
    """Noise and background without an echo: in all but about one window of a hundred no sample is above the floor,
    and every measure is NaN (not the noise's centroid)."""
    rng = np.random.default_rng(3)
    times = 1e-9 * np.arange(3000)
    rows = 0.05 + rng.normal(0.0, 0.01, (200, 3000))
    mean, floor = wm.window_noise(rows)
    empty = [all(math.isnan(getattr(m, f.name)) for f in dataclasses.fields(m))
             for m in (wm.measure(SYSTEM, times, row, (mu, fl)) for row, mu, fl in zip(rows, mean, floor))]
    assert sum(empty) >= 190  # 198 expected (σ 1.4): 190 is over 5 standard deviations below


def test_smoothing_gain_is_the_filtered_noises_sigma():
    """White noise of unit σ through gaussian_filter1d(·, sd): σ √Σw², close to the continuous kernel's
    (2√π·sd)^(−1/2), and what 10⁶ filtered samples show."""
    from scipy.ndimage import gaussian_filter1d

    for sd in (2.97, 6.37, 29.7):
        gain = wm.smoothing_gain(sd)
        assert gain == pytest.approx((2.0 * math.sqrt(math.pi) * sd) ** -0.5, rel=1e-3)
        filtered = gaussian_filter1d(np.random.default_rng(5).normal(0.0, 1.0, 10 ** 6), sd)
        assert filtered.std() == pytest.approx(gain, rel=0.01)


def _two_gaussians_on_a_background(seed: int, background: float):
    """A Gaussian of 1 W (σ 6.37 ns at sample 400.3) and one of 0.6 W (σ 9 ns at sample 600) on ``background`` [W],
    with white noise of 0.01 W, in 1000 samples of 1 ns: (times [s], waveform [W], truth (time, amplitude, σ))."""
    rng = np.random.default_rng(seed)
    times = 2.8e-3 + 1e-9 * np.arange(1000)
    truth = [(times[0] + 400.3e-9, 1.0, 6.37e-9), (times[0] + 600e-9, 0.6, 9e-9)]
    echo = background + rng.normal(0.0, 0.01, len(times))
    for t0, a, s in truth:
        echo += a * np.exp(-0.5 * ((times - t0) / s) ** 2)
    return times, echo, truth


@pytest.mark.parametrize("background", [0.05, 5.0])
@pytest.mark.parametrize("seed", range(3))
def test_a_noisy_echo_is_decomposed_less_its_noise_mean(background, seed):
    """The Gaussians have no offset: the window's noise mean (window_noise) is taken off before the fit, and the
    components are the echo's within their fit's noise (amplitude ~0.004 W, centre ~0.03 ns, σ ~0.6 %; tolerances 5
    times those), whatever the background: 5 % of the peak, or 5 times it (left in, it was fitted into the Gaussians:
    amplitudes 4-5 % high and widths 7-13 % wide at 5 %, two Gaussians 474 ns wide at the window's ends at 5 times)."""
    times, echo, truth = _two_gaussians_on_a_background(seed, background)
    mean, floor = (float(v[0]) for v in wm.window_noise(echo[None, :]))
    found = wm.decompose(SYSTEM, times, echo, noise=(mean, floor))
    assert len(found) == 2
    for g, (t0, a, s) in zip(found, truth):
        assert abs(g.time_s - t0) < 0.15e-9 and abs(g.amplitude_w - a) < 0.02 and g.sigma_s == pytest.approx(s, rel=0.03)


def test_windows_of_noise_alone_have_no_components():
    """Noise and background without an echo, decomposed less their noise mean: a maximum of the smoothed noise counts
    only above the floor scaled by the smoothing's gain, which noise alone crosses in fewer windows than the raw
    floor (one in a hundred): no components in at least 196 of 200 windows (the mean, less the background, leaves
    the 5 % prominence rule to pass most noise maxima)."""
    rng = np.random.default_rng(8)
    times = 1e-9 * np.arange(1000)
    rows = 0.05 + rng.normal(0.0, 0.01, (200, 1000))
    mean, floor = wm.window_noise(rows)
    found = [len(wm.decompose(SYSTEM, times, row, noise=(mu, fl))) for row, mu, fl in zip(rows, mean, floor)]
    assert sum(n > 0 for n in found) <= 4
