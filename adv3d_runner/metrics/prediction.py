"""Trajectory-prediction metrics over K modes: ADE / FDE, minADE, meanADE, and the paper's
prediction loss (Eq. 5).

Shapes: predictions ``(N, K, H, 2)`` (N actors, K modes, H future steps at dt, positions in m),
ground truth ``(N, H', 2)`` with validity ``(N, H')``. Only steps where the ground truth is
valid count; if H' != H the shorter horizon is used (e.g. an episode that ends before the 6 s
prediction horizon). An actor with no valid future step has no error (NaN per actor) and is
left out of the averages; the aggregate counts how many actors contributed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PredictionMetrics:
    """Averages over actors with at least one valid future step (NaN if there are none)."""

    min_ade: float
    mean_ade: float
    min_fde: float
    mean_fde: float
    n_actors: int

    def as_dict(self) -> dict:
        return {"min_ade": self.min_ade, "mean_ade": self.mean_ade, "min_fde": self.min_fde,
                "mean_fde": self.mean_fde, "n_actors": self.n_actors}


def _prepare(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None):
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if p.ndim == 3:  # (K, H, 2) for one actor
        p, g = p[None], g[None]
        valid = None if valid is None else np.asarray(valid)[None]
    if p.ndim != 4 or p.shape[-1] != 2 or g.ndim != 3 or g.shape[-1] != 2 or g.shape[0] != p.shape[0]:
        raise ValueError(f"need predictions (N, K, H, 2) and ground truth (N, H, 2), got {p.shape} and {g.shape}")
    v = np.ones(g.shape[:2], bool) if valid is None else np.asarray(valid, bool).reshape(g.shape[:2])
    H = min(p.shape[2], g.shape[1])
    p, g, v = p[:, :, :H], g[:, :H], v[:, :H]
    v = v & np.all(np.isfinite(g), axis=-1)
    return p, np.nan_to_num(g), v


def displacement_errors(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per actor and mode ADE and FDE.

    Args:
        pred: (N, K, H, 2) m (or (K, H, 2) for one actor). gt: (N, H', 2). valid: (N, H') bool.
    Returns:
        ade (N, K): mean L2 error over valid steps; fde (N, K): L2 error at the last valid step.
        NaN for actors without a valid step. Non-finite predictions give +inf errors.
    """
    p, g, v = _prepare(pred, gt, valid)
    err = np.linalg.norm(p - g[:, None], axis=-1)  # (N, K, H)
    err = np.where(np.isfinite(err), err, np.inf)
    n = v.sum(axis=1)  # (N,)
    with np.errstate(invalid="ignore"):
        ade = np.sum(np.where(v[:, None], err, 0.0), axis=-1) / np.maximum(n, 1)[:, None]
    N, K = p.shape[:2]
    fde = np.full((N, K), np.nan)
    has = n > 0
    if np.any(has):
        last = p.shape[2] - 1 - np.argmax(v[:, ::-1], axis=1)  # last valid index per actor
        rows = np.nonzero(has)[0]
        fde[rows] = err[rows, :, last[rows]]
    ade[~has] = np.nan
    return ade, fde


def min_ade(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(N,) best-mode ADE per actor (NaN without valid steps)."""
    ade, _ = displacement_errors(pred, gt, valid)
    return _nan_reduce(ade, np.min)


def mean_ade(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(N,) ADE averaged over the K modes per actor (NaN without valid steps)."""
    ade, _ = displacement_errors(pred, gt, valid)
    return _nan_reduce(ade, np.mean)


def _nan_reduce(x: np.ndarray, fn) -> np.ndarray:
    out = np.full(x.shape[0], np.nan)
    ok = ~np.isnan(x).any(axis=1)
    if np.any(ok):
        out[ok] = fn(x[ok], axis=1)
    return out


def prediction_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> PredictionMetrics:
    """minADE, meanADE, minFDE, meanFDE averaged over actors with a valid future step."""
    ade, fde = displacement_errors(pred, gt, valid)
    ok = ~np.isnan(ade).any(axis=1)
    if not np.any(ok):
        nan = float("nan")
        return PredictionMetrics(nan, nan, nan, nan, 0)
    return PredictionMetrics(float(np.mean(ade[ok].min(axis=1))), float(np.mean(ade[ok].mean(axis=1))),
                             float(np.mean(fde[ok].min(axis=1))), float(np.mean(fde[ok].mean(axis=1))),
                             int(ok.sum()))


def prediction_loss(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None,
                    reduction: str = "mean") -> float:
    """Paper Eq. 5 for one frame: ``1/K sum_modes sum_steps ||g - p||`` per actor, averaged over
    actors with a valid step (0.0 if none).

    ``reduction="sum"`` sums the errors over the horizon as written in Eq. 5; ``"mean"`` (default)
    averages them, i.e. the meanADE the paper reports (same optimum, a scale independent of H).
    """
    p, g, v = _prepare(pred, gt, valid)
    err = np.linalg.norm(p - g[:, None], axis=-1)
    err = np.where(np.isfinite(err), err, 1e6)  # a broken prediction is very wrong, not NaN
    per_mode = np.sum(np.where(v[:, None], err, 0.0), axis=-1)  # (N, K)
    n = v.sum(axis=1)
    ok = n > 0
    if not np.any(ok):
        return 0.0
    if reduction == "mean":
        per_mode = per_mode / np.maximum(n, 1)[:, None]
    elif reduction != "sum":
        raise ValueError("reduction must be 'mean' or 'sum'")
    return float(np.mean(per_mode[ok].mean(axis=1)))


def match_to_ground_truth(pred_boxes: np.ndarray, gt_boxes: np.ndarray, max_distance: float = 3.0) -> np.ndarray:
    """Which ground-truth actor each tracked/predicted actor is (to look up its true future).

    One-to-one Hungarian assignment (``scipy.optimize.linear_sum_assignment``) on centre
    distance, accepting pairs closer than ``max_distance`` m.

    Args:
        pred_boxes: (N, 5) current boxes of the tracks that have predictions.
        gt_boxes: (G, 5) current ground-truth boxes (non-finite rows never match).
    Returns:
        (N,) int: index into ``gt_boxes``, or -1 for tracks without a ground-truth actor
        (false positives, which have no future to compare with).
    """
    from scipy.optimize import linear_sum_assignment

    p = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 5)
    g = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 5)
    out = np.full(len(p), -1, np.int64)
    if len(p) == 0 or len(g) == 0:
        return out
    dist = np.hypot(p[:, None, 0] - g[None, :, 0], p[:, None, 1] - g[None, :, 1])
    dist = np.where(np.isfinite(dist), dist, np.inf)
    ok = dist <= max_distance
    rows, cols = linear_sum_assignment(np.where(ok, dist, 1e9))
    keep = ok[rows, cols]
    out[rows[keep]] = cols[keep]
    return out
