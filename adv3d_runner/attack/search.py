"""Black-box search algorithms behind one ask/tell interface (paper section 3.3, appendix A.4).

Every searcher works in the unit cube ``[0, 1]^D`` (D = 5 per attacked actor: 3 PCA latents +
width and length scale) and **maximises** the adversarial objective::

    searcher = make_searcher("bo", dim=5, seed=0, budget=100)
    while not searcher.exhausted:
        X = searcher.ask(2)             # (n, D) unit vectors, n <= 2 (fewer when exhausted)
        y = [objective(x) for x in X]   # NaN / inf for failed queries
        searcher.tell(X, y)

``ask`` must be followed by a ``tell`` of the same rows before the next ``ask`` (batch
ask/tell): that keeps a run deterministic whatever order parallel workers finish in, and lets
a run resume by replaying its journal (same seed + same history = same next asks).

A non-finite ``y`` (a shape with no surface, a simulation error) is *penalised*: searchers see
the worst finite value observed so far (0 before any finite value), so failed regions are
avoided without poisoning the GP with infinities.

Algorithms (``ALGORITHMS``): ``bo`` (GP-UCB, written here in numpy, see :class:`BayesOpt`),
``random`` (uniform), ``grid`` (3 levels per dimension, 3^D points), ``blendsearch`` (FLAML's
BlendSearch), ``bruteforce`` (a fixed candidate list, e.g. the library assets' unit vectors),
``skopt`` (scikit-optimize's GP optimiser, a library cross-check of ``bo``, see
:class:`SkoptSearcher`).
"""
from __future__ import annotations

import contextlib
import itertools
import warnings
from typing import Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve, LinAlgError
from scipy.optimize import minimize

from ..errors import ConfigError
from ..fileio import MEMORY_BUDGET, gib
from .names import ALGORITHMS  # noqa: F401  (re-exported)

# Paper appendix A.4.
LENGTH_SCALE = 0.1
UCB_BETA = 1.0
N_INITIAL = 11
BUDGET = 100


def penalise(y: np.ndarray) -> np.ndarray:
    """Replace non-finite values by the worst (smallest) finite value, 0 if none is finite.

    Args:
        y: (N,) objective values (maximised).
    Returns:
        (N,) float64, all finite.
    """
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    ok = np.isfinite(y)
    worst = float(y[ok].min()) if ok.any() else 0.0
    return np.where(ok, y, worst)


class Searcher:
    """Base class: keeps the history, checks the ask/tell protocol, tracks the best query.

    Attributes:
        dim: D. seed: the run seed. budget: queries the searcher will hand out at most.
        X: (N, D) told points. y: (N,) told values as given (may be non-finite).
    """

    name = "base"

    def __init__(self, dim: int, seed: int = 0, budget: int = BUDGET):
        if int(dim) < 1:
            raise ConfigError(f"search dimension must be >= 1, got {dim}")
        self.dim = int(dim)
        self.seed = int(seed)
        self.budget = int(budget)
        self.X = np.zeros((0, self.dim))
        self.y = np.zeros(0)
        self._pending: np.ndarray | None = None
        self._asked = 0

    # -------------------------------------------------------------- protocol
    @property
    def n_told(self) -> int:
        return len(self.y)

    @property
    def remaining(self) -> int:
        """Queries still to hand out (budget and, for finite searchers, candidates left)."""
        return max(self.budget - self._asked, 0)

    @property
    def exhausted(self) -> bool:
        return self.remaining == 0

    def ask(self, n: int = 1) -> np.ndarray:
        """Next ``min(n, remaining)`` points, (n, D) in [0, 1]."""
        if self._pending is not None:
            raise RuntimeError("ask() called again before tell() of the previous batch")
        n = min(int(n), self.remaining)
        X = np.zeros((0, self.dim)) if n <= 0 else np.clip(np.asarray(self._ask(n), dtype=np.float64).reshape(n, self.dim), 0.0, 1.0)
        self._pending = X
        self._asked += len(X)
        return X.copy()

    def tell(self, X: np.ndarray, y: Sequence[float]) -> None:
        """Report the values of the last asked batch (same rows, same order)."""
        X = np.asarray(X, dtype=np.float64).reshape(-1, self.dim)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        if len(X) != len(y):
            raise ValueError(f"{len(X)} points but {len(y)} values")
        if self._pending is None or self._pending.shape != X.shape or not np.allclose(self._pending, X, rtol=0, atol=1e-12):
            raise RuntimeError("tell() must report exactly the points of the last ask()")
        self._pending = None
        self._tell(X, y)
        self.X = np.vstack([self.X, X])
        self.y = np.concatenate([self.y, y])

    def best(self) -> tuple[np.ndarray | None, float]:
        """(best point (D,) or None, best finite value or -inf)."""
        ok = np.isfinite(self.y)
        if not ok.any():
            return None, float("-inf")
        i = int(np.flatnonzero(ok)[np.argmax(self.y[ok])])
        return self.X[i].copy(), float(self.y[i])

    # -------------------------------------------------------------- to implement
    def _ask(self, n: int) -> np.ndarray:
        raise NotImplementedError

    def _tell(self, X: np.ndarray, y: np.ndarray) -> None:
        """Hook for searchers with their own state (the history is kept by the base class)."""


class RandomSearch(Searcher):
    """Uniform random points in the unit cube from ``default_rng(seed)``."""

    name = "random"

    def __init__(self, dim: int, seed: int = 0, budget: int = BUDGET):
        super().__init__(dim, seed, budget)
        self._rng = np.random.default_rng(seed)

    def _ask(self, n: int) -> np.ndarray:
        return self._rng.random((n, self.dim))


class CandidateSearch(Searcher):
    """Hands out a fixed list of candidates in order (grid search, brute force)."""

    name = "candidates"

    def __init__(self, candidates: np.ndarray, seed: int = 0, budget: int | None = None):
        c = np.asarray(candidates, dtype=np.float64)
        if c.ndim != 2 or len(c) == 0:
            raise ConfigError(f"need a non-empty (C, D) candidate array, got shape {c.shape}")
        super().__init__(c.shape[1], seed, len(c) if budget is None else min(int(budget), len(c)))
        self.candidates = np.clip(c, 0.0, 1.0)

    def _ask(self, n: int) -> np.ndarray:
        return self.candidates[self._asked : self._asked + n]


def grid_points(dim: int, levels: Sequence[float] = (1 / 6, 0.5, 5 / 6)) -> np.ndarray:
    """All ``len(levels)^dim`` grid points, (L^D, D), lexicographic order.

    The default levels are the centres of three equal cells per dimension, so the grid samples
    the interior of the latent box (its corners are the library's per-dimension extremes taken
    together, the least realistic shapes)."""
    lv = np.asarray(levels, dtype=np.float64)
    return np.array(list(itertools.product(lv, repeat=int(dim))), dtype=np.float64).reshape(-1, dim)


class GridSearch(CandidateSearch):
    """Grid search, 3 points per dimension (paper: 3^5 = 243 queries).

    The grid is visited in a seeded random order so that a budget below 3^D samples the whole
    grid evenly instead of varying only the last dimensions."""

    name = "grid"

    def __init__(self, dim: int, seed: int = 0, budget: int | None = None,
                 levels: Sequence[float] = (1 / 6, 0.5, 5 / 6)):
        pts = grid_points(dim, levels)
        pts = pts[np.random.default_rng(seed).permutation(len(pts))]
        super().__init__(pts, seed, budget)


class BruteForce(CandidateSearch):
    """Evaluate a fixed candidate list (the library assets' unit vectors), in the given order."""

    name = "bruteforce"


# ---------------------------------------------------------------------------- Bayesian opt.

def matern32_product(A: np.ndarray, B: np.ndarray, length_scale: float = LENGTH_SCALE) -> np.ndarray:
    """Product Matern-3/2 kernel ``prod_d (1 + sqrt(3) r_d / l) exp(-sqrt(3) r_d / l)``,
    ``r_d = |a_d - b_d|`` (unit signal variance).

    Args:
        A: (N, D). B: (M, D). length_scale: l, in unit-cube units.
    Returns:
        (N, M) float64 in (0, 1], exactly 1 on the diagonal of A vs A.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    # row blocks of A, so the four (rows, M, D) temporaries stay under _KERNEL_BLOCK_BYTES whatever
    # N, M and D are; each entry is the same sum over d, so the result does not depend on the blocks
    rows = max(1, _KERNEL_BLOCK_BYTES // max(1, 4 * 8 * B.shape[0] * A.shape[1]))
    if rows >= len(A):
        return _matern32_block(A, B, length_scale)
    out = np.empty((len(A), len(B)))
    for i in range(0, len(A), rows):
        out[i:i + rows] = _matern32_block(A[i:i + rows], B, length_scale)
    return out


#: Largest temporaries of one block of :func:`matern32_product` (bytes; four (rows, M, D) arrays).
_KERNEL_BLOCK_BYTES = 32 * 2**20


def _matern32_block(A: np.ndarray, B: np.ndarray, length_scale: float) -> np.ndarray:
    r = np.abs(A[:, None, :] - B[None, :, :]) * (np.sqrt(3.0) / length_scale)
    # log-space product: exp(sum_d log(1 + r_d) - r_d) stays accurate for tiny kernel values
    return np.exp(np.sum(np.log1p(r) - r, axis=-1))


class GaussianProcess:
    """Exact GP regression with a fixed product Matern-3/2 kernel (no hyper-parameter fit).

    Written here in numpy rather than taken from scikit-learn / BoTorch: the paper fixes the
    kernel (length scale 0.1, no fitting), so a library brings only dependencies, and we need
    control over the numerics: targets are standardised with a std floor (constant costs give
    a flat, finite posterior), a small noise term keeps duplicate points well posed, and the
    Cholesky factorisation retries with growing jitter if it still fails.

    Args:
        length_scale: kernel length scale in the unit cube. noise: observation noise variance,
            relative to the standardised targets. std_floor: smallest std used to standardise.
    """

    def __init__(self, length_scale: float = LENGTH_SCALE, noise: float = 1e-6, std_floor: float = 1e-9):
        self.length_scale = float(length_scale)
        self.noise = float(noise)
        self.std_floor = float(std_floor)
        self.X = np.zeros((0, 0))
        self.mu_y, self.sd_y = 0.0, 1.0

    def fit(self, X: np.ndarray, y: np.ndarray) -> "GaussianProcess":
        """Condition on (N, D) points and (N,) finite targets."""
        X = np.asarray(X, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(y)):
            raise ValueError("GP targets must be finite (penalise failed queries first)")
        self.X = X
        self.mu_y = float(y.mean()) if len(y) else 0.0
        sd = float(y.std()) if len(y) > 1 else 0.0
        # (Nearly) constant targets carry no shape information: use unit scale instead of
        # dividing by ~0, so the posterior stays flat at the mean with prior uncertainty.
        self.sd_y = sd if sd > self.std_floor * max(1.0, abs(self.mu_y)) else 1.0
        z = (y - self.mu_y) / self.sd_y
        K = matern32_product(X, X, self.length_scale)
        jitter = self.noise
        for _ in range(8):
            try:
                self._chol = cho_factor(K + jitter * np.eye(len(X)), lower=True, check_finite=False)
                if np.all(np.isfinite(self._chol[0])):
                    break
            except LinAlgError:
                pass
            jitter *= 10.0
        else:  # pragma: no cover - a kernel matrix with 1e1 on the diagonal always factors
            raise LinAlgError("GP covariance is not positive definite even with jitter")
        self.jitter = jitter
        self._alpha = cho_solve(self._chol, z, check_finite=False) if len(X) else np.zeros(0)
        return self

    def predict(self, Xq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean and std at (M, D) points, in the original target units."""
        Xq = np.atleast_2d(np.asarray(Xq, dtype=np.float64))
        if len(self.X) == 0:
            return np.full(len(Xq), self.mu_y), np.full(len(Xq), self.sd_y)
        Ks = matern32_product(Xq, self.X, self.length_scale)  # (M, N)
        mean = Ks @ self._alpha
        v = cho_solve(self._chol, Ks.T, check_finite=False)  # (N, M)
        var = np.maximum(1.0 - np.sum(Ks.T * v, axis=0), 0.0)
        return self.mu_y + self.sd_y * mean, self.sd_y * np.sqrt(var)


def latin_hypercube(n: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    """n points, one per row of each of the n equal strata of every dimension, (n, D)."""
    u = (rng.random((n, dim)) + np.arange(n)[:, None]) / n
    for d in range(dim):
        u[:, d] = u[rng.permutation(n), d]
    return u


class BayesOpt(Searcher):
    """GP-UCB Bayesian optimisation (paper appendix A.4): product Matern-3/2 kernel with length
    scale 0.1, UCB ``mu + beta * sigma`` with beta = 1, the first 11 queries a Latin hypercube.

    The acquisition is maximised by scoring ``n_candidates`` uniform points plus Gaussian
    perturbations of the best observed points, then polishing the ``n_polish`` best with
    L-BFGS-B inside the unit cube. Batches (parallel workers) use the "kriging believer":
    each chosen point is added to the GP with its posterior mean as a fake observation, which
    removes its uncertainty, before the next point of the batch is chosen. All randomness comes
    from ``default_rng(seed)`` and the number of queries already told, so a resumed run asks
    the same points as an uninterrupted one.
    """

    name = "bo"

    def __init__(self, dim: int, seed: int = 0, budget: int = BUDGET, n_initial: int = N_INITIAL,
                 length_scale: float = LENGTH_SCALE, beta: float = UCB_BETA, n_candidates: int = 2048,
                 n_polish: int = 4, noise: float = 1e-6):
        super().__init__(dim, seed, budget)
        self.n_initial = int(n_initial)
        self.length_scale = float(length_scale)
        self.beta = float(beta)
        self.n_candidates = int(n_candidates)
        self.n_polish = int(n_polish)
        self.noise = float(noise)
        self._init = latin_hypercube(self.n_initial, self.dim, np.random.default_rng([self.seed, 0])) if self.n_initial else np.zeros((0, dim))

    def _ask(self, n: int) -> np.ndarray:
        out = []
        Xf, yf = self.X.copy(), penalise(self.y) if len(self.y) else np.zeros(0)
        for j in range(n):
            i = self._asked + j  # query index: the next point depends only on it and the history
            if i < self.n_initial:
                x = self._init[i]
            elif len(yf) == 0:
                x = np.random.default_rng([self.seed, 1, i]).random(self.dim)
            else:
                gp = GaussianProcess(self.length_scale, self.noise).fit(Xf, yf)
                x = self._maximise_ucb(gp, Xf, yf, np.random.default_rng([self.seed, 1, i]))
                # kriging believer for the rest of the batch
                Xf = np.vstack([Xf, x])
                yf = np.append(yf, gp.predict(x[None])[0][0])
            out.append(x)
        return np.array(out)

    def ucb(self, gp: GaussianProcess, X: np.ndarray) -> np.ndarray:
        mean, sd = gp.predict(X)
        return mean + self.beta * sd

    def _maximise_ucb(self, gp: GaussianProcess, X: np.ndarray, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        cand = [rng.random((self.n_candidates, self.dim))]
        top = X[np.argsort(-y, kind="stable")[:5]]
        for scale in (0.02, 0.05, 0.1):  # local candidates around the best points
            cand.append(np.clip(np.repeat(top, 40, axis=0) + rng.normal(0.0, scale, (40 * len(top), self.dim)), 0.0, 1.0))
        C = np.vstack(cand)
        a = self.ucb(gp, C)
        order = np.argsort(-a, kind="stable")
        best_x, best_a = C[order[0]], a[order[0]]
        bounds = [(0.0, 1.0)] * self.dim
        for k in order[: self.n_polish]:
            res = minimize(lambda x: -self.ucb(gp, x[None])[0], C[k], method="L-BFGS-B", bounds=bounds,
                           options={"maxiter": 30})
            if np.all(np.isfinite(res.x)) and -res.fun > best_a:
                best_x, best_a = np.clip(res.x, 0.0, 1.0), -float(res.fun)
        return best_x


# ---------------------------------------------------------------------------- BlendSearch

class BlendSearchSearcher(Searcher):
    """FLAML's BlendSearch (global search + local CFO search; Wang et al. 2021) through its
    ``suggest`` / ``on_trial_complete`` API, one ``tune.uniform(0, 1)`` per dimension.

    Needs ``pip install flaml`` (and ``optuna`` for its global part; without it FLAML falls
    back to local search only). Failed queries are reported with the penalised value."""

    name = "blendsearch"

    def __init__(self, dim: int, seed: int = 0, budget: int = BUDGET):
        super().__init__(dim, seed, budget)
        import logging
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                from flaml import BlendSearch, tune
            except ImportError as exc:  # pragma: no cover - depends on the install
                raise ConfigError("--algo blendsearch needs FLAML: pip install flaml") from exc
        logging.getLogger("flaml").setLevel(logging.ERROR)
        self._keys = [f"u{d}" for d in range(dim)]
        space = {k: tune.uniform(0.0, 1.0) for k in self._keys}
        try:
            import optuna

            optuna.logging.set_verbosity(optuna.logging.WARNING)
        except ImportError:  # pragma: no cover
            pass
        self._bs = BlendSearch(metric="objective", mode="max", space=space, seed=int(seed) % (2**31))
        self._trial_ids: list[str] = []
        self._fallback = np.random.default_rng([seed, 2])

    def _ask(self, n: int) -> np.ndarray:
        X, self._trial_ids, self._configs = [], [], []
        for j in range(n):
            tid = f"t{self._asked + j}"
            cfg = self._bs.suggest(tid)
            if cfg is None or any(k not in cfg for k in self._keys):  # FLAML converged / no suggestion: keep the budget with random points
                X.append(self._fallback.random(self.dim))
                self._trial_ids.append("")
                self._configs.append({})
            else:
                X.append([float(cfg[k]) for k in self._keys])
                self._trial_ids.append(tid)
                self._configs.append(dict(cfg))
        return np.array(X)

    def _tell(self, X: np.ndarray, y: np.ndarray) -> None:
        yp = penalise(np.concatenate([self.y, y]))[len(self.y):]
        for tid, cfg, v in zip(self._trial_ids, self._configs, yp):
            if tid:  # FLAML reads the trial's config back from the result (as Ray Tune sends it)
                self._bs.on_trial_complete(tid, {"objective": float(v), "config": cfg})


# ---------------------------------------------------------------------------- scikit-optimize

class SkoptSearcher(Searcher):
    """scikit-optimize's Bayesian optimiser (``skopt.Optimizer``, ask/tell) as a library
    cross-check of :class:`BayesOpt` (paper Table 5, docs/results.md).

    Set up like ours where the paper fixes a choice, and left as the library's own where
    :class:`BayesOpt` departs from common practice, so the comparison asks one question: does
    a standard, fitted GP find better shapes than the paper's fixed kernel?

    * same as ``bo``: the unit cube, the budget, ``n_initial`` (11) space-filling first queries
      (skopt's Latin hypercube, ``initial_point_generator="lhs"``), the acquisition UCB with
      beta = 1 (skopt minimises, so it is told ``-y`` and uses ``LCB`` with ``kappa = 1``,
      ``mu - kappa sigma`` of ``-y``), the acquisition maximised over ``n_points`` (2048)
      random candidates with the best ``n_restarts`` (4) polished by L-BFGS-B, and batches by a
      fantasy of the batch's earlier points (skopt's constant liar ``cl_min``: the best value
      so far, where ours uses the posterior mean);
    * skopt's own: its default GP (``base_estimator="GP"``: constant x Matern-5/2 with one
      length scale per dimension, bounds [0.01, 100], and a Gaussian noise level, all fitted by
      marginal likelihood after every tell, normalised targets), where ours fixes a product
      Matern-3/2 with length scale 0.1 and no fit.

    Failed (non-finite) queries are told as the worst finite value seen at their tell, as for
    BlendSearch. All randomness comes from ``random_state=seed``: skopt draws from one
    ``RandomState`` in the order of the asks and tells, so the same seed, batch and told values
    give the same points, and a resumed run (the driver replays the journal through ask/tell)
    asks what the uninterrupted one did. Needs ``pip install scikit-optimize`` (the ``skopt``
    extra of pyproject.toml).
    """

    name = "skopt"

    def __init__(self, dim: int, seed: int = 0, budget: int = BUDGET, n_initial: int = N_INITIAL,
                 kappa: float = UCB_BETA, n_points: int = 2048, n_restarts: int = 4):
        super().__init__(dim, seed, budget)
        try:
            from skopt import Optimizer
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ConfigError('--algo skopt needs scikit-optimize: pip install -e ".[skopt]"') from exc
        self.n_initial = int(n_initial)
        self._opt = Optimizer([(0.0, 1.0)] * self.dim, base_estimator="GP", n_initial_points=self.n_initial,
                              initial_point_generator="lhs", acq_func="LCB", acq_optimizer="lbfgs",
                              acq_func_kwargs={"kappa": float(kappa)},
                              acq_optimizer_kwargs={"n_points": int(n_points), "n_restarts_optimizer": int(n_restarts),
                                                    "n_jobs": 1},
                              random_state=int(seed) % (2**32))

    def _ask(self, n: int) -> np.ndarray:
        with _quiet_skopt():
            # one point: skopt's sequential ask (its ask(n_points=1) would go through a copy)
            X = [self._opt.ask()] if n == 1 else self._opt.ask(n_points=int(n))
        return np.asarray(X, dtype=np.float64)

    def _tell(self, X: np.ndarray, y: np.ndarray) -> None:
        yp = penalise(np.concatenate([self.y, y]))[len(self.y):]
        with _quiet_skopt():
            self._opt.tell([[float(v) for v in x] for x in X], [-float(v) for v in yp])  # skopt minimises


@contextlib.contextmanager
def _quiet_skopt():
    """While skopt works: silence skopt's "evaluated at point ... before" and scikit-learn's
    convergence warnings (they would break the progress bars; the journal shows duplicates),
    and hold BLAS to one thread. Why the thread limit: the same seed must give the same points,
    and once (a CI run on a loaded 2-core machine, OpenBLAS with 2 threads) the two same-seed
    runs of ``tests/test_attack_search.py`` asked different points; one thread fixes the order
    of every floating-point sum in the GP fit and the acquisition optimisation. The GP holds at
    most a few hundred points, so the second thread bought nothing."""
    from threadpoolctl import threadpool_limits  # scikit-learn's own dependency, present with skopt

    with warnings.catch_warnings(), threadpool_limits(limits=1):
        warnings.simplefilter("ignore", UserWarning)  # ConvergenceWarning is a UserWarning
        yield


# ---------------------------------------------------------------------------- memory

#: Acquisition candidates BO scores per ask: ``n_candidates`` uniform points plus 40 around
#: each of the 5 best points at 3 scales (:meth:`BayesOpt._maximise_ucb`); skopt's ``n_points``.
_BO_CANDIDATES = 2048 + 3 * 40 * 5
#: Grid levels per dimension (:class:`GridSearch`).
_GRID_LEVELS = 3


def search_memory(algo: str, dim: int, budget: int, n_initial: int = N_INITIAL, batch: int = 1,
                  candidates: int = 0) -> float:
    """Bytes a searcher's arrays take at their largest, its last ask (float64 throughout):

    * every searcher: the told history (budget x D) and one asked batch;
    * ``bo`` / ``skopt``: the initial design (n_initial x D), the acquisition candidates
      (:data:`_BO_CANDIDATES` x D), the GP's covariance, its factor and a working copy
      (3 x budget^2) and the candidates' cross-covariances and solves (4 x candidates x budget),
      plus one block of the kernel (:data:`_KERNEL_BLOCK_BYTES`);
    * ``grid``: every point of the 3^D grid, as numpy rows and as the tuples it is built from;
    * ``blendsearch``: a Python dict per told point (about 100 bytes per entry);
    * ``bruteforce``: the ``candidates`` rows.
    A float: a grid's size overflows any integer type numpy has."""
    dim, budget, n_initial, batch = int(dim), int(budget), int(n_initial), int(batch)
    need = 8.0 * (budget + batch) * dim
    if algo in ("bo", "skopt"):
        need += 8.0 * (n_initial + _BO_CANDIDATES) * dim + 8.0 * 3 * budget * budget \
            + 8.0 * 4 * _BO_CANDIDATES * budget + _KERNEL_BLOCK_BYTES
    elif algo == "grid":
        need += float(_GRID_LEVELS) ** min(dim, 1024) * (8.0 * 2 * dim + 64)
    elif algo == "blendsearch":
        need += 100.0 * budget * dim
    elif algo == "bruteforce":
        need += 8.0 * int(candidates) * dim
    return need


def check_search_memory(algo: str, dim: int, budget: int, n_initial: int = N_INITIAL, batch: int = 1,
                        what: str = "") -> None:
    """Refuse a search whose arrays would take more than ``fileio.MEMORY_BUDGET``
    (:func:`search_memory`), before any is allocated.

    Raises:
        ConfigError: naming the options that set the size, ``what`` first (where the dimension
            comes from, e.g. ``--vd-lattice 1000,1000,1000 (3000000000 dimensions per actor)``).
    """
    need = search_memory(algo, dim, budget, n_initial, batch)
    if need > MEMORY_BUDGET:
        raise ConfigError(f"{what + ': ' if what else ''}--algo {algo} with --budget {budget} over {dim} search "
                          f"dimensions would need about {gib(need)} of memory, more than the {gib(MEMORY_BUDGET)} "
                          "budget (docs/reliability.md, \"Memory\"); give fewer dimensions (actors, lattice nodes) "
                          "or a smaller --budget")


# ---------------------------------------------------------------------------- factory

def make_searcher(algo: str, dim: int, seed: int = 0, budget: int = BUDGET,
                  candidates: np.ndarray | None = None, **options) -> Searcher:
    """Build a searcher by name (``ALGORITHMS``). ``candidates`` (C, D) is required for
    ``bruteforce``; ``options`` go to the searcher's constructor (e.g. ``n_initial`` for BO and skopt)."""
    if algo == "bo":
        return BayesOpt(dim, seed, budget, **options)
    if algo == "random":
        return RandomSearch(dim, seed, budget)
    if algo == "grid":
        return GridSearch(dim, seed, budget, **options)
    if algo == "blendsearch":
        return BlendSearchSearcher(dim, seed, budget)
    if algo == "skopt":
        return SkoptSearcher(dim, seed, budget, **options)
    if algo == "bruteforce":
        if candidates is None:
            raise ConfigError("bruteforce needs a candidate list (the library assets' unit vectors)")
        return BruteForce(candidates, seed, budget)
    raise ConfigError(f"unknown search algorithm {algo!r}; choose one of {', '.join(ALGORITHMS)}")
