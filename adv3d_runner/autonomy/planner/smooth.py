"""A longitudinal profile that follows a leader with the least jerk: the speed plan of one
extra current-lane candidate (``ProposalConfig.smooth_follow``).

The IDM candidates react to the leader one step at a time, and on real traffic every plan
brakes now and eases off later while the next plan brakes again (docs/autonomy.md, real traffic). This
candidate instead plans the whole horizon at once, in the spirit of the piecewise-jerk speed
optimisation of Apollo's planner (Zhang et al. 2018, "Optimal trajectory generation for
autonomous vehicles under centripetal acceleration constraints..."; the speed QP of Apollo
5.0): the jerk of each 0.1 s step is the unknown, and a weighted least-squares problem asks
for little jerk and acceleration, the target speed, and (as a soft constraint, only where it is
violated) a gap of at least ``jam + headway x v`` behind the predicted leader, plus v >= 0 and
the acceleration limits. The one-sided rows are found by a few active-set passes, each a
(T x T) linear solve of the normal equations: no QP library needed for 50 unknowns.

Units: m, s, m/s, m/s^2, m/s^3. A few 50 x 50 products and Cholesky solves per plan, as compiled
loops (~0.17 ms; not BLAS, see ``_matmul``).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ...jit import kernel


@dataclass(frozen=True)
class SmoothWeights:
    """Squared-residual weights of the profile's least-squares problem.

    Attributes:
        jerk: per (m/s^3)^2 of each step's jerk.
        accel: per (m/s^2)^2 of each step's acceleration.
        speed: per (m/s)^2 of each step's deviation from the target speed.
        gap: per m^2 of each step's shortfall of the gap (soft constraint).
        limits: per unit^2 of v < 0 or an acceleration outside its limits (soft constraints).
    """

    jerk: float = 3.0
    accel: float = 3.0
    speed: float = 0.05
    gap: float = 20.0
    limits: float = 1000.0


@lru_cache(maxsize=8)
def _maps(steps: int, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear maps from the (T,) jerks to the (T,) accelerations, the (T,) speeds at the
    ends of the steps and the (T,) distances travelled by then (each without its part that
    comes from the initial speed and acceleration)."""
    lower = np.tril(np.ones((steps, steps)))
    accel = dt * lower  # a_k = a0 + dt * sum_{i <= k} j_i
    speed = dt * _matmul(lower, accel)  # v_{k+1} = v0 + dt * sum_{i <= k} a_i
    # s_{k+1} = s_k + v_k dt + a_k dt^2 / 2, v_k the speed at the start of step k
    speed_start = np.vstack([np.zeros((1, steps)), speed[:-1]])
    dist = dt * _matmul(lower, speed_start) + 0.5 * dt * dt * _matmul(lower, accel)
    for m in (accel, speed, dist):
        m.setflags(write=False)
    return accel, speed, dist


def free_road_speeds(v0: float, v_target: float, max_accel: float, comfortable_decel: float, dt: float,
                     steps: int) -> np.ndarray:
    """(steps,) speeds at the ends of the steps of the IDM's free-road approach to
    ``v_target``: a = max_accel (1 - (v / v_target)^4), at most ``comfortable_decel`` of
    braking (m/s, m/s^2, s)."""
    out = np.empty(steps)
    v, vt = float(v0), max(float(v_target), 0.1)
    for k in range(steps):
        r = (v / vt) ** 4
        v = max(v + dt * max(max_accel * (1.0 - r), -comfortable_decel), 0.0)
        out[k] = v
    return out


def smooth_profile(v0: float, a0: float, v_target: float, bound: np.ndarray, jam: float, headway: float,
                   dt: float, max_accel: float, max_decel: float, recover: float = 8.0, comfortable_decel: float = 2.0,
                   weights: SmoothWeights = SmoothWeights(), passes: int = 6) -> np.ndarray:
    """Accelerations of the least-jerk profile behind a predicted leader.

    Args:
        v0, a0: speed (m/s, >= 0) and acceleration (m/s^2) now.
        v_target: target speed, m/s; the profile is drawn towards the speeds of the IDM's free-road
            approach to it (:func:`free_road_speeds`), not to the target itself.
        bound: (T,) the leader's rear bumper less the ego's half length at the end of each step,
            as arc length from the ego's position now (m; +inf where no leader): the bumper
            gap is ``bound - s``.
        jam, headway: the gap kept, ``jam + headway x v`` (m, s). A gap that is already
            shorter is not asked to open at once: the shortfall allowed falls linearly from
            today's to 0 over ``recover`` s (asking for all of it at the first step is what
            makes the IDM brake hard for a car that cuts in).
        dt: step, s; max_accel, max_decel: acceleration limits (> 0), m/s^2;
            comfortable_decel: the free-road approach's braking when above the target, m/s^2.
    Returns:
        (T,) accelerations of the steps, m/s^2.
    """
    bound = np.asarray(bound, dtype=np.float64)
    T = len(bound)
    A, V, S = _maps(T, dt)
    k = np.arange(1, T + 1) * dt
    a_free = np.full(T, a0)
    v_free = v0 + a0 * k
    s_free = v0 * k + 0.5 * a0 * k * k
    w = weights
    # normal equations: the rows that always hold (jerk, acceleration, speed) once per grid and
    # weights; each pass adds the one-sided rows that are active (a few 50 x 50 products)
    G = _fixed_normal(T, dt, w)
    v_ref = free_road_speeds(v0, v_target, max_accel, comfortable_decel, dt, T)
    g = -w.accel * _matmul(A.T, a_free) + w.speed * _matmul(V.T, v_ref - v_free)
    has_bound = np.isfinite(bound)
    # one-sided rows: gap (s + headway v <= bound - jam + allowed), v >= 0, -max_decel <= a <= max_accel
    gap_now = bound[0] - v0 * dt if has_bound[0] else np.inf  # ~ the bumper gap now
    short_now = max(0.0, jam + headway * v0 - gap_now)
    allowed = short_now * np.maximum(0.0, 1.0 - k / recover)
    gap_m = S + headway * V
    gap_r = np.where(has_bound, bound - jam + allowed - (s_free + headway * v_free), 0.0)
    one_sided = ((w.gap, gap_m, gap_r), (w.limits, V, -v_free), (w.limits, A, -max_decel - a_free),
                 (w.limits, A, max_accel - a_free))
    active = np.zeros((4, T), bool)
    j = _solve_spd(G, g)
    for _ in range(passes):
        a, v, s = a_free + _matmul(A, j), v_free + _matmul(V, j), s_free + _matmul(S, j)
        violated = np.stack([has_bound & (s + headway * v > bound - jam + allowed + 1e-6), v < -1e-6,
                             a < -max_decel - 1e-6, a > max_accel + 1e-6])
        if not (violated & ~active).any():
            break
        active |= violated  # rows only join: the passes cannot cycle
        Ga, ga = G.copy(), g.copy()
        for (weight, rows, rhs), on in zip(one_sided, active):
            if on.any():
                m = rows[on]
                Ga += weight * _matmul(m.T, m)
                ga += weight * _matmul(m.T, rhs[on])
        j = _solve_spd(Ga, ga)
    return a_free + _matmul(A, j)


@lru_cache(maxsize=8)
def _fixed_normal(steps: int, dt: float, w: SmoothWeights) -> np.ndarray:
    """(T, T) normal matrix of the jerk, acceleration and speed rows."""
    A, V, _ = _maps(steps, dt)
    G = w.jerk * np.eye(steps) + w.accel * _matmul(A.T, A) + w.speed * _matmul(V.T, V)
    G.setflags(write=False)
    return G


# The products and the solve are plain loops rather than BLAS / LAPACK: OpenBLAS sums in another
# order with another number of threads, and the plans (hence the episodes) would then depend on
# the machine's thread count (a test's recorded plans differed by 6e-14 m between 1 and 2 threads).

def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a (n, m) matrix and a (m,) vector or (m, p) matrix, summed in index order."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if b.ndim == 1:
        return _matvec(a, np.ascontiguousarray(b, dtype=np.float64))
    return _matmat(a, np.ascontiguousarray(b, dtype=np.float64))


@kernel
def _matvec(a, x):
    n, m = a.shape
    out = np.zeros(n)
    for i in range(n):
        acc = 0.0
        for k in range(m):
            acc += a[i, k] * x[k]
        out[i] = acc
    return out


@kernel
def _matmat(a, b):
    n, m = a.shape
    p = b.shape[1]
    out = np.zeros((n, p))
    for i in range(n):
        for k in range(m):
            aik = a[i, k]
            if aik != 0.0:
                for j in range(p):
                    out[i, j] += aik * b[k, j]
    return out


@kernel
def _solve_spd(G, g):
    """x with G x = g for a symmetric positive definite (n, n) G: Cholesky, then the two
    triangular solves."""
    n = G.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = G[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            t = G[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    y = np.empty(n)
    for i in range(n):
        t = g[i]
        for k in range(i):
            t -= L[i, k] * y[k]
        y[i] = t / L[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        t = y[i]
        for k in range(i + 1, n):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]
    return x
