"""The batched Trust Region Reflective solver (flightsim.core.trf_batch) against SciPy's least_squares run on each
problem alone (method "trf", x_scale "jac", the same bounds and tolerances): sums of Gaussians with noise, bounds
active at the solution, infinite bounds, a rank-deficient start, padded residuals and a noise-free closed form."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from flightsim.core.trf_batch import least_squares_batch

L = 120  # residual rows of every problem (the padded length)


class Gaussians:
    """Sums of m Gaussians a exp(−((x − c)/w)²/2) minus a target, problem by problem at x = 0 … count − 1 (zero
    beyond count): the batched interface and SciPy's (one problem)."""

    def __init__(self, target: np.ndarray, counts: np.ndarray):
        self.x = np.arange(L, dtype=np.float64)
        self.inside = self.x[None, :] < counts[:, None]
        self.target = np.where(self.inside, target, 0.0)

    def terms(self, p, inside):
        m = p.shape[-1] // 3
        amp, centre, width = p[..., :m, None], p[..., m:2 * m, None], p[..., 2 * m:, None]
        u = (self.x - centre) / width
        return amp, width, u, np.exp(-0.5 * u * u) * inside[..., None, :]

    def residual(self, p, rows):
        amp, _, _, e = self.terms(p, self.inside[rows])
        return (amp * e).sum(axis=1) - self.target[rows]

    def jacobian(self, p, rows):
        amp, width, u, e = self.terms(p, self.inside[rows])
        return np.concatenate([e, amp * e * u / width, amp * e * u * u / width], axis=1)

    def one(self, i):
        """(residual, jacobian) of problem i alone, over its own rows, for SciPy."""
        n = int(self.inside[i].sum())
        target = self.target[i, :n]

        def residual(p):
            return self.residual(p[None, :], np.array([i]))[0, :n]

        def jacobian(p):
            return self.jacobian(p[None, :], np.array([i]))[0, :, :n].T

        return residual, jacobian, target


def _problems(count: int, m: int, seed: int):
    """Noisy sums of m Gaussians with random windows; starts and bounds as a waveform fit sets them."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(60, L + 1, count)
    centres = np.sort(rng.uniform(10.0, 50.0, (count, m)), axis=1)
    widths = rng.uniform(2.0, 8.0, (count, m))
    amps = rng.uniform(0.2, 2.0, (count, m))
    x = np.arange(L)
    clean = (amps[:, :, None] * np.exp(-0.5 * ((x - centres[:, :, None]) / widths[:, :, None]) ** 2)).sum(axis=1)
    target = clean + rng.normal(0.0, 0.05, (count, L))
    start = np.concatenate([amps * rng.uniform(0.5, 1.5, (count, m)), centres + rng.normal(0.0, 2.0, (count, m)),
                            np.full((count, m), 4.0)], axis=1)
    lower = np.concatenate([np.zeros((count, m)), np.zeros((count, m)), np.full((count, m), 1.0)], axis=1)
    upper = np.concatenate([np.full((count, m), np.inf), np.repeat(counts[:, None] - 1.0, m, axis=1),
                            np.full((count, m), 40.0)], axis=1)
    return Gaussians(target, counts), np.clip(start, lower, upper), lower, upper, counts


def _scipy(model: Gaussians, x0, lower, upper) -> np.ndarray:
    out = np.empty_like(x0)
    for i in range(len(x0)):
        residual, jacobian, _ = model.one(i)
        out[i] = least_squares(residual, x0[i], jac=jacobian, bounds=(lower[i], upper[i]), x_scale="jac").x
    return out


def _cost(model: Gaussians, x) -> np.ndarray:
    f = model.residual(x, np.arange(len(x)))
    return 0.5 * np.sum(f * f, axis=1)


@pytest.mark.parametrize("m", [1, 2, 3])
def test_noisy_gaussian_sums_reach_scipys_solutions(m):
    """Each problem's cost equals SciPy's to 1e-9, and its parameters SciPy's to 1e-7 but for a few (≤ 2 %) whose
    last step falls on the other side of a stopping test: a weak component's amplitude in a flat valley, where the
    tolerances (a cost change below 1e-8 of the cost) allow δx ~ √(2·1e-8·F/h) ~ 1e-5 (F ~ 0.15, h ≳ 5)."""
    model, x0, lower, upper, counts = _problems(150, m, seed=m)
    got = least_squares_batch(model, x0, lower, upper, counts)
    expected = _scipy(model, x0, lower, upper)
    np.testing.assert_allclose(_cost(model, got), _cost(model, expected), rtol=1e-9, atol=0.0)
    apart = np.abs(got - expected).max(axis=1)
    assert apart.max() < 1e-5 and np.mean(apart < 1e-7) >= 0.98, (apart.max(), np.mean(apart < 1e-7))
    assert ((got >= lower) & (got <= upper)).all()


def test_a_negative_mode_ends_on_its_bound_as_scipys():
    """A second Gaussian held to a dip it cannot fit (amplitudes ≥ 0, its centre within 5 samples of the dip): SciPy
    leaves its amplitude at the bound; so does the batch, with the other parameters equal."""
    rng = np.random.default_rng(11)
    count = 40
    x = np.arange(L)
    target = np.exp(-0.5 * ((x - 30.0) / 4.0) ** 2) - 0.5 * np.exp(-0.5 * ((x - 60.0) / 3.0) ** 2)
    counts = np.full(count, L)
    model = Gaussians(target + rng.normal(0.0, 0.01, (count, L)), counts)
    x0 = np.tile([1.0, 0.3, 31.0, 60.0, 5.0, 3.0], (count, 1))
    lower = np.tile([0.0, 0.0, 0.0, 55.0, 1.0, 2.0], (count, 1))
    upper = np.tile([np.inf, np.inf, L - 1.0, 65.0, 40.0, 4.0], (count, 1))
    got = least_squares_batch(model, x0, lower, upper, counts)
    expected = _scipy(model, x0, lower, upper)
    assert (expected[:, 1] < 1e-6).all()  # the case: SciPy's amplitude on its bound
    np.testing.assert_allclose(got, expected, rtol=0.0, atol=1e-7)


def test_a_rank_deficient_jacobian_follows_scipy():
    """A second Gaussian far beyond the samples (its three Jacobian columns exactly zero: the SVD's rank test fails
    and the subproblem's LM parameter comes from its guess) beside one that fits: the same steps as SciPy's."""
    model, x0, lower, upper, counts = _problems(30, 1, seed=7)
    x0 = np.concatenate([x0[:, :1], np.full((30, 1), 0.5), x0[:, 1:2], np.full((30, 1), 900.0),
                         x0[:, 2:], np.full((30, 1), 2.0)], axis=1)
    lower = np.concatenate([lower[:, :1], lower[:, :1], lower[:, 1:2], lower[:, 1:2], lower[:, 2:], lower[:, 2:]],
                           axis=1)
    upper = np.concatenate([upper[:, :1], upper[:, :1], upper[:, 1:2], np.full((30, 1), 1000.0), upper[:, 2:],
                            upper[:, 2:]], axis=1)
    got = least_squares_batch(model, x0, lower, upper, counts)
    expected = _scipy(model, x0, lower, upper)
    np.testing.assert_allclose(_cost(model, got), _cost(model, expected), rtol=1e-9, atol=0.0)
    # the far Gaussian's centre and width have no gradient and stay (to round-off); its amplitude, unseen as well,
    # drifts on round-off in both (a direction of no cost; not compared) and with it ‖x‖ in the step test: a run
    # stops where a step falls below 1e-8·‖x‖, ~1e-5 when the amplitude has drifted to 1e3
    np.testing.assert_allclose(got[:, [0, 2, 4]], expected[:, [0, 2, 4]], rtol=0.0, atol=1e-5)
    np.testing.assert_allclose(got[:, [3, 5]], np.tile([900.0, 2.0], (30, 1)), rtol=0.0, atol=1e-9)


def test_a_noise_free_gaussian_is_found_exactly():
    """Closed form: a noise-free Gaussian (amplitude 1.3, centre 41.25, width 5.5) from a start 3 samples off."""
    target = np.tile(1.3 * np.exp(-0.5 * ((np.arange(L) - 41.25) / 5.5) ** 2), (5, 1))
    counts = np.array([L, 100, 90, 80, 70])
    x0 = np.tile([1.0, 44.0, 4.0], (5, 1))
    lower, upper = np.tile([0.0, 0.0, 1.0], (5, 1)), np.tile([np.inf, L - 1.0, 40.0], (5, 1))
    got = least_squares_batch(Gaussians(target, counts), x0, lower, upper, counts)
    np.testing.assert_allclose(got, np.tile([1.3, 41.25, 5.5], (5, 1)), rtol=0.0, atol=1e-9)


def test_no_problems_and_starts_on_their_bounds():
    """An empty batch gives an empty answer; starts on a bound are moved inside it as SciPy moves them."""
    model, x0, lower, upper, counts = _problems(20, 1, seed=3)
    assert least_squares_batch(model, x0[:0], lower[:0], upper[:0], counts[:0]).shape == (0, 3)
    x0[:, 0], x0[:, 2] = 0.0, 40.0  # amplitude on its lower bound, width on its upper
    np.testing.assert_allclose(least_squares_batch(model, x0, lower, upper, counts), _scipy(model, x0, lower, upper),
                               rtol=0.0, atol=1e-7)


class Logs:
    """r(x) = ln x − t, NaN below zero: the first Gauss-Newton step from 50·eᵗ lands below zero."""

    def __init__(self, t: np.ndarray):
        self.t = t

    def residual(self, p, rows):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.log(p) - self.t[rows, None]

    def jacobian(self, p, rows):
        return (1.0 / p)[:, :, None]


def test_a_step_to_non_finite_residuals_shrinks_the_radius_as_scipys():
    """Residuals NaN beyond a point the steps reach (ln x below zero): SciPy's trust region shrinks to a quarter of
    the step and tries again. Each problem's trial points are SciPy's, one for one (to 1e-9), ending at x = eᵗ."""
    t = np.linspace(0.0, 2.0, 9)
    x0 = 50.0 * np.exp(t)[:, None]
    lower, upper = np.full_like(x0, -1e6), np.full_like(x0, 1e6)
    model = Logs(t)
    trials = [[] for _ in t]
    residual = model.residual

    def recorded(p, rows):
        for row, x in zip(rows, p[:, 0]):
            trials[row].append(x)
        return residual(p, rows)

    model.residual = recorded
    got = least_squares_batch(model, x0, lower, upper, np.ones(9, dtype=np.int64))
    for i in range(9):
        expected = []

        def one(x, i=i):
            expected.append(x[0])
            return residual(x[None], np.array([i]))[0]

        least_squares(one, x0[i], jac=lambda x: np.array([[1.0 / x[0]]]), bounds=(lower[i], upper[i]), x_scale="jac")
        assert min(expected) < 0.0  # the case: trial points where the residuals are NaN
        assert len(trials[i]) == len(expected), (i, len(trials[i]), len(expected))
        np.testing.assert_allclose(trials[i], expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got[:, 0], np.exp(t), rtol=1e-8)
