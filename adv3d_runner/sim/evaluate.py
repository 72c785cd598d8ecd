"""Metrics of one episode (paper Table 1 columns plus safety): ``episode_metrics(result, lanes)``.

* **Detection** (AP and recall at BEV IoU 0.5, pooled over the frames): ground truth = actors
  whose centre is 0-50 m ahead of the ego (the paper's ROI) and that the LiDAR hit with at
  least ``min_gt_points`` returns in that frame. Detections in the ROI that match (IoU >= 0.5)
  an actor with fewer returns (fully occluded) are ignored, neither TP nor FP.
* **Prediction** (minADE / meanADE over the 6 s horizon, m): every predicted track in the ROI
  is matched to a ground-truth actor (Hungarian on centre distance, <= 3 m) and compared with
  that actor's actual future (its log, or the reactive traffic's continuation), over the
  steps where it exists. Unmatched tracks (false positives) have no ground truth and are left
  out. Averaged over all (frame, track) pairs.
* **Planning comfort**: lateral acceleration and jerk of every chosen plan, averaged over the
  plans; **driving comfort**: of the executed ego trajectory (``metrics.comfort``).
* **Occupancy** (instance-free stacks, Autonomy-B, whose outputs carry an occupancy field
  instead of detections and predictions; :mod:`adv3d_runner.metrics.occupancy`): occupancy mAP
  and Soft-IoU, flow-grounded mAP and Soft-IoU and foreground flow EPE on the query set of
  :func:`occupancy_frames`: per frame a 1 m grid 0-50 m ahead of the ego and 12 m to either
  side (the paper's ROI) at the times ``OCCUPANCY_TIMES`` (0-5 s), the grid carried forward at
  the ego's current speed (x + v t: on a highway the traffic of the ROI moves with the ego, a
  grid fixed in the current frame would at 5 s only hold cars that were 100-150 m behind, out of
  sensor range). The detection and prediction blocks of such an episode are null.
* **Collision** (footprint overlap with any actor), ``at_fault`` (the first collision is with
  an actor ahead of the ego: a replayed actor can drive into a slower ego from behind),
  minimum ego-actor footprint distance, **off road** (largest distance of an ego footprint
  corner outside the union of the lane strips; ``off_road`` when > ``OFF_ROAD_TOLERANCE``),
  **progress** (path length, m) and the **hardest braking** of the driven speed trace
  (``hardest_braking_mps2``, m/s^2, :func:`hardest_braking`).

:func:`detection_frames` and :func:`prediction_pairs` give the per-frame inputs the attack
objective (paper Eq. 4-5) needs, with the same ground-truth rules. Both are computed once per
episode into an :class:`EpisodeEvaluation` (:func:`episode_evaluation`) that the metrics and
the objective (``attack.objective.episode_objective``) share.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry.boxes import box_corners, iou_pairwise
from ..metrics.comfort import Comfort, collisions, driving_comfort, mean_comfort, planning_comfort, trajectory_comfort
from ..metrics.detection import (IOU_THRESHOLD, ROI_AHEAD, FrameMatch, average_precision_of_matches, match_frame,
                                 roi_mask)
from ..metrics.occupancy import FLOW_LAG, OccupancySample, flow_grounded, occupancy_metrics, occupancy_targets
from ..metrics.prediction import match_to_ground_truth, prediction_metrics
from ..scene import lanes as lanegeo

METRICS_FORMAT = "adv3d-episode-metrics"
METRICS_VERSION = 1
MIN_GT_POINTS = 5
OFF_ROAD_TOLERANCE = 0.3  # m a footprint corner may stray outside the lanes (onto the shoulder paint)
OCCUPANCY_TIMES = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)  # s, query times of the occupancy metrics
OCCUPANCY_LATERAL = 12.0  # m to either side of the ego (its lane and about two more each side)
OCCUPANCY_SPACING = 1.0   # m between query points


def detection_frames(result, min_gt_points: int = MIN_GT_POINTS, ahead: float = ROI_AHEAD
                     ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame (gt boxes (G, 5), detected boxes (D, 5), scores (D,)), map frame, restricted
    to the ROI, with the visibility rule of the module docstring."""
    frames = []
    for k in range(result.frames):
        ego = result.ego_poses[k]
        gt = result.gt_boxes(k)
        valid = np.isfinite(gt).all(axis=1)
        gt = gt[valid]
        vis = result.actor_points[k][valid] >= min_gt_points
        in_roi = roi_mask(gt, ego, ahead) if len(gt) else np.zeros(0, bool)
        det = result.outputs[k].detections
        d, s = det.boxes, det.scores
        keep = roi_mask(d, ego, ahead) if len(d) else np.zeros(0, bool)
        d, s = d[keep], s[keep]
        hidden = gt[in_roi & ~vis]
        if len(hidden) and len(d):
            d_ok = ~(iou_pairwise(d, hidden) >= 0.5).any(axis=1)
            d, s = d[d_ok], s[d_ok]
        frames.append((gt[in_roi & vis], d, s))
    return frames


def prediction_pairs(result, ahead: float = ROI_AHEAD, max_distance: float = 3.0
                     ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame (predictions (M, K, H, 2), true futures (M, H, 2), valid (M, H)) of the
    predicted tracks in the ROI that match a ground-truth actor."""
    out = []
    for k in range(result.frames):
        o = result.outputs[k]
        preds = o.predictions
        H = preds.horizon
        if len(preds) == 0:
            out.append((np.zeros((0, preds.num_modes, H, 2)), np.zeros((0, H, 2)), np.zeros((0, H), bool)))
            continue
        row = {int(t): i for i, t in enumerate(o.tracks.ids)}
        tb = np.array([o.tracks.boxes[row[int(t)]] for t in preds.track_ids]).reshape(-1, 5)
        in_roi = roi_mask(tb, result.ego_poses[k], ahead)
        gt = result.gt_boxes(k)
        valid = np.flatnonzero(np.isfinite(gt).all(axis=1))
        match = match_to_ground_truth(tb, gt[valid], max_distance) if len(valid) else np.full(len(tb), -1)
        use = np.flatnonzero(in_roi & (match >= 0))
        actors = valid[match[use]]
        fut = result.actor_poses[k + 1:k + 1 + H, :, :2]  # (<=H, N, 2)
        gt_fut = np.full((len(use), H, 2), np.nan)
        gt_fut[:, :len(fut)] = np.transpose(fut[:, actors], (1, 0, 2))
        ok = np.isfinite(gt_fut).all(axis=-1)
        out.append((preds.trajectories[use], np.nan_to_num(gt_fut), ok))
    return out


def occupancy_grid(ahead: float = ROI_AHEAD, lateral: float = OCCUPANCY_LATERAL,
                   spacing: float = OCCUPANCY_SPACING) -> np.ndarray:
    """(G, 2) ego-frame query points of the occupancy metrics at t = 0: x in [0, ahead],
    |y| <= lateral, every ``spacing`` m."""
    xs = np.arange(0.0, ahead + 1e-9, spacing)
    ys = np.arange(-lateral, lateral + 1e-9, spacing)
    return np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)


def occupancy_frames(result, times: tuple[float, ...] = OCCUPANCY_TIMES) -> list[list[OccupancySample]] | None:
    """Per frame, per query time, the query points of the occupancy metrics with their ground
    truth (the episode's actor boxes, the adversarial ones with their substituted dimensions)
    and the stack's prediction (its field queried once per frame); None when the stack gives no
    occupancy. A time past the episode's ground truth is left out; the flow-grounded prediction
    is None where the boxes ``FLOW_LAG`` s before the query time are before the episode."""
    outs = result.outputs
    if not outs or all(o.occupancy is None for o in outs):
        return None
    grid = occupancy_grid()
    dt = float(result.dt)
    lag = int(round(FLOW_LAG / dt))
    n_gt = len(result.actor_poses)
    frames: list[list[OccupancySample]] = []
    for k, o in enumerate(outs):
        field = o.occupancy
        if field is None:
            frames.append([])
            continue
        x0, y0, yaw = result.ego_poses[k]
        v = float(result.ego_speeds[k])
        c, s = np.cos(yaw), np.sin(yaw)
        use = [t for t in times if k + int(round(t / dt)) < n_gt and t <= field.horizon + 1e-9]
        pts, tq = [], []
        for t in use:
            lx, ly = grid[:, 0] + v * t, grid[:, 1]
            pts.append(np.stack([x0 + c * lx - s * ly, y0 + s * lx + c * ly], axis=1))
            tq.append(np.full(len(grid), t))
        if not use:
            frames.append([])
            continue
        occ_p, flow_p = field.query(np.concatenate(pts), np.concatenate(tq))
        samples = []
        for i, t in enumerate(use):
            j = k + int(round(t / dt))
            sl = slice(i * len(grid), (i + 1) * len(grid))
            before = result.gt_boxes(j - lag) if j - lag >= 0 else None
            occ, flow, fv = occupancy_targets(pts[i], result.gt_boxes(j), before, FLOW_LAG)
            grounded = None if before is None else flow_grounded(occ_p[sl], flow_p[sl], pts[i], before, FLOW_LAG)
            samples.append(OccupancySample(t, occ, occ_p[sl], flow, flow_p[sl], fv, grounded))
        frames.append(samples)
    return frames


@dataclass(frozen=True, eq=False)
class EpisodeEvaluation:
    """The per-frame inputs of the episode metrics and the attack objective, computed once.

    Attributes:
        detection: T tuples (gt boxes (G, 5), detected boxes (D, 5), scores (D,))
            (:func:`detection_frames`).
        prediction: T tuples (predictions (M, K, H, 2), true futures (M, H, 2), valid (M, H))
            (:func:`prediction_pairs`).
        min_gt_points: the visibility rule ``detection`` was made with.
        occupancy: per frame the occupancy query slices (:func:`occupancy_frames`), or None for
            a stack without occupancy output.
        plan_comfort: each plan's :func:`~adv3d_runner.metrics.comfort.trajectory_comfort`
            (the planning comfort and the objective's c_plan), or None: computed by each.
    """

    detection: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    prediction: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    min_gt_points: int = MIN_GT_POINTS
    occupancy: list[list[OccupancySample]] | None = None
    plan_comfort: list[Comfort] | None = None
    _matches: dict = field(default_factory=dict, repr=False)

    #: the outputs the stack did not provide ("detections", "tracks", "predictions"; docs/stacks.md)
    not_available: tuple[str, ...] = ()

    @property
    def instance_free(self) -> bool:
        """The stack gave occupancy instead of detections and predictions (Autonomy-B)."""
        return self.occupancy is not None

    def matches(self, iou_threshold: float = IOU_THRESHOLD) -> list[FrameMatch]:
        """Each ``detection`` frame's :func:`~adv3d_runner.metrics.detection.match_frame` at
        ``iou_threshold``, made once (the metrics' AP and the objective's terms share them)."""
        key = float(iou_threshold)
        if key not in self._matches:
            self._matches[key] = [match_frame(g, d, s, key) for g, d, s in self.detection]
        return self._matches[key]


def episode_evaluation(result, min_gt_points: int = MIN_GT_POINTS) -> EpisodeEvaluation:
    """Detection frames, prediction pairs, occupancy slices and each plan's comfort of an
    episode, once (see :class:`EpisodeEvaluation`)."""
    return EpisodeEvaluation(detection_frames(result, min_gt_points), prediction_pairs(result), int(min_gt_points),
                             occupancy_frames(result), [trajectory_comfort(p, result.dt) for p in result.plans()],
                             not_available=not_provided(result))


def not_provided(result) -> tuple[str, ...]:
    """Which of detections, tracks and predictions the episode's stack never provided (a plugin
    stack says so per frame, ``AutonomyOutputs.provided``; adv3d's own stacks provide them, or
    occupancy instead). Their metrics and objective terms are reported as not available."""
    said = [o.provided for o in result.outputs if getattr(o, "provided", None) is not None]
    if not said:
        return ()
    given = frozenset().union(*said)
    return tuple(k for k in ("detections", "tracks", "predictions") if k not in given)


def off_road_distance(lanes, boxes: np.ndarray) -> np.ndarray:
    """(T,) largest distance (m) of a footprint corner outside every lane strip, per box (T, 5)."""
    corners = box_corners(np.asarray(boxes, float).reshape(-1, 5)).reshape(-1, 2)  # (T*4, 2)
    best = np.full(len(corners), np.inf)
    for lane in lanes:
        pts = np.asarray(lane.centerline, float)
        s, d, _ = lanegeo.project(pts, corners)
        total = lanegeo.length(pts)
        half = 0.5 * np.asarray(lanegeo.width_at(pts, np.atleast_1d(lane.width), np.clip(s, 0, total)))
        out = np.hypot(np.maximum(np.abs(d) - half, 0.0), np.maximum(np.maximum(-s, s - total), 0.0))
        best = np.minimum(best, out)
    return best.reshape(-1, 4).max(axis=1)


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def hardest_braking(speeds: np.ndarray, dt: float) -> float:
    """The most negative acceleration of a speed trace (m/s^2, forward differences of the (T,)
    speeds over ``dt`` s); 0 for a trace that never slows down or has one frame."""
    v = np.asarray(speeds, dtype=np.float64).reshape(-1)
    return float(min(0.0, np.min(np.diff(v)) / float(dt))) if len(v) > 1 else 0.0


def episode_metrics(result, lanes, min_gt_points: int = MIN_GT_POINTS,
                    evaluation: EpisodeEvaluation | None = None) -> dict:
    """The metrics document of one episode (JSON-ready; see module docstring).

    ``evaluation``: the episode's :class:`EpisodeEvaluation` when the caller already has it
    (made with the same ``min_gt_points``); computed here otherwise.
    """
    if evaluation is None:
        evaluation = episode_evaluation(result, min_gt_points)
    elif evaluation.min_gt_points != int(min_gt_points):
        raise ValueError(f"evaluation made with min_gt_points={evaluation.min_gt_points}, not {min_gt_points}")
    det = average_precision_of_matches(evaluation.matches(IOU_THRESHOLD), [s for _, _, s in evaluation.detection])
    pairs = evaluation.prediction
    K = max((p.shape[1] for p, _, _ in pairs if len(p)), default=3)
    H = max((p.shape[2] for p, _, _ in pairs if len(p)), default=60)
    pred = np.concatenate([p for p, _, _ in pairs if len(p)] or [np.zeros((0, K, H, 2))])
    gt = np.concatenate([g for _, g, _ in pairs if len(g)] or [np.zeros((0, H, 2))])
    ok = np.concatenate([v for _, _, v in pairs if len(v)] or [np.zeros((0, H), bool)])
    pm = prediction_metrics(pred, gt, ok) if len(pred) else None
    ego_boxes = result.ego_boxes()
    T = result.frames
    act = np.stack([result.gt_boxes(k) for k in range(T)]) if T else np.zeros((0, 0, 5))
    rep = collisions(ego_boxes, act, result.actor_valid[:T])
    at_fault = False
    if rep.collided:
        e = ego_boxes[rep.first_frame]
        for i in rep.actors:
            b = act[rep.first_frame, i]
            if not np.isfinite(b).all():
                continue
            rel = b[:2] - e[:2]
            at_fault |= bool(rel[0] * np.cos(e[4]) + rel[1] * np.sin(e[4]) > 0)
    off = off_road_distance(lanes, ego_boxes)
    pc = (planning_comfort(result.plans(), result.dt) if evaluation.plan_comfort is None
          else mean_comfort(evaluation.plan_comfort))
    dc = driving_comfort(result.ego_poses, result.dt)
    path = float(np.sum(np.hypot(*np.diff(result.ego_poses[:, :2], axis=0).T))) if T > 1 else 0.0
    timing = {k: _f(1000 * np.mean(v)) for k, v in result.timings.items()}
    total = float(np.sum(result.timings.get("total", np.zeros(1))))
    doc = {
        "format": METRICS_FORMAT, "version": METRICS_VERSION,
        "scene": result.scene_id, "start_frame": result.start_frame, "frames": T, "dt": result.dt,
        "closed_loop": result.closed_loop, "reactive": result.reactive, "seed": result.seed,
        "adversarial_actors": [int(a) for a in result.actor_ids[result.adversarial]],
        "detection": {"ap": _f(det.ap), "recall": _f(det.recall), "n_gt": int(det.n_gt), "n_det": int(det.n_det),
                      "n_tp": int(det.n_tp), "iou_threshold": 0.5, "roi_ahead_m": ROI_AHEAD,
                      "min_gt_points": int(min_gt_points)},
        "prediction": {"min_ade": _f(pm.min_ade) if pm else None, "mean_ade": _f(pm.mean_ade) if pm else None,
                       "min_fde": _f(pm.min_fde) if pm else None, "mean_fde": _f(pm.mean_fde) if pm else None,
                       "n": int(len(pred))},
        "planning_comfort": {"lat": pc.lat, "jerk": pc.jerk, "max_lat": pc.max_lat, "max_jerk": pc.max_jerk},
        "driving_comfort": {"lat": dc.lat, "jerk": dc.jerk, "max_lat": dc.max_lat, "max_jerk": dc.max_jerk},
        "collision": {"collided": rep.collided, "at_fault": bool(at_fault), "first_frame": rep.first_frame,
                      "actors": [int(result.actor_ids[i]) for i in rep.actors]},
        "min_distance": _f(rep.min_distance),
        "off_road": bool(off.max(initial=0.0) > OFF_ROAD_TOLERANCE), "off_road_m": float(off.max(initial=0.0)),
        "progress_m": path, "mean_speed": _f(np.mean(result.ego_speeds)) if T else None,
        "hardest_braking_mps2": hardest_braking(result.ego_speeds[:T], result.dt),
        "ms_per_frame": timing, "fps": _f(T / total) if total > 0 else None,
    }
    if evaluation.not_available:  # a plugin stack without these outputs: not available, never zero
        doc["not_available"] = list(evaluation.not_available)
        if "detections" in evaluation.not_available:
            doc["detection"] = None
        if "predictions" in evaluation.not_available:
            doc["prediction"] = None
    if evaluation.instance_free:  # no boxes, no trajectories: occupancy and flow instead
        doc["detection"] = None
        doc["prediction"] = None
        occ = occupancy_metrics([s for frame in evaluation.occupancy for s in frame])
        occ.update(roi_ahead_m=ROI_AHEAD, lateral_m=OCCUPANCY_LATERAL, spacing_m=OCCUPANCY_SPACING,
                   flow_lag_s=FLOW_LAG)
        doc["occupancy"] = occ
    return doc
