"""metrics.stats on hand-made data with known answers: bootstrap intervals, the paired
sign-flip permutation test, Wilcoxon and the sign test."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.metrics.stats import (bootstrap_ci, paired_permutation_test, paired_summary, sign_test,
                                        wilcoxon_signed_rank)


def test_bootstrap_constant_and_single_value():
    assert bootstrap_ci([2.5, 2.5, 2.5]) == (2.5, 2.5, 2.5)
    assert bootstrap_ci([7.0]) == (7.0, 7.0, 7.0)
    est, lo, hi = bootstrap_ci([np.nan, np.inf])
    assert np.isnan(est) and np.isnan(lo) and np.isnan(hi)
    assert bootstrap_ci([1.0, np.nan, 1.0]) == (1.0, 1.0, 1.0)  # non-finite scenes left out


def test_bootstrap_two_values_percentiles():
    # resampled means of [0, 1]: 0 (p 1/4), 0.5 (1/2), 1 (1/4): the 2.5 / 97.5 percentiles are 0 and 1,
    # the 30 / 70 percentiles 0.5
    assert bootstrap_ci([0.0, 1.0]) == (0.5, 0.0, 1.0)
    assert bootstrap_ci([0.0, 1.0], confidence=0.4) == (0.5, 0.5, 0.5)


def test_bootstrap_seeded_and_median_statistic():
    x = np.random.default_rng(3).normal(size=12)
    assert bootstrap_ci(x, seed=1) == bootstrap_ci(x, seed=1)
    assert bootstrap_ci(x, seed=1) != bootstrap_ci(x, seed=2)
    est, lo, hi = bootstrap_ci(x, statistic=lambda a: np.median(a, axis=1))
    assert est == pytest.approx(np.median(x)) and lo <= est <= hi


def test_bootstrap_covers_the_true_mean_about_95_percent():
    rng = np.random.default_rng(0)
    hits = 0
    trials = 300
    for k in range(trials):
        _, lo, hi = bootstrap_ci(rng.normal(size=20), n_resamples=2000, seed=k)
        hits += lo <= 0.0 <= hi
    # the percentile interval under-covers slightly at n = 20 (about 93 %)
    assert 0.88 <= hits / trials <= 0.98


def test_permutation_exact_known_p_values():
    # d = [1, 2, 3]: of the 8 sign patterns only +++ and --- reach |sum| 6 -> 2/8
    assert paired_permutation_test([1.0, 2.0, 3.0]) == pytest.approx(0.25)
    # 8 equal positive changes: 2 of 256 patterns as extreme
    assert paired_permutation_test(np.ones(8)) == pytest.approx(2 / 256)
    # d = [5, 1, 1, 1]: sums 5 +-1 +-1 +-1 in {8, 6, 6, 6, 4, 4, 4, 2} and their negatives
    assert paired_permutation_test([5.0, 1.0, 1.0, 1.0]) == pytest.approx(2 / 16)
    assert paired_permutation_test([5.0, 1.0, 1.0, 1.0], alternative="greater") == pytest.approx(1 / 16)
    assert paired_permutation_test([5.0, 1.0, 1.0, 1.0], alternative="less") == pytest.approx(1.0)
    # mean 0: every pattern is as extreme
    assert paired_permutation_test([1.0, -1.0]) == 1.0
    assert paired_permutation_test([0.0, 0.0]) == 1.0 and paired_permutation_test([]) == 1.0
    # a zero difference doubles the patterns but moves no sum: same p as without it
    assert paired_permutation_test([1.0, 2.0, 3.0, 0.0]) == pytest.approx(0.25)
    with pytest.raises(ValueError):
        paired_permutation_test([1.0], alternative="both")


def test_permutation_monte_carlo_beyond_exact():
    d = np.ones(25)  # exact p would be 2 / 2^25
    p = paired_permutation_test(d, n_permutations=20_000, seed=4)
    assert p == paired_permutation_test(d, n_permutations=20_000, seed=4)
    assert 0 < p <= 5 / 20_001
    mixed = np.r_[np.ones(13), -np.ones(12)]  # mean 0.04: far from significant
    assert paired_permutation_test(mixed, n_permutations=20_000) > 0.5


def test_wilcoxon_and_sign_test_known_values():
    # 5 positive differences of distinct size: exact two-sided Wilcoxon p = 2 / 2^5
    assert wilcoxon_signed_rank([1.0, 2.0, 3.0, 4.0, 5.0]) == pytest.approx(0.0625)
    # sign test: 5 of 5 positive -> 2 x (1/2)^5; 4 of 5 -> 2 x 6/32
    assert sign_test([1.0, 2.0, 3.0, 4.0, 5.0]) == pytest.approx(0.0625)
    assert sign_test([1.0, 2.0, -3.0, 4.0, 5.0]) == pytest.approx(0.375)
    assert sign_test([0.0, 0.0]) == 1.0 and wilcoxon_signed_rank([0.0]) == 1.0


def test_paired_summary():
    a = np.array([3.0, 5.0, 4.0, np.nan, 2.0])
    b = np.array([1.0, 2.0, 4.0, 0.0, 1.0])
    s = paired_summary(a, b)
    assert s["n"] == 4 and s["mean_diff"] == pytest.approx((2 + 3 + 0 + 1) / 4)
    assert (s["greater"], s["equal"], s["less"]) == (3, 1, 0)
    assert s["ci"][0] <= s["mean_diff"] <= s["ci"][1]
    # d = [2, 3, 0, 1]: |sum| >= 6 for +++ / --- of the non-zero three, x2 for the zero's sign
    assert s["p_permutation"] == pytest.approx(4 / 16)
    with pytest.raises(ValueError):
        paired_summary([1.0], [1.0, 2.0])
