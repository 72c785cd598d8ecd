"""Search algorithms: GP numerics, BO against random search, grid coverage, ask/tell protocol."""
from __future__ import annotations

import random

import numpy as np
import pytest

from adv3d_runner.attack.search import (BayesOpt, GaussianProcess, GridSearch, RandomSearch, grid_points,
                                        latin_hypercube, make_searcher, matern32_product, penalise)
from adv3d_runner.errors import ConfigError

CENTRE = np.array([0.73, 0.21, 0.58, 0.87, 0.34])


def peak(x: np.ndarray) -> float:
    """A bowl with a narrow peak: random search almost never lands on the peak in 60 queries."""
    d2 = float(np.sum((x - CENTRE) ** 2))
    return -d2 + 2.0 * np.exp(-d2 / (2 * 0.05**2))


def run(searcher, f, batch=1):
    while not searcher.exhausted:
        X = searcher.ask(batch)
        searcher.tell(X, [f(x) for x in X])
    return searcher.best()[1]


def test_matern_product_kernel_values():
    a = np.array([[0.0, 0.0]])
    b = np.array([[0.1, 0.0], [0.1, 0.1], [0.0, 0.0]])
    k = matern32_product(a, b, 0.1)[0]
    one = (1 + np.sqrt(3)) * np.exp(-np.sqrt(3))  # r = l in one dimension
    assert k == pytest.approx([one, one**2, 1.0], rel=1e-12)  # product over dimensions


def test_gp_interpolates_and_is_finite_with_duplicates():
    rng = np.random.default_rng(0)
    X = rng.random((8, 5))
    X = np.vstack([X, X[:3], X[:3]])  # every one of the first three points three times
    y = np.sin(X.sum(axis=1) * 3)
    gp = GaussianProcess().fit(X, y)
    mean, sd = gp.predict(X[:8])
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(sd))
    assert mean == pytest.approx(y[:8], abs=1e-3)
    assert np.all(sd < 1e-2)
    m2, s2 = gp.predict(rng.random((100, 5)))
    assert np.all(np.isfinite(m2)) and np.all(s2 >= 0)


def test_gp_constant_costs_flat_posterior():
    X = np.random.default_rng(1).random((12, 5))
    for c in (0.0, 3.7, -1e6):
        gp = GaussianProcess().fit(X, np.full(12, c))
        mean, sd = gp.predict(np.random.default_rng(2).random((50, 5)))
        assert np.all(np.isfinite(mean)) and np.all(np.isfinite(sd))
        assert mean == pytest.approx(np.full(50, c), abs=1e-6 * max(1, abs(c)))


def test_bo_ask_with_duplicates_constant_and_nonfinite_costs():
    s = BayesOpt(5, seed=3, budget=20, n_initial=3, n_candidates=256)
    X = s.ask(3)
    s.tell(X, [1.0, 1.0, 1.0])  # constant
    X = s.ask(1)
    s.tell(X, [np.nan])  # failed query
    for _ in range(4):
        X = s.ask(2)
        assert X.shape == (2, 5) and np.all(np.isfinite(X)) and np.all((X >= 0) & (X <= 1))
        s.tell(X, [np.inf, 1.0])
    # an exact duplicate of a told point with a different value
    s2 = BayesOpt(5, seed=0, budget=5, n_initial=0, n_candidates=64)
    s2.X = np.repeat(np.full((1, 5), 0.5), 4, axis=0)
    s2.y = np.array([1.0, 2.0, np.nan, 1.0])
    X = s2.ask(1)
    assert np.all(np.isfinite(X))


def test_penalise_nonfinite_uses_worst_finite():
    assert penalise([1.0, np.nan, -2.0, np.inf]).tolist() == [1.0, -2.0, -2.0, -2.0]
    assert penalise([np.nan, np.nan]).tolist() == [0.0, 0.0]


def test_bo_avoids_failed_region():
    """Non-finite costs are penalised: BO should not keep querying where queries fail."""
    def f(x):
        return np.nan if x[0] > 0.5 else -float(np.sum((x - 0.3) ** 2))
    s = BayesOpt(5, seed=0, budget=40, n_candidates=512)
    run(s, f)
    late = s.X[20:]
    assert np.mean(late[:, 0] > 0.5) < 0.25


def test_bo_beats_random_on_narrow_optimum():
    budget = 60
    bo = [run(BayesOpt(5, seed=s, budget=budget, n_candidates=1024, n_polish=2), peak) for s in range(3)]
    rs = [run(RandomSearch(5, seed=s, budget=budget), peak) for s in range(3)]
    assert np.mean(bo) > np.mean(rs) + 0.5, (bo, rs)
    assert min(bo) > max(rs)


def test_bo_first_queries_are_latin_hypercube_and_deterministic():
    a = BayesOpt(5, seed=7, budget=11)
    X = a.ask(11)
    strata = np.floor(X * 11).astype(int)
    for d in range(5):
        assert sorted(strata[:, d]) == list(range(11))
    b = BayesOpt(5, seed=7, budget=11)
    assert np.array_equal(b.ask(11), X)


def test_bo_same_seed_same_queries_and_batches():
    def go(batch):
        s = BayesOpt(5, seed=1, budget=16, n_initial=4, n_candidates=256)
        run(s, peak, batch)
        return s.X
    assert np.array_equal(go(2), go(2))


def test_grid_covers_all_points():
    g = GridSearch(3, seed=0, budget=1000)
    assert g.budget == 27
    X = []
    while not g.exhausted:
        x = g.ask(4)
        g.tell(x, np.zeros(len(x)))
        X.append(x)
    X = np.vstack(X)
    assert len(X) == 27 and len(np.unique(X, axis=0)) == 27
    assert set(np.round(np.unique(X), 6)) == {round(1 / 6, 6), 0.5, round(5 / 6, 6)}
    assert len(grid_points(5)) == 243


def test_ask_tell_protocol_errors():
    s = RandomSearch(2, seed=0, budget=3)
    X = s.ask(2)
    with pytest.raises(RuntimeError):
        s.ask(1)
    with pytest.raises(RuntimeError):
        s.tell(X + 0.1, [0, 0])
    s.tell(X, [0, 1])
    assert len(s.ask(5)) == 1  # budget caps the batch
    with pytest.raises(ConfigError):
        make_searcher("nope", 2)
    with pytest.raises(ConfigError):
        make_searcher("bruteforce", 2)


def test_latin_hypercube_strata():
    X = latin_hypercube(7, 3, np.random.default_rng(0))
    assert np.all((X >= 0) & (X < 1))
    for d in range(3):
        assert sorted(np.floor(X[:, d] * 7).astype(int)) == list(range(7))


def test_blendsearch_ask_tell_deterministic():
    pytest.importorskip("flaml")
    pytest.importorskip("optuna")

    def go():
        s = make_searcher("blendsearch", 5, seed=4, budget=12)
        vals = []
        while not s.exhausted:
            X = s.ask(2)
            y = [peak(x) if i else np.nan for i, x in enumerate(X)]  # one failure per batch
            s.tell(X, y)
            vals.append(X)
        return np.vstack(vals)
    a, b = go(), go()
    assert a.shape == (12, 5) and np.all((a >= 0) & (a <= 1))
    assert np.array_equal(a, b)


def test_bruteforce_hands_out_candidates_in_order():
    c = np.random.default_rng(0).random((5, 5))
    s = make_searcher("bruteforce", 5, budget=100, candidates=c)
    X = s.ask(3)
    s.tell(X, [0, 1, 2])
    X2 = s.ask(3)
    assert np.array_equal(np.vstack([X, X2]), c) and s.exhausted


# ---------------------------------------------------------------------------- scikit-optimize

def _skopt_run(seed, batch, budget=10, f=peak, fail_every=0):
    s = make_searcher("skopt", 5, seed=seed, budget=budget, n_initial=6)
    k = 0
    while not s.exhausted:
        X = s.ask(batch)
        y = []
        for x in X:
            k += 1
            y.append(np.nan if fail_every and k % fail_every == 0 else f(x))
        s.tell(X, y)
    return s


def test_skopt_same_seed_same_points_and_initial_latin_hypercube():
    """Same seed, same points: skopt draws everything (the Latin hypercube, the GP fit's restarts,
    the acquisition candidates, the constant liar's copy) from its seeded ``RandomState``, so the
    numpy and Python global generators and the BLAS thread count outside the searcher do not
    matter. The points agree to rounding, not always bit for bit: in a clean-clone CI run (AMD
    EPYC, OpenBLAS AVX-512 kernels) 3 of 50 coordinates differed by 7e-14 between two runs in
    one process, which one thread does not explain; OpenBLAS's kernels sum in an order that can
    depend on where an array starts in memory, and the GP's solves pass that on. A real
    divergence (another seed, a global generator leaking in) moves points by far more than 1e-9.
    (Across CPUs the BLAS kernel changes the GP fit in the last bits, and the later asks with it.)"""
    pytest.importorskip("skopt")
    from threadpoolctl import threadpool_limits  # scikit-learn's dependency, present with skopt

    np.random.seed(1)
    random.seed(1)
    a = _skopt_run(seed=3, batch=2, fail_every=5)  # failed queries and batches (constant liar) included
    np.random.seed(2)
    random.seed(2)
    with threadpool_limits(limits=2):
        b = _skopt_run(seed=3, batch=2, fail_every=5)
    assert a.X.shape == (10, 5) and np.all((a.X >= 0) & (a.X <= 1))
    np.testing.assert_allclose(b.X, a.X, rtol=0, atol=1e-9, err_msg="same seed, different points")
    assert not np.array_equal(_skopt_run(seed=4, batch=2, fail_every=5).X, a.X)
    # the first n_initial queries are a Latin hypercube: one point per stratum of every dimension
    strata = np.floor(a.X[:6] * 6).astype(int)
    for d in range(5):
        assert sorted(strata[:, d]) == list(range(6)), (d, strata[:, d])
    # the batch changes the asks after the initial design (constant liar), not before
    c = _skopt_run(seed=3, batch=1, fail_every=5)
    np.testing.assert_array_equal(c.X[:6], a.X[:6])
    assert not np.array_equal(c.X, a.X)


def _bowl(x: np.ndarray) -> float:
    """A 5-D bowl, maximum 0 at u = 0.4: minus the squared distance to the optimum."""
    return -float(np.sum((x - 0.4) ** 2))


def _queries_to_reach(searcher, radius: float) -> tuple[int, float]:
    """Ask/tell one point at a time until the best point lies within ``radius`` (Euclidean) of the
    bowl's optimum or the budget is spent: (queries used, or budget + 1 if never within; best
    distance)."""
    while not searcher.exhausted:
        X = searcher.ask(1)
        searcher.tell(X, [_bowl(x) for x in X])
        if np.sqrt(-searcher.best()[1]) < radius:
            return searcher.n_told, float(np.sqrt(-searcher.best()[1]))
    return searcher.budget + 1, float(np.sqrt(-searcher.best()[1]))


def test_skopt_beats_random_and_finds_the_optimum_region():
    """On the 5-D bowl skopt's fitted GP reaches the optimum's neighbourhood (within 0.1) in
    about 20-30 queries, which random search essentially never does (a ball of radius 0.1 is
    5e-5 of the cube). Claimed over seeds, by the median, not seed by seed: which query first
    lands inside depends on the GP's hyperparameter fit, and that depends on the BLAS kernel the
    CPU gets in the last bits (the asks of two CPUs part at the first GP ask by 1e-15 to 1e-5 and
    are unrelated a dozen queries later). Measured on seeds 0-11 under OpenBLAS's SkylakeX,
    Haswell, Nehalem and Prescott kernels: 20-32 queries (median 24-25); after 20 queries skopt is
    still only just ahead of random (median distance 0.31-0.35 against 0.38), so no claim is
    made there."""
    pytest.importorskip("skopt")
    radius, budget, seeds = 0.1, 40, (0, 1, 2)
    sk = [_queries_to_reach(make_searcher("skopt", 5, seed=s, budget=budget, n_initial=6), radius) for s in seeds]
    rs = [_queries_to_reach(RandomSearch(5, seed=s, budget=budget), radius) for s in seeds]
    n_sk, d_sk = np.median([n for n, _ in sk]), np.median([d for _, d in sk])
    d_rs = np.median([d for _, d in rs])
    assert n_sk <= 30, (sk, rs)  # at least two of three seeds within 0.1 in 30 queries
    assert d_sk < 0.5 * d_rs, (sk, rs)  # with at most the queries random search had
