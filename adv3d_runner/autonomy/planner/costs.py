"""Named cost terms of the sampling planner. Each term maps plain arrays over B candidates to a
(B,) array of non-negative, *unweighted* costs; :mod:`.scorer` weights and sums them. Units are
stated per term so weights read as "cost per unit".

Shared geometry helpers (ego/actor boxes over time, ego-actor clearance, Frenet road geometry)
are here too, so each term can be tested on hand-made arrays.

Time axes: candidate arrays are (B, T + 1) (index 0 = now); actor forecasts (N, K, T + 1, 3)
on the same grid; mode probabilities (N, K).
"""
from __future__ import annotations

import numpy as np

from ...geometry.angles import wrap_angle
from ...geometry.boxes import box_separation
from ...jit import kernel
from ...scene.corridor import CorridorSet, project_on_segments


# ------------------------------------------------------------------ geometry helpers

def poses_to_boxes(poses: np.ndarray, length: float | np.ndarray, width: float | np.ndarray) -> np.ndarray:
    """Footprint boxes (..., 5) from poses (..., 3) and dimensions (broadcasting)."""
    p = np.asarray(poses, dtype=np.float64)
    L = np.broadcast_to(np.asarray(length, dtype=np.float64), p.shape[:-1])
    W = np.broadcast_to(np.asarray(width, dtype=np.float64), p.shape[:-1])
    return np.stack([p[..., 0], p[..., 1], L, W, p[..., 2]], axis=-1)


def clearance(ego_poses: np.ndarray, ego_dims: tuple[float, float], actor_poses: np.ndarray,
              actor_dims: np.ndarray, max_distance: float = 5.0) -> np.ndarray:
    """Footprint clearance between each candidate and each actor mode at each time.

    The clearance is the separating-axis gap (:func:`adv3d_runner.geometry.boxes.box_separation`):
    exact for side-by-side and nose-to-tail boxes, a slight underestimate (conservative) when the
    closest features are two corners; 0 exactly when the footprints overlap or touch.

    Args:
        ego_poses: (B, T, 3). ego_dims: (length, width). actor_poses: (N, K, T, 3).
        actor_dims: (N, 2). max_distance: pairs whose bounding circles are further apart than
            this are not computed exactly (reported as +inf).
    Returns:
        (B, N, K, T) m; 0 where the footprints overlap or touch.
    """
    B, T = ego_poses.shape[:2]
    N, K = actor_poses.shape[:2]
    out = np.full((B, N, K, T), np.inf)
    if N == 0 or B == 0:
        return out
    Ta = min(T, actor_poses.shape[2])
    ap = actor_poses[:, :, :Ta]
    if Ta < T:  # hold the last predicted pose
        ap = np.concatenate([ap, np.repeat(ap[:, :, -1:], T - Ta, axis=2)], axis=2)
    r_e = 0.5 * np.hypot(*ego_dims)
    r_a = 0.5 * np.hypot(actor_dims[:, 0], actor_dims[:, 1])  # (N,)
    cd = np.hypot(ego_poses[:, None, None, :, 0] - ap[None, ..., 0], ego_poses[:, None, None, :, 1] - ap[None, ..., 1])
    thr = r_e + r_a + max_distance  # (N,)
    # the separating-axis gap of the near pairs in one compiled pass (box_separation's float64
    # operations in its order; cos and sin stay numpy's): clearance_numpy is the reference
    ep = np.ascontiguousarray(ego_poses, dtype=np.float64)
    ap = np.ascontiguousarray(ap, dtype=np.float64)
    _near_separation(np.ascontiguousarray(cd), thr, ep, ap, np.cos(ep[..., 2]), np.sin(ep[..., 2]),
                     np.cos(ap[..., 2]), np.sin(ap[..., 2]), float(ego_dims[0]), float(ego_dims[1]),
                     np.ascontiguousarray(actor_dims, dtype=np.float64), out)
    return out


@kernel
def _near_separation(cd, thr, ep, ap, ce, se, ca, sa, Le, We, adims, out):
    """:func:`clearance`'s exact part: for every (b, n, k, t) with ``cd <= thr[n]``,
    ``out[b, n, k, t] = max(box_separation(ego box, actor box), 0)`` (in place)."""
    B, N, K, T = cd.shape
    for b in range(B):
        for n in range(N):
            for k in range(K):
                for t in range(T):
                    if not cd[b, n, k, t] <= thr[n]:
                        continue
                    # _axis_overlaps with a = the ego's box, b = the actor's
                    hla, hwa = 0.5 * _maximum0(Le), 0.5 * _maximum0(We)
                    hlb, hwb = 0.5 * _maximum0(adims[n, 0]), 0.5 * _maximum0(adims[n, 1])
                    dx, dy = ap[n, k, t, 0] - ep[b, t, 0], ap[n, k, t, 1] - ep[b, t, 1]
                    c1, s1 = ce[b, t], se[b, t]
                    c2, s2 = ca[n, k, t], sa[n, k, t]
                    c = abs(c1 * c2 + s1 * s2)
                    s = abs(c1 * s2 - s1 * c2)
                    o1 = hla + hlb * c + hwb * s - abs(dx * c1 + dy * s1)
                    o2 = hwa + hlb * s + hwb * c - abs(-dx * s1 + dy * c1)
                    o3 = hlb + hla * c + hwa * s - abs(dx * c2 + dy * s2)
                    o4 = hwb + hla * s + hwa * c - abs(-dx * s2 + dy * c2)
                    m = _minimum(_minimum(_minimum(o1, o2), o3), o4)
                    gap = -m
                    if not np.isfinite(gap):
                        gap = np.inf
                    out[b, n, k, t] = _maximum0(gap)


@kernel
def _maximum0(x):
    """``np.maximum(x, 0.0)`` of a float (NaN kept, -0.0 kept as numpy keeps it)."""
    return x if (x >= 0.0 or x != x) else 0.0


@kernel
def _minimum(x, y):
    """``np.minimum`` of two floats (NaN propagates)."""
    return x if (x <= y or x != x) else y




def clearance_numpy(ego_poses: np.ndarray, ego_dims: tuple[float, float], actor_poses: np.ndarray,
                    actor_dims: np.ndarray, max_distance: float = 5.0) -> np.ndarray:
    """:func:`clearance` (same arguments and returns) in numpy: the definition its compiled
    pass is tested against."""
    B, T = ego_poses.shape[:2]
    N, K = actor_poses.shape[:2]
    out = np.full((B, N, K, T), np.inf)
    if N == 0 or B == 0:
        return out
    Ta = min(T, actor_poses.shape[2])
    ap = actor_poses[:, :, :Ta]
    if Ta < T:  # hold the last predicted pose
        ap = np.concatenate([ap, np.repeat(ap[:, :, -1:], T - Ta, axis=2)], axis=2)
    r_e = 0.5 * np.hypot(*ego_dims)
    r_a = 0.5 * np.hypot(actor_dims[:, 0], actor_dims[:, 1])  # (N,)
    cd = np.hypot(ego_poses[:, None, None, :, 0] - ap[None, ..., 0], ego_poses[:, None, None, :, 1] - ap[None, ..., 1])
    near = cd <= r_e + r_a[None, :, None, None] + max_distance
    b, n, k, t = np.nonzero(near)
    if len(b):
        eb = poses_to_boxes(ego_poses[b, t], ego_dims[0], ego_dims[1])
        ab = poses_to_boxes(ap[n, k, t], actor_dims[n, 0], actor_dims[n, 1])
        out[b, n, k, t] = np.maximum(box_separation(eb, ab), 0.0)
    return out


def near_actors(ego_poses: np.ndarray, ego_speeds: np.ndarray, ego_dims: tuple[float, float],
                actor_poses: np.ndarray, actor_dims: np.ndarray, max_distance: float,
                time_headway: float = 1.0, min_gap: float = 2.0,
                lateral_margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Which actors can contribute to the interaction terms at all (a cheap, exact pre-filter).

    From the centre distance between every candidate pose and every actor mode at each time:
    ``clear`` (N,) bool, the actor comes within bounding-circle range + ``max_distance`` of some
    candidate (elsewhere :func:`clearance` is +inf, so collision, buffer and the rear-end
    exemption do not see it); ``head`` (N,) bool, it comes closer than the largest desired
    headway gap (+ half the summed lengths, and the half widths + ``lateral_margin`` across)
    (elsewhere :func:`headway_cost` gives it 0, which
    never changes the per-time maximum over actors). ego_poses (B, T, 3), ego_speeds (B, T),
    actor_poses (N, K, T', 3), actor_dims (N, 2)."""
    N = actor_poses.shape[0]
    if N == 0 or ego_poses.shape[0] == 0:
        return np.zeros(N, bool), np.zeros(N, bool)
    cd = np.sqrt(_closest_approach2(np.ascontiguousarray(ego_poses[..., 0]), np.ascontiguousarray(ego_poses[..., 1]),
                                    np.ascontiguousarray(actor_poses[..., 0]),
                                    np.ascontiguousarray(actor_poses[..., 1])))  # (N,) closest approach
    r_e = 0.5 * np.hypot(*ego_dims)
    r_a = 0.5 * np.hypot(actor_dims[:, 0], actor_dims[:, 1])
    clear = cd <= r_e + r_a + max_distance + 1e-6
    desired = min_gap + time_headway * max(float(np.max(ego_speeds)), 0.0)
    # in the path ahead and short of the gap means lon < desired + half lengths and
    # |lat| < half widths + margin, so the centres are closer than the hypotenuse of the two
    head = cd < np.hypot(desired + 0.5 * (ego_dims[0] + actor_dims[:, 0]),
                         0.5 * (ego_dims[1] + actor_dims[:, 1]) + lateral_margin) + 1e-6
    return clear, head


def road_geometry(poses: np.ndarray, travelled: np.ndarray, corridors: CorridorSet, s_start: np.ndarray,
                  ego_dims: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Lane-centre deviation and off-road excess of candidate poses against every corridor.

    The footprint centre is projected onto each corridor; the corners follow from the heading
    relative to the lane (a locally straight lane: exact up to ~L^2 kappa / 8, about 1 cm for a
    5 m car on a 300 m curve).

    Args:
        poses: (B, T, 3). travelled: (B, T) distance driven since now (m), used to seed the
            local projections. s_start: (C,) the ego's arc length on each corridor now.
    Returns:
        centre_dev (B, T): |d| to the nearest lane centre (m);
        excess (B, T): the largest distance of any footprint corner outside the union of the
        corridors' lane strips (m, 0 when fully on the road).
    """
    L, W = ego_dims
    lx = np.array([L / 2, L / 2, -L / 2, -L / 2])
    ly = np.array([-W / 2, W / 2, W / 2, -W / 2])
    B, T = poses.shape[:2]
    p = np.ascontiguousarray(poses, dtype=np.float64).reshape(B * T, -1)
    guess = s_start[:, None] + np.asarray(travelled, np.float64).reshape(1, B * T)  # (C, B T)
    cs = corridors
    dev, exc = _road_geometry(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]),
                              np.ascontiguousarray(p[:, 2]), np.ascontiguousarray(guess), lx, ly,
                              cs._px, cs._py, cs._ux, cs._uy, cs._hd, cs.width, int(cs._P),
                              cs.spacing.astype(np.float64), cs.n_points.astype(np.int64),
                              cs.length.astype(np.float64), cs.ends.astype(np.bool_))
    return dev.reshape(B, T), exc.reshape(B, T)


@kernel
def _road_geometry(x, y, yaw, guess, lx, ly, px, py, ux, uy, hd, width, P, spacing, n_points, length, ends):
    """:func:`road_geometry` of n poses (x, y, yaw (n,); guess (C, n): the arc lengths seeding
    the projection on each corridor) on a :class:`CorridorSet`'s flat arrays: centre deviation
    and road excess, (n,) each.

    Compiled because, as numpy, it ran ~20 calls per corridor on (B, T, 4) arrays every plan.
    The same arithmetic in the same order as that version (``CorridorSet.project_local`` with
    window 3, ``heading_on``, ``road_excess_on``, min over corridors, max over corners), NaN
    propagating like numpy's minimum and maximum."""
    n = len(x)
    C = guess.shape[0]
    dev = np.full(n, np.inf)
    corner = np.full((n, 4), np.inf)
    for ci in range(C):
        last_i = n_points[ci] - 2
        sp = spacing[ci]
        for k in range(n):
            i0 = min(max(np.int64(np.floor(guess[ci, k] / sp)), 0), last_i)
            sc, dc = project_on_segments(x[k], y[k], i0, 3, px, py, ux, uy, ci * P, ci * (P - 1), sp, last_i)
            dev[k] = _nan_min(dev[k], abs(dc))
            ih = min(max(np.int64(np.floor(sc / sp)), 0), last_i)
            rel = yaw[k] - hd[ci * (P - 1) + ih]
            cr, sr = np.cos(rel), np.sin(rel)
            for j in range(4):
                s_k = sc + lx[j] * cr - ly[j] * sr
                d_k = dc + lx[j] * sr + ly[j] * cr
                i = min(max(np.int64(np.floor(s_k / sp)), 0), last_i)
                f = _nan_min(_nan_max(s_k / sp - i, 0.0), 1.0)
                half = 0.5 * ((1 - f) * width[ci, i] + f * width[ci, i + 1])
                lat = _nan_max(abs(d_k) - half, 0.0)
                e = np.hypot(lat, _nan_max(s_k - length[ci], 0.0)) if ends[ci] else lat
                corner[k, j] = _nan_min(corner[k, j], e)
    exc = np.empty(n)
    for k in range(n):
        m = corner[k, 0]
        for j in range(1, 4):
            m = _nan_max(m, corner[k, j])
        exc[k] = m
    return dev, exc


@kernel
def _nan_min(a, b):
    """numpy's ``minimum`` of two floats (NaN if either is)."""
    if np.isnan(a) or np.isnan(b):
        return np.nan
    return a if a <= b else b


@kernel
def _nan_max(a, b):
    """numpy's ``maximum`` of two floats (NaN if either is)."""
    if np.isnan(a) or np.isnan(b):
        return np.nan
    return a if a >= b else b


# ------------------------------------------------------------------ cost terms

def from_behind(ego_poses: np.ndarray, actor_poses: np.ndarray, max_heading_diff: float = np.pi / 4) -> np.ndarray:
    """Whether each actor mode is behind the ego and driving the same way, per candidate and time:
    its centre is behind the ego's centre (in the ego's frame) and its heading within
    ``max_heading_diff`` of the ego's. ego_poses (B, T, 3), actor_poses (N, K, T', 3) ->
    (B, N, K, T) bool. Used to exempt being rear-ended from the collision and buffer terms."""
    B, T = ego_poses.shape[:2]
    ap = actor_poses[:, :, :T]
    if ap.shape[2] < T:
        ap = np.concatenate([ap, np.repeat(ap[:, :, -1:], T - ap.shape[2], axis=2)], axis=2)
    e = ego_poses[:, None, None]
    lon = (ap[None, ..., 0] - e[..., 0]) * np.cos(e[..., 2]) + (ap[None, ..., 1] - e[..., 1]) * np.sin(e[..., 2])
    dh = np.abs(wrap_angle(ap[None, ..., 2] - e[..., 2]))
    return (lon < 0.0) & (dh < max_heading_diff)


def collision_cost(dist: np.ndarray, probs: np.ndarray, exempt: np.ndarray | None = None) -> np.ndarray:
    """Expected collisions: sum over actor modes of probability x [footprints overlap at some
    time], discounted from 1 (now) to 0.5 (horizon end) so later collisions are preferred when
    none can be avoided. dist: (B, N, K, T) from :func:`clearance`; probs (N, K); ``exempt``
    (B, N, K, T) bool marks times when an overlap would not be the ego's fault (being rear-ended
    while keeping its lane, see :func:`from_behind`); a collision is judged at its first
    overlap. Unit: collisions."""
    if dist.shape[1] == 0:
        return np.zeros(dist.shape[0])
    T = dist.shape[-1]
    hit = dist <= 1e-9
    any_hit = hit.any(axis=-1)
    first = np.argmax(hit, axis=-1)
    if exempt is not None:  # a collision that starts as a rear-end stays exempt while they overlap
        any_hit &= ~np.take_along_axis(exempt, first[..., None], axis=-1)[..., 0]
    w = np.where(any_hit, 1.0 - 0.5 * first / max(T - 1, 1), 0.0)
    return np.einsum("bnk,nk->b", w, probs)


def avoidable_later(speeds: np.ndarray, travelled: np.ndarray, dt: float, reaction: float, decel: float) -> np.ndarray:
    """Where a collision could still be avoided by a later plan: (B, T) bool, True at step t
    when the candidate, braking at ``decel`` (m/s^2) from step t - ``reaction`` (s) on, would
    stop before the point it reaches at t: v(t - r)^2 / (2 decel) < s(t) - s(t - r). False for
    t < ``reaction``. speeds, travelled: (B, T) m/s and m driven since now.

    Why (crawls of real traffic, docs/autonomy.md): the collision term counts every predicted mode with its probability,
    and at 1-2 m/s the predictor gives a leader that in fact keeps crawling a 10-20 % mode that
    stops; every candidate that follows the leader then "collides" with that mode seconds ahead,
    and only the stop targets win. Re-planning every 0.1 s sees such a mode coming; a collision
    that is still avoidable ``reaction`` s before it (only below 2 decel reaction m/s) is the
    next plans' business."""
    k = int(round(reaction / dt))
    out = np.zeros(speeds.shape, bool)
    if 0 < k < speeds.shape[1]:
        v = speeds[:, :-k]
        out[:, k:] = v * v / (2.0 * decel) < travelled[:, k:] - travelled[:, :-k]
    return out


def _horizon_weights(T: int, last: float = 0.5) -> np.ndarray:
    """Per-time weights from 1 (now) to ``last`` (horizon end), normalised to mean 1: the far
    future is predicted less well, so violations there count less."""
    w = np.linspace(1.0, last, T) if T > 1 else np.ones(1)
    return w / w.mean()


def buffer_cost(dist: np.ndarray, probs: np.ndarray, buffer: float = 1.0, exempt: np.ndarray | None = None) -> np.ndarray:
    """Clearance below ``buffer`` m, as a fraction of the buffer, averaged over time (weights
    falling from 1 now to 0.5 at the horizon, normalised) and summed over actor modes weighted by
    probability; ``exempt`` as in :func:`collision_cost`. Unit: (buffer fraction) x (fraction
    of horizon)."""
    if dist.shape[1] == 0:
        return np.zeros(dist.shape[0])
    short = np.clip((buffer - dist) / buffer, 0.0, 1.0)
    if exempt is not None:  # judged at the first violation: an actor overtaking from behind
        first = np.argmax(short > 0, axis=-1)
        short = np.where(np.take_along_axis(exempt, first[..., None], axis=-1), 0.0, short)
    w = _horizon_weights(dist.shape[-1])
    return np.einsum("bnkt,t,nk->b", short, w, probs) / dist.shape[-1]


def headway_cost(ego_poses: np.ndarray, ego_speeds: np.ndarray, ego_dims: tuple[float, float],
                 actor_poses: np.ndarray, actor_dims: np.ndarray, probs: np.ndarray,
                 time_headway: float = 1.0, min_gap: float = 2.0, lateral_margin: float = 0.3) -> np.ndarray:
    """Following too closely: for an actor ahead in the ego's path (in the ego's frame at each
    time, ahead and laterally overlapping the ego's width plus margin), the shortfall of the
    bumper gap below ``min_gap + time_headway x speed``, as a fraction of that distance.
    Per time the worst actor counts (its modes weighted by probability); averaged over time with
    weights falling from 1 now to 0.5 at the horizon (normalised, as :func:`buffer_cost`).
    ego_poses (B, T, 3), ego_speeds (B, T), actor_poses (N, K, T, 3). Unit: fraction."""
    B, T = ego_poses.shape[:2]
    if actor_poses.shape[0] == 0:
        return np.zeros(B)
    yaw = ego_poses[..., 2]
    desired = min_gap + time_headway * np.maximum(ego_speeds, 0.0)  # (B, T)
    short = _headway_shortfall(np.ascontiguousarray(ego_poses[..., 0]), np.ascontiguousarray(ego_poses[..., 1]),
                               np.cos(yaw), np.sin(yaw), np.ascontiguousarray(desired),
                               np.ascontiguousarray(actor_poses[..., 0]), np.ascontiguousarray(actor_poses[..., 1]),
                               0.5 * (ego_dims[1] + actor_dims[:, 1]) + lateral_margin,
                               0.5 * (ego_dims[0] + actor_dims[:, 0]))
    per_actor = np.einsum("bnkt,nk->bnt", short, probs)
    return (per_actor.max(axis=1) * _horizon_weights(T)).mean(axis=-1)


def lane_center_cost(centre_dev: np.ndarray) -> np.ndarray:
    """Mean distance (m) of the ego centre from the nearest lane centre line. centre_dev (B, T)."""
    return np.mean(centre_dev, axis=-1)


def drivable_area_cost(excess: np.ndarray) -> np.ndarray:
    """Mean over time of how far (m) the footprint reaches outside the lanes. excess (B, T)."""
    return np.mean(excess, axis=-1)


def speed_limit_cost(speeds: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Mean over time of the speed above the limit (m/s). speeds, limits (B, T)."""
    return np.mean(np.maximum(speeds - limits, 0.0), axis=-1)


def progress_cost(distance: np.ndarray, reference: float) -> np.ndarray:
    """Missing progress: ``1 - distance / reference`` clipped to [0, 1], with ``reference`` the
    distance driving at the speed limit for the whole horizon (m). distance (B,) m. Unit: fraction."""
    return np.clip(1.0 - np.asarray(distance, dtype=np.float64) / max(reference, 1e-6), 0.0, 1.0)


def progress_reference(distance: np.ndarray, safe: np.ndarray, limit_distance: float, floor: float) -> float:
    """The distance that counts as full progress (m), as nuPlan's PDM scorer normalises ego
    progress: the longest ``distance`` (B,) m among the ``safe`` (B,) bool candidates (all of
    them when none is safe), at least ``floor`` m and at most ``limit_distance`` m (driving at
    the speed limit for the horizon). Against the speed limit alone, at crawl speeds stopping
    cost a tenth of a full progress loss and lost to a few units of headway cost (docs/autonomy.md, real traffic)."""
    d = np.asarray(distance, dtype=np.float64)
    pool = d[np.asarray(safe, bool)] if np.any(safe) else d
    best = float(np.max(pool)) if pool.size else 0.0
    return float(min(max(best, floor), limit_distance))


def jerk_cost(accel: np.ndarray, accel_now: float, dt: float) -> np.ndarray:
    """Mean |longitudinal jerk| (m/s^3), including the step from the current acceleration.
    accel (B, T) m/s^2 per step."""
    a = np.concatenate([np.full((accel.shape[0], 1), float(accel_now)), accel], axis=1)
    return np.mean(np.abs(np.diff(a, axis=1)), axis=1) / dt


def lateral_accel_cost(speeds: np.ndarray, curvature: np.ndarray) -> np.ndarray:
    """Mean |lateral acceleration| v^2 kappa (m/s^2). speeds (B, T) at the start of each step,
    curvature (B, T)."""
    return np.mean(np.abs(speeds * speeds * curvature), axis=1)


def lane_change_cost(is_current: np.ndarray, is_committed: np.ndarray) -> np.ndarray:
    """1 for candidates heading to a lane other than the current one, unless a lane change to
    that lane is already in progress (``is_committed``, the previous plan's target): a
    hysteresis that stops dithering between lanes. Both (B,) bool. Unit: lane changes."""
    return np.where(np.asarray(is_current, bool) | np.asarray(is_committed, bool), 0.0, 1.0)


def offset_change_cost(offsets: np.ndarray, same_target: np.ndarray, previous_offset: float | None,
                       confirmed_offset: float | None = None, unconfirmed_factor: float = 0.0) -> np.ndarray:
    """|target lateral offset - the previous plan's| (m) for candidates on the previous plan's
    target lane: hysteresis against flipping between in-lane nudges (weighted below the lane-centre
    term, so a nudge that is no longer needed is still undone). 0 on other lanes (see
    :func:`lane_change_cost`), for the first plan, and for candidates keeping their present
    offset (NaN).

    Confirmation: a change to an offset other than ``confirmed_offset`` (the offset the
    previous plan would have chosen without this surcharge, see
    :class:`~.planner.SamplingPlanner`) costs ``1 + unconfirmed_factor`` times as much, so a
    nudge is only taken once it has been the best choice on two consecutive plans: a one-frame
    blip in the predictions (a fresh, noisy track) does not make the offset go A-B-A."""
    off = np.asarray(offsets, dtype=np.float64)
    if previous_offset is None or not np.isfinite(previous_offset):
        return np.zeros(off.shape)
    change = np.abs(off - previous_offset)
    cost = np.where(np.asarray(same_target, bool) & np.isfinite(change), change, 0.0)
    if unconfirmed_factor > 0.0:
        confirmed = confirmed_offset is not None and np.isfinite(confirmed_offset)
        pending = ~np.isclose(off, confirmed_offset) if confirmed else np.ones(off.shape, bool)
        cost = np.where(pending, cost * (1.0 + unconfirmed_factor), cost)
    return cost


# ------------------------------------------------------------------ occupancy terms (Autonomy-B)
# Inputs come from :mod:`.occupancy`: the ramped occupancy (:func:`.occupancy.occupancy_hit`) at
# sample points on each candidate's footprint or buffer ring at the queried times.

def occupancy_collision_cost(hit: np.ndarray, times: np.ndarray, horizon: float) -> np.ndarray:
    """Collision likelihood from occupancy: per queried time the largest ramped occupancy over
    the footprint samples, discounted from 1 (now) to 0.5 (``horizon``) as :func:`collision_cost`;
    the worst time counts. hit (B, S, P) in [0, 1]; times (S,) s. Unit: collisions."""
    if hit.shape[1] == 0 or hit.shape[2] == 0:
        return np.zeros(hit.shape[0])
    w = 1.0 - 0.5 * np.clip(np.asarray(times, dtype=np.float64) / max(horizon, 1e-9), 0.0, 1.0)
    return np.max(hit.max(axis=2) * w[None], axis=1)


def occupancy_buffer_cost(hit: np.ndarray) -> np.ndarray:
    """Buffer intrusion from occupancy: per queried time the largest ramped occupancy over the
    buffer-ring samples, averaged over time with weights falling from 1 now to 0.5 at the
    horizon (normalised, as :func:`buffer_cost`). hit (B, S, P) in [0, 1]. Unit: (buffer
    occupied) x (fraction of horizon)."""
    if hit.shape[1] == 0 or hit.shape[2] == 0:
        return np.zeros(hit.shape[0])
    return (hit.max(axis=2) * _horizon_weights(hit.shape[1])[None]).mean(axis=1)


@kernel
def _closest_approach2(ego_x: np.ndarray, ego_y: np.ndarray, act_x: np.ndarray, act_y: np.ndarray) -> np.ndarray:
    """Squared closest centre distance (m^2) of each actor to any candidate at the same time:
    ego_x, ego_y (B, T), act_x, act_y (N, K, T') (held at their last pose beyond T') -> (N,).
    Compiled: as numpy it built four (B, N, K, T) temporaries every plan for one minimum."""
    B, T = ego_x.shape
    N, K, Ta = act_x.shape
    out = np.full(N, np.inf)
    for n in range(N):
        best = np.inf
        for k in range(K):
            for t in range(T):
                ta = min(t, Ta - 1)
                ax, ay = act_x[n, k, ta], act_y[n, k, ta]
                for b in range(B):
                    dx = ego_x[b, t] - ax
                    dy = ego_y[b, t] - ay
                    d2 = dx * dx + dy * dy
                    if d2 < best:
                        best = d2
        out[n] = best
    return out


@kernel
def _headway_shortfall(ego_x, ego_y, cos_yaw, sin_yaw, desired, act_x, act_y, lat_band, half_len):
    """:func:`headway_cost`'s shortfall (B, N, K, T), a fraction in [0, 1]: for an actor-mode
    ahead of the candidate (in its frame: lon > 0, |lat| < ``lat_band``), how far the bumper gap
    ``lon - half_len`` falls short of ``desired``, as a fraction of it; 0 elsewhere.

    Args:
        ego_x, ego_y, cos_yaw, sin_yaw, desired: (B, T) candidate positions (m), heading and
            desired gap (m). act_x, act_y: (N, K, T') actor-modes (held beyond T'), m.
        lat_band, half_len: (N,) half summed widths + margin, half summed lengths, m.
    Compiled: as numpy it made a dozen (B, N, K, T) temporaries every plan.
    """
    B, T = ego_x.shape
    N, K, Ta = act_x.shape
    out = np.zeros((B, N, K, T))
    for b in range(B):
        for n in range(N):
            for k in range(K):
                for t in range(T):
                    ta = min(t, Ta - 1)
                    dx = act_x[n, k, ta] - ego_x[b, t]
                    dy = act_y[n, k, ta] - ego_y[b, t]
                    c, s = cos_yaw[b, t], sin_yaw[b, t]
                    lon = c * dx + s * dy
                    lat = -s * dx + c * dy
                    if lon > 0 and abs(lat) < lat_band[n]:
                        want = desired[b, t]
                        out[b, n, k, t] = min(max((want - (lon - half_len[n])) / want, 0.0), 1.0)
    return out
