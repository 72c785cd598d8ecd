"""Search algorithms: GP numerics, BO against random search, grid coverage, ask/tell protocol."""
from __future__ import annotations

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
    pytest.importorskip("skopt")
    a = _skopt_run(seed=3, batch=2, fail_every=5)  # failed queries and batches (constant liar) included
    b = _skopt_run(seed=3, batch=2, fail_every=5)
    assert a.X.shape == (10, 5) and np.all((a.X >= 0) & (a.X <= 1))
    assert np.array_equal(a.X, b.X)
    assert not np.array_equal(_skopt_run(seed=4, batch=2, fail_every=5).X, a.X)
    # the first n_initial queries are a Latin hypercube: one point per stratum of every dimension
    strata = np.floor(a.X[:6] * 6).astype(int)
    for d in range(5):
        assert sorted(strata[:, d]) == list(range(6))
    # the batch changes the asks after the initial design (constant liar), not before
    c = _skopt_run(seed=3, batch=1, fail_every=5)
    assert np.array_equal(c.X[:6], a.X[:6]) and not np.array_equal(c.X, a.X)


def test_skopt_beats_random_and_finds_the_optimum_region():
    """On the 5-D bowl (maximum at u = 0.4) skopt's GP gets closer with 20 queries than random
    search does, for every seed, and its best point lies in the optimum's neighbourhood."""
    pytest.importorskip("skopt")
    for seed in range(2):
        s = _skopt_run(seed=seed, batch=1, budget=20, f=lambda x: -float(np.sum((x - 0.4) ** 2)))
        r = RandomSearch(5, seed=seed, budget=20)
        run(r, lambda x: -float(np.sum((x - 0.4) ** 2)))
        x, v = s.best()
        assert v > r.best()[1] + 0.02, (seed, v, r.best()[1])
        assert np.max(np.abs(x - 0.4)) < 0.1, x
