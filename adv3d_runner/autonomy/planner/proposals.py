"""Candidate trajectories (PDM-Closed style): lane-relative paths x speed profiles, each turned
into a trajectory of the kinematic bicycle by a closed-loop rollout.

A candidate is (corridor, lateral offset, target speed):

* corridor: the ego's current lane, its left and its right neighbour (when they exist), each
  chained through successors (:mod:`adv3d_runner.scene.corridor`);
* lateral offset: metres left of that lane's centre (nudges within the current lane; the
  neighbours are driven on their centre);
* target speed: a fraction of the speed limit; 0 means "come to a stop comfortably".
  One extra *emergency stop* candidate brakes at the maximum deceleration on the current lane.

The reference path moves from the ego's present lateral position and slope to the target
offset with a cubic (Hermite) transition over ``max(min_transition, speed x transition_time x |offset change| / lane width)``
metres (so a lane change re-planned half-way keeps its lateral speed). Every candidate is
then simulated for ``horizon`` s at ``dt`` with all candidates in one vectorised loop:

* steering: pure pursuit on the reference path (look-ahead ``max(min_lookahead, speed x
  lookahead_time)``), curvature clipped by the steering limit and the lateral acceleration
  limit ``max_lat_accel / v^2``;
* speed: the ACC model (the Intelligent Driver Model blended with the constant-acceleration
  heuristic, :func:`_acc_blend`) towards the target speed, following the nearest predicted
  actor ahead in the candidate's corridor, each actor at the expected position of its modes
  inside the corridor's lane strip (:func:`_expected_leaders`; modes with probability >=
  ``min_mode_prob`` count), with an acceleration deadband and jerk limits (not for the
  emergency stop);
* motion: :func:`adv3d_runner.dynamics.bicycle.step` (exact arcs, speed >= 0).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ...dynamics.bicycle import BicycleParams
from ...geometry.angles import wrap_angle
from ...jit import kernel
from ...scene.corridor import CorridorSet, project_on_segments
from .smooth import SmoothWeights, smooth_profile


@dataclass(frozen=True)
class ProposalConfig:
    """Candidate generation parameters (m, s, m/s, m/s^2, m/s^3).

    Attributes:
        horizon: plan length, s; dt: step, s.
        lateral_offsets: offsets (m, left +) tried on the current lane.
        neighbour_offsets: offsets tried on the left/right lanes.
        speed_fractions: target speeds as fractions of the speed limit (0 = stop).
        emergency_stop: add the max-braking candidate.
        transition_time, min_transition: lateral transition length = max(min, v x time).
        lookahead_time, min_lookahead: pure-pursuit look-ahead distance.
        max_lat_accel: curvature limit at speed.
        idm_accel, idm_decel: IDM maximum acceleration / comfortable deceleration.
        idm_gap, idm_headway: IDM jam distance (m) and time headway (s).
        max_decel: hardest braking of any candidate (and of the emergency stop).
        max_jerk: |da/dt| limit of the IDM candidates; max_release_jerk: the limit while
            the acceleration rises from a negative value (releasing the brakes);
            max_brake_jerk: the limit while the IDM asks for harder braking than
            ``idm_decel`` (firm braking builds up faster than comfortable speed changes).
        firm_release: braking harder than ``idm_decel`` is released at ``max_brake_jerk`` (as
            fast as it builds up) instead of ``max_release_jerk``.
        accel_deadband: m/s^2; an IDM candidate keeps its previous step's acceleration while
            the IDM's demand differs from it by less than this (0: off).
        min_mode_prob: predicted modes below this probability are ignored as leaders.
        lane_margin: extra lateral margin when deciding that an actor is in a corridor, m.
        leader_speed_window: s over which a leader's predicted speed is averaged for the IDM
            (0.1 = one step; predicted positions jitter by centimetres per step).
        idm_coolness: c of the ACC model (:func:`_acc_blend`): 0 is the plain IDM; towards 1
            the IDM's braking for a gap that is short but not closing is softened to about
            ``idm_decel`` (a car that cuts in ahead, the short headways of dense traffic).
        leader_modes: how an actor's predicted modes lead the IDM: ``"expected"``, one leader
            per actor at the probability-weighted mean of its in-lane modes
            (:func:`_expected_leaders`); ``"quantile"``, at the ``leader_quantile``
            probability-weighted quantile of those modes (0: the slowest); ``"nearest"``, every
            mode a leader of its own, so the IDM follows the nearest, i.e. slowest, mode, and at
            step 0 (a tie) the first one (the planner before the real-traffic tuning, docs/archive.md).
        leader_quantile: see ``leader_modes``.
        alongside_leads: an actor alongside the ego when the plan starts (in the lane strip,
            its centre ahead of the ego's but the bumper gap <= 0: a car merging in beside the
            ego) makes the IDM brake at ``max_decel`` (True, an earlier planner,
            docs/archive.md); False: it leads only once it is ahead (gap > 0), and until then the
            candidates follow the next actor ahead (the collision and buffer terms still see it).
        accel_targets: m/s^2; extra candidates on the current lane (offset 0) that move their
            acceleration to each of these at the jerk limits and hold it (speed >= 0) instead of
            following the IDM: smooth speed profiles for the scorer to choose when they are safe
            (empty: none, the default; an experiment kept for diagnosis, docs/archive.md).
        headway_relaxation: s; 0 (the default): the IDM always asks for ``idm_headway``.
            Otherwise the planner keeps an effective headway (``SamplingPlanner``): a leader
            found at a shorter headway that is not closing in (a car that cuts in, or the ego
            starting in dense traffic) sets it to that headway (at least ``min_headway``), and
            from there it relaxes back to ``idm_headway`` linearly, the whole way in this many
            seconds (the relaxation of Schakel, Knoop & van Arem 2012's LMRS after lane
            changes). Without it the IDM brakes at once to open a 1 s gap to 1.5 s.
        smooth_follow: add one current-lane candidate whose speed plan is the least-jerk
            profile behind the predicted leaders (:func:`.smooth.smooth_profile`, planned over
            the whole horizon at once instead of the IDM's step-by-step reaction; the default);
            False: none (an earlier planner, docs/archive.md). ``smooth_weights``: its (jerk, acceleration, speed, gap) weights
            (:class:`.smooth.SmoothWeights`); ``smooth_recover``: s over which a gap shorter
            than the IDM's ``idm_gap + idm_headway x v`` is to open. ``smooth_speed_weights``:
            one more such candidate per value, with that speed weight instead of
            ``smooth_weights``' (a profile that keeps closer to the free-road speeds, for the
            scorer to weigh progress against comfort; empty: none). ``smooth_resolution``:
            m/s^2; > 0: such a candidate's first acceleration (the one executed) moves from the
            present acceleration only in whole multiples of it, and is held while its plan
            asks for less than half of one. The profile is continuous in its inputs, so without
            it every change of a detection changed the executed acceleration in its last bits
            and the ego's path with it (the attack's static-hit cache then serves nothing
            after that frame); with it a small change of the inputs mostly changes nothing.
            0: off (an earlier planner, docs/archive.md; 0.1 by default).
            ``smooth_resolution_speed``: m/s; > 0: below this speed the resolution shrinks in
            proportion to the speed (to a tenth of it at most): in crawls the profile asks for
            a few hundredths of m/s^2 and a whole step made it lose to the IDM's candidates.
            0: a fixed resolution.
            ``smooth_cautious``: add one more least-jerk candidate (``smooth-c``) whose leader
            is, at every step, the nearest in-lane mode of any actor, of any probability (the
            modes the collision term counts, not only those of ``min_mode_prob``): when one
            mode of the leader stops, even a 1 % one at the end of the horizon, the collision
            term rejects the ``smooth`` profile behind the expected leader, and only the IDM's
            step-by-step braking was left (crawls of the train recordings, docs/autonomy.md;
            the default). False: none (an earlier planner, docs/archive.md).
        firm_braking: m/s^2; braking demanded harder than this builds up at ``max_brake_jerk``
            and is released as fast (``firm_release``); None: ``idm_decel``.
        stop_jerk: m/s^3; > 0: every candidate but the emergency stop brakes at most
            sqrt(2 stop_jerk v) at speed v, so that a stop ends with the braking eased off at
            that jerk instead of the speed's clamp at 0 ending it within one step; 0: off (an
            earlier planner, docs/archive.md; 4 by default).
        min_headway: s, the shortest headway ``headway_relaxation`` accepts.
        closing_speed: m/s; a leader slower than the ego by more than this is closing in, and
            its short headway is not accepted.
        moveoff_gap: m; > 0 (and < ``idm_gap``): the IDM's jam distance falls towards this
            while the ego is slow and its leader pulls away (:func:`moveoff_jam_gap`), so that
            the ego moves off behind a queue's leader as soon as the leader does instead of
            standing until the gap has grown past ``idm_gap`` (recorded queues stand at 2-3 m
            bumper gaps; the ``headway`` cost accepts 2 m at standstill); 0: off.
            ``moveoff_speed`` (m/s): the ego speed at which the jam distance is ``idm_gap``
            again; ``moveoff_dv`` (m/s): the leader's lead in speed at which the whole drop
            applies.
        moveoff_stand: a fraction in (0, 1): the move-off rule's lower jam distance is at most
            this fraction of the candidate's gap to its leader now (step 0), so that an ego that
            rolled in and stopped closer than ``moveoff_gap`` (a stop from a crawl ends 1.5 m
            behind the leader) moves off as the leader pulls away instead of waiting for the gap
            to grow to ``moveoff_gap``; 0: off (docs/benchmark.md, rolling-in starts).
        moveoff_start_only: True: the move-off rule applies to a candidate only when it holds at
            its step 0 (the ego slower than ``moveoff_speed`` now and its leader faster); False:
            at every step of the rollout, so that a slow follow (an ego slowing behind a slower
            leader) whose rollout later falls below the leader's speed follows closer in its
            later steps, which changes which candidate wins.
    """

    horizon: float = 5.0
    dt: float = 0.1
    lateral_offsets: tuple[float, ...] = (-0.5, 0.0, 0.5)
    neighbour_offsets: tuple[float, ...] = (0.0,)
    speed_fractions: tuple[float, ...] = (0.0, 0.4, 0.7, 0.85, 1.0)
    emergency_stop: bool = True
    transition_time: float = 4.0
    min_transition: float = 15.0
    lookahead_time: float = 1.0
    min_lookahead: float = 6.0
    max_lat_accel: float = 3.0
    idm_accel: float = 1.5
    idm_decel: float = 2.0
    idm_gap: float = 3.0
    idm_headway: float = 1.5
    max_decel: float = 7.0
    max_jerk: float = 1.5
    max_release_jerk: float = 3.0
    max_brake_jerk: float = 4.0
    min_mode_prob: float = 0.1
    lane_margin: float = 0.3
    leader_speed_window: float = 1.5
    idm_coolness: float = 0.9
    firm_release: bool = True
    accel_deadband: float = 0.2
    leader_modes: str = "expected"
    leader_quantile: float = 0.0
    alongside_leads: bool = False
    accel_targets: tuple[float, ...] = ()
    headway_relaxation: float = 0.0
    min_headway: float = 0.8
    closing_speed: float = 0.5
    firm_braking: float | None = None
    smooth_follow: bool = True
    smooth_weights: tuple[float, ...] = (3.0, 3.0, 0.05, 20.0)
    smooth_recover: float = 8.0
    smooth_speed_weights: tuple[float, ...] = ()
    smooth_resolution: float = 0.1
    stop_jerk: float = 4.0
    smooth_resolution_speed: float = 0.0
    smooth_cautious: bool = True
    moveoff_gap: float = 0.0
    moveoff_speed: float = 3.0
    moveoff_dv: float = 1.0
    moveoff_stand: float = 0.0
    moveoff_start_only: bool = False

    def __post_init__(self):
        if self.leader_modes not in ("expected", "quantile", "nearest"):
            raise ValueError(f"leader_modes must be 'expected', 'quantile' or 'nearest', got {self.leader_modes!r}")
        if self.headway_relaxation < 0.0 or not 0.0 < self.min_headway <= self.idm_headway:
            raise ValueError(f"headway_relaxation must be >= 0 s and min_headway in (0, idm_headway], got "
                             f"{self.headway_relaxation!r} and {self.min_headway!r}")
        if self.moveoff_gap < 0.0 or self.moveoff_speed <= 0.0 or self.moveoff_dv <= 0.0:
            raise ValueError(f"moveoff_gap must be >= 0 m and moveoff_speed, moveoff_dv > 0 m/s, got "
                             f"{self.moveoff_gap!r}, {self.moveoff_speed!r}, {self.moveoff_dv!r}")
        if not 0.0 <= self.moveoff_stand < 1.0:
            raise ValueError(f"moveoff_stand must be in [0, 1), got {self.moveoff_stand!r}")
        if self.firm_braking is not None and self.firm_braking <= 0.0:
            raise ValueError(f"firm_braking must be > 0 m/s^2 or None, got {self.firm_braking!r}")

    @property
    def steps(self) -> int:
        return int(round(self.horizon / self.dt))


#: Rules whose switch, at its "off" value, leaves every plan bit for bit as before the rule
#: existed: switch field -> (off value, the rule's fields). While off, the rule's fields are left
#: out of the planner's fingerprint (:func:`fingerprint_fields`), so adding a rule switched off
#: does not invalidate kept runs and caches.
RULES_OFF = {"moveoff_gap": (0.0, ("moveoff_gap", "moveoff_speed", "moveoff_dv", "moveoff_stand",
                                   "moveoff_start_only")),
             "moveoff_stand": (0.0, ("moveoff_stand",)),
             "moveoff_start_only": (False, ("moveoff_start_only",))}


def fingerprint_fields(proposals: dict) -> dict:
    """``dataclasses.asdict`` of a :class:`ProposalConfig` less the fields of every rule of
    :data:`RULES_OFF` that is switched off (what the planner's fingerprint hashes)."""
    out = dict(proposals)
    for switch, (off, names) in RULES_OFF.items():
        if out.get(switch) == off:
            for name in names:
                out.pop(name, None)
    return out


@dataclass
class CandidateSpec:
    """What each candidate aims for: (B,) arrays."""

    corridor: np.ndarray  # int, index into the CorridorSet
    offset: np.ndarray  # m
    target_speed: np.ndarray  # m/s (0 = stop)
    emergency: np.ndarray  # bool
    labels: list[str] = field(default_factory=list)
    accel_target: np.ndarray | None = None  # m/s^2 held instead of the IDM; NaN: the IDM
    smooth: np.ndarray | None = None  # bool: the least-jerk speed plan instead of the IDM (smooth_follow)
    cautious: np.ndarray | None = None  # bool: a smooth candidate behind the nearest modes (smooth_cautious)

    def __len__(self) -> int:
        return len(self.corridor)


@dataclass
class Candidates:
    """Rolled-out candidates.

    Attributes:
        spec: what each candidate aimed for.
        states: (B, T + 1, 4) x, y, yaw, v; index 0 = the ego now.
        accel: (B, T) m/s^2; curvature: (B, T) 1/m (controls of each step).
        s: (B, T + 1) arc length along the candidate's own corridor (projected every 5th step,
            integrated in between); d: (B, T + 1) offset (NaN where not projected).
        leader_gap: (B, T + 1) bumper gap to the IDM leader (m, +inf without leader).
        dt: s.
        leader_speed: (B,) the IDM leader's speed at step 0 (m/s, NaN without leader).
    """

    spec: CandidateSpec
    states: np.ndarray
    accel: np.ndarray
    curvature: np.ndarray
    s: np.ndarray
    d: np.ndarray
    leader_gap: np.ndarray
    dt: float
    leader_speed: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.states)

    @property
    def poses(self) -> np.ndarray:
        return self.states[..., :3]

    @property
    def speeds(self) -> np.ndarray:
        return self.states[..., 3]


@dataclass
class ActorForecast:
    """Predicted actors in the planner's time grid (map frame).

    Attributes:
        poses: (N, K, T + 1, 3) x, y, yaw; index 0 = now.
        dims: (N, 2) length, width, m.
        probs: (N, K) mode probabilities.
        ids: (N,) track ids.
    """

    poses: np.ndarray
    dims: np.ndarray
    probs: np.ndarray
    ids: np.ndarray

    def __len__(self) -> int:
        return len(self.poses)

    def subset(self, keep: np.ndarray) -> "ActorForecast":
        """The actors where ``keep`` (N,) bool is true (self when all are kept)."""
        if keep.all():
            return self
        return ActorForecast(self.poses[keep], self.dims[keep], self.probs[keep], self.ids[keep])

    @classmethod
    def empty(cls, steps: int, modes: int = 1) -> "ActorForecast":
        return cls(np.zeros((0, modes, steps + 1, 3)), np.zeros((0, 2)), np.zeros((0, modes)), np.zeros(0, np.int64))


def make_specs(corridors: CorridorSet, lane_names: list[str], speed_limit: float, config: ProposalConfig,
               current_index: int = 0) -> CandidateSpec:
    """Cartesian product of corridors x offsets x target speeds (+ the fixed-acceleration
    candidates of ``accel_targets`` and the emergency stop)."""
    cor, off, tgt, emg, labels, acc, smooth, cautious = [], [], [], [], [], [], [], []
    for ci in range(len(corridors)):
        offsets = config.lateral_offsets if ci == current_index else config.neighbour_offsets
        for o in offsets:
            for f in config.speed_fractions:
                cor.append(ci)
                off.append(o)
                tgt.append(f * speed_limit)
                emg.append(False)
                acc.append(np.nan)
                labels.append(f"{lane_names[ci]}/d{o:+.1f}/v{f * speed_limit:.1f}")
    for a in config.accel_targets:
        cor.append(current_index)
        off.append(0.0)
        tgt.append(speed_limit)
        emg.append(False)
        acc.append(float(a))
        labels.append(f"{lane_names[current_index]}/d+0.0/a{a:+.1f}")
    if config.smooth_follow:
        suffixes = ["smooth"] + [f"smooth-s{w:g}" for w in config.smooth_speed_weights]
        for suffix in suffixes + (["smooth-c"] if config.smooth_cautious else []):
            if suffix == "smooth-c":
                cautious.append(len(cor))
            cor.append(current_index)
            off.append(0.0)
            tgt.append(speed_limit)
            emg.append(False)
            acc.append(np.nan)
            smooth.append(len(cor) - 1)
            labels.append(f"{lane_names[current_index]}/d+0.0/{suffix}")
    if config.emergency_stop:
        cor.append(current_index)
        off.append(np.nan)  # keep the present lateral position
        tgt.append(0.0)
        emg.append(True)
        acc.append(np.nan)
        labels.append(f"{lane_names[current_index]}/emergency-stop")
    flags = cflags = None
    if smooth:
        flags = np.zeros(len(cor), bool)
        flags[smooth] = True
    if cautious:
        cflags = np.zeros(len(cor), bool)
        cflags[cautious] = True
    return CandidateSpec(np.array(cor, np.int64), np.array(off, float), np.array(tgt, float), np.array(emg, bool), labels,
                         np.array(acc, float), flags, cflags)


def _hermite(u: np.ndarray, d0: np.ndarray, slope0: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """Cubic from (u=0: d0, slope0) to (u=1: d1, slope 0); u in [0, 1]."""
    u2, u3 = u * u, u * u * u
    return (2 * u3 - 3 * u2 + 1) * d0 + (u3 - 2 * u2 + u) * slope0 + (3 * u2 - 2 * u3) * d1


def rollout_candidates(ego_pose: np.ndarray, ego_speed: float, ego_accel: float, spec: CandidateSpec,
                       corridors: CorridorSet, actors: ActorForecast, ego_length: float, ego_width: float,
                       config: ProposalConfig = ProposalConfig(),
                       params: BicycleParams = BicycleParams(), headway: float | None = None) -> Candidates:
    """Simulate every candidate (see module docstring). ``headway``: the IDM's time headway
    (s) for this plan instead of ``config.idm_headway`` (``headway_relaxation``)."""
    B, T, dt = len(spec), config.steps, config.dt
    c = spec.corridor
    pose = np.asarray(ego_pose, dtype=np.float64).reshape(3)
    v0 = max(float(ego_speed), 0.0)

    # ego's Frenet start on each corridor (global projection once)
    s_start = np.zeros(len(corridors))
    d_start = np.zeros(len(corridors))
    for ci in range(len(corridors)):
        s_ci, d_ci = corridors.project(ci, pose[:2])
        s_start[ci], d_start[ci] = float(s_ci), float(d_ci)
    s0, d0 = s_start[c], d_start[c]
    target_d = np.where(np.isnan(spec.offset), d0, spec.offset)
    # transition length proportional to the lateral distance still to go, so re-planning in the
    # middle of a lane change keeps its lateral speed instead of restarting a full-length S-curve
    lane_w = corridors.width_at(c, s0)
    frac = np.minimum(1.0, np.abs(target_d - d0) / np.maximum(lane_w, 1e-6))
    trans_len = np.maximum(config.min_transition, v0 * config.transition_time * frac)
    # start the transition with the ego's present lateral slope (heading relative to the lane):
    # a cubic Hermite from (d0, slope0) to (target, 0), so re-planning does not restart the
    # S-curve with zero slope (which would make every lane change crawl)
    herr = wrap_angle(pose[2] - corridors.pose_at(c, s0)[:, 2])
    slope0 = np.tan(np.clip(herr, -0.5, 0.5)) * trans_len  # dd/du for u = (s - s0) / trans_len
    span = target_d - d0
    slope0 = np.where(np.abs(span) > 1e-6, np.clip(slope0 / np.where(span == 0, 1, span), -1.0, 3.0) * span, 0.0)

    # actors' Frenet coordinates on each corridor, for the IDM leader
    modes: dict | None = {} if spec.cautious is not None and spec.cautious.any() else None
    leader_s, leader_ok, leader_len = _actor_frenet(actors, corridors, spec, target_d, ego_width, config, T, modes)
    has_leaders = leader_s.shape[1] > 0

    # time-major leader arrays (one contiguous (B, M) slab per step), step-independent parts first
    if has_leaders:
        lead_s_t = np.ascontiguousarray(leader_s.transpose(2, 0, 1))
        lead_ok_t = leader_ok.transpose(2, 0, 1)
        lead_s_ok = np.ascontiguousarray(np.where(lead_ok_t, lead_s_t, -np.inf))  # out of the lane: never leads
        lead_back = lead_s_t - (leader_len + 0.5 * ego_length)  # the leader's rear bumper less the ego's half length
        # (T, B, M) leader speeds, as the mean over ``leader_speed_window`` s ahead: predicted
        # positions jitter by centimetres per step, which one-step differences turn into
        # +-0.3 m/s of speed noise that the IDM passes on to the ego's acceleration
        w = max(1, int(round(config.leader_speed_window / dt)))
        ahead_w = np.minimum(np.arange(T) + w, T)
        lead_v = np.maximum((lead_s_t[ahead_w] - lead_s_t[:-1]) / ((ahead_w - np.arange(T)) * dt)[:, None, None], 0.0)
        if config.idm_coolness > 0.0:  # (T, B, M) leader accelerations over the same window, for the CAH
            ahead_v = np.minimum(np.arange(T) + w, T - 1)
            span = np.maximum(ahead_v - np.arange(T), 1) * dt
            lead_a = (lead_v[ahead_v] - lead_v) / span[:, None, None]
        else:
            lead_a = np.zeros_like(lead_v)
    else:
        lead_s_ok = lead_back = np.full((T + 1, B, 0), -np.inf)
        lead_v = lead_a = np.zeros((T, B, 0))
    P = corridors._P
    geometry = (corridors._px, corridors._py, corridors._ux, corridors._uy,
                (c * P).astype(np.int64), (c * (P - 1)).astype(np.int64),
                np.ascontiguousarray(corridors.spacing[c], dtype=np.float64),
                (corridors.n_points[c] - 2).astype(np.int64))
    # the reference path's lateral offset as a function of u (Hermite coefficients per candidate)
    hermite = np.ascontiguousarray(np.stack([d0, slope0, -3 * d0 - 2 * slope0 + 3 * target_d,
                                             2 * d0 + slope0 - 2 * target_d]), dtype=np.float64)
    v_des = np.maximum(spec.target_speed, 0.0)
    up_release = config.max_release_jerk * dt
    limits = np.array([
        config.idm_accel, config.idm_decel, config.idm_gap, config.idm_headway if headway is None else headway,
        config.max_decel,
        config.max_jerk * dt, config.max_brake_jerk * dt, up_release,
        config.accel_deadband, config.idm_coolness, config.lookahead_time, config.min_lookahead,
        config.max_lat_accel, params.max_curvature, params.max_accel, params.max_decel, params.max_speed,
        params.lr, dt,
        1.0 if (config.firm_release and config.max_brake_jerk * dt > up_release) else 0.0,
        # the proposal's own limits are within the vehicle's: the step's clamps would be no-ops
        0.0 if (-params.max_decel <= -config.max_decel and config.idm_accel <= params.max_accel) else 1.0,
        1.0 if config.alongside_leads else 0.0,
        config.idm_decel if config.firm_braking is None else config.firm_braking,
        config.smooth_resolution, config.stop_jerk, config.smooth_resolution_speed,
        config.moveoff_gap, config.moveoff_speed, config.moveoff_dv, config.moveoff_stand,
        1.0 if config.moveoff_start_only else 0.0,
    ], dtype=np.float64)
    cautious = _mode_bounds(spec, target_d, s0, modes, ego_length, T) if modes else {}
    plan = _smooth_plans(spec, s0, v0, float(ego_accel), lead_s_ok, lead_back, config, params, headway, T, cautious)
    states, acc, kap, s_hist, d_hist, gap_hist, lead_v0 = _rollout_kernel(
        pose, v0, float(ego_accel), np.ascontiguousarray(s0, dtype=np.float64), 1.0 / trans_len, hermite,
        v_des, np.ascontiguousarray(spec.emergency, dtype=np.bool_),
        np.full(B, np.nan) if spec.accel_target is None else np.ascontiguousarray(spec.accel_target, dtype=np.float64),
        plan, *geometry,
        lead_s_ok, np.ascontiguousarray(lead_back), np.ascontiguousarray(lead_v), np.ascontiguousarray(lead_a),
        limits, T)
    return Candidates(spec, states, acc, kap, s_hist, d_hist, gap_hist, dt, lead_v0)


def _mode_bounds(spec: CandidateSpec, target_d: np.ndarray, s0: np.ndarray, modes: dict, ego_length: float,
                 T: int) -> dict[int, np.ndarray]:
    """Per ``smooth-c`` candidate b, the (T,) arc length (m, from the ego's s0) it may reach at
    each step: the rear of the nearest actor-mode that is in its lane strip then and was in it and
    ahead at step 0, over every mode of ``modes`` (:func:`_actor_frenet`'s ``modes_out``, any
    probability); +inf where none leads. The same rule as :func:`_smooth_plans` applies to the
    expected leaders."""
    s_all, d_all, half_l, band, prob_ok = (modes[k] for k in ("s", "d", "half_l", "band", "prob_ok"))
    out = {}
    for b in np.flatnonzero(spec.cautious):
        ci = int(spec.corridor[b])
        ok = (np.abs(d_all[ci] - target_d[b]) < band[:, None]) & prob_ok[:, None]  # (M, T + 1)
        back = s_all[ci] - (half_l + 0.5 * ego_length)[:, None]
        ahead = ok[:, 0] & (s_all[ci][:, 0] > s0[b]) & (back[:, 0] > s0[b])  # leads from the start
        lead = np.where(ok[ahead, 1:], back[ahead, 1:], np.inf)
        out[int(b)] = (lead.min(axis=0) if len(lead) else np.full(T, np.inf)) - s0[b]
    return out


def _smooth_plans(spec: CandidateSpec, s0: np.ndarray, v0: float, a0: float, lead_s_ok: np.ndarray,
                  lead_back: np.ndarray, config: ProposalConfig, params: BicycleParams, headway: float | None,
                  T: int, cautious: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """(B, T) accelerations of the ``smooth_follow`` candidates (NaN rows for the others), or a
    (0, T) array when there are none. Their leaders: the actor-modes in the lane strip and ahead
    of the ego at step 0, the nearest one at each step (lead_s_ok, lead_back: (T + 1, B, M), see
    :func:`_rollout_kernel`)."""
    if spec.smooth is None or not spec.smooth.any():
        return np.zeros((0, T))
    plan = np.full((len(spec), T), np.nan)
    base = SmoothWeights(*config.smooth_weights)
    # the smooth candidates in make_specs' order: the base weights, then one per extra speed weight
    variants = [base] + [replace(base, speed=float(w)) for w in config.smooth_speed_weights]
    if config.smooth_cautious:
        variants.append(base)  # smooth-c: the same weights behind the nearest modes
    max_accel = min(config.idm_accel, params.max_accel)
    max_decel = min(config.max_decel, params.max_decel)
    done: list[tuple[np.ndarray, SmoothWeights, float, int]] = []
    for b, weights in zip(np.flatnonzero(spec.smooth), variants):
        if cautious and int(b) in cautious:  # smooth-c: behind every mode (:func:`_mode_bounds`)
            bound = cautious[int(b)]
        else:
            ahead = (lead_s_ok[0, b] > s0[b]) & (lead_back[0, b] > s0[b])  # (M,) leads from the start
            back = np.where(np.isfinite(lead_s_ok[1:, b][:, ahead]), lead_back[1:, b][:, ahead], np.inf)
            bound = (back.min(axis=1) if back.shape[1] else np.full(T, np.inf)) - s0[b]
        # smooth-c behind single-mode actors (Autonomy-B's lane leaders, oracle forecasts) has
        # the smooth candidate's bound: the same problem, solved once
        same = [k for bd, w, v, k in done if w == weights and v == spec.target_speed[b] and np.array_equal(bd, bound)]
        if same:
            plan[b] = plan[same[0]]
            continue
        done.append((bound, weights, float(spec.target_speed[b]), int(b)))
        plan[b] = smooth_profile(v0, a0, float(spec.target_speed[b]), bound, config.idm_gap,
                                 config.idm_headway if headway is None else headway, config.dt,
                                 max_accel, max_decel, config.smooth_recover, config.idm_decel, weights)
    return plan


# indices into the ``limits`` vector of :func:`_rollout_kernel`
(_IDM_ACCEL, _IDM_DECEL, _IDM_GAP, _IDM_HEADWAY, _MAX_DECEL, _JERK_DN, _BRAKE_DN, _UP_RELEASE, _DEADBAND,
 _COOLNESS, _LA_TIME, _LA_MIN, _LAT_LIM, _KAPPA_MAX, _VEH_ACC, _VEH_DEC, _VEH_SPEED, _LR, _DT, _FIRM_RELEASE,
 _CLAMP_VEHICLE, _ALONGSIDE_LEADS, _FIRM_AT, _SMOOTH_RES, _STOP_JERK, _SMOOTH_RES_SPEED,
 _MOVEOFF_GAP, _MOVEOFF_SPEED, _MOVEOFF_DV, _MOVEOFF_STAND, _MOVEOFF_START) = range(31)


@kernel
def _rollout_kernel(pose, v0, a0, s0, inv_trans, hermite, v_des, emergency, accel_target, accel_plan, px, py, ux, uy,
                    base_p, base_u,
                    spacing, last_i, lead_s_ok, lead_back, lead_v, lead_a, limits, T):
    """The closed-loop rollout of every candidate (module docstring), one candidate at a time.

    Compiled (:mod:`adv3d_runner.jit`): the same loop in numpy ran ~100 small array calls per
    step for ~25 candidates, and their overhead was most of the planner's time.

    Args:
        pose: (3,) ego x, y, yaw (m, rad); v0: speed >= 0, m/s; a0: present acceleration, m/s^2.
        s0, inv_trans: (B,) start arc length on the candidate's corridor (m) and 1 / its lateral
            transition length (1/m); hermite: (4, B) the lateral offset's cubic in u, low order
            first; v_des: (B,) target speed (m/s, <= 0.1: stop); emergency: (B,) bool;
            accel_target: (B,) m/s^2 held instead of the IDM's (NaN: the IDM); accel_plan:
            (B', T) m/s^2 of each step instead of the IDM's and the deadband's (B' = B, or 0
            rows: none; NaN: the IDM).
        px, py, ux, uy: the CorridorSet's flattened points and segment unit vectors;
        base_p, base_u, spacing, last_i: (B,) the candidate's corridor: its first point and
            segment index, point spacing (m) and last segment index.
        lead_s_ok: (T + 1, B, M) leader arc lengths, -inf where not in the lane; lead_back:
            (T + 1, B, M) rear bumper less the ego's half length, m; lead_v, lead_a: (T, B, M)
            leader speed (m/s) and acceleration (m/s^2).
        limits: see the ``_IDM_ACCEL`` ... indices; T: steps.
    Returns:
        states (B, T + 1, 4), accel (B, T), curvature (B, T), s (B, T + 1), d (B, T + 1),
        leader_gap (B, T + 1), leader speed at step 0 (B,) (NaN: none).
    """
    B = s0.shape[0]
    M = lead_s_ok.shape[2]
    idm_accel, idm_decel, dt = limits[_IDM_ACCEL], limits[_IDM_DECEL], limits[_DT]
    max_decel, jerk_dn, brake_dn = limits[_MAX_DECEL], limits[_JERK_DN], limits[_BRAKE_DN]
    up_release, up_accel, deadband = limits[_UP_RELEASE], limits[_JERK_DN], limits[_DEADBAND]
    coolness, lr, firm_at = limits[_COOLNESS], limits[_LR], limits[_FIRM_AT]
    sqrt_ab = 2.0 * np.sqrt(idm_accel * idm_decel)
    half_dt2 = 0.5 * dt * dt
    two_pi = 2 * np.pi
    states = np.empty((B, T + 1, 4))
    acc = np.zeros((B, T))
    kap = np.zeros((B, T))
    s_hist = np.empty((B, T + 1))
    d_hist = np.full((B, T + 1), np.nan)
    gap_hist = np.full((B, T + 1), np.inf)
    lead_v0 = np.full(B, np.nan)
    alongside = np.zeros(M, np.bool_)
    for b in range(B):
        x, y, yaw, v = pose[0], pose[1], pose[2], v0
        states[b, 0, 0], states[b, 0, 1], states[b, 0, 2], states[b, 0, 3] = x, y, yaw, v
        s_cur = s0[b]
        a_prev = a0
        stop_target = v_des[b] <= 0.1
        v_des_safe = max(v_des[b], 0.1)
        v_lead = 0.0
        a_lead = 0.0
        moveoff_low = limits[_MOVEOFF_GAP]  # the move-off rule's lower jam distance (set at step 0)
        for k in range(T + 1):
            if k % 5 == 0 or k == T:  # exact projection now and then; in between the arc length driven
                i0 = np.int64(np.floor(s_cur * (1.0 / spacing[b])))
                s_cur, d_cur = project_on_segments(x, y, i0, 2, px, py, ux, uy, base_p[b], base_u[b], spacing[b],
                                                   last_i[b])
                d_hist[b, k] = d_cur
            s_hist[b, k] = s_cur
            # leader: the nearest predicted actor ahead in the candidate's corridor at this time
            gap = np.inf
            j = 0
            for m in range(M):
                if lead_s_ok[k, b, m] > s_cur:
                    g = lead_back[k, b, m] - s_cur
                    if k == 0:
                        alongside[m] = g <= 0.0 and limits[_ALONGSIDE_LEADS] == 0.0
                    if alongside[m]:
                        if g <= 0.0:
                            continue
                        alongside[m] = False  # ahead now: it leads from here on
                    if g < gap:
                        gap, j = g, m
                elif k == 0:
                    alongside[m] = False
            if M > 0:
                gap_hist[b, k] = gap
            if k == T:
                break
            if gap < np.inf:
                v_lead = lead_v[k, b, j]
                a_lead = lead_a[k, b, j]
                if k == 0:
                    lead_v0[b] = v_lead
                    if limits[_MOVEOFF_STAND] > 0.0:
                        moveoff_low = min(moveoff_low, limits[_MOVEOFF_STAND] * gap)
                    if limits[_MOVEOFF_START] > 0.0 and not (v_lead > v and v < limits[_MOVEOFF_SPEED]):
                        moveoff_low = 0.0  # the rule does not hold now: off for this candidate
            elif k == 0 and limits[_MOVEOFF_START] > 0.0:
                moveoff_low = 0.0
            # ---- longitudinal: IDM (ACC model) towards the target speed
            if stop_target:  # stop target: brake comfortably
                free = -idm_decel * min(1.0, v)
            else:
                r = v / v_des_safe
                r *= r
                free = idm_accel * (1.0 - r * r)
            a = max(free, -idm_decel)  # above the target: slow down comfortably
            if gap < np.inf:
                if gap <= 0.0:
                    a = -max_decel
                else:
                    jam = moveoff_jam_gap(limits[_IDM_GAP], v, v_lead, moveoff_low, limits[_MOVEOFF_SPEED],
                                          limits[_MOVEOFF_DV])
                    s_star = jam + max(0.0, v * limits[_IDM_HEADWAY] + v * (v - v_lead) / sqrt_ab)
                    q = s_star / max(gap, 0.1)
                    a = a - idm_accel * (q * q)
                    if coolness > 0.0:
                        a = _acc_blend_one(a, v, v_lead, a_lead, max(gap, 0.1), idm_accel, idm_decel, coolness)
            a = min(max(a, -max_decel), idm_accel)
            if not np.isnan(accel_target[b]):
                a = accel_target[b]
            planned = accel_plan.shape[0] > 0 and not np.isnan(accel_plan[b, k])
            if planned:
                a = min(max(accel_plan[b, k], -max_decel), idm_accel)  # smooth already: no deadband
                if k == 0 and limits[_SMOOTH_RES] > 0.0:
                    # the command moves from the present acceleration in whole steps of the
                    # resolution (held within half a step): see ProposalConfig.smooth_resolution
                    res = limits[_SMOOTH_RES]
                    if limits[_SMOOTH_RES_SPEED] > 0.0:
                        res *= min(1.0, max(v, 0.1 * limits[_SMOOTH_RES_SPEED]) / limits[_SMOOTH_RES_SPEED])
                    a = a_prev + res * np.floor((a - a_prev) / res + 0.5)
            elif deadband > 0.0 and abs(a - a_prev) < deadband:
                # hold the acceleration while the demand stays within the band: the leader's gap
                # and speed jitter by centimetres and tenths of m/s from frame to frame, and every
                # plan passed that on to the executed acceleration at up to max_jerk
                a = a_prev
            # jerk limit; releasing the brakes may be faster (max_release_jerk) so that a plan that
            # braked hard does not keep the ego decelerating for seconds after the reason is gone
            down = brake_dn if (brake_dn != jerk_dn and a < -firm_at) else jerk_dn
            up = up_release if a_prev < 0 else up_accel
            if limits[_FIRM_RELEASE] > 0.0 and a_prev < -firm_at:
                # firm braking is released as fast as it builds up: released at the comfortable
                # rate, one emergency stop kept the ego braking for seconds after the reason was gone
                up = brake_dn
            a = min(max(a, a_prev - down), a_prev + up)
            if limits[_STOP_JERK] > 0.0 and a < 0.0:
                # ease off the brake towards standstill: -sqrt(2 j v) is the deceleration of a
                # stop whose braking falls to zero at jerk j as the speed does (without it the
                # speed's clamp at 0 ended a -2.5 m/s^2 stop within one step: 20 m/s^3)
                a = max(a, -np.sqrt(2.0 * limits[_STOP_JERK] * v))
            if emergency[b]:
                a = -max_decel
            if v <= 1e-6 and a < 0:
                a = 0.0  # standing still: no braking "stored up"
            # ---- lateral: pure pursuit on the reference path
            s_la = s_cur + max(limits[_LA_MIN], v * limits[_LA_TIME])
            u = min(max((s_la - s0[b]) * inv_trans[b], 0.0), 1.0)
            d_ref = ((hermite[3, b] * u + hermite[2, b]) * u + hermite[1, b]) * u + hermite[0, b]
            tx, ty = _path_point(s_la, d_ref, px, py, ux, uy, base_p[b], base_u[b], spacing[b], last_i[b])
            dx, dy = tx - x, ty - y
            kappa = 2.0 * (np.cos(yaw) * dy - np.sin(yaw) * dx) / max(dx * dx + dy * dy, 1e-6)
            k_lim = min(limits[_KAPPA_MAX], limits[_LAT_LIM] / max(v * v, 1e-6))
            kappa = min(max(kappa, -k_lim), k_lim)
            # ---- motion: exact arc of the kinematic bicycle, speed >= 0 (bicycle.step)
            if limits[_CLAMP_VEHICLE] > 0.0:
                a = min(max(a, -limits[_VEH_DEC]), limits[_VEH_ACC])
            v_end = v + a * dt
            if v_end < 0:  # a braking vehicle stops when v reaches 0 and stays there
                t_stop = v / (-a if a < 0 else 1.0)
                s_step = max(0.5 * v * t_stop, 0.0)
            else:
                s_step = max(v * dt + a * half_dt2, 0.0)
            direction = yaw if lr == 0.0 else yaw + np.arcsin(min(max(kappa * lr, -1.0), 1.0))
            dth = kappa * s_step
            # s sin(dth / 2) / (dth / 2), as numpy.sinc computes it (exact and finite at dth = 0)
            xs = dth / two_pi
            ys = np.pi * (1.0e-20 if xs == 0 else xs)
            chord = s_step * (np.sin(ys) / ys)
            mid = direction + 0.5 * dth
            x = x + chord * np.cos(mid)
            y = y + chord * np.sin(mid)
            yaw = yaw + dth
            v1 = min(max(v_end, 0.0), limits[_VEH_SPEED])
            states[b, k + 1, 0], states[b, k + 1, 1], states[b, k + 1, 2], states[b, k + 1, 3] = x, y, yaw, v1
            # the acceleration actually applied (speed clamped at 0 when braking to a stop)
            a_applied = (v1 - v) / dt
            acc[b, k] = a_applied
            kap[b, k] = kappa
            a_prev = a_applied
            s_cur = s_cur + 0.5 * (v + v1) * dt  # arc length driven (next guess)
            v = v1
    return states, acc, kap, s_hist, d_hist, gap_hist, lead_v0


@kernel
def _path_point(s, d, px, py, ux, uy, base_p, base_u, spacing, last_i):
    """:meth:`CorridorSet.pose_at` (position only) of (s, d) on one corridor: (x, y), m."""
    fi = min(max(np.floor(s * (1.0 / spacing)), 0.0), np.float64(last_i))
    i = np.int64(fi)
    ku, kp = base_u + i, base_p + i
    t = s - fi * spacing
    return px[kp] + t * ux[ku] - d * uy[ku], py[kp] + t * uy[ku] + d * ux[ku]


def _actor_frenet(actors: ActorForecast, corridors: CorridorSet, spec: CandidateSpec, target_d: np.ndarray,
                  ego_width: float, config: ProposalConfig, T: int, modes_out: dict | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per candidate, the actor-mode arc lengths on its corridor over time and whether the
    actor-mode is inside the candidate's lane strip (around its target offset), for the M of the
    N * K actor-modes that are ever inside some candidate's strip.

    ``modes_out``: a dict that receives every actor-mode's projection before the leaders are
    chosen: ``s``, ``d`` (C, N * K, T + 1) on each corridor (d = inf where not projected),
    ``half_l``, ``band`` (N * K,) and ``prob_ok`` (N * K,) bool. With it,
    modes below ``min_mode_prob`` are projected too (``prob_ok`` marks every mode of p > 0);
    the leaders returned are the same.

    Returns:
        s (B, M, T + 1), ok (B, M, T + 1) bool, half_length (M,).
    """
    B = len(spec)
    N = len(actors)
    if N == 0:
        return np.zeros((B, 0, T + 1)), np.zeros((B, 0, T + 1), bool), np.zeros(0)
    K = actors.poses.shape[1]
    xy = actors.poses[:, :, :T + 1, :2]
    M = N * K
    # modes too unlikely to lead are not projected at all (the smooth-c candidates' leaders are
    # every mode the collision term sees: all of them with ``modes_out``)
    relevant = ((actors.probs > 0.0) if modes_out is not None else (actors.probs >= config.min_mode_prob)).reshape(M)
    s_all = np.zeros((len(corridors), M, T + 1))
    d_all = np.full((len(corridors), M, T + 1), np.inf)
    xy = xy.reshape(M, T + 1, 2)[relevant]
    # global projection every 5th step, local projection of every step around the interpolation
    coarse, left, right, w = _coarse_steps(T)
    half_w = np.repeat(0.5 * actors.dims[:, 1], K)
    rel_idx = np.flatnonzero(relevant)
    # A mode whose every step stays clearly outside all of a corridor's lane bands can never lead
    # there, so its per-step projection on that corridor is skipped. From below, |d| at a step
    # is |d| interpolated between the coarse steps, less the step's distance from the straight
    # chord between them, less a margin for the corridor bending under the chord.
    # (compiled passes with the numpy version's float64 operations in its order:
    # _actor_frenet_numpy is the tests' reference)
    off_chord, chord2 = _chord_gaps(np.ascontiguousarray(xy, dtype=np.float64), coarse[left], coarse[right], w)
    band = 0.5 * ego_width + half_w[relevant] + config.lane_margin  # (M_rel,)
    for ci in range(len(corridors)):
        on_c = spec.corridor == ci
        if not on_c.any():
            continue
        s_c, d_c = corridors.project_near(ci, xy[:, coarse])
        reach = float(np.max(np.abs(target_d[on_c])))
        k_max = _max_abs_step(corridors.heading[ci], int(corridors.n_points[ci]) - 1) / corridors.spacing[ci]
        near, guess = _near_modes(np.ascontiguousarray(d_c), np.ascontiguousarray(s_c), left, right, w, off_chord,
                                  chord2, float(k_max), band + reach)
        if len(near) == 0:
            continue
        s_ci, d_ci = corridors.project_local(np.full(guess.shape, ci), xy[near], guess, window=2)
        s_all[ci, rel_idx[near]] = s_ci
        d_all[ci, rel_idx[near]] = d_ci
    half_l = np.repeat(0.5 * actors.dims[:, 0], K)
    prob_ok = (actors.probs.reshape(M) >= config.min_mode_prob)
    # candidates sharing a corridor and a target offset share their leaders: decide once per
    # (corridor, offset) group, keep only the actor-modes that are ever in some group's lane
    groups, inv = _groups(spec.corridor, target_d)
    gc = groups[:, 0].astype(np.int64)
    # an actor is in the candidate's lane when its footprint overlaps the ego's lateral band
    band_m = 0.5 * ego_width + half_w + config.lane_margin  # (M,)
    if modes_out is not None:
        modes_out.update(s=s_all, d=d_all, half_l=half_l, band=band_m, prob_ok=actors.probs.reshape(M) > 0.0)
    if config.leader_modes == "expected" and K > 1:
        # the lane test and _expected_leaders (quantile None) in one compiled pass
        s_g, ok_g = _lane_expected_leaders(d_all, s_all, gc, np.ascontiguousarray(groups[:, 1]), band_m, prob_ok,
                                           np.ascontiguousarray(actors.probs, dtype=np.float64),
                                           float(config.min_mode_prob))
        used = ok_g.any(axis=(0, 2))
        return s_g[:, used][inv], ok_g[:, used][inv], (0.5 * actors.dims[:, 0])[used]
    lat = np.abs(d_all[gc] - groups[:, 1][:, None, None])  # (G, M, T+1)
    ok = (lat < band_m[None, :, None]) & prob_ok[None, :, None]
    if config.leader_modes != "nearest" and K > 1:
        q = None if config.leader_modes == "expected" else config.leader_quantile
        s_g, ok_g = _expected_leaders(s_all[gc], ok, actors.probs, config.min_mode_prob, q)
        used = ok_g.any(axis=(0, 2))
        return s_g[:, used][inv], ok_g[:, used][inv], (0.5 * actors.dims[:, 0])[used]
    used = ok.any(axis=(0, 2))
    s = s_all[:, used][gc[inv]]  # (B, M_used, T+1)
    return s, ok[:, used][inv], half_l[used]


def _actor_frenet_numpy(actors: ActorForecast, corridors: CorridorSet, spec: CandidateSpec, target_d: np.ndarray,
                        ego_width: float, config: ProposalConfig, T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_actor_frenet` (same arguments and returns) in numpy: the definition its compiled
    passes are tested against."""
    B = len(spec)
    N = len(actors)
    if N == 0:
        return np.zeros((B, 0, T + 1)), np.zeros((B, 0, T + 1), bool), np.zeros(0)
    K = actors.poses.shape[1]
    xy = actors.poses[:, :, :T + 1, :2]
    M = N * K
    # modes too unlikely to lead are not projected at all
    relevant = (actors.probs >= config.min_mode_prob).reshape(M)
    s_all = np.zeros((len(corridors), M, T + 1))
    d_all = np.full((len(corridors), M, T + 1), np.inf)
    xy = xy.reshape(M, T + 1, 2)[relevant]
    # global projection every 5th step, local projection of every step around the interpolation
    coarse, left, right, w = _coarse_steps(T)
    half_w = np.repeat(0.5 * actors.dims[:, 1], K)
    rel_idx = np.flatnonzero(relevant)
    # A mode whose every step stays clearly outside all of a corridor's lane bands can never lead
    # there, so its per-step projection on that corridor is skipped. From below, |d| at a step
    # is |d| interpolated between the coarse steps, less the step's distance from the straight
    # chord between them, less a margin for the corridor bending under the chord.
    wl = w[None, :, None]
    p_l, p_r = xy[:, coarse[left]], xy[:, coarse[right]]
    off_chord = np.linalg.norm(xy - (p_l * (1 - wl) + p_r * wl), axis=-1)  # (M_rel, T+1)
    chord2 = np.sum((p_r - p_l) ** 2, axis=-1)
    band = 0.5 * ego_width + half_w[relevant] + config.lane_margin  # (M_rel,)
    for ci in range(len(corridors)):
        on_c = spec.corridor == ci
        if not on_c.any():
            continue
        s_c, d_c = corridors.project_near(ci, xy[:, coarse])
        reach = float(np.max(np.abs(target_d[on_c])))
        k_max = float(np.max(np.abs(np.diff(corridors.heading[ci, :int(corridors.n_points[ci]) - 1])),
                             initial=0.0)) / corridors.spacing[ci]
        d_lerp = np.abs(d_c[..., left] * (1 - w) + d_c[..., right] * w)
        low = d_lerp - off_chord - (0.2 + 0.5 * chord2 * k_max + 0.02 * d_lerp)
        near = np.flatnonzero((low < (band + reach)[:, None]).any(axis=1))
        if len(near) == 0:
            continue
        guess = s_c[near][..., left] * (1 - w) + s_c[near][..., right] * w
        s_ci, d_ci = corridors.project_local(np.full(guess.shape, ci), xy[near], guess, window=2)
        s_all[ci, rel_idx[near]] = s_ci
        d_all[ci, rel_idx[near]] = d_ci
    half_l = np.repeat(0.5 * actors.dims[:, 0], K)
    prob_ok = (actors.probs.reshape(M) >= config.min_mode_prob)
    # candidates sharing a corridor and a target offset share their leaders: decide once per
    # (corridor, offset) group, keep only the actor-modes that are ever in some group's lane
    groups, inv = _groups(spec.corridor, target_d)
    gc = groups[:, 0].astype(np.int64)
    # an actor is in the candidate's lane when its footprint overlaps the ego's lateral band
    lat = np.abs(d_all[gc] - groups[:, 1][:, None, None])  # (G, M, T+1)
    ok = (lat < (0.5 * ego_width + half_w[None, :, None] + config.lane_margin)) & prob_ok[None, :, None]
    if config.leader_modes != "nearest" and K > 1:
        q = None if config.leader_modes == "expected" else config.leader_quantile
        s_g, ok_g = _expected_leaders(s_all[gc], ok, actors.probs, config.min_mode_prob, q)
        used = ok_g.any(axis=(0, 2))
        return s_g[:, used][inv], ok_g[:, used][inv], (0.5 * actors.dims[:, 0])[used]
    used = ok.any(axis=(0, 2))
    s = s_all[:, used][gc[inv]]  # (B, M_used, T+1)
    return s, ok[:, used][inv], half_l[used]


@kernel
def _chord_gaps(xy: np.ndarray, cl: np.ndarray, cr: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_actor_frenet`'s chord geometry: xy (R, T + 1, 2), each step's coarse steps left
    and right ``cl``, ``cr`` (T + 1,) and weight ``w`` -> the step's distance from the chord
    between them (R, T + 1) and the chord's squared length (R, T + 1)."""
    R, T1 = xy.shape[0], xy.shape[1]
    off = np.empty((R, T1))
    ch2 = np.empty((R, T1))
    for r in range(R):
        for t in range(T1):
            a, b, wt = cl[t], cr[t], w[t]
            om = 1 - wt
            lx, ly, rx, ry = xy[r, a, 0], xy[r, a, 1], xy[r, b, 0], xy[r, b, 1]
            ex = xy[r, t, 0] - (lx * om + rx * wt)
            ey = xy[r, t, 1] - (ly * om + ry * wt)
            off[r, t] = np.sqrt(ex * ex + ey * ey)
            dx, dy = rx - lx, ry - ly
            ch2[r, t] = dx * dx + dy * dy
    return off, ch2


@kernel
def _max_abs_step(h: np.ndarray, n: int) -> float:
    """``np.max(np.abs(np.diff(h[:n])), initial=0.0)`` (NaN propagates as numpy's does)."""
    m = 0.0
    for i in range(n - 1):
        v = abs(h[i + 1] - h[i])
        if v > m or v != v:
            m = v
            if v != v:
                break
    return m


@kernel
def _near_modes(d_c: np.ndarray, s_c: np.ndarray, left: np.ndarray, right: np.ndarray, w: np.ndarray,
                off_chord: np.ndarray, chord2: np.ndarray, k_max: float, lim: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_actor_frenet`'s test of which modes can come within ``lim`` (R,) of a corridor
    (their rows, int64) and, for those, the arc lengths interpolated between the coarse
    projections (n_near, T + 1)."""
    R, T1 = d_c.shape[0], len(w)
    rows = np.empty(R, np.int64)
    n = 0
    for r in range(R):
        for t in range(T1):
            a, b, wt = left[t], right[t], w[t]
            d_lerp = abs(d_c[r, a] * (1 - wt) + d_c[r, b] * wt)
            low = d_lerp - off_chord[r, t] - (0.2 + 0.5 * chord2[r, t] * k_max + 0.02 * d_lerp)
            if low < lim[r]:
                rows[n] = r
                n += 1
                break
    guess = np.empty((n, T1))
    for i in range(n):
        r = rows[i]
        for t in range(T1):
            wt = w[t]
            guess[i, t] = s_c[r, left[t]] * (1 - wt) + s_c[r, right[t]] * wt
    return rows[:n], guess


@kernel
def _lane_expected_leaders(d_all: np.ndarray, s_all: np.ndarray, gc: np.ndarray, gd: np.ndarray, band: np.ndarray,
                           prob_ok: np.ndarray, probs: np.ndarray, min_prob: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_actor_frenet`'s lane test (actor-mode m in group g's lane at step t: ``|d - gd[g]| <
    band[m]`` on the group's corridor ``gc[g]``, and ``prob_ok[m]``) followed by
    :func:`_expected_leaders` without a quantile: (G, N, T + 1) s and lead. The sums over a
    actor's modes run in mode order, as numpy's reduction over that axis does."""
    G = len(gc)
    N, K = probs.shape
    T1 = d_all.shape[2]
    s_out = np.empty((G, N, T1))
    lead = np.empty((G, N, T1), np.bool_)
    thr = min_prob - 1e-12
    for g in range(G):
        c, off = gc[g], gd[g]
        for a in range(N):
            for t in range(T1):
                mass = 0.0
                acc = 0.0
                for k in range(K):
                    m = a * K + k
                    wk = probs[a, k] if (abs(d_all[c, m, t] - off) < band[m]) and prob_ok[m] else 0.0
                    p = wk * s_all[c, m, t]
                    if k == 0:
                        mass = wk
                        acc = p
                    else:
                        mass = mass + wk
                        acc = acc + p
                ld = mass >= thr
                lead[g, a, t] = ld
                if ld:
                    den = mass if (mass >= 1e-12 or mass != mass) else 1e-12
                    s_out[g, a, t] = acc / den
                else:
                    s_out[g, a, t] = 0.0
    return s_out, lead




_COARSE: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}


def _coarse_steps(T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The steps of a T-step horizon projected globally (every 5th and the last), and per step
    (T + 1) the coarse steps left and right of it and its weight between them; made once per T."""
    if T not in _COARSE:
        coarse = np.unique(np.r_[np.arange(0, T + 1, 5), T])
        right = np.clip(np.searchsorted(coarse, np.arange(T + 1)), 1, len(coarse) - 1)
        left = right - 1
        w = (np.arange(T + 1) - coarse[left]) / np.maximum(coarse[right] - coarse[left], 1)
        for a in (coarse, left, right, w):
            a.flags.writeable = False
        _COARSE[T] = (coarse, left, right, w)
    return _COARSE[T]


def _groups(corridor: np.ndarray, target_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique`` of the rows (corridor, target offset), (G, 2) sorted, and each candidate's
    row index (B,), for the ~25 candidates of a plan without ``unique(axis=0)``'s structured
    sort."""
    keys = list(zip(corridor.astype(np.float64).tolist(), np.asarray(target_d, np.float64).tolist()))
    rows = sorted(set(keys))
    where = {k: i for i, k in enumerate(rows)}
    return np.array(rows, np.float64).reshape(-1, 2), np.array([where[k] for k in keys], np.int64)


@kernel
def moveoff_jam_gap(jam_gap: float, v: float, v_lead: float, moveoff_gap: float, moveoff_speed: float,
                    moveoff_dv: float) -> float:
    """The IDM's jam distance s0 (m) for an ego at ``v`` behind a leader at ``v_lead`` (m/s).

    ``jam_gap`` (the IDM's s0), except while the ego is slower than ``moveoff_speed`` and the
    leader faster than the ego: then it falls linearly towards ``moveoff_gap``, by the fraction
    (1 - v / moveoff_speed) x min(1, (v_lead - v) / moveoff_dv). At standstill the IDM's
    acceleration is a_max (1 - (s0 / gap)^2), which is not positive while the gap is below s0:
    with s0 = 3 m an ego standing 2.5 m behind a leader that rolls off waits until the leader has
    opened the gap past 3 m (3.2 m with the acceleration deadband). A leader that stands or is
    slower than the ego (an approach, a stop) keeps ``jam_gap``, so where the ego stops is
    unchanged. The value is continuous in ``v`` and ``v_lead``. ``moveoff_gap`` <= 0 or >=
    ``jam_gap``: off (``jam_gap``).
    """
    if moveoff_gap <= 0.0 or moveoff_gap >= jam_gap or v_lead <= v or v >= moveoff_speed:
        return jam_gap
    w = (1.0 - v / moveoff_speed) * min(1.0, (v_lead - v) / moveoff_dv)
    return jam_gap - (jam_gap - moveoff_gap) * w


@kernel
def _acc_blend(a_idm: np.ndarray, v: np.ndarray, v_lead: np.ndarray, a_lead: np.ndarray, gap: np.ndarray,
               a_max: float, b: float, coolness: float) -> np.ndarray:
    """The ACC model's acceleration (Kesting, Treiber & Helbing 2010, "Enhanced intelligent driver
    model to access the impact of driving strategies on traffic capacity", Phil. Trans. R. Soc. A
    368, Eqs. 2.3-2.5): the IDM blended with the constant-acceleration heuristic (CAH).

    The IDM brakes hard whenever the gap is below its desired gap, even when the leader is not
    slower (a car that cuts in, or the short headways of dense real traffic); the CAH (both cars
    keep their accelerations) says such a situation is not critical, and the blend then brakes at
    most about ``b``. Where the CAH is itself negative (closing in on a slower or braking
    leader), the blend follows it less ``b``: as firm as the situation needs.

    Args:
        a_idm, v, v_lead, a_lead, gap: (B,) IDM acceleration (m/s^2), ego and leader speed (m/s),
            leader acceleration (m/s^2), bumper gap (m, > 0).
        a_max: the ego's maximum acceleration; b: comfortable deceleration, m/s^2;
        coolness: c in [0, 1] (0.99 in the paper; 0 is the IDM).
    Returns:
        (B,) m/s^2.
    """
    out = np.empty_like(a_idm)
    for i in range(len(a_idm)):
        out[i] = _acc_blend_one(a_idm[i], v[i], v_lead[i], a_lead[i], gap[i], a_max, b, coolness)
    return out


@kernel
def _acc_blend_one(a_idm, v, v_lead, a_lead, gap, a_max, b, coolness):
    """:func:`_acc_blend` of one candidate (scalars)."""
    a_l = min(a_lead, a_max)
    closing = v - v_lead
    if v_lead * closing <= -2.0 * gap * a_l:  # the leader stops before the gap closes
        a_cah = v * v * a_l / max(v_lead * v_lead - 2.0 * gap * a_l, 1e-6)
    else:
        closing_pos = max(closing, 0.0)
        a_cah = a_l - closing_pos * closing_pos / (2.0 * gap)
    if a_idm >= a_cah:
        return a_idm
    return (1.0 - coolness) * a_idm + coolness * (a_cah + b * np.tanh((a_idm - a_cah) / b))


def _expected_leaders(s: np.ndarray, ok: np.ndarray, probs: np.ndarray, min_prob: float,
                      quantile: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One leader per actor: its modes merged into their expected arc length.

    Why: following the nearest of an actor's modes makes the IDM follow its slowest mode (a
    mode of probability 0.2 that is 20 % slower than the likely one), and at the first step,
    where every mode starts at the tracked pose, the tie picks the first mode instead: the
    leader's speed jumps between step 0 and step 1 of every plan, so each plan asks for a hard
    brake one step ahead that the next plan takes back (NGSIM US-101 train recordings, issue
    17). The interaction cost terms still see every mode with its probability.

    Args:
        s: (G, N * K, T + 1) arc lengths of the actor-modes on each group's corridor, m.
        ok: (G, N * K, T + 1) bool, the actor-mode is inside the group's lane strip.
        probs: (N, K) mode probabilities (normalised per actor).
        min_prob: an actor leads at a step when its in-lane modes hold at least this much
            probability.
    Returns:
        s (G, N, T + 1): the probability-weighted mean of the in-lane modes' arc lengths;
        ok (G, N, T + 1) bool.
    """
    G, M, T1 = s.shape
    N, K = probs.shape
    w = np.where(ok.reshape(G, N, K, T1), probs[None, :, :, None], 0.0)
    mass = w.sum(axis=2)  # (G, N, T+1)
    lead = mass >= min_prob - 1e-12
    s4 = s.reshape(G, N, K, T1)
    if quantile is None:
        s_lead = (w * s4).sum(axis=2) / np.maximum(mass, 1e-12)
    else:  # the probability-weighted quantile of the in-lane modes' arc lengths
        order = np.argsort(np.where(w > 0, s4, np.inf), axis=2, kind="stable")
        w_sorted = np.take_along_axis(w, order, axis=2)
        cum = np.cumsum(w_sorted, axis=2) / np.maximum(mass, 1e-12)[:, :, None]
        first = np.argmax((cum >= quantile - 1e-12) & (w_sorted > 0), axis=2)[:, :, None]
        s_lead = np.take_along_axis(np.take_along_axis(s4, order, axis=2), first, axis=2)[:, :, 0]
    return np.where(lead, s_lead, 0.0), lead
