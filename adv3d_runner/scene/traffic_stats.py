"""Traffic statistics of scenes, to compare generated traffic with recorded traffic (docs/scenes.md).

Every vehicle of a scene counts, the ego included (in a recorded scene it is a recorded car),
over its recorded frames only (``synthetic`` frames, the ``--extend``-ed tail of a short
recording, are left out). Three samples per scene (:func:`traffic_samples`):

* **speed** (m/s): every vehicle in every frame.
* **time headway** (s): per vehicle and frame with speed > ``MIN_SPEED``, the bumper-to-bumper
  gap to the nearest vehicle ahead in its lane (in the follower's frame: ahead, lateral offset
  below ``LANE_HALF_WIDTH``), divided by its speed; only gaps up to ``MAX_GAP`` (car
  following, not free driving).
* **lane changes per window**: each vehicle's frames are cut into windows of ``WINDOW`` s
  (the last, incomplete one dropped) and the lane changes in each are counted. A lane change
  is a change of the vehicle's lane (``LaneMap.locate_many``) to a lane beside it (a left or
  right neighbour of its lane, or of that lane's predecessors or successors: lanelets are
  split along the road), after which the vehicle stays ``DEBOUNCE`` s in the new lane (a car
  driving on a lane line would otherwise count many times).

:func:`ks_distance` is the two-sample Kolmogorov-Smirnov statistic (the largest gap between
the two empirical CDFs, 0 = identical, 1 = disjoint); it works for the discrete lane-change
counts too. :func:`compare` gives all three plus the sample sizes and means.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from .lanemap import LaneMap

STATS = ("speed", "headway", "lane_changes")
MIN_SPEED = 1.0          # m/s: below it a time headway is meaningless (queues)
LANE_HALF_WIDTH = 1.6    # m: a vehicle this close laterally (follower's frame) is in the same lane
MAX_GAP = 80.0           # m: larger gaps are free driving, not following
WINDOW = 5.0             # s per lane-change window (the episode length)
DEBOUNCE = 0.5           # s a vehicle must stay in its new lane for a lane change to count


def _vehicles(scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Poses (V, F, 3), speeds (V, F), usable (V, F) bool and lengths (V,) of the ego and every
    actor; usable = present and recorded (not synthetic)."""
    poses, valid = scene.all_actor_poses()
    speeds = np.stack([scene.actor_speeds(a.id) for a in scene.actors]) if scene.actors else np.zeros((0, scene.frames))
    synth = np.stack([scene.actor_synthetic(a.id) for a in scene.actors]) if scene.actors else np.zeros((0, scene.frames), bool)
    ego_syn = scene.ego.track.synthetic if scene.ego.track.synthetic is not None else np.zeros(scene.frames, bool)
    P = np.concatenate([scene.ego_poses()[None], poses])
    V = np.concatenate([scene.ego_speeds()[None], speeds])
    ok = np.concatenate([~np.asarray(ego_syn, bool)[None], valid & ~synth])
    lengths = np.concatenate([[float(scene.ego.dimensions[0])], scene.actor_dimensions()[:, 0]])
    return P, np.where(ok, V, np.nan), ok, lengths


def _lateral_pairs(lane_map: LaneMap) -> set[tuple[int, int]]:
    """(a, b) lane-id pairs where moving from a to b is a lane change (see module docstring)."""
    by_id = lane_map.by_id
    pred: dict[int, set[int]] = {}
    for lane in by_id.values():
        for s in lane.successors:
            pred.setdefault(int(s), set()).add(int(lane.id))
    pairs: set[tuple[int, int]] = set()
    for lane in by_id.values():
        a = int(lane.id)
        near = {a} | {int(s) for s in lane.successors} | pred.get(a, set())
        for x in near:
            lx = by_id.get(x)
            if lx is None:
                continue
            for side in (lx.left, lx.right):
                if side is not None:
                    pairs.add((a, int(side)))
                    side_lane = by_id.get(int(side))
                    if side_lane is not None:  # the neighbour's next / previous lanelet
                        for y in list(side_lane.successors) + list(pred.get(int(side), ())):
                            pairs.add((a, int(y)))
    return pairs


def _count_lane_changes(ids: np.ndarray, pairs: set[tuple[int, int]], hold: int) -> np.ndarray:
    """(F,) lane ids of one vehicle (-1 unknown) -> (F,) bool: a lane change happens at this
    frame (the vehicle then stays ``hold`` frames in the new lane)."""
    out = np.zeros(len(ids), bool)
    current = None
    for f in range(len(ids)):
        lid = int(ids[f])
        if lid < 0 or lid == current:
            continue
        if current is None:
            current = lid
            continue
        stays = ids[f:f + hold]
        if len(stays) < hold or not np.all(stays == lid):
            continue  # flicker across a lane line, or too close to the end to tell
        if (current, lid) in pairs:
            out[f] = True
        current = lid
    return out


def traffic_samples(scene, lane_map: LaneMap | None = None) -> dict[str, np.ndarray]:
    """The three samples of one scene (see the module docstring): ``speed`` (n,) m/s,
    ``headway`` (m,) s, ``lane_changes`` (w,) counts per window; plus ``vehicle_seconds`` (1,)
    and ``lane_change_total`` (1,) for rates."""
    lane_map = lane_map if lane_map is not None else LaneMap.from_scene(scene)
    P, V, ok, lengths = _vehicles(scene)
    n_veh, F = ok.shape
    dt = float(scene.dt)
    speed = V[ok]
    # headways: pairwise in each frame (few dozen vehicles)
    heads = []
    for f in range(F):
        idx = np.flatnonzero(ok[:, f] & (V[:, f] > MIN_SPEED))
        oth = np.flatnonzero(ok[:, f])
        if len(idx) == 0 or len(oth) < 2:
            continue
        p, q = P[idx, f], P[oth, f]
        c, s = np.cos(p[:, 2])[:, None], np.sin(p[:, 2])[:, None]
        dx, dy = q[None, :, 0] - p[:, None, 0], q[None, :, 1] - p[:, None, 1]
        lon, lat = c * dx + s * dy, -s * dx + c * dy
        gap = lon - 0.5 * (lengths[idx][:, None] + lengths[oth][None])
        ahead = (lon > 0) & (np.abs(lat) < LANE_HALF_WIDTH) & (idx[:, None] != oth[None])
        g = np.where(ahead, gap, np.inf).min(axis=1)
        keep = np.isfinite(g) & (g <= MAX_GAP)
        heads.append(np.maximum(g[keep], 0.0) / V[idx[keep], f])
    headway = np.concatenate(heads) if heads else np.zeros(0)
    # lane changes
    pairs = _lateral_pairs(lane_map)
    hold = max(1, int(round(DEBOUNCE / dt)))
    win = int(round(WINDOW / dt))
    flat = P.reshape(-1, 3)
    ids = np.full(n_veh * F, -1, np.int64)
    use = ok.reshape(-1)
    if use.any():
        ids[use] = lane_map.locate_many(flat[use])[0]
    ids = ids.reshape(n_veh, F)
    counts, total = [], 0
    for i in range(n_veh):
        frames = np.flatnonzero(ok[i])
        if len(frames) == 0:
            continue
        changes = _count_lane_changes(np.where(ok[i], ids[i], -1), pairs, hold)
        total += int(changes.sum())
        first = frames[0]
        n_win = (frames[-1] - first + 1) // win
        for w in range(n_win):
            counts.append(int(changes[first + w * win:first + (w + 1) * win].sum()))
    return {"speed": speed, "headway": headway, "lane_changes": np.asarray(counts, np.float64),
            "vehicle_seconds": np.array([ok.sum() * dt]), "lane_change_total": np.array([float(total)])}


def pool(samples: Iterable[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate the samples of several scenes."""
    rows = list(samples)
    keys = STATS + ("vehicle_seconds", "lane_change_total")
    return {k: np.concatenate([r[k] for r in rows]) if rows else np.zeros(0) for k in keys}


def ks_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov statistic sup |F_a - F_b| (NaN when a sample is empty)."""
    a, b = np.sort(np.asarray(a, np.float64)), np.sort(np.asarray(b, np.float64))
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    grid = np.concatenate([a, b])
    fa = np.searchsorted(a, grid, side="right") / len(a)
    fb = np.searchsorted(b, grid, side="right") / len(b)
    return float(np.max(np.abs(fa - fb)))


def summary(pooled: dict[str, np.ndarray]) -> dict:
    """Sample sizes, means and quartiles, and the lane-change rate (per vehicle and minute)."""
    out = {}
    for k in STATS:
        x = pooled[k]
        out[k] = {"n": int(len(x)), "mean": float(np.mean(x)) if len(x) else None,
                  "quartiles": [float(q) for q in np.percentile(x, [25, 50, 75])] if len(x) else None}
    vs = float(np.sum(pooled["vehicle_seconds"]))
    out["lane_changes_per_vehicle_minute"] = float(np.sum(pooled["lane_change_total"]) / (vs / 60.0)) if vs else None
    return out


def compare(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    """KS distance per statistic between two pooled samples."""
    return {k: ks_distance(a[k], b[k]) for k in STATS}
