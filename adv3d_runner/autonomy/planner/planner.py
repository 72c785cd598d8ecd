"""The sampling planner: corridors -> candidates -> named costs -> the cheapest plan.

``SamplingPlanner.reset(lane_map)`` hands the planner the scene's
:class:`~adv3d_runner.scene.lanemap.LaneMap` once per episode (nuPlan's ``initialize``);
``SamplingPlanner.plan(ego_state, predictions, tracks)`` then returns a
:class:`~adv3d_runner.autonomy.interface.Plan` whose ``cost_terms`` hold the weighted breakdown
of the chosen candidate; :meth:`SamplingPlanner.plan_with_scores` also returns every
candidate and its :class:`~.scorer.ScoreTable` (for debugging, tests and the replay file).

Two obstacle models, one scorer: from predicted actors (Autonomy-A: ``predictions`` and
``tracks``; the ``collision`` and ``buffer`` terms), or from an occupancy field (Autonomy-B:
``plan(ego_state, occupancy=field)``; the ``occupancy_collision`` and ``occupancy_buffer`` terms
read the field along each candidate's footprint over time, and the proposals' IDM and the
headway term follow the lane leaders the field shows, :mod:`.occupancy`). Every other term is
the same.

With no lane under the ego (empty map, or the ego far from every lane) the planner brakes to a
stop along its heading: there is no road to plan on.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
import numpy as np

from ...dynamics.bicycle import BicycleParams, rollout
from ...errors import ConfigError
from ...geometry.angles import wrap_angle
from ...jit import kernel
from ...scene.corridor import DEFAULT_SPEED_LIMIT, ChainCache, CorridorSet, build_corridor
from ...scene.lanemap import LaneMap
from ..interface import EgoState, Plan, Predictions, Tracks
from . import costs
from . import occupancy as occmodel
from .proposals import ActorForecast, Candidates, ProposalConfig, make_specs, rollout_candidates
from .scorer import CostWeights, ScoreTable, score

DEFAULT_ACTOR_DIMS = (4.6, 1.9)  # m, used when a prediction has no matching track
YAW_CHORD = 4.0  # m of forward motion over which a predicted actor's heading is measured


@dataclass(frozen=True)
class PlannerConfig:
    """Planner parameters.

    Attributes:
        proposals: candidate generation (:class:`.proposals.ProposalConfig`).
        weights: cost weights (:class:`.scorer.CostWeights`).
        buffer: clearance buffer of the buffer term, m.
        time_headway, min_gap: the headway term's desired gap = min_gap + time_headway x speed.
        actor_range: actors further than this from the ego now are ignored, m.
        corridor_behind: corridor length kept behind the ego, m.
        default_speed_limit: m/s for lanes without one.
        off_lane_distance: if the ego is further than this from every lane strip, it has no
            lane (brakes to a stop), m.
        exempt_rear_end: ignore collisions and buffer violations with actors that come from
            behind in the same direction, for candidates that keep the current lane.
        offset_confirm_factor: an in-lane offset change that was not already the (unsurcharged)
            choice of the previous plan costs this much more in the offset-change term
            (:func:`.costs.offset_change_cost`): nudges need two consecutive plans to agree.
        occupancy: how an occupancy field is queried (Autonomy-B, :mod:`.occupancy`).
        open_map_border: a corridor whose last lane stops at the edge of the mapped area
            (:meth:`~adv3d_runner.scene.lanemap.LaneMap.border_ends`: no lane goes on beyond it)
            is not a dead end: the road goes on. Real recordings are cut out of a longer road,
            and braking for the cut slowed the ego down before the end of most real scenes
            (docs/autonomy.md, real traffic). Lane drops stay dead ends.
        exempt_overlap_now: an actor-mode whose box overlaps the ego's footprint already now
            counts in neither the collision nor the buffer term: no plan can undo a present
            overlap, and on the learned stack it is nearly always a mislocalised detection
            beside the ego, for which every candidate "collided" and the emergency stop won
            (NGSIM US-101 train recordings, docs/autonomy.md).
        progress_floor: None: full progress is driving at the speed limit for the horizon; a
            number (m): full progress is the longest distance among the candidates without
            expected collision, at least this much (:func:`.costs.progress_reference`, as
            nuPlan's PDM scorer), so that stopping costs as much at crawl speeds as at speed.
        emergency_min_collision: the emergency stop may be chosen only when every other
            candidate expects at least this many collisions (its collision term, unweighted);
            None: it competes like any candidate. Otherwise soft terms or an unlikely mode
            decided it: a track that appeared beside the ego filled every candidate's buffer
            term, or a 5 % mode touched every candidate, and the emergency stop's -7 m/s^2 scored
            lowest (NGSIM US-101 train recordings, docs/autonomy.md).
        contingency_time, contingency_decel: None: off. A number (s): a collision with an
            actor-mode that the candidate could still avoid by braking at ``contingency_decel``
            from ``contingency_time`` s before it (:func:`.costs.avoidable_later`: only at
            speeds below 2 x decel x time) is left to the later plans and does not count in the
            collision term (the buffer term still sees it).
        own_lane_floor: None: off. A number (m): the ``own_progress`` term, progress against
            the longest collision-free candidate on the current lane (at least this many m,
            :func:`.costs.progress_reference`): stopping costs as much at a crawl as at speed,
            and unlike ``progress_floor`` a lane change earns nothing from it.
    """

    proposals: ProposalConfig = field(default_factory=ProposalConfig)
    weights: CostWeights = field(default_factory=CostWeights)
    buffer: float = 1.0
    time_headway: float = 1.0
    min_gap: float = 2.0
    actor_range: float = 120.0
    corridor_behind: float = 20.0
    default_speed_limit: float = DEFAULT_SPEED_LIMIT
    off_lane_distance: float = 10.0
    exempt_rear_end: bool = True
    offset_confirm_factor: float = 4.0
    occupancy: occmodel.OccupancyPlanConfig = field(default_factory=occmodel.OccupancyPlanConfig)
    open_map_border: bool = True
    exempt_overlap_now: bool = True
    progress_floor: float | None = None
    emergency_min_collision: float | None = 0.5
    contingency_time: float | None = None
    contingency_decel: float = 2.0
    own_lane_floor: float | None = None

    @classmethod
    def from_overrides(cls, overrides: dict, source: str = "planner overrides") -> "PlannerConfig":
        """The default config with some fields replaced, for diagnosis and tuning runs
        (``bench/sanity.py --planner-config``, ``bench/real_planner.py --config``).

        ``overrides`` is ``{"proposals": {...}, "weights": {...}, "planner": {...}}`` (each part
        optional): fields of :class:`.proposals.ProposalConfig`, :class:`.scorer.CostWeights` and
        of this class. Numbers stay numbers (a JSON ``1`` for a float field is fine); an optional
        field (``emergency_min_collision``, ``progress_floor``) takes ``null``.

        Raises:
            ConfigError: an unknown part or field, or a value of the wrong type, naming it and
                ``source``.
        """
        if not isinstance(overrides, dict):
            raise ConfigError(f"{source}: expected an object with parts proposals, weights, planner")
        unknown = set(overrides) - {"proposals", "weights", "planner"}
        if unknown:
            raise ConfigError(f"{source}: unknown part(s) {sorted(unknown)}; use proposals, weights, planner")
        parts = {"proposals": ProposalConfig, "weights": CostWeights, "planner": cls}
        kwargs: dict[str, dict] = {}
        for part, klass in parts.items():
            given = overrides.get(part, {})
            if not isinstance(given, dict):
                raise ConfigError(f"{source}: {part} must be an object of field: value")
            known = {f.name: f for f in fields(klass) if f.name not in ("proposals", "weights", "occupancy")}
            for name, value in given.items():
                if name not in known:
                    raise ConfigError(f"{source}: {part}.{name} is not a field; choose from {', '.join(sorted(known))}")
                default = getattr(klass(), name)
                if value is None and "None" in str(known[name].type):  # an optional field switched off
                    continue
                if isinstance(default, bool) != isinstance(value, bool) or (
                        isinstance(default, (int, float)) and not isinstance(value, (int, float))) or (
                        isinstance(default, tuple) and not isinstance(value, (list, tuple))):
                    raise ConfigError(f"{source}: {part}.{name} = {value!r}, expected a value like {default!r}")
            kwargs[part] = {k: tuple(v) if isinstance(v, list) else
                            float(v) if v is not None and isinstance(getattr(klass(), k), float) else v
                            for k, v in given.items()}
        try:
            return cls(proposals=ProposalConfig(**kwargs["proposals"]), weights=CostWeights(**kwargs["weights"]),
                       **kwargs["planner"])
        except (TypeError, ValueError) as e:  # a value of the right type out of its range
            raise ConfigError(f"{source}: {e}") from None


def forecast_from(predictions: Predictions | None, tracks: Tracks | None, steps: int, dt: float,
                  ego_xy: np.ndarray | None = None, max_range: float = np.inf) -> ActorForecast:
    """Join predictions with their tracks and resample onto the planner's grid.

    Returns poses (N, K, steps + 1, 3): index 0 = the track's current pose (or, without a track,
    the first predicted point extrapolated one step back); later steps = predicted positions
    (held at the last prediction past its horizon), yaw from the direction of motion over the
    last ``YAW_CHORD`` m (the track's yaw until the actor has moved that far, see
    :func:`_yaw_from_motion`)."""
    if predictions is None or len(predictions) == 0:
        return ActorForecast.empty(steps)
    traj = np.asarray(predictions.trajectories, dtype=np.float64)
    if abs(predictions.dt - dt) > 1e-9:
        raise ValueError(f"prediction dt {predictions.dt} != planner dt {dt}")
    N, K, H = traj.shape[:3]
    by_id = {} if tracks is None else {int(i): r for r, i in enumerate(tracks.ids)}
    now = np.empty((N, 3))
    dims = np.empty((N, 2))
    for n, tid in enumerate(predictions.track_ids):
        r = by_id.get(int(tid))
        if r is not None:
            now[n] = tracks.boxes[r, [0, 1, 4]]
            dims[n] = tracks.boxes[r, 2:4]
        else:
            p0, p1 = traj[n, 0, 0], traj[n, 0, min(1, H - 1)]
            now[n, :2] = 2 * p0 - p1
            now[n, 2] = np.arctan2(*(p1 - p0)[::-1]) if np.linalg.norm(p1 - p0) > 1e-6 else 0.0
            dims[n] = DEFAULT_ACTOR_DIMS
    xy = np.empty((N, K, steps + 1, 2))
    xy[:, :, 0] = now[:, None, :2]
    take = min(steps, H)
    xy[:, :, 1:take + 1] = traj[:, :, :take]
    if take < steps:
        xy[:, :, take + 1:] = traj[:, :, -1:]
    probs = np.asarray(predictions.probabilities, dtype=np.float64)
    probs = probs / np.maximum(probs.sum(axis=1, keepdims=True), 1e-12)
    ok = np.all(np.isfinite(xy), axis=(1, 2, 3)) & np.all(np.isfinite(now), axis=1)
    if ego_xy is not None:
        ok &= np.hypot(*(now[:, :2] - np.asarray(ego_xy)[None]).T) <= max_range
    xy, now, dims, probs = xy[ok], now[ok], dims[ok], probs[ok]
    ids = np.asarray(predictions.track_ids)[ok]
    yaw = _yaw_from_motion(xy, now[:, 2])
    poses = np.concatenate([xy, yaw[..., None]], axis=-1)
    return ActorForecast(poses, np.maximum(dims, 0.0), probs, ids)


def relaxed_headway(previous: float | None, cands: Candidates, ego_speed: float, pc: ProposalConfig) -> float:
    """The IDM's time headway (s) for the next plan (``ProposalConfig.headway_relaxation``).

    ``previous`` (None: ``idm_headway``) relaxes towards ``idm_headway`` by one plan step (one
    plan per ``pc.dt``); then the current lane's leader in ``cands`` (the first current-lane
    candidate at offset 0: its bumper gap and speed at step 0) lowers it to the headway it is
    found at, ``(gap - idm_gap) / speed`` (the headway at which the IDM would neither brake nor
    speed up for it), unless that is below ``min_headway`` (too close to accept: braked for as
    before) or the leader is closing in (slower than the ego by more than ``closing_speed``: a
    short gap that the ego drove into is braked for)."""
    full = pc.idm_headway
    h = full if previous is None else min(full, previous + pc.dt * (full - pc.min_headway) / pc.headway_relaxation)
    spec = cands.spec
    own = np.flatnonzero((spec.corridor == 0) & (spec.offset == 0.0) & ~spec.emergency)
    if len(own) == 0 or cands.leader_speed is None or ego_speed < 1.0:
        return h
    b = int(own[0])
    gap, v_lead = float(cands.leader_gap[b, 0]), float(cands.leader_speed[b])
    if np.isfinite(gap) and np.isfinite(v_lead) and v_lead >= ego_speed - pc.closing_speed:
        h_found = (gap - pc.idm_gap) / ego_speed
        if h_found >= pc.min_headway:
            h = min(h, h_found)
    return h


def _yaw_from_motion(xy: np.ndarray, yaw0: np.ndarray, chord: float = YAW_CHORD) -> np.ndarray:
    """Heading along (N, K, T, 2) positions: the direction of the last ``chord`` m of forward
    motion, i.e. from the latest earlier point at least ``chord`` m further back along the
    actor's present heading ``yaw0`` (N,) to this one; ``yaw0`` until the actor has moved that
    far forward (index 0 always). :func:`_yaw_from_motion_numpy` is the definition (and the
    reasons); here the progress, its running maximum and the search for the chord's start are
    one compiled pass (:func:`_chord_vectors`) around numpy's cos, sin and arctan2: the same
    bits, 0.22 -> 0.08 ms per plan (docs/autonomy.md)."""
    N, K, T = xy.shape[:3]
    if N * K == 0 or T == 0:
        return _yaw_from_motion_numpy(xy, yaw0, chord)
    fwd = np.stack([np.cos(yaw0), np.sin(yaw0)], axis=-1)  # (N, 2)
    d, ok = _chord_vectors(np.ascontiguousarray(xy, dtype=np.float64), np.ascontiguousarray(fwd), float(chord))
    if d.shape[0] == 0:  # a non-finite position or heading: numpy's NaN rules
        return _yaw_from_motion_numpy(xy, yaw0, chord)
    yaw = np.where(ok, np.arctan2(d[..., 1], d[..., 0]), np.repeat(yaw0, K)[:, None])
    yaw[:, 0] = np.repeat(yaw0, K)
    return yaw.reshape(N, K, T)


@kernel
def _chord_vectors(xy: np.ndarray, fwd: np.ndarray, chord: float) -> tuple[np.ndarray, np.ndarray]:
    """The chord of :func:`_yaw_from_motion_numpy` at each point: d (N K, T, 2) from the chord's
    start to the point, and ok (N K, T) where the actor has moved ``chord`` m forward; (0, T, 2)
    and (0, T) when a value is not finite.

    The numpy version's arithmetic: the progress (x - x0) fx + (y - y0) fy, its running
    maximum, and the start as ``np.searchsorted`` finds it in the rows made one sorted array
    (row r's progress plus r x span, the target progress minus ``chord`` plus r x span, the
    same roundings): within row r the last index whose shifted progress is <= the target (the
    earlier rows all are, the later ones none)."""
    N, K, T = xy.shape[0], xy.shape[1], xy.shape[2]
    rows = N * K
    prog = np.empty((rows, T))
    mx = 0.0
    for n in range(N):
        fx, fy = fwd[n, 0], fwd[n, 1]
        if not (np.isfinite(fx) and np.isfinite(fy)):
            return np.zeros((0, T, 2)), np.zeros((0, T), np.bool_)
        for k in range(K):
            r = n * K + k
            x0, y0 = xy[n, k, 0, 0], xy[n, k, 0, 1]
            run = 0.0
            for t in range(T):
                x, y = xy[n, k, t, 0], xy[n, k, t, 1]
                if not (np.isfinite(x) and np.isfinite(y)):
                    return np.zeros((0, T, 2)), np.zeros((0, T), np.bool_)
                v = (x - x0) * fx + (y - y0) * fy
                if t == 0 or v > run:
                    run = v
                prog[r, t] = run
                if run > mx:
                    mx = run
    span = mx + chord + 1.0
    d = np.empty((rows, T, 2))
    ok = np.empty((rows, T), np.bool_)
    for r in range(rows):
        n, k = r // K, r % K
        off = float(r) * span
        i = -1  # the last s with prog[r, s] + off <= target (nondecreasing in s)
        for t in range(T):
            target = (prog[r, t] - chord) + off
            while i + 1 < T and prog[r, i + 1] + off <= target:
                i += 1
            ok[r, t] = i >= 0
            s = i if i > 0 else 0
            d[r, t, 0] = xy[n, k, t, 0] - xy[n, k, s, 0]
            d[r, t, 1] = xy[n, k, t, 1] - xy[n, k, s, 1]
    return d, ok


def _yaw_from_motion_numpy(xy: np.ndarray, yaw0: np.ndarray, chord: float = YAW_CHORD) -> np.ndarray:
    """:func:`_yaw_from_motion` as numpy alone (the test's reference). Heading along (N, K, T, 2) positions: the direction of the last ``chord`` m of forward
    motion, i.e. from the latest earlier point at least ``chord`` m further back along the
    actor's present heading ``yaw0`` (N,) to this one; ``yaw0`` until the actor has moved that
    far forward (index 0 always).

    Why a chord and not each 0.1 s step: a predicted path jitters by a few centimetres from step
    to step, which for a slow actor (a step of 0.2-0.8 m in stop-and-go traffic) turned into
    heading errors of 10-30 degrees; rotated that much, a truck in the next lane overlapped the
    ego's footprint and every candidate "collided" (NGSIM US-101 scenes, docs/autonomy.md). Progress is
    measured along ``yaw0`` (running maximum), so lateral jitter and backward jitter of a
    standing actor add nothing and it keeps its heading."""
    N, K, T = xy.shape[:3]
    fwd = np.stack([np.cos(yaw0), np.sin(yaw0)], axis=-1)[:, None, None, :]         # (N, 1, 1, 2)
    prog = np.maximum.accumulate(np.sum((xy - xy[:, :, :1]) * fwd, axis=-1), axis=2)  # (N, K, T), >= 0
    rows = N * K
    if rows == 0 or T == 0:
        return np.broadcast_to(yaw0[:, None, None], (N, K, T)).copy()
    # per row, the last index i with prog[i] <= prog[t] - chord (rows made one sorted array)
    span = float(prog.max(initial=0.0)) + chord + 1.0
    offset = (np.arange(rows) * span)[:, None]
    flat = (prog.reshape(rows, T) + offset).ravel()
    i = np.searchsorted(flat, (prog.reshape(rows, T) - chord + offset).ravel(), side="right") - 1
    i = i.reshape(rows, T) - (np.arange(rows) * T)[:, None]
    ok = i >= 0  # moved at least ``chord`` forward since the start
    p = xy.reshape(rows, T, 2)
    d = p - np.take_along_axis(p, np.maximum(i, 0)[..., None], axis=1)
    yaw = np.where(ok, np.arctan2(d[..., 1], d[..., 0]), np.repeat(yaw0, K)[:, None])
    yaw[:, 0] = np.repeat(yaw0, K)
    return yaw.reshape(N, K, T)


class SamplingPlanner:
    """Lane-relative sampling planner (see package docstring). Call :meth:`reset` with the
    scene's lane map before the first :meth:`plan` of an episode."""

    def __init__(self, config: PlannerConfig = PlannerConfig(), params: BicycleParams | None = None):
        self.config = config
        self.params = params
        self.lane_map: LaneMap | None = None
        self._chains, self._chains_of = ChainCache(), None  # corridor geometry of the map _chains_of
        self._forget()

    def reset(self, lane_map: LaneMap) -> None:
        """Start an episode on ``lane_map`` (kept until the next reset) and forget the previous
        plan's target (lane-change and offset hysteresis, offset confirmation), the effective IDM
        headway (``headway_relaxation``) and, planning on occupancy, the previous frame's lane
        leaders."""
        self.lane_map = lane_map
        self._forget()

    def _chain_cache(self, lanes: LaneMap) -> ChainCache:
        """The corridor geometry cache of ``lanes`` (a new one when the map changed)."""
        if self._chains_of is not lanes:
            self._chains, self._chains_of = ChainCache(), lanes
        return self._chains

    def _forget(self) -> None:
        self._prev_target_ids: frozenset[int] = frozenset()  # lane ids of the previous target corridor
        self._prev_offset: float | None = None
        self._confirmed_offset: float | None = None  # offset the previous plan wanted before confirmation
        self._occ_leaders: np.ndarray | None = None  # Autonomy-B: the previous frame's lane leaders
        self._headway: float | None = None  # the IDM's effective headway (headway_relaxation), s

    def plan(self, ego: EgoState, predictions: Predictions | None = None, tracks: Tracks | None = None,
             occupancy=None) -> Plan:
        """The cheapest candidate as a :class:`Plan` (``cost_terms`` = its weighted breakdown).
        ``occupancy``: an :class:`~adv3d_runner.autonomy.interface.OccupancyField` to plan on
        instead of ``predictions`` / ``tracks`` (see module docstring)."""
        return self.plan_with_scores(ego, predictions, tracks, occupancy)[0]

    def plan_with_scores(self, ego: EgoState, predictions: Predictions | None = None,
                         tracks: Tracks | None = None, occupancy=None
                         ) -> tuple[Plan, Candidates | None, ScoreTable | None]:
        lanes = self.lane_map
        if lanes is None:
            raise RuntimeError("SamplingPlanner.reset(lane_map) must be called before planning")
        cfg = self.config
        pc = cfg.proposals
        params = self.params or BicycleParams(wheelbase=ego.wheelbase)
        T, dt = pc.steps, pc.dt
        forecast = forecast_from(predictions, tracks, T, dt, ego.pose[:2], cfg.actor_range)

        lane_id, _, d_lane = lanes.locate(ego.pose) if len(lanes) else (None, 0.0, 0.0)
        by_id = lanes.by_id
        if lane_id is not None:
            half = 0.5 * float(np.max(np.asarray(by_id[lane_id].width, dtype=np.float64)))
            if abs(d_lane) - half > cfg.off_lane_distance:
                lane_id = None
        if lane_id is None:
            return self._stop_plan(ego, params), None, None

        current = by_id[lane_id]
        ahead = max(60.0, ego.speed * pc.horizon + 80.0)
        chain_ids = [lane_id]
        names = [f"lane{lane_id}"]
        for side in ("left", "right"):
            nid = getattr(current, side, None)
            if nid is not None and int(nid) in by_id:
                chain_ids.append(int(nid))
                names.append(f"{side}{int(nid)}")
        cors = [build_corridor(by_id, lid, ego.pose[:2], cfg.corridor_behind, ahead,
                               default_speed_limit=cfg.default_speed_limit, cache=self._chain_cache(lanes))
                for lid in chain_ids]
        if cfg.open_map_border:
            border = lanes.border_ends()
            cors = [replace(c, ends=False) if c.ends and c.lane_ids[-1] in border else c for c in cors]
        corridors = CorridorSet(cors)
        limit_now = float(corridors.limit_at(np.array(0), np.array(cfg.corridor_behind)))
        spec = make_specs(corridors, names, limit_now, pc, current_index=0)
        if occupancy is not None:  # instance-free: the lane leaders the occupancy shows
            forecast, self._occ_leaders = occmodel.occupancy_leaders(occupancy, corridors, ego.pose[:2], ego.length,
                                                                     T, dt, cfg.occupancy, self._occ_leaders)
        cands = rollout_candidates(ego.pose, ego.speed, ego.acceleration, spec, corridors, forecast,
                                   ego.length, ego.width, pc, params, headway=self._headway)
        table = self.score_candidates(cands, corridors, forecast, ego, limit_now, occupancy)
        i = table.best
        # what this plan would have chosen without the confirmation surcharge: a change to that
        # offset is confirmed for the next plan
        raw_oc = table.raw["offset_change"]  # > 0 exactly where the plain |change| is > 0
        plain_oc = costs.offset_change_cost(spec.offset, raw_oc > 0, self._prev_offset)
        base = table.total - cfg.weights.offset_change * (raw_oc - plain_oc)
        w = table.argmin(base)
        self._confirmed_offset = None if spec.emergency[w] else float(spec.offset[w])
        self._prev_target_ids = frozenset(corridors.corridors[int(spec.corridor[i])].lane_ids)
        self._prev_offset = None if spec.emergency[i] else float(spec.offset[i])
        if pc.headway_relaxation > 0.0:
            self._headway = relaxed_headway(self._headway, cands, ego.speed, pc)
        traj = cands.poses[i].copy()
        traj[:, 2] = wrap_angle(traj[:, 2])  # map-frame yaw in [-pi, pi)
        plan = Plan(trajectory=traj, speed=cands.speeds[i].copy(), acceleration=cands.accel[i].copy(),
                    curvature=cands.curvature[i].copy(), dt=dt, cost=float(table.total[i]),
                    cost_terms=table.breakdown(i), label=spec.labels[i])
        return plan, cands, table

    def score_candidates(self, cands: Candidates, corridors: CorridorSet, forecast: ActorForecast, ego: EgoState,
                         limit_now: float, occupancy=None) -> ScoreTable:
        """All named cost terms of every candidate, weighted (see :mod:`.scorer`); with
        ``occupancy`` the collision and buffer terms come from the field (module docstring)."""
        cfg = self.config
        dims = (ego.length, ego.width)
        poses, speeds = cands.poses, cands.speeds
        # actors that come nowhere near any candidate cannot change the interaction terms: drop
        # them before the per-pair work (exact, see costs.near_actors)
        near_clear, near_head = costs.near_actors(poses, speeds, dims, forecast.poses, forecast.dims,
                                                  cfg.buffer + 0.5, cfg.time_headway, cfg.min_gap)
        fc = forecast.subset(near_clear)
        fh = forecast.subset(near_head)
        if occupancy is not None:
            interaction = self._occupancy_terms(occupancy, cands, ego)
        else:
            interaction = None
            dist = costs.clearance(poses, dims, fc.poses, fc.dims, max_distance=cfg.buffer + 0.5)
        travelled = np.concatenate([np.zeros((len(cands), 1)),
                                    np.cumsum(0.5 * (speeds[:, 1:] + speeds[:, :-1]) * cands.dt, axis=1)], axis=1)
        s_start = np.array([float(corridors.project(ci, ego.pose[:2])[0]) for ci in range(len(corridors))])
        dev, excess = costs.road_geometry(poses, travelled, corridors, s_start, dims)
        limits = corridors.limit_at(cands.spec.corridor[:, None], cands.s)
        horizon = cands.dt * (poses.shape[1] - 1)
        # corridor 0 is the current lane; a corridor sharing a lane with the previous plan's
        # target corridor continues that plan (lane ids change along the road in sections)
        same = np.array([bool(self._prev_target_ids & set(corridors.corridors[int(c)].lane_ids))
                         for c in cands.spec.corridor])
        # being rear-ended while keeping the lane is not the ego's fault (as nuPlan's at-fault
        # collisions); changing lanes in front of a faster car is
        if interaction is not None:  # the same order of terms as below (the sum is order-sensitive)
            (k_col, collision), (k_buf, buffer) = interaction
        else:
            exempt = None
            if cfg.exempt_rear_end and len(fc):
                exempt = costs.from_behind(poses, fc.poses) & (cands.spec.corridor == 0)[:, None, None, None]
            if cfg.exempt_overlap_now and len(fc):
                now = np.broadcast_to((dist[0, :, :, 0] <= 1e-9)[None, :, :, None], dist.shape)
                exempt = now if exempt is None else exempt | now
            exempt_col = exempt
            if cfg.contingency_time is not None and len(fc):
                later = costs.avoidable_later(speeds, travelled, cands.dt, cfg.contingency_time, cfg.contingency_decel)
                later = np.broadcast_to(later[:, None, None, :], dist.shape)
                exempt_col = later if exempt is None else exempt | later
            k_col, collision = "collision", costs.collision_cost(dist, fc.probs, exempt_col)
            k_buf, buffer = "buffer", costs.buffer_cost(dist, fc.probs, cfg.buffer, exempt)
        reference = limit_now * horizon
        if cfg.progress_floor is not None:  # relative to the best safe candidate (PDM)
            safe = (collision <= 0.0) & ~cands.spec.emergency
            reference = costs.progress_reference(travelled[:, -1], safe, reference, cfg.progress_floor)
        raw = {
            k_col: collision,
            "drivable_area": costs.drivable_area_cost(excess),
            k_buf: buffer,
            "headway": costs.headway_cost(poses, speeds, dims, fh.poses, fh.dims, fh.probs,
                                          cfg.time_headway, cfg.min_gap),
            "speed_limit": costs.speed_limit_cost(speeds, limits),
            "progress": costs.progress_cost(travelled[:, -1], reference),
            "lane_center": costs.lane_center_cost(dev),
            "lane_change": costs.lane_change_cost(cands.spec.corridor == 0, same),
            "offset_change": costs.offset_change_cost(cands.spec.offset, same, self._prev_offset,
                                                      self._confirmed_offset, cfg.offset_confirm_factor),
            "jerk": costs.jerk_cost(cands.accel, ego.acceleration, cands.dt),
            "lat_accel": costs.lateral_accel_cost(speeds[:, :-1], cands.curvature),
        }
        if cfg.own_lane_floor is not None:  # stopping costs where the own lane lets the ego move
            own = (cands.spec.corridor == 0) & ~cands.spec.emergency
            ref_own = costs.progress_reference(travelled[own, -1], (collision[own] <= 0.0), reference,
                                               cfg.own_lane_floor)
            raw["own_progress"] = costs.progress_cost(travelled[:, -1], ref_own)
        eligible = None
        if cfg.emergency_min_collision is not None and cands.spec.emergency.any():
            others = ~cands.spec.emergency
            if np.any(raw[k_col][others] < cfg.emergency_min_collision):
                eligible = others
        return score(raw, cfg.weights, eligible)

    def _occupancy_terms(self, occupancy, cands: Candidates, ego: EgoState) -> tuple[tuple[str, np.ndarray], ...]:
        """(name, (B,) raw cost) of the occupancy collision and buffer terms (:mod:`.occupancy`)."""
        cfg = self.config
        oc = cfg.occupancy
        steps = occmodel.query_steps(cands.poses.shape[1] - 1, oc.query_every)
        inside, ring = occmodel.footprint_samples(ego.length, ego.width, oc.buffer_gap)
        exempt = (cands.spec.corridor == 0) if cfg.exempt_rear_end else None
        occ = occmodel.candidate_occupancy(occupancy, cands.poses, np.concatenate([inside, ring]), steps, cands.dt,
                                           exempt)
        horizon = cands.dt * (cands.poses.shape[1] - 1)
        hit = occmodel.occupancy_hit(occ, steps * cands.dt, horizon, oc.ramp, oc.ramp_end)
        return (("occupancy_collision", costs.occupancy_collision_cost(hit[..., :len(inside)], steps * cands.dt, horizon)),
                ("occupancy_buffer", costs.occupancy_buffer_cost(hit[..., len(inside):])))

    def _stop_plan(self, ego: EgoState, params: BicycleParams) -> Plan:
        pc = self.config.proposals
        T = pc.steps
        state0 = np.array([ego.pose[0], ego.pose[1], ego.pose[2], ego.speed])
        acc = np.full((1, T), -pc.idm_decel)
        states = rollout(state0, acc, curvature=np.zeros((1, T)), dt=pc.dt, params=params)[0]
        a = np.diff(states[:, 3]) / pc.dt
        traj = states[:, :3].copy()
        traj[:, 2] = wrap_angle(traj[:, 2])
        return Plan(trajectory=traj, speed=states[:, 3], acceleration=a, curvature=np.zeros(T), dt=pc.dt,
                    label="no-lane/stop")
