"""Occupancy and flow metrics of an instance-free stack (Autonomy-B), as in ImplicitO
(Agro et al., CVPR 2023) and the Waymo occupancy-flow challenge (Mahjourian et al., 2022).

Everything is defined on a set of **query points** q = (x, y, t): BEV positions (m) at a time t
(s) after the frame. For each query point the ground truth is

* occupancy o(q) in {0, 1}: the point lies inside some actor's footprint box at time t
  (:func:`occupancy_targets`);
* backward flow f(q) (m/s, 2-D): the velocity of the footprint point of the actor that occupies
  q, as the backward difference over ``lag`` = ``FLOW_LAG`` s: f = (p - p_before) / lag, where
  p_before is where the same body point of that actor was ``lag`` s earlier (a rigid motion of
  its box); unknown (``flow_valid`` False) when the actor did not exist ``lag`` s earlier.

and the model predicts an occupancy probability o^(q) in [0, 1] and a flow f^(q). The metrics:

* **Soft-IoU** (:func:`soft_iou`): sum o o^ / sum (o + o^ - o o^) over the query points; 0 when
  both are all zero (Waymo's convention).
* **AP** (:func:`occupancy_ap`): average precision of o^ as a ranking of the query points for
  "occupied", ``sum_n (R_n - R_{n-1}) P_n`` over the distinct score thresholds (scikit-learn's
  definition; tied scores form one threshold); NaN without any occupied point. **mAP** = the
  mean of the per-query-time APs (:func:`occupancy_metrics`).
* **Foreground flow EPE** (:func:`flow_epe`): mean ||f - f^|| over the occupied query points
  whose flow is known (m/s).
* **Flow-grounded occupancy** (:func:`flow_grounded`): the predicted occupancy is multiplied by
  the ground-truth occupancy at time t - lag of the point the predicted flow traces back to,
  w(q) = o(x - lag f^_x, y - lag f^_y, t - lag); AP and Soft-IoU of o^ w against o. It is high
  only where occupancy *and* flow are right (Waymo's "flow-warped occupancy"; our ground truth
  is a set of boxes, so the origin occupancy is evaluated exactly at the warped point instead of
  bilinearly on a grid).

numpy only; positions, boxes and flows must be in one frame (the evaluation uses the ego frame
of the query's frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: s, the backward difference of the flow ground truth and the flow-grounded warp.
FLOW_LAG = 0.5


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Which box contains each point (closed boxes; the nearest centre wins where boxes overlap).

    Args:
        points: (Q, 2) x, y (m). boxes: (N, 5) x, y, length, width, yaw; non-finite rows are
            ignored.
    Returns:
        (Q,) int64 box index, -1 for points in no box.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    out = np.full(len(p), -1, np.int64)
    best = np.full(len(p), np.inf)
    for i in np.flatnonzero(np.isfinite(b).all(axis=1)):
        x, y, length, width, yaw = b[i]
        r = 0.5 * np.hypot(length, width)
        near = np.flatnonzero((np.abs(p[:, 0] - x) <= r) & (np.abs(p[:, 1] - y) <= r))
        if not len(near):
            continue
        dx, dy = p[near, 0] - x, p[near, 1] - y
        c, s = np.cos(yaw), np.sin(yaw)
        u, v = c * dx + s * dy, -s * dx + c * dy
        d2 = dx * dx + dy * dy
        take = (np.abs(u) <= 0.5 * length) & (np.abs(v) <= 0.5 * width) & (d2 < best[near])
        out[near[take]] = i
        best[near[take]] = d2[take]
    return out


def occupancy_targets(points: np.ndarray, boxes_now: np.ndarray, boxes_before: np.ndarray | None,
                      lag: float = FLOW_LAG) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth occupancy and backward flow of query points at one time.

    Args:
        points: (Q, 2) query positions (m).
        boxes_now: (N, 5) the actors' boxes at the query time (NaN rows: absent).
        boxes_before: (N, 5) the same actors ``lag`` s earlier (NaN rows: absent then), or None
            (the flow is unknown everywhere).
        lag: s.
    Returns:
        occupied (Q,) bool; flow (Q, 2) m/s (0 where unknown); flow_valid (Q,) bool (occupied
        and the occupying actor existed ``lag`` s earlier).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    idx = points_in_boxes(p, boxes_now)
    occ = idx >= 0
    flow = np.zeros((len(p), 2))
    valid = np.zeros(len(p), bool)
    if boxes_before is None or not occ.any():
        return occ, flow, valid
    now = np.asarray(boxes_now, dtype=np.float64).reshape(-1, 5)[idx[occ]]
    before = np.asarray(boxes_before, dtype=np.float64).reshape(-1, 5)[idx[occ]]
    ok = np.isfinite(before).all(axis=1)
    q = p[occ]
    c0, s0 = np.cos(now[:, 4]), np.sin(now[:, 4])
    dx, dy = q[:, 0] - now[:, 0], q[:, 1] - now[:, 1]
    u, v = c0 * dx + s0 * dy, -s0 * dx + c0 * dy  # the body point in the actor's frame
    c1, s1 = np.cos(before[:, 4]), np.sin(before[:, 4])
    px = before[:, 0] + c1 * u - s1 * v
    py = before[:, 1] + s1 * u + c1 * v
    f = np.stack([q[:, 0] - px, q[:, 1] - py], axis=1) / float(lag)
    rows = np.flatnonzero(occ)
    flow[rows[ok]] = f[ok]
    valid[rows[ok]] = True
    return occ, flow, valid


# ------------------------------------------------------------------ scores

def soft_iou(occupied: np.ndarray, predicted: np.ndarray) -> float:
    """Soft-IoU ``sum o o^ / sum (o + o^ - o o^)`` (0 when the denominator is 0).

    Args:
        occupied: (Q,) ground truth in [0, 1] (bool accepted). predicted: (Q,) in [0, 1].
    """
    o = np.asarray(occupied, dtype=np.float64).reshape(-1)
    p = np.asarray(predicted, dtype=np.float64).reshape(-1)
    inter = float(np.sum(o * p))
    union = float(np.sum(o + p - o * p))
    return inter / union if union > 0 else 0.0


def occupancy_ap(occupied: np.ndarray, predicted: np.ndarray) -> float:
    """Average precision of ``predicted`` as a ranking for ``occupied`` (see module docstring).

    Args:
        occupied: (Q,) bool. predicted: (Q,) scores (higher = more likely occupied).
    Returns:
        AP in [0, 1]; NaN when no point is occupied.
    """
    o = np.asarray(occupied, bool).reshape(-1)
    p = np.asarray(predicted, dtype=np.float64).reshape(-1)
    n_pos = int(o.sum())
    if n_pos == 0:
        return float("nan")
    order = np.argsort(-p, kind="stable")
    ps, os_ = p[order], o[order]
    tp = np.cumsum(os_)
    # one precision/recall point per distinct score (the last index of each run of ties)
    last = np.r_[np.flatnonzero(ps[1:] != ps[:-1]), len(ps) - 1]
    tp_at = tp[last].astype(np.float64)
    precision = tp_at / (last + 1)
    recall = tp_at / n_pos
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def flow_epe(flow_true: np.ndarray, flow_pred: np.ndarray, mask: np.ndarray) -> float:
    """Mean end-point error ``||f - f^||`` over the points where ``mask`` (m/s); NaN if none.

    Args:
        flow_true, flow_pred: (Q, 2). mask: (Q,) bool (occupied and flow known).
    """
    m = np.asarray(mask, bool).reshape(-1)
    if not m.any():
        return float("nan")
    d = np.asarray(flow_true, dtype=np.float64).reshape(-1, 2)[m] - np.asarray(flow_pred, dtype=np.float64).reshape(-1, 2)[m]
    return float(np.mean(np.hypot(d[:, 0], d[:, 1])))


def flow_grounded(predicted: np.ndarray, flow_pred: np.ndarray, points: np.ndarray, boxes_before: np.ndarray,
                  lag: float = FLOW_LAG) -> np.ndarray:
    """Flow-grounded predicted occupancy o^(q) x o(q - lag f^(q), t - lag) (see module docstring).

    Args:
        predicted: (Q,) o^ at the query points (time t). flow_pred: (Q, 2) f^ (m/s).
        points: (Q, 2). boxes_before: (N, 5) ground-truth boxes at t - ``lag``.
    Returns:
        (Q,) in [0, 1].
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    origin = p - float(lag) * np.asarray(flow_pred, dtype=np.float64).reshape(-1, 2)
    warped = points_in_boxes(origin, boxes_before) >= 0
    return np.asarray(predicted, dtype=np.float64).reshape(-1) * warped


# ------------------------------------------------------------------ pooled metrics

@dataclass(frozen=True)
class OccupancySample:
    """Query points of one time slice with their ground truth and prediction (one frame, one
    query time; the metrics pool slices of the same query time over frames).

    Attributes:
        time: s after the frame. occupied (Q,) bool; predicted (Q,) in [0, 1].
        flow_true, flow_pred: (Q, 2) m/s; flow_valid (Q,) bool.
        grounded: (Q,) flow-grounded prediction, or None when the ground truth ``lag`` s
            earlier is not known (then the slice is left out of the flow-grounded metrics).
    """

    time: float
    occupied: np.ndarray
    predicted: np.ndarray
    flow_true: np.ndarray
    flow_pred: np.ndarray
    flow_valid: np.ndarray
    grounded: np.ndarray | None = None


def _mean(values: list[float]) -> float | None:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else None


def occupancy_metrics(samples: list[OccupancySample]) -> dict:
    """mAP, Soft-IoU, flow-grounded mAP and Soft-IoU, foreground EPE of pooled slices.

    Slices are pooled per query time (over frames); AP and Soft-IoU are computed per query time
    and averaged over the query times (those with an occupied point, for AP); EPE is the mean
    over every occupied query point with a known flow.

    Returns:
        dict with ``map``, ``soft_iou``, ``flow_grounded_map``, ``flow_grounded_soft_iou``,
        ``epe`` (None where undefined), ``n_queries``, ``n_occupied``, ``times`` (the query times)
        and ``per_time`` (time -> ap, soft_iou).
    """
    by_time: dict[float, list[OccupancySample]] = {}
    for s in samples:
        by_time.setdefault(round(float(s.time), 6), []).append(s)
    aps, ious, gaps, gious, per_time = [], [], [], [], {}
    n_q = n_occ = 0
    for t in sorted(by_time):
        ss = by_time[t]
        o = np.concatenate([s.occupied for s in ss])
        p = np.concatenate([s.predicted for s in ss])
        ap, iou = occupancy_ap(o, p), soft_iou(o, p)
        aps.append(ap)
        ious.append(iou)
        n_q += len(o)
        n_occ += int(o.sum())
        row = {"ap": None if not np.isfinite(ap) else ap, "soft_iou": iou}
        g = [s for s in ss if s.grounded is not None]
        if g:
            go = np.concatenate([s.occupied for s in g])
            gp = np.concatenate([s.grounded for s in g])
            gap, giou = occupancy_ap(go, gp), soft_iou(go, gp)
            gaps.append(gap)
            gious.append(giou)
            row.update(flow_grounded_ap=None if not np.isfinite(gap) else gap, flow_grounded_soft_iou=giou)
        per_time[f"{t:g}"] = row
    ft = np.concatenate([s.flow_true for s in samples]) if samples else np.zeros((0, 2))
    fp = np.concatenate([s.flow_pred for s in samples]) if samples else np.zeros((0, 2))
    fv = np.concatenate([s.flow_valid & s.occupied for s in samples]) if samples else np.zeros(0, bool)
    epe = flow_epe(ft, fp, fv)
    return {"map": _mean(aps), "soft_iou": _mean(ious), "flow_grounded_map": _mean(gaps),
            "flow_grounded_soft_iou": _mean(gious), "epe": None if not np.isfinite(epe) else epe,
            "n_queries": int(n_q), "n_occupied": int(n_occ), "n_flow": int(fv.sum()),
            "times": [float(t) for t in sorted(by_time)], "per_time": per_time}


def frame_terms(samples: list[OccupancySample]) -> tuple[float, float]:
    """The per-frame terms of Autonomy-B's attack objective over one frame's query set Q (all
    its time slices together): (Soft-IoU of occupancy, foreground flow EPE in m/s; 0 when no
    occupied query point has a known flow)."""
    if not samples:
        return 0.0, 0.0
    o = np.concatenate([s.occupied for s in samples])
    p = np.concatenate([s.predicted for s in samples])
    mask = np.concatenate([s.flow_valid & s.occupied for s in samples])
    epe = flow_epe(np.concatenate([s.flow_true for s in samples]), np.concatenate([s.flow_pred for s in samples]), mask)
    return soft_iou(o, p), (epe if np.isfinite(epe) else 0.0)
