import math

import numpy as np
import pytest

from stam import stats
from stam.errors import StamError
from stam.stats import (bootstrap_ci, bootstrap_intervals, bootstrap_means, paired_halfwidth, ratio_ci,
                        required_test_size, seed_variance_ratio, widen, wilson_interval)


def test_wilson_interval():
    lo, hi = wilson_interval(10, 10)
    assert hi == 1.0 and lo == pytest.approx(10 / (10 + 1.96 ** 2), abs=1e-9)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(1.96 ** 2 / (10 + 1.96 ** 2), abs=1e-9)
    lo, hi = wilson_interval(905, 1000)
    assert lo < 0.905 < hi and hi - lo == pytest.approx(0.036, abs=0.002)
    assert wilson_interval(0, 0) is None


@pytest.mark.parametrize("p, n", [(0.3, 1100), (0.5, 400), (0.1, 2000)])
def test_bootstrap_ci_of_a_known_rate(p, n):
    # Exactly round(p n) correct sequences: the interval holds p and is as wide as the binomial's
    # normal interval, 2 x 1.96 sqrt(p (1 - p) / n), up to the bootstrap's own noise.
    correct = np.zeros(n)
    correct[np.random.default_rng(0).permutation(n)[:round(p * n)]] = 1
    mean, lo, hi = bootstrap_ci(correct)
    assert mean == pytest.approx(p)
    assert lo < p < hi
    assert hi - lo == pytest.approx(2 * 1.96 * math.sqrt(p * (1 - p) / n), rel=0.05)
    assert (hi - lo) / 2 == pytest.approx(paired_halfwidth(n, p * (1 - p)), rel=0.05)


def test_bootstrap_covers_the_true_rate_about_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    p, n, trials = 0.3, 200, 200
    hits = 0
    for t in range(trials):
        _, lo, hi = bootstrap_ci(rng.random(n) < p, resamples=1000, seed=t)
        hits += lo <= p <= hi
    # 95% nominal; with 200 trials the count's sd is about 3 (binomial), so 180 is far below.
    assert 180 <= hits <= 198, hits


def test_paired_difference_of_identical_models_is_exactly_zero():
    a = (np.random.default_rng(2).random(500) < 0.4).astype(float)
    mean, lo, hi = bootstrap_ci(a - a)
    assert (mean, lo, hi) == (0.0, 0.0, 0.0)
    both = bootstrap_intervals(np.stack([a, a], axis=1))
    reps = bootstrap_means(np.stack([a, a], axis=1))
    assert np.array_equal(both[0], both[1]) and np.array_equal(reps[:, 0], reps[:, 1])


def test_pairing_narrows_the_difference_of_correlated_models():
    # Model b is model a with 5% of the sequences flipped: the paired interval of b - a is far
    # narrower than what two independent accuracies would give.
    rng = np.random.default_rng(3)
    a = (rng.random(1000) < 0.5).astype(float)
    b = a.copy()
    flip = rng.permutation(1000)[:50]
    b[flip] = 1 - b[flip]
    _, lo, hi = bootstrap_ci(b - a)
    unpaired = 2 * 1.96 * math.sqrt(2 * 0.25 / 1000)
    assert hi - lo < 0.4 * unpaired
    assert (hi - lo) / 2 == pytest.approx(paired_halfwidth(1000, np.var(b - a)), rel=0.1)


def test_bootstrap_is_deterministic_and_seeded():
    x = np.random.default_rng(4).random((300, 3))
    assert np.array_equal(bootstrap_means(x), bootstrap_means(x))
    assert np.array_equal(bootstrap_intervals(x), bootstrap_intervals(x))
    assert not np.array_equal(bootstrap_means(x, seed=1), bootstrap_means(x, seed=2))
    # One column alone sees the same resamples as within a block of columns.
    assert np.allclose(bootstrap_means(x[:, 1]), bootstrap_means(x)[:, 1])


def test_bootstrap_of_nothing_is_an_error():
    with pytest.raises(StamError, match="zero rows"):
        bootstrap_means(np.zeros(0))


def test_ratio_ci():
    num = np.r_[np.ones(30), np.zeros(70)]   # mean 0.3
    den = np.r_[np.ones(60), np.zeros(40)]   # mean 0.6
    r, lo, hi = ratio_ci(num, den)
    assert r == pytest.approx(0.5) and lo < 0.5 < hi
    assert ratio_ci(num, num) == (1.0, 1.0, 1.0)
    assert ratio_ci(num, np.zeros(100)) is None


def test_required_test_size_inverts_the_half_width():
    for d in (0.05, 0.03, 0.01):
        n = required_test_size(d)
        assert paired_halfwidth(n) <= d < paired_halfwidth(n - 1)
    # A 100-sequence split: about +-10 points on a paired difference at the planning variance.
    assert 100 * paired_halfwidth(100) == pytest.approx(9.8, abs=0.1)
    assert stats.MIN_TEST_SEQUENCES >= required_test_size(0.05)


def test_seed_variance_ratio():
    rng = np.random.default_rng(5)
    # Seeds flip sequences independently: the ratio is near 1.
    indep = [(rng.random((3, 1000)) < 0.4).astype(float) for _ in range(40)]
    r = seed_variance_ratio(indep)
    assert r["cells"] == 40 and 0.6 < r["ratio"] < 1.5
    # One seed is right on 10% more of the sequences everywhere: a shared shift, ratio well above 1.
    shifted = []
    for _ in range(40):
        c = (rng.random((3, 1000)) < np.array([[0.3], [0.4], [0.5]])).astype(float)
        shifted.append(c)
    assert seed_variance_ratio(shifted)["ratio"] > 5
    assert seed_variance_ratio([np.ones((1, 10))])["ratio"] is None
    assert seed_variance_ratio([np.ones((3, 10))])["ratio"] is None


def test_widen_adds_in_quadrature_on_each_side():
    assert widen(0.5, 0.4, 0.6, 0.0) == (0.4, 0.6)
    z2v = 1.959963984540054 ** 2 * 0.0009
    lo, hi = widen(0.5, 0.45, 0.62, 0.0009)
    assert lo == pytest.approx(0.5 - np.sqrt(0.05 ** 2 + z2v)) and hi == pytest.approx(0.5 + np.sqrt(0.12 ** 2 + z2v))
    assert widen(0.5, 0.4, 0.6, -1.0) == (0.4, 0.6)   # a negative estimate adds nothing


def test_widened_intervals_cover_a_shared_seed_shift():
    # Each seed moves a cell's whole threshold by b ~ N(0, 0.08): the bootstrap over sequences of the
    # seed-averaged correctness cannot see it and under-covers; adding the pooled shift restores 95%.
    rng = np.random.default_rng(11)
    seeds, n, cells_per_run, sigma, p, trials = 3, 200, 12, 0.08, 0.4, 200
    plain = wide = 0
    estimates = []
    for t in range(trials):
        cells = [(rng.random(n)[None, :] < p + rng.normal(0, sigma, seeds)[:, None]).astype(float)
                 for _ in range(cells_per_run)]
        shift = seed_variance_ratio(cells)["shift_variance"]
        estimates.append(shift)
        mean, lo, hi = bootstrap_ci(cells[0].mean(0), resamples=400, seed=t)
        plain += lo <= p <= hi
        wlo, whi = widen(mean, lo, hi, shift / seeds)
        wide += wlo <= p <= whi
    assert np.mean(estimates) == pytest.approx(sigma ** 2, rel=0.15)
    assert plain / trials < 0.85 and 0.90 <= wide / trials <= 0.99, (plain, wide)
