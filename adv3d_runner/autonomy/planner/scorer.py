"""Scorer: weighted sum of the named cost terms, with a per-term breakdown.

Default weights (cost per unit of each term, see :mod:`.costs` for the units):

============== ======== ==========================================================
term           weight   meaning of one unit
============== ======== ==========================================================
collision      1000     one expected collision within the horizon
drivable_area   200     1 m outside the lanes, averaged over the horizon
buffer           30     clearance fully eaten (0 m of a 1 m buffer) over the horizon
headway          15     gap fully below 2 m + 1.0 s x speed over the horizon
speed_limit       5     1 m/s over the limit on average
progress         20     no progress at all (vs. driving at the limit for the horizon)
lane_center       2     1 m from the nearest lane centre on average
lane_change       2     starting a lane change
offset_change     1     moving the in-lane target offset by 1 m from the previous plan's
jerk            0.3     1 m/s^3 mean |jerk|
lat_accel       1.0     1 m/s^2 mean |lateral acceleration|
occupancy_collision 1000 a footprint surely occupied now (Autonomy-B; discounted later)
occupancy_buffer     30 the buffer ring surely occupied over the whole horizon (Autonomy-B)
own_progress     20     no progress against the best collision-free candidate of the own lane
                        (only with ``PlannerConfig.own_lane_floor``; off by default)
============== ======== ==========================================================

Autonomy-A plans with ``collision`` and ``buffer`` (from predicted actors); Autonomy-B, which
has no actors, with ``occupancy_collision`` and ``occupancy_buffer`` (from the occupancy field,
:mod:`.occupancy`) at the same weights, and every other term the same.

Safety terms dominate by orders of magnitude so that comfort and progress only choose among
safe candidates; progress (20 for a full horizon) outweighs a lane change (2) plus the lateral
cost of changing, so a blocked lane is left for a free one, while an unnecessary lane change is
not worth its cost.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ...jit import kernel

TERMS = ("collision", "drivable_area", "buffer", "headway", "speed_limit", "progress", "lane_center",
         "lane_change", "offset_change", "jerk", "lat_accel", "occupancy_collision", "occupancy_buffer",
         "own_progress")
#: The terms only an instance-based plan has (from predicted actors) and only an
#: occupancy-based plan has (from the occupancy field); a plan has one pair, not both.
#: Terms present only when their planner option is on (``PlannerConfig.own_lane_floor``).
OPTIONAL_TERMS = ("own_progress",)
ACTOR_TERMS = ("collision", "buffer")
OCCUPANCY_TERMS = ("occupancy_collision", "occupancy_buffer")


@dataclass(frozen=True)
class CostWeights:
    collision: float = 1000.0
    drivable_area: float = 200.0
    buffer: float = 30.0
    headway: float = 15.0
    speed_limit: float = 5.0
    progress: float = 20.0
    lane_center: float = 2.0
    lane_change: float = 2.0
    offset_change: float = 1.0
    jerk: float = 0.3
    lat_accel: float = 1.0
    occupancy_collision: float = 1000.0
    occupancy_buffer: float = 30.0
    own_progress: float = 20.0

    def as_dict(self) -> dict[str, float]:
        # dataclasses.asdict deep-copies through its recursion: ~100 us a plan for 13 floats
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class ScoreTable:
    """Scores of all candidates.

    Attributes:
        raw: term -> (B,) unweighted cost.
        weighted: term -> (B,) weight x raw.
        total: (B,) sum of the weighted terms.
        best: index of the lowest total among the eligible candidates (ties: the lowest index,
            i.e. the earlier candidate).
        eligible: (B,) bool, the candidates that may be chosen (all unless :func:`score` was
            given a mask).
    """

    raw: dict[str, np.ndarray]
    weighted: dict[str, np.ndarray]
    total: np.ndarray
    best: int
    weights: dict[str, float] = field(default_factory=dict)
    eligible: np.ndarray | None = None

    def argmin(self, values: np.ndarray) -> int:
        """Index of the lowest of ``values`` (B,) among the eligible candidates."""
        if self.eligible is None or not self.eligible.any():
            return int(np.argmin(values))
        return int(np.argmin(np.where(self.eligible, values, np.inf)))

    def breakdown(self, i: int | None = None) -> dict[str, float]:
        """Weighted per-term costs of candidate ``i`` (default: the best)."""
        i = self.best if i is None else i
        return {k: float(v[i]) for k, v in self.weighted.items()}


def score(raw_terms: dict[str, np.ndarray], weights: CostWeights = CostWeights(),
          eligible: np.ndarray | None = None) -> ScoreTable:
    """Weight and sum the terms (every term of :data:`TERMS` that is present; unknown terms raise).

    ``eligible`` (B,) bool: the candidates the best may be chosen from (PDM-Closed's gating, as
    opposed to a weighted term); all when None or when none is eligible."""
    w = weights.as_dict()
    unknown = set(raw_terms) - set(w)
    if unknown:
        raise KeyError(f"unknown cost terms {sorted(unknown)}")
    raw = {k: _finite_terms(np.asarray(v, dtype=np.float64)) for k, v in raw_terms.items()}
    weighted = {k: w[k] * v for k, v in raw.items()}
    total = np.sum(np.stack(list(weighted.values())), axis=0)
    table = ScoreTable(raw, weighted, total, 0, w, None if eligible is None else np.asarray(eligible, bool))
    table.best = table.argmin(total)
    return table


def _finite_terms(v: np.ndarray) -> np.ndarray:
    """``np.nan_to_num(v, nan=1e6, posinf=1e6)`` (a new float64 array, -inf to the most negative
    float) without its ~20 us of numpy calls, paid for each of ~12 terms in every plan."""
    return _finite_kernel(np.ascontiguousarray(v).reshape(-1)).reshape(v.shape)


@kernel
def _finite_kernel(v: np.ndarray) -> np.ndarray:
    out = np.empty_like(v)
    lowest = -np.finfo(np.float64).max
    for i in range(v.size):
        x = v[i]
        if np.isnan(x) or x == np.inf:
            out[i] = 1e6
        elif x == -np.inf:
            out[i] = lowest
        else:
            out[i] = x
    return out
