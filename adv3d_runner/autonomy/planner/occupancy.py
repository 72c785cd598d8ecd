"""Occupancy as the planner's obstacle model (Autonomy-B): what the sampling planner asks an
:class:`~adv3d_runner.autonomy.interface.OccupancyField` and how the answers become the inputs
of the named cost terms (:func:`.costs.occupancy_collision_cost`, :func:`.costs.occupancy_buffer_cost`).

Instance-free: there are no actors, only occupancy and flow at query points.

* **Footprint and buffer samples** (:func:`footprint_samples`): points on the ego's footprint
  (a 3 x 2 grid, spacing below a car's size, so a car overlapping the footprint covers one)
  and on a ring ``buffer_gap`` m outside it, in the ego's own frame. Each candidate's samples
  are moved along its trajectory and queried every ``query_every`` planner steps
  (:func:`candidate_occupancy`), in one batch per frame.
* **Lane leaders** (:func:`occupancy_leaders`): the IDM of the proposals (and the headway term)
  follow the point along each corridor's centre line ahead of the ego where the field first
  calls the lane occupied now (probability >= ``leader_threshold``), moving along the lane at
  the speed of the flow predicted over that occupied stretch: a "free space ends here" marker as
  an :class:`~.proposals.ActorForecast` of one short virtual actor per corridor. A leader
  that continues one of the previous frame's (within ``leader_match`` m of where that one
  should be now) has its speed smoothed (``leader_smoothing``: the weight of the new
  measurement): the flow at the leader is noisy from frame to frame, and through the IDM's
  approach term that noise became acceleration jitter.
* **Occupancy ramp** (:func:`occupancy_hit`): probabilities below the ramp's lower end are the
  model's noise floor and count 0, above its upper end they count 1, linear in between. The
  ramp moves from ``ramp`` now to ``ramp_end`` at the horizon: the shipped model's predictions
  smear out with time (its AP and Soft-IoU fall with the query time, ``docs/occupancy.md``),
  and with a fixed ramp every fast candidate paid for that smear, so the planner dithered
  between target speeds.

Rear-end exemption (as Autonomy-A's ``exempt_rear_end``): for candidates that keep the current
lane, samples behind the ego's centre are not counted (a car closing in from behind is not the
ego's fault).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...scene.corridor import CorridorSet
from .proposals import ActorForecast


@dataclass(frozen=True)
class OccupancyPlanConfig:
    """How the planner queries occupancy (m, s).

    Attributes:
        query_every: planner steps between occupancy queries (5 x 0.1 s = 0.5 s).
        buffer_gap: m, distance of the buffer ring outside the footprint.
        ramp: occupancy probabilities mapped linearly onto [0, 1] between these two, now;
        ramp_end: the same at the horizon (linear in time in between).
        leader_range: m ahead of the ego's front scanned for a lane leader (55 m: the model's
            grid ends 72 m ahead, and near that edge it shows phantom occupancy; Autonomy-A's
            detector sees 60 m ahead); leader_spacing: m.
        leader_threshold: occupancy probability that ends the free lane.
        leader_length, leader_width: m, the virtual leader's footprint.
        leader_length_avg: m of occupied lane beyond the leader's rear over which its speed is
            averaged.
        leader_smoothing: weight of the new speed of a leader that continues one of the
            previous frame's (1 = no smoothing); leader_match: m, how close to its predicted
            position it must be to continue it.
    """

    query_every: int = 5
    buffer_gap: float = 0.5
    ramp: tuple[float, float] = (0.3, 0.7)
    ramp_end: tuple[float, float] = (0.6, 0.9)
    leader_range: float = 55.0
    leader_spacing: float = 1.0
    leader_threshold: float = 0.5
    leader_length: float = 0.5
    leader_width: float = 1.8
    leader_length_avg: float = 4.0
    leader_smoothing: float = 0.3
    leader_match: float = 2.0


def footprint_samples(length: float, width: float, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample points in the vehicle frame (+x forward, origin at the footprint centre).

    Returns:
        inside (6, 2): a 3 x 2 grid on the footprint (0.4 m / 0.3 m in from its edges);
        ring (8, 2): two points on each side of the footprint widened by ``gap`` m.
    """
    hl, hw = 0.5 * float(length), 0.5 * float(width)
    xs = np.array([-(hl - 0.4), 0.0, hl - 0.4])
    ys = np.array([-(hw - 0.3), hw - 0.3])
    inside = np.array([(x, y) for x in xs for y in ys])
    ring = np.array([(hl + gap, -0.5 * hw), (hl + gap, 0.5 * hw), (-(hl + gap), -0.5 * hw), (-(hl + gap), 0.5 * hw),
                     (-0.5 * hl, hw + gap), (0.5 * hl, hw + gap), (-0.5 * hl, -(hw + gap)), (0.5 * hl, -(hw + gap))])
    return inside, ring


def occupancy_hit(occ: np.ndarray, times: np.ndarray | None = None, horizon: float = 5.0,
                  ramp: tuple[float, float] = OccupancyPlanConfig.ramp,
                  ramp_end: tuple[float, float] | None = None) -> np.ndarray:
    """Occupancy probability -> how much it counts, in [0, 1] (see module docstring).

    Args:
        occ: (..., S, P) probabilities at S query times (the second-last axis).
        times: (S,) s; with ``ramp_end`` the ramp moves linearly from ``ramp`` at 0 to
            ``ramp_end`` at ``horizon``. Without them the ramp is ``ramp`` everywhere.
    """
    o = np.asarray(occ, dtype=np.float64)
    if times is None or ramp_end is None:
        lo, hi = ramp
        return np.clip((o - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    f = np.clip(np.asarray(times, dtype=np.float64) / max(horizon, 1e-9), 0.0, 1.0)[:, None]  # (S, 1)
    lo = ramp[0] + (ramp_end[0] - ramp[0]) * f
    hi = ramp[1] + (ramp_end[1] - ramp[1]) * f
    return np.clip((o - lo) / np.maximum(hi - lo, 1e-9), 0.0, 1.0)


def query_steps(T: int, every: int) -> np.ndarray:
    """Planner step indices (S,) queried: 0, every, 2 every, ..., T."""
    return np.unique(np.r_[np.arange(0, T + 1, max(1, int(every))), T])


def candidate_occupancy(field, poses: np.ndarray, local: np.ndarray, steps: np.ndarray, dt: float,
                        exempt_rear: np.ndarray | None = None) -> np.ndarray:
    """Occupancy at vehicle-frame sample points along every candidate.

    Args:
        field: an ``OccupancyField`` of the current frame.
        poses: (B, T + 1, 3) candidate poses (map frame). local: (P, 2) sample points in the
            vehicle frame. steps: (S,) planner steps to query (time = step x dt).
        exempt_rear: (B,) bool, candidates whose samples behind the centre (local x < 0) do
            not count (reported as 0).
    Returns:
        (B, S, P) occupancy probabilities. All candidates at step 0 share one query.
    """
    B = poses.shape[0]
    S, P = len(steps), len(local)
    out = np.zeros((B, S, P))
    if B == 0 or P == 0:
        return out
    pz = poses[:, steps]                                   # (B, S, 3)
    c, s = np.cos(pz[..., 2])[..., None], np.sin(pz[..., 2])[..., None]
    x = pz[..., 0, None] + c * local[:, 0] - s * local[:, 1]   # (B, S, P)
    y = pz[..., 1, None] + s * local[:, 0] + c * local[:, 1]
    t = np.broadcast_to((steps * dt)[None, :, None], x.shape)
    first = steps == 0
    # step 0 is the same pose for every candidate: ask once
    rows = np.ones((B, S), bool)
    rows[1:, first] = False
    occ, _ = field.query(np.stack([x[rows], y[rows]], axis=-1).reshape(-1, 2), t[rows].reshape(-1))
    out[rows] = occ.reshape(-1, P)
    if first.any() and B > 1:
        out[1:, first] = out[0, first]
    if exempt_rear is not None:
        out[np.ix_(np.asarray(exempt_rear, bool), np.arange(S), local[:, 0] < 0)] = 0.0
    return out


def occupancy_leaders(field, corridors: CorridorSet, ego_xy: np.ndarray, ego_length: float, steps: int,
                      dt: float, config: OccupancyPlanConfig = OccupancyPlanConfig(),
                      previous: np.ndarray | None = None, frame_dt: float = 0.1
                      ) -> tuple[ActorForecast, np.ndarray]:
    """One virtual leader per corridor where the field shows an occupied stretch ahead now.

    Along each corridor's centre line, from the ego's front bumper to ``leader_range`` m
    beyond it every ``leader_spacing`` m, the free lane ends where the occupancy at t = 0 first
    reaches ``leader_threshold`` (linearly interpolated between the last free and the first
    occupied sample, so the end does not jump by a whole spacing from frame to frame). The
    leader (``leader_length`` long) starts there and moves along the corridor at the speed of
    the flow predicted over the occupied stretch (the occupancy-weighted mean along the lane of
    the samples up to ``leader_length_avg`` m beyond the end, >= 0: one edge sample alone is
    noisy).

    Args:
        previous: (M, 4) the previous frame's leaders (x, y, heading, speed), or None.
        frame_dt: s since the previous frame.
    Returns:
        ActorForecast with poses (N, 1, steps + 1, 3), N <= len(corridors), probabilities 1
        (``ids`` are the corridor indices), and (N, 4) the leaders' x, y, heading, speed now
        (``previous`` of the next frame).
    """
    C = len(corridors)
    s_ahead = np.arange(0.0, config.leader_range + 1e-9, config.leader_spacing)
    s0 = np.array([float(corridors.project(ci, np.asarray(ego_xy, float))[0]) for ci in range(C)])
    s_all = s0[:, None] + 0.5 * float(ego_length) + s_ahead[None]          # (C, M)
    ci = np.repeat(np.arange(C), len(s_ahead)).reshape(C, -1)
    pts = corridors.pose_at(ci, s_all)                                      # (C, M, 3)
    occ, flow = field.query(pts[..., :2].reshape(-1, 2), np.zeros(pts[..., 0].size))
    occ = occ.reshape(C, -1)
    flow = flow.reshape(C, -1, 2)
    along = flow[..., 0] * np.cos(pts[..., 2]) + flow[..., 1] * np.sin(pts[..., 2])   # (C, M) m/s
    thr = config.leader_threshold
    hit = occ >= thr
    n_avg = max(1, int(round(config.leader_length_avg / config.leader_spacing)) + 1)
    poses, ids, state = [], [], []
    for c in range(C):
        j = np.flatnonzero(hit[c])
        if not len(j):
            continue
        j = int(j[0])
        s_end = s_all[c, j]
        if j > 0:  # where the occupancy crosses the threshold between samples j - 1 and j
            o0, o1 = occ[c, j - 1], occ[c, j]
            s_end = s_all[c, j - 1] + (thr - o0) / max(o1 - o0, 1e-9) * (s_all[c, j] - s_all[c, j - 1])
        blob = slice(j, min(j + n_avg, len(s_ahead)))
        w = occ[c, blob] * hit[c, blob]
        v = max(float(np.sum(w * along[c, blob]) / max(np.sum(w), 1e-9)), 0.0)
        start = corridors.pose_at(np.array(c), np.array(s_end + 0.5 * config.leader_length))
        if previous is not None and len(previous):
            p = np.asarray(previous, dtype=np.float64).reshape(-1, 4)
            px = p[:, 0] + p[:, 3] * frame_dt * np.cos(p[:, 2])
            py = p[:, 1] + p[:, 3] * frame_dt * np.sin(p[:, 2])
            d = np.hypot(px - start[0], py - start[1])
            m = int(np.argmin(d))
            if d[m] <= config.leader_match:
                v = p[m, 3] + config.leader_smoothing * (v - p[m, 3])
        s_t = s_end + 0.5 * config.leader_length + v * dt * np.arange(steps + 1)
        poses.append(corridors.pose_at(np.full(steps + 1, c), s_t))
        ids.append(c)
        state.append([start[0], start[1], start[2], v])
    if not poses:
        return ActorForecast.empty(steps), np.zeros((0, 4))
    n = len(poses)
    return (ActorForecast(np.stack(poses)[:, None], np.tile([config.leader_length, config.leader_width], (n, 1)),
                          np.ones((n, 1)), np.array(ids, np.int64)), np.array(state))
