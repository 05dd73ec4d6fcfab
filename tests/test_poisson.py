"""The Poisson tails and quantiles of flightsim.core.poisson against scipy.stats.poisson (what they replace, bit for
bit), over counts below the support, zero, tiny, small and large means."""
import numpy as np
import pytest
from scipy.stats import poisson

from flightsim.core.poisson import at_least, upper_quantile

MEANS = np.concatenate([[0.0, 1e-300, 1e-12, 1e-9], np.linspace(0.0, 60.0, 6001), np.geomspace(1e-6, 1e6, 4001)])


def test_tail_probability_is_scipys_poisson_survival_bit_for_bit():
    """``at_least(k, λ)`` = P(K ≥ k) = ``scipy.stats.poisson.sf(k - 1, λ)`` to the last bit: counts below the
    support (k ≤ 0), λ = 0, small and large means, and the integer and float64 inputs the finder hands it."""
    rng = np.random.default_rng(7)
    k = np.concatenate([np.arange(-3, 90), rng.integers(-2, 400, 20_000)])
    lam = np.concatenate([np.zeros(31), np.full(31, 1e-9), np.linspace(0.5, 300.0, 31), rng.random(20_000) * 200.0])
    expected = poisson.sf(k - 1, lam)
    assert np.array_equal(at_least(k, lam), expected)
    assert np.array_equal(at_least(k.astype(np.float64), lam), expected)
    assert at_least(np.array([0, 1]), np.array([0.0, 0.0])).tolist() == [1.0, 0.0]



@pytest.mark.parametrize("p", [1e-12, 1e-6, 1e-3, 0.05, 0.5, 0.999, 1.0])
def test_upper_quantile_is_scipys_poisson_isf_bit_for_bit(p):
    """``upper_quantile(p, λ)`` = ``scipy.stats.poisson.isf(p, λ)`` for every mean (ATL08's dense-count limits take
    it at dragann_p over each segment's background, zero where a segment has no photons), p = 1 included."""
    assert np.array_equal(upper_quantile(p, MEANS), poisson.isf(p, MEANS))


def test_upper_quantile_is_the_least_count_whose_tail_is_within_p():
    """The definition itself, by counting: P(K > k) ≤ p at k, and > p at k − 1 (the sum of the PMF in float64)."""
    lam = np.array([0.3, 2.0, 7.5, 40.0])
    k = upper_quantile(1e-3, lam).astype(int)
    for m, kk in zip(lam, k):
        pmf = np.exp(-m + np.arange(200) * np.log(m) - np.cumsum(np.r_[0.0, np.log(np.arange(1, 200))]))
        tail = 1.0 - np.cumsum(pmf)  # P(K > j)
        assert tail[kk] <= 1e-3 < tail[kk - 1]


@pytest.mark.parametrize("p", [0.0, -0.1, 1.5, float("nan")])
def test_upper_quantile_refuses_a_chance_outside_0_1(p):
    with pytest.raises(ValueError, match="tail chance"):
        upper_quantile(p, np.array([1.0]))
