"""Statistics of experiments over scenes: bootstrap confidence intervals and paired tests.

Flat functions on arrays (numpy, scipy), usable on their own. The unit of analysis is the
scene: a value per scene (already averaged over seeds and evaluation seeds by the caller), and
for a comparison of two conditions on the same scenes the per-scene difference.

* :func:`bootstrap_ci`: percentile bootstrap of a statistic (default the mean) over scenes,
  resampling scenes with replacement, ``n_resamples`` draws (default :data:`N_RESAMPLES` =
  10 000) from ``numpy.random.default_rng(seed)``: the same values and seed give the same
  interval. Percentile rather than BCa: with 6-20 scenes the acceleration estimate of BCa is
  itself noisy, and the percentile interval is the one every reader can recompute.
* :func:`paired_permutation_test`: the paired sign-flip permutation test of the mean
  difference (the protocol's test). Under H0 the two conditions are exchangeable within a
  scene, so each difference is as likely to have either sign; the p-value is the share of the
  2^n sign patterns whose mean difference is at least as far from 0 as the observed one. Exact
  (every pattern enumerated) up to :data:`EXACT_MAX_N` scenes, seeded Monte Carlo beyond. Why
  this test: it tests the statistic the tables report (the mean paired change, the centre of
  the bootstrap interval), needs no normality, is exact at our scene counts, and, unlike a
  rank test, does not discard how large the changes are (a few scenes carry most of an
  attack's effect).
* :func:`wilcoxon_signed_rank` and :func:`sign_test`: the rank and the count versions, given
  beside it (the report used Wilcoxon so far; the sign test is the number of scenes where the
  change goes one way).
* :func:`paired_summary`: all of the above for two conditions on the same scenes.
* :func:`holm` and :func:`benjamini_hochberg`: a table's p-values adjusted for its number of
  tests (Holm's step-down family-wise correction; Benjamini-Hochberg's false discovery rate).
* :func:`paired_mde`: the smallest mean paired difference the design detects with a given
  power, from the measured spread of the per-scene differences.

Zero differences: they carry no sign; the permutation test keeps them (they move no mean), the
sign test drops them, Wilcoxon drops them (``zero_method="wilcox"``).
"""
from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

#: Bootstrap resamples (the percentile interval's Monte Carlo error on a 95 % bound is then
#: about 0.2 percentile points).
N_RESAMPLES = 10_000
CONFIDENCE = 0.95
#: Up to this many scenes the permutation test enumerates all 2^n sign patterns (2^20 ~ 1e6).
EXACT_MAX_N = 20
#: Monte Carlo sign patterns beyond EXACT_MAX_N.
N_PERMUTATIONS = 100_000
# Relative tolerance when comparing a permuted statistic with the observed one: patterns that
# give the same mean up to rounding count as "as extreme" (otherwise p depends on float noise).
_TIE_RTOL = 1e-9


def _finite(values) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    return v[np.isfinite(v)]


def bootstrap_ci(values, statistic: Callable[[np.ndarray], np.ndarray] | None = None, *,
                 n_resamples: int = N_RESAMPLES, confidence: float = CONFIDENCE,
                 seed: int = 0) -> tuple[float, float, float]:
    """Percentile bootstrap interval of a statistic over scenes.

    Args:
        values: (n,) one value per scene; non-finite values are left out (a scene where the
            metric is undefined).
        statistic: maps an (B, n) array of resamples to (B,) statistics along axis 1
            (default: the mean).
        n_resamples: B, the number of resamples.
        confidence: the interval's coverage, e.g. 0.95 -> the 2.5 and 97.5 percentiles.
        seed: of ``numpy.random.default_rng``.
    Returns:
        (statistic of the values, lower bound, upper bound); NaNs when no value is finite; for a
        single value the interval is that value.
    """
    v = _finite(values)
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be >= 1, got {n_resamples}")
    stat = statistic or (lambda a: a.mean(axis=1))
    if len(v) == 0:
        return float("nan"), float("nan"), float("nan")
    est = float(stat(v[None, :])[0])
    if len(v) == 1:
        return est, est, est
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(v), size=(int(n_resamples), len(v)))
    boot = np.asarray(stat(v[idx]), dtype=np.float64)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(boot, [alpha, 1.0 - alpha])
    return est, float(lo), float(hi)


def paired_permutation_test(diff, *, alternative: str = "two-sided", n_permutations: int = N_PERMUTATIONS,
                            seed: int = 0) -> float:
    """p-value of the paired sign-flip permutation test of the mean difference.

    Args:
        diff: (n,) per-scene differences (condition a - condition b); non-finite values left out.
        alternative: ``"two-sided"`` (|mean| as extreme), ``"greater"`` (mean >= observed) or
            ``"less"``.
        n_permutations: Monte Carlo sign patterns when n > :data:`EXACT_MAX_N` (the observed
            pattern is counted too, so p > 0).
        seed: of the Monte Carlo draws (unused when exact).
    Returns:
        p in (0, 1]; 1.0 for no finite difference or all differences 0.
    """
    d = _finite(diff)
    if alternative not in ("two-sided", "greater", "less"):
        raise ValueError(f"alternative must be two-sided, greater or less, got {alternative!r}")
    n = len(d)
    if n == 0 or not np.any(d):
        return 1.0
    if n <= EXACT_MAX_N:
        signs = np.array(list(itertools.product((1.0, -1.0), repeat=n)))  # (2^n, n), first = observed
    else:
        rng = np.random.default_rng(seed)
        signs = np.vstack([np.ones(n), rng.choice((1.0, -1.0), size=(int(n_permutations), n))])
    means = signs @ d / n
    obs = float(d.mean())
    tol = _TIE_RTOL * max(1.0, float(np.abs(d).max()))
    if alternative == "two-sided":
        hits = np.abs(means) >= abs(obs) - tol
    elif alternative == "greater":
        hits = means >= obs - tol
    else:
        hits = means <= obs + tol
    return float(hits.sum() / len(means))


def wilcoxon_signed_rank(diff, alternative: str = "two-sided") -> float:
    """p-value of the Wilcoxon signed-rank test (scipy; zero differences dropped; exact null
    distribution when there are no ties and at most 50 non-zero differences, normal
    approximation otherwise). 1.0 when no difference is non-zero."""
    from scipy.stats import wilcoxon

    d = _finite(diff)
    d = d[d != 0]
    if len(d) == 0:
        return 1.0
    return float(wilcoxon(d, alternative=alternative, zero_method="wilcox").pvalue)


def sign_test(diff, alternative: str = "two-sided") -> float:
    """p-value of the sign test: the number of positive differences among the non-zero ones
    against Binomial(n, 1/2) (scipy ``binomtest``, exact). 1.0 when none is non-zero."""
    from scipy.stats import binomtest

    d = _finite(diff)
    d = d[d != 0]
    if len(d) == 0:
        return 1.0
    return float(binomtest(int(np.sum(d > 0)), len(d), 0.5, alternative=alternative).pvalue)


def paired_summary(a, b, *, n_resamples: int = N_RESAMPLES, confidence: float = CONFIDENCE,
                   seed: int = 0) -> dict:
    """Two conditions on the same scenes: per-scene difference a - b, its mean with a bootstrap
    interval, the count of scenes with a > b / a == b / a < b, and the three tests' two-sided
    p-values (``p_permutation`` is the protocol's test).

    Args:
        a, b: (n,) per-scene values of the two conditions, in the same scene order; pairs with a
            non-finite value are left out.
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"paired values need the same shape, got {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    mean, lo, hi = bootstrap_ci(d, n_resamples=n_resamples, confidence=confidence, seed=seed)
    return {"n": int(len(d)), "mean_diff": mean, "ci": [lo, hi], "confidence": confidence,
            "n_resamples": int(n_resamples), "bootstrap_seed": int(seed),
            "greater": int(np.sum(d > 0)), "equal": int(np.sum(d == 0)), "less": int(np.sum(d < 0)),
            "p_permutation": paired_permutation_test(d, seed=seed), "p_wilcoxon": wilcoxon_signed_rank(d),
            "p_sign": sign_test(d)}


def _adjust_input(pvalues) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pvalues, dtype=np.float64).reshape(-1)
    if np.any(p[np.isfinite(p)] < 0) or np.any(p[np.isfinite(p)] > 1):
        raise ValueError(f"p-values must lie in [0, 1], got {p.tolist()}")
    return p, np.flatnonzero(np.isfinite(p))


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error over the m finite p-values).

    Sorted ascending p_(1) <= ... <= p_(m): adjusted p_(i) = max_{j <= i} min(1, (m - j + 1) p_(j)).
    A test is rejected at family-wise level alpha when its adjusted p <= alpha.

    Args:
        pvalues: (m,) p-values; non-finite ones (a test that could not run) stay NaN and do not
            count in m.
    Returns:
        (m,) adjusted p-values in the input's order.
    """
    p, ok = _adjust_input(pvalues)
    out = np.full(p.shape, np.nan)
    m = len(ok)
    if m == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    scaled = np.minimum(1.0, (m - np.arange(m)) * p[order])
    out[order] = np.maximum.accumulate(scaled)
    return out


def benjamini_hochberg(pvalues) -> np.ndarray:
    """Benjamini-Hochberg adjusted p-values (q-values; false discovery rate over the m finite
    p-values): sorted ascending, q_(i) = min_{j >= i} min(1, m p_(j) / j).

    Args:
        pvalues: (m,) p-values; non-finite ones stay NaN and do not count in m.
    Returns:
        (m,) q-values in the input's order.
    """
    p, ok = _adjust_input(pvalues)
    out = np.full(p.shape, np.nan)
    m = len(ok)
    if m == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    scaled = np.minimum(1.0, m * p[order] / np.arange(1, m + 1))
    out[order] = np.minimum.accumulate(scaled[::-1])[::-1]
    return out


#: Power and two-sided level of the tables' detectable difference.
POWER = 0.8
ALPHA = 0.05


def paired_mde(sd_diff: float, n: int, *, alpha: float = ALPHA, power: float = POWER) -> float:
    """The smallest mean paired difference a design of n scenes detects with probability
    ``power`` at two-sided level ``alpha``, from the standard deviation of the per-scene
    differences (paired t approximation)::

        MDE = (t_{1 - alpha/2, n-1} + t_{power, n-1}) * sd_diff / sqrt(n)

    (with normal quantiles instead of t's this is the familiar (z_{1-a/2} + z_{0.8}) sd / sqrt(n),
    2.80 sd / sqrt(n) at alpha 0.05; the t quantiles are larger for few scenes, 3.15 sd / sqrt(n)
    at n = 10). Why this form for the protocol's sign-flip permutation test: the permutation test
    of the mean has the t test's power asymptotically (Hoeffding 1952), the formula is closed and
    recomputable by hand, and a simulated power would need an assumed distribution of the
    differences that 8-13 scenes cannot pin down. Where the exact sign-flip test cannot reach
    ``alpha`` at all (its smallest two-sided p is 2 / 2^n: n <= 5 at alpha 0.05) no difference
    is detectable and the result is ``inf``.

    Args:
        sd_diff: sample standard deviation (ddof 1) of the per-scene differences, in the
            metric's unit.
        n: scenes (pairs).
    Returns:
        the detectable difference in the metric's unit; ``inf`` when n < 2, sd is not finite or
        the sign-flip test cannot reach ``alpha``; 0 when sd_diff is 0 and n is large enough.
    """
    from scipy.stats import t

    if not (0.0 < alpha < 1.0 and 0.0 < power < 1.0):
        raise ValueError(f"alpha and power must lie in (0, 1), got {alpha}, {power}")
    if n < 2 or not np.isfinite(sd_diff) or 2.0 ** (1 - n) > alpha:
        return float("inf")
    df = n - 1
    return float((t.ppf(1.0 - alpha / 2.0, df) + t.ppf(power, df)) * abs(sd_diff) / np.sqrt(n))


#: The largest scene count :func:`scenes_to_detect` searches.
MAX_PLANNED_SCENES = 100_000


def scenes_to_detect(sd_diff: float, delta: float, *, alpha: float = ALPHA, power: float = POWER) -> int | None:
    """The fewest scenes n whose design detects a mean paired difference ``delta`` with
    probability ``power`` (``paired_mde(sd_diff, n) <= |delta|``): the size a table needs for a
    difference as large as, say, the one it measured, from its measured per-scene spread.

    Args:
        sd_diff: standard deviation (ddof 1) of the per-scene differences.
        delta: the difference to detect, in the metric's unit.
    Returns:
        n (at least 6, the exact sign-flip test's smallest at 0.05); None when ``delta`` is 0 or
        not finite, sd is not finite, or more than :data:`MAX_PLANNED_SCENES` scenes would be
        needed.
    """
    if not (np.isfinite(delta) and np.isfinite(sd_diff)) or delta == 0.0:
        return None
    lo, hi = 2, MAX_PLANNED_SCENES
    if paired_mde(sd_diff, hi, alpha=alpha, power=power) > abs(delta):
        return None
    while lo < hi:  # paired_mde falls with n: bisect for the first n that reaches |delta|
        mid = (lo + hi) // 2
        if paired_mde(sd_diff, mid, alpha=alpha, power=power) <= abs(delta):
            hi = mid
        else:
            lo = mid + 1
    return int(lo)
