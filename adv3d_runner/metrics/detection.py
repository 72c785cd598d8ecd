"""Detection metrics on BEV boxes: greedy matching, AP and recall at an IoU threshold, the
paper's region of interest, and the per-frame true/false-positive terms of the attack objective.

Boxes are ``(N, 5)`` arrays ``(x, y, length, width, yaw)`` (see :mod:`.boxes`); scores ``(N,)``
are detection confidences in [0, 1].

Matching (per frame, as in PASCAL VOC / KITTI): detections are visited in decreasing score
order (ties keep their input order, so results are deterministic); each takes the still
unmatched ground-truth box with the highest IoU if that IoU >= the threshold (true positive),
otherwise it is a false positive (a duplicate of an already matched box is a false positive).

AP is the VOC all-point interpolated average precision: over all frames, detections are sorted
by score, cumulative precision/recall computed, precision made monotonically non-increasing
from the right (the "envelope"), and AP = sum over recall steps of (delta recall) x (envelope
precision). Recall is the fraction of ground-truth boxes matched by any detection.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from ..geometry.boxes import as_boxes, iou_pairwise
from ..geometry.frames import boxes_to_frame
from ..jit import kernel

IOU_THRESHOLD = 0.5
# The paper evaluates vehicles within 50 m ahead of the ego ("ROI").
ROI_AHEAD = 50.0


@dataclass
class FrameMatch:
    """Greedy matching of one frame.

    Attributes:
        tp: (D,) bool, detection i is a true positive.
        matched_gt: (D,) int, index of the matched ground-truth box, -1 for false positives.
        iou: (D,) float, IoU with the matched box for true positives; for false positives the
            best IoU with any ground-truth box (0 if none), used by the FP term.
        n_gt: number of ground-truth boxes.
    """

    tp: np.ndarray
    matched_gt: np.ndarray
    iou: np.ndarray
    n_gt: int


@dataclass
class DetectionMetrics:
    """AP and recall over a set of frames. ``ap``/``recall`` are NaN when there is no
    ground-truth box at all (undefined; check ``n_gt``). ``precision``/``recall_curve`` are the
    raw (not interpolated) curves over the score-sorted detections."""

    ap: float
    recall: float
    n_gt: int
    n_det: int
    n_tp: int
    precision_curve: np.ndarray
    recall_curve: np.ndarray

    def as_dict(self) -> dict:
        return {"ap": self.ap, "recall": self.recall, "n_gt": self.n_gt, "n_det": self.n_det, "n_tp": self.n_tp}


def _scores(scores: np.ndarray, n: int) -> np.ndarray:
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(s) != n:
        raise ValueError(f"got {len(s)} scores for {n} boxes")
    return np.nan_to_num(s, nan=0.0)


def match_frame(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray,
                iou_threshold: float = IOU_THRESHOLD) -> FrameMatch:
    """Greedy score-ordered matching of one frame's detections to its ground truth.

    Args:
        gt_boxes: (G, 5). det_boxes: (D, 5). det_scores: (D,).
    Returns:
        :class:`FrameMatch` with per-detection arrays in the input order.
    """
    gt, scores, iou, tp, matched, best_iou = _match_inputs(gt_boxes, det_boxes, det_scores)
    if iou is not None and len(gt):
        _greedy_match(iou, np.argsort(-scores, kind="stable"), float(iou_threshold), tp, matched, best_iou)
    return FrameMatch(tp, matched, best_iou, len(gt))


def _match_inputs(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray):
    """What both matchers start from: gt (G, 5), scores (D,), the (D, G) IoU (None without
    detections), and the per-detection outputs: tp (D,) False, matched (D,) -1, best IoU (D,)."""
    gt = as_boxes(gt_boxes).reshape(-1, 5)
    det = as_boxes(det_boxes).reshape(-1, 5)
    scores = _scores(det_scores, len(det))
    D = len(det)
    tp, matched, best_iou = np.zeros(D, bool), np.full(D, -1, np.int64), np.zeros(D)
    if D == 0:
        return gt, scores, None, tp, matched, best_iou
    iou = iou_pairwise(det, gt)  # (D, G)
    if len(gt):
        best_iou = iou.max(axis=1)
    return gt, scores, iou, tp, matched, best_iou


def match_frame_numpy(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray,
                      iou_threshold: float = IOU_THRESHOLD) -> FrameMatch:
    """:func:`match_frame` with its greedy loop in numpy (the test's reference)."""
    gt, scores, iou, tp, matched, best_iou = _match_inputs(gt_boxes, det_boxes, det_scores)
    if iou is None:
        return FrameMatch(tp, matched, best_iou, len(gt))
    taken = np.zeros(len(gt), bool)
    for i in np.argsort(-scores, kind="stable"):
        if len(gt) == 0:
            break
        cand = np.where(taken, -1.0, iou[i])
        j = int(np.argmax(cand))
        if cand[j] >= iou_threshold and cand[j] > 0:
            tp[i] = True
            matched[i] = j
            taken[j] = True
            best_iou[i] = iou[i, j]
    return FrameMatch(tp, matched, best_iou, len(gt))


@kernel
def _greedy_match(iou: np.ndarray, order: np.ndarray, thr: float, tp: np.ndarray, matched: np.ndarray,
                  best_iou: np.ndarray) -> None:
    """The greedy loop of :func:`match_frame`, in place: detections in ``order``, each takes
    the free ground truth of highest IoU (``np.argmax`` of the IoU row with taken columns at
    -1: the first maximum, the first NaN if any) if that IoU is >= ``thr`` and > 0. Compiled:
    three numpy calls per detection cost more than the IoU matrix."""
    G = iou.shape[1]
    taken = np.zeros(G, np.bool_)
    for i in order:
        j = 0
        best = -1.0 if taken[0] else iou[i, 0]
        if best == best:
            for g in range(1, G):
                v = -1.0 if taken[g] else iou[i, g]
                if v != v:
                    j = g
                    best = v
                    break
                if v > best:
                    j = g
                    best = v
        if best >= thr and best > 0:
            tp[i] = True
            matched[i] = j
            taken[j] = True
            best_iou[i] = iou[i, j]


def average_precision(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
                      iou_threshold: float = IOU_THRESHOLD) -> DetectionMetrics:
    """AP (VOC all-point interpolation) and recall over frames.

    Args:
        frames: iterable of ``(gt_boxes (G, 5), det_boxes (D, 5), det_scores (D,))``, one per
            frame; apply :func:`roi_mask` first to restrict to the region of interest.
        iou_threshold: BEV IoU needed for a true positive (paper: 0.5).
    """
    frames = list(frames)
    return average_precision_of_matches([match_frame(gt, det, sc, iou_threshold) for gt, det, sc in frames],
                                        [sc for _, _, sc in frames])


def average_precision_of_matches(matches: Sequence[FrameMatch], scores: Sequence[np.ndarray]) -> DetectionMetrics:
    """:func:`average_precision` from each frame's :func:`match_frame` (made once and shared
    with the attack objective, ``sim.evaluate.EpisodeEvaluation.matches``) and its scores (D,)."""
    all_scores, all_tp = [], []
    n_gt = 0
    for m, sc in zip(matches, scores):
        n_gt += m.n_gt
        all_scores.append(_scores(sc, len(m.tp)))
        all_tp.append(m.tp)
    scores = np.concatenate(all_scores) if all_scores else np.zeros(0)
    tp = np.concatenate(all_tp) if all_tp else np.zeros(0, bool)
    return ap_from_matches(scores, tp, n_gt)


def ap_from_matches(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> DetectionMetrics:
    """AP and recall from pooled detections: scores (D,), true-positive flags (D,), number of
    ground-truth boxes. Ties in score keep the given order (stable sort)."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    tp = np.asarray(tp, bool).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    tp_sorted = tp[order]
    ctp = np.cumsum(tp_sorted)
    cfp = np.cumsum(~tp_sorted)
    n_det = len(scores)
    n_tp = int(tp.sum())
    precision = ctp / np.maximum(ctp + cfp, 1)
    if n_gt == 0:
        return DetectionMetrics(float("nan"), float("nan"), 0, n_det, n_tp, precision, np.zeros(n_det))
    recall = ctp / n_gt
    ap = voc_ap(recall, precision)
    return DetectionMetrics(ap, n_tp / n_gt, int(n_gt), n_det, n_tp, precision, recall)


def grouped_average_precision(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                              groups: Sequence, iou_threshold: float = IOU_THRESHOLD) -> dict:
    """AP and recall per group of ground-truth boxes (e.g. vehicles whose mesh was seen in
    training against vehicles whose mesh was left out), matching every detection once.

    Each frame's detections are matched to *all* its ground truth (:func:`match_frame`), so a
    group's numbers are what the overall evaluation says about that group's boxes. Then, per
    group ``g``:

    * a true positive matched to a box of ``g`` counts for ``g``; one matched to a box of
      another group is left out of ``g`` (neither true nor false positive: KITTI's rule for
      boxes of another difficulty);
    * a false positive is *attributed* to the group of the ground-truth box it overlaps most
      (best IoU > 0: a mislocalised or duplicate detection of that vehicle);
    * a false positive that overlaps no ground-truth box ("background") belongs to no vehicle:
      ``ap`` leaves it out; ``ap_with_background_fp`` counts every background false positive
      against every group (a lower bound that penalises a small group more, because its true
      positives are fewer for the same false positives).

    Recall (matched boxes / boxes of the group) does not depend on the attribution.

    Args:
        frames: iterable of ``(gt_boxes (G, 5), gt_group (G,), det_boxes (D, 5), det_scores (D,))``
            per frame; ``gt_group`` holds a label of ``groups`` per box (labels not in ``groups``
            take part in the matching but are reported in no group).
        groups: the group labels to report, in this order.
        iou_threshold: BEV IoU of a true positive.
    Returns:
        ``{"groups": {label: {"ap", "recall", "n_gt", "n_tp", "n_fp", "ap_with_background_fp"}},
        "n_det", "n_fp_background"}``; a group without boxes has NaN ap / recall.
    """
    labels = list(groups)
    index = {g: k for k, g in enumerate(labels)}
    all_scores, all_tp, all_owner = [], [], []
    n_gt = np.zeros(len(labels), np.int64)
    for gt, gt_group, det, sc in frames:
        gt = as_boxes(gt).reshape(-1, 5)
        det = as_boxes(det).reshape(-1, 5)
        gidx = np.array([index.get(g, -2) for g in np.asarray(gt_group).reshape(-1)], np.int64)
        if len(gidx) != len(gt):
            raise ValueError(f"got {len(gidx)} group labels for {len(gt)} ground-truth boxes")
        n_gt += np.bincount(gidx[gidx >= 0], minlength=len(labels))
        m = match_frame(gt, det, sc, iou_threshold)
        # owner: group index of the box a detection belongs to; -1 background, -2 unreported
        owner = np.full(len(det), -1, np.int64)
        if len(det) and len(gt):
            iou = iou_pairwise(det, gt)
            best = np.argmax(iou, axis=1)
            near = iou[np.arange(len(det)), best] > 0
            owner[near] = gidx[best[near]]
            owner[m.tp] = gidx[m.matched_gt[m.tp]]
        all_scores.append(_scores(sc, len(det)))
        all_tp.append(m.tp)
        all_owner.append(owner)
    scores = np.concatenate(all_scores) if all_scores else np.zeros(0)
    tp = np.concatenate(all_tp) if all_tp else np.zeros(0, bool)
    owner = np.concatenate(all_owner) if all_owner else np.zeros(0, np.int64)
    background = (owner == -1) & ~tp
    out = {}
    for k, label in enumerate(labels):
        own = owner == k
        m = ap_from_matches(scores[own], tp[own], int(n_gt[k]))
        wide = ap_from_matches(scores[own | background], tp[own | background], int(n_gt[k]))
        out[label] = {"ap": m.ap, "recall": m.recall, "n_gt": m.n_gt, "n_tp": m.n_tp, "n_fp": m.n_det - m.n_tp,
                      "ap_with_background_fp": wide.ap}
    return {"groups": out, "n_det": int(len(scores)), "n_fp_background": int(background.sum())}


def voc_ap(recall: np.ndarray, precision: np.ndarray) -> float:
    """All-point interpolated AP (VOC 2010+): area under the monotone precision envelope.

    Args:
        recall, precision: (D,) curves over score-sorted detections (recall non-decreasing).
    """
    r = np.concatenate([[0.0], np.asarray(recall, dtype=np.float64), [1.0]])
    p = np.concatenate([[0.0], np.asarray(precision, dtype=np.float64), [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]  # envelope: max precision at recall >= r
    steps = np.nonzero(r[1:] != r[:-1])[0]
    return float(np.sum((r[steps + 1] - r[steps]) * p[steps + 1]))


def roi_mask(boxes: np.ndarray, ego_pose: np.ndarray, ahead: float = ROI_AHEAD, behind: float = 0.0,
             lateral: float | None = None) -> np.ndarray:
    """Which boxes are in the paper's region of interest: centre within ``ahead`` m in front of
    the ego (and ``behind`` m behind it), optionally within ``lateral`` m to either side.

    Args:
        boxes: (N, 5) map frame. ego_pose: (3,) x, y, yaw of the ego in the map frame.
    Returns:
        (N,) bool.
    """
    local = boxes_to_frame(as_boxes(boxes).reshape(-1, 5), ego_pose)
    ok = (local[:, 0] >= -behind) & (local[:, 0] <= ahead)
    if lateral is not None:
        ok &= np.abs(local[:, 1]) <= lateral
    return ok


def evaluate_frames(gt: Sequence[np.ndarray], det: Sequence[np.ndarray], scores: Sequence[np.ndarray],
                    ego_poses: Sequence[np.ndarray] | None = None, iou_threshold: float = IOU_THRESHOLD,
                    ahead: float = ROI_AHEAD, lateral: float | None = None) -> DetectionMetrics:
    """AP/recall over frames, restricted to the ROI of each frame's ego pose when given (both the
    ground truth and the detections are filtered by their centre)."""
    frames = []
    for t in range(len(gt)):
        g = as_boxes(gt[t]).reshape(-1, 5)
        d = as_boxes(det[t]).reshape(-1, 5)
        s = _scores(scores[t], len(d))
        if ego_poses is not None:
            g = g[roi_mask(g, ego_poses[t], ahead, lateral=lateral)]
            keep = roi_mask(d, ego_poses[t], ahead, lateral=lateral)
            d, s = d[keep], s[keep]
        frames.append((g, d, s))
    return average_precision(frames, iou_threshold)


# ------------------------------------------------------------------ attack objective terms
# Paper Eq. 4: l_det = -alpha * sum_TP IoU * conf + beta * sum_FP (1 - IoU) * conf.

def true_positive_term(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray,
                       iou_threshold: float = IOU_THRESHOLD) -> float:
    """Sum over true-positive detections of IoU x confidence (one frame; paper Eq. 4)."""
    m = match_frame(gt_boxes, det_boxes, det_scores, iou_threshold)
    s = _scores(det_scores, len(m.tp))
    return float(np.sum(m.iou[m.tp] * s[m.tp]))


def false_positive_term(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray,
                        iou_threshold: float = IOU_THRESHOLD) -> float:
    """Sum over false-positive detections of (1 - IoU) x confidence, IoU being the detection's
    best IoU with any ground-truth box (0 if none) (one frame; paper Eq. 4)."""
    m = match_frame(gt_boxes, det_boxes, det_scores, iou_threshold)
    s = _scores(det_scores, len(m.tp))
    fp = ~m.tp
    return float(np.sum((1.0 - m.iou[fp]) * s[fp]))


def detection_frame_terms(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray,
                iou_threshold: float = IOU_THRESHOLD, match: FrameMatch | None = None) -> tuple[float, float]:
    """(:func:`true_positive_term`, :func:`false_positive_term`) of one frame from one matching
    (the attack objective needs both for every frame of every query); ``match``: that frame's
    :func:`match_frame` at ``iou_threshold`` when the caller has it."""
    m = match_frame(gt_boxes, det_boxes, det_scores, iou_threshold) if match is None else match
    s = _scores(det_scores, len(m.tp))
    fp = ~m.tp
    return float(np.sum(m.iou[m.tp] * s[m.tp])), float(np.sum((1.0 - m.iou[fp]) * s[fp]))


def detection_loss(gt_boxes: np.ndarray, det_boxes: np.ndarray, det_scores: np.ndarray, alpha: float = 1.0,
                   beta: float = 1.0, iou_threshold: float = IOU_THRESHOLD) -> float:
    """Paper Eq. 4 for one frame: ``-alpha * TP + beta * FP`` (higher = worse detection)."""
    return (-alpha * true_positive_term(gt_boxes, det_boxes, det_scores, iou_threshold)
            + beta * false_positive_term(gt_boxes, det_boxes, det_scores, iou_threshold))
