"""Microscopic traffic: IDM car following + MOBIL lane changes, vectorised with numpy.

Vehicles live in road coordinates: arc length ``s`` (m, centre of the vehicle) along a common
reference line and an integer lane index (0 = rightmost, increasing to the left). A lane may
exist only over an interval ``[lane_start[k], lane_end[k]]`` (on-ramp acceleration lanes, lane
drops). Geometry (where lane k lies in the plane) is the caller's business: see
``adv3d_runner.scene.generate``.

IDM (Treiber, Hennecke & Helbing 2000), acceleration of a follower with speed v, desired speed
v0, bumper-to-bumper gap g and approach rate dv = v - v_leader::

    s*(v, dv) = s0 + max(0, v T + v dv / (2 sqrt(a b)))
    dv/dt     = a (1 - (v / v0)^delta - (s* / g)^2)

Standard highway parameters (Treiber & Kesting, "Traffic Flow Dynamics", table 11.2):
T = 1.5 s, s0 = 2 m, a = 1.0 m/s^2, b = 1.5 m/s^2, delta = 4. Numerical safety: the gap is
floored at ``min_gap`` (0.1 m) so a zero or negative gap yields the strongest braking instead of
inf/NaN; the acceleration is clipped to [-b_max, a] with b_max = 9 m/s^2 (physical limit); the
speed update is ballistic and stops at zero within a step (Treiber & Kesting 2013), so speeds
are never negative and vehicles never reverse.

MOBIL (Kesting, Treiber & Helbing 2007): vehicle c changes to the adjacent lane when the
new follower n is not forced to brake harder than b_safe and::

    a~_c - a_c + p [(a~_n - a_n) + (a~_o - a_o)] > a_thr (+ bias)

with politeness p = 0.2, b_safe = 4 m/s^2, a_thr = 0.1 m/s^2, and a small keep-right bias
0.2 m/s^2. Additionally the target gap must be physically free (both gaps >= ``min_lc_gap``,
1 m), a vehicle never enters a lane that ends within ``avoid_ending_lane`` m, a vehicle whose
lane ends gets a mandatory incentive growing as the end nears, a lane change takes
``lc_duration`` s (the vehicle belongs to the target lane from its start) and vehicles wait
``lc_cooldown`` s between changes. Per step only one direction (left on even steps, right on
odd steps) and at most one vehicle per target lane may start a change, so two vehicles never
claim the same gap at once.

Everything is deterministic: no random numbers are drawn here (driver heterogeneity comes in
through the per-vehicle v0 / T arrays chosen by the caller from a seeded generator).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters (SI units). v0 and T may be overridden per vehicle (``Traffic.v0/T``)."""

    T: float = 1.5        # desired time headway, s
    s0: float = 2.0       # jam distance, m
    a: float = 1.0        # maximum acceleration, m/s^2
    b: float = 1.5        # comfortable deceleration, m/s^2
    delta: float = 4.0    # acceleration exponent
    b_max: float = 9.0    # physical braking limit, m/s^2 (clip)
    min_gap: float = 0.1  # gap floor, m (avoids division by zero)


@dataclass(frozen=True)
class MOBILParams:
    """MOBIL parameters (SI units)."""

    politeness: float = 0.2
    b_safe: float = 4.0          # m/s^2, max deceleration imposed on the new follower
    a_thr: float = 0.1           # m/s^2, switching threshold
    right_bias: float = 0.2      # m/s^2, keep-right incentive
    min_lc_gap: float = 1.0      # m, both gaps in the target lane must be at least this
    lc_duration: float = 3.0     # s, duration of the lateral manoeuvre
    lc_cooldown: float = 4.0     # s, minimum time between two changes
    avoid_ending_lane: float = 300.0  # m, never enter a lane ending within this distance
    mandatory_range: float = 250.0    # m, ramp of the mandatory incentive before a lane end


def idm_acceleration(v: np.ndarray, v0: np.ndarray, gap: np.ndarray, v_lead: np.ndarray,
                     params: IDMParams = IDMParams(), T: np.ndarray | None = None) -> np.ndarray:
    """IDM acceleration (m/s^2), elementwise over broadcastable arrays.

    Args:
        v: follower speed (m/s); negative values are treated as 0.
        v0: desired speed (m/s); floored at 0.1 m/s.
        gap: bumper-to-bumper gap (m); ``inf`` for a free road; <= 0 means touching/overlap and
            gives the strongest braking (-b_max).
        v_lead: leader speed (m/s) (ignored where gap is inf).
        T: per-vehicle time headway (s), default ``params.T``.
    Returns:
        acceleration in [-b_max, a], never NaN for finite or infinite gaps.
    """
    v = np.maximum(np.asarray(v, dtype=np.float64), 0.0)
    v0 = np.maximum(np.asarray(v0, dtype=np.float64), 0.1)
    gap = np.asarray(gap, dtype=np.float64)
    v_lead = np.where(np.isfinite(gap), np.asarray(v_lead, dtype=np.float64), v)
    T = params.T if T is None else np.asarray(T, dtype=np.float64)
    dv = v - np.maximum(v_lead, 0.0)
    s_star = params.s0 + np.maximum(0.0, v * T + v * dv / (2.0 * np.sqrt(params.a * params.b)))
    g = np.maximum(gap, params.min_gap)
    interaction = np.where(np.isfinite(g), (s_star / g) ** 2, 0.0)
    acc = params.a * (1.0 - (v / v0) ** params.delta - interaction)
    return np.clip(acc, -params.b_max, params.a)


def integrate(s: np.ndarray, v: np.ndarray, acc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Ballistic update that stops at zero speed inside the step (no reversing).

    Returns:
        (s_new, v_new) with v_new >= 0 and s_new >= s.
    """
    v = np.maximum(v, 0.0)
    v_new = v + acc * dt
    stops = v_new < 0.0  # only possible with acc < 0
    safe_acc = np.where(stops, acc, -1.0)
    ds = np.where(stops, -v * v / (2.0 * safe_acc), v * dt + 0.5 * acc * dt * dt)
    return s + np.maximum(ds, 0.0), np.maximum(v_new, 0.0)


@dataclass
class Traffic:
    """State of all vehicles; call ``step(dt)`` to advance.

    Arrays are (N,): ``s`` m, ``v`` m/s, ``lane`` int, ``length`` m, ``v0`` m/s, ``T`` s,
    ``active`` bool, ``lane_prev`` int (lane before the current/last change), ``lc_progress``
    in [0, 1] (1 = no change in progress), ``lc_timer`` s since the last change started.
    Lane existence: ``lane_start`` / ``lane_end`` (K,) m (+-inf for through lanes); lane
    changes to or from lane k happen only on ``[lane_open[k], lane_end[k]]`` (an on-ramp is
    physically separated before its acceleration lane opens). Vehicles
    whose ``s`` passes ``road_end`` become inactive.
    """

    lane_start: np.ndarray
    lane_end: np.ndarray
    road_end: float = np.inf
    lane_open: np.ndarray | None = None  # lane changes to/from lane k only where s >= lane_open[k]
    lane_changes: bool = True  # False: pure IDM car following (lanes are independent)
    idm: IDMParams = IDMParams()
    mobil: MOBILParams = MOBILParams()
    s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lane: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    v0: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T: np.ndarray = field(default_factory=lambda: np.zeros(0))
    active: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    lane_prev: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    lc_progress: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lc_timer: np.ndarray = field(default_factory=lambda: np.zeros(0))
    step_count: int = 0

    def __post_init__(self) -> None:
        self.lane_start = np.asarray(self.lane_start, dtype=np.float64)
        self.lane_end = np.asarray(self.lane_end, dtype=np.float64)
        self.lane_open = self.lane_start.copy() if self.lane_open is None else np.asarray(self.lane_open, dtype=np.float64)

    @property
    def n_lanes(self) -> int:
        return len(self.lane_start)

    def add(self, s: float, lane: int, v: float, length: float, v0: float, T: float | None = None) -> int:
        """Add one vehicle; returns its index (indices are stable for the run)."""
        self.s = np.append(self.s, float(s))
        self.v = np.append(self.v, max(0.0, float(v)))
        self.lane = np.append(self.lane, int(lane))
        self.length = np.append(self.length, float(length))
        self.v0 = np.append(self.v0, float(v0))
        self.T = np.append(self.T, self.idm.T if T is None else float(T))
        self.active = np.append(self.active, True)
        self.lane_prev = np.append(self.lane_prev, int(lane))
        self.lc_progress = np.append(self.lc_progress, 1.0)
        self.lc_timer = np.append(self.lc_timer, np.inf)
        return len(self.s) - 1

    # ------------------------------------------------------------------ neighbours
    def _lane_order(self, lane: int) -> np.ndarray:
        """Indices of the active vehicles in ``lane`` sorted by s."""
        idx = np.flatnonzero(self.active & (self.lane == lane))
        return idx[np.argsort(self.s[idx], kind="stable")]

    def _neighbours(self, s: np.ndarray, lane: int, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """For positions ``s`` (M,) in ``lane``: index of the vehicle ahead and behind (-1 if
        none), ignoring vehicles in ``exclude`` (M,) (the querying vehicle itself)."""
        order = self._lane_order(lane)
        M = len(s)
        ahead = np.full(M, -1)
        behind = np.full(M, -1)
        if len(order) == 0:
            return ahead, behind
        so = self.s[order]
        # ties: a vehicle at exactly the same s counts as ahead (conservative for both)
        pos = np.searchsorted(so, s, side="left")
        n = len(order)
        padded = np.concatenate([[-1], order, [-1, -1]])  # padded[j + 1] == order[j]
        a = pos.copy()
        b = pos - 1
        if exclude is not None:
            a = np.where(padded[a + 1] == exclude, a + 1, a)
            b = np.where(padded[b + 1] == exclude, b - 1, b)
            a = np.where(padded[np.minimum(a, n) + 1] == exclude, a + 1, a)  # tie at same s
        ahead = np.where(a < n, padded[np.minimum(a, n) + 1], -1)
        behind = np.where(b >= 0, padded[np.maximum(b, -1) + 1], -1)
        return ahead, behind

    def _gap_to(self, i: np.ndarray, s_i: np.ndarray, len_i: np.ndarray, lead: np.ndarray, lane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gap (m) and leader speed for followers at ``s_i`` to ``lead`` (-1: none), including
        the virtual standing obstacle at the end of ``lane``."""
        has = lead >= 0
        li = np.where(has, lead, 0)
        gap = np.where(has, self.s[li] - s_i - 0.5 * (self.length[li] + len_i), np.inf)
        v_lead = np.where(has, self.v[li], 0.0)
        end = self.lane_end[lane]
        gap_end = end - s_i - 0.5 * len_i
        use_end = np.isfinite(end) & (gap_end < gap)
        return np.where(use_end, gap_end, gap), np.where(use_end, 0.0, v_lead)

    def accelerations(self) -> np.ndarray:
        """IDM acceleration of every vehicle in its current lane (0 for inactive)."""
        acc = np.zeros(len(self.s))
        for k in range(self.n_lanes):
            order = self._lane_order(k)
            if len(order) == 0:
                continue
            lead = np.append(order[1:], -1)
            gap, v_lead = self._gap_to(order, self.s[order], self.length[order], lead, np.full(len(order), k))
            acc[order] = idm_acceleration(self.v[order], self.v0[order], gap, v_lead, self.idm, self.T[order])
        return acc

    # ------------------------------------------------------------------ MOBIL
    def _lane_exists(self, lane: int, s: np.ndarray) -> np.ndarray:
        return (s >= self.lane_open[lane]) & (s <= self.lane_end[lane])

    def lane_change_candidates(self, direction: int, acc_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vehicles that want and may change by ``direction`` (+1 left, -1 right).

        Returns:
            (indices, incentives) of vehicles whose MOBIL criterion holds and whose target gap
            is free and safe.
        """
        p = self.mobil
        cand = np.flatnonzero(self.active & (self.lc_progress >= 1.0) & (self.lc_timer >= p.lc_cooldown))
        out_i, out_gain = [], []
        for k in range(self.n_lanes):
            target = k + direction
            if target < 0 or target >= self.n_lanes:
                continue
            idx = cand[self.lane[cand] == k]
            if len(idx) == 0:
                continue
            s_i = self.s[idx]
            ok = self._lane_exists(target, s_i) & self._lane_exists(k, s_i)
            # never move into a lane that ends soon (unless the own lane ends sooner)
            ok &= (self.lane_end[target] - s_i > p.avoid_ending_lane) | (self.lane_end[target] > self.lane_end[k])
            idx, s_i = idx[ok], s_i[ok]
            if len(idx) == 0:
                continue
            len_i, v_i = self.length[idx], self.v[idx]
            tl = np.full(len(idx), target)
            lead_new, fol_new = self._neighbours(s_i, target)
            gap_front, vl_new = self._gap_to(idx, s_i, len_i, lead_new, tl)
            # gap behind: to the new follower
            hasf = fol_new >= 0
            fi = np.where(hasf, fol_new, 0)
            gap_back = np.where(hasf, s_i - self.s[fi] - 0.5 * (len_i + self.length[fi]), np.inf)
            free = (gap_front >= p.min_lc_gap) & (gap_back >= p.min_lc_gap)
            # new follower's acceleration with us as its leader (safety), and before
            acc_nf_new = np.where(hasf, idm_acceleration(self.v[fi], self.v0[fi], gap_back, v_i, self.idm, self.T[fi]), 0.0)
            acc_nf_old = np.where(hasf, acc_now[fi], 0.0)
            safe = acc_nf_new >= -p.b_safe
            # own acceleration after the change
            acc_c_new = idm_acceleration(v_i, self.v0[idx], gap_front, vl_new, self.idm, self.T[idx])
            acc_c_old = acc_now[idx]
            # old follower: gains when we leave (its new leader is our leader)
            lead_old, fol_old = self._neighbours(s_i, k, exclude=idx)
            haso = fol_old >= 0
            oi = np.where(haso, fol_old, 0)
            gap_o, vl_o = self._gap_to(oi, self.s[oi], self.length[oi], lead_old, np.full(len(idx), k))
            acc_o_new = np.where(haso, idm_acceleration(self.v[oi], self.v0[oi], gap_o, vl_o, self.idm, self.T[oi]), 0.0)
            acc_o_old = np.where(haso, acc_now[oi], 0.0)
            gain = acc_c_new - acc_c_old + p.politeness * ((acc_nf_new - acc_nf_old) + (acc_o_new - acc_o_old))
            gain += p.right_bias * (-direction)  # keep right: bonus for right, malus for left
            # mandatory: own lane ends ahead -> growing incentive to leave it
            to_end = self.lane_end[k] - s_i
            mandatory = np.isfinite(to_end) & (to_end < p.mandatory_range) & (self.lane_end[target] > self.lane_end[k])
            gain += np.where(mandatory, 3.0 * (1.0 - np.clip(to_end, 0, None) / p.mandatory_range) + 0.5, 0.0)
            want = free & safe & (gain > p.a_thr)
            out_i.append(idx[want])
            out_gain.append(gain[want])
        if not out_i:
            return np.zeros(0, int), np.zeros(0)
        return np.concatenate(out_i), np.concatenate(out_gain)

    # ------------------------------------------------------------------ step
    def step(self, dt: float) -> None:
        """Advance all active vehicles by ``dt`` s (IDM, then MOBIL decisions)."""
        acc = self.accelerations()
        direction = 1 if self.step_count % 2 == 0 else -1
        if self.lane_changes:
            who, gain = self.lane_change_candidates(direction, acc)
        else:
            who, gain = np.zeros(0, int), np.zeros(0)
        if len(who):
            target = self.lane[who] + direction
            # one change per target lane per step: the largest incentive wins
            order = np.lexsort((-gain, target))
            first = np.ones(len(order), bool)
            first[1:] = target[order][1:] != target[order][:-1]
            chosen = who[order][first]
            self.lane_prev[chosen] = self.lane[chosen]
            self.lane[chosen] += direction
            self.lc_progress[chosen] = 0.0
            self.lc_timer[chosen] = 0.0
            acc = self.accelerations()  # leaders changed
        act = self.active
        self.s[act], self.v[act] = integrate(self.s[act], self.v[act], acc[act], dt)
        self.lc_timer[act] += dt
        self.lc_progress[act] = np.minimum(1.0, self.lc_progress[act] + dt / self.mobil.lc_duration)
        self.active &= self.s <= self.road_end
        self.step_count += 1


def equilibrium_speed(gap: np.ndarray, v0: np.ndarray, params: IDMParams = IDMParams(), T: np.ndarray | float | None = None) -> np.ndarray:
    """IDM steady-state speed (m/s) for a bumper-to-bumper ``gap`` (m), found by bisection on
    a(1 - (v/v0)^delta - (s*(v,0)/gap)^2) = 0. Used to start traffic near equilibrium."""
    gap = np.maximum(np.asarray(gap, dtype=np.float64), params.min_gap)
    v0 = np.broadcast_to(np.asarray(v0, dtype=np.float64), gap.shape)
    T = params.T if T is None else T
    lo = np.zeros_like(gap)
    hi = v0.copy()
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        f = 1.0 - (mid / v0) ** params.delta - ((params.s0 + mid * T) / gap) ** 2
        lo = np.where(f > 0, mid, lo)
        hi = np.where(f > 0, hi, mid)
    return lo
