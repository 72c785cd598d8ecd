"""The adversarial objective of paper Eq. 3-5, summed over the frames of an episode.

``C = sum_t [ w_det * l_det^t + lambda_pred * l_pred^t + lambda_plan * c_plan^t ]`` with

* ``l_det^t = -alpha * sum_TP IoU * conf + beta * sum_FP (1 - IoU) * conf`` over the frame's
  detections in the region of interest (:mod:`adv3d_runner.metrics.detection`);
* ``l_pred^t`` = ``1/K sum_modes sum_h ||g - p||``: the displacement error of the predicted tracks
  matched to ground-truth actors, **summed over the H waypoints** as Eq. 5 writes it (m), averaged
  over the modes and over those actors (:func:`adv3d_runner.metrics.prediction.prediction_loss`).
  ``pred_reduction="mean"`` averages over the waypoints instead (the multi-modal ADE, the form
  runs made before the protocol of docs/results.md): the same optimum for the term alone, but with lambda_pred = 0.1 it
  weighs prediction about H = 60 times less in the sum of the three terms;
* ``c_plan^t = c_jerk + c_lat``: mean |jerk| + mean |lateral acceleration| of the frame's plan
  (:func:`adv3d_runner.metrics.comfort.plan_comfort_cost`).

Higher C = worse autonomy; the attack **maximises** C. Every weight is configurable and the
paper's ablations (Table 3 / supp. Table 6) are named presets (:data:`ABLATIONS`): M0 = all
three terms (the paper's full objective), M1 = detection only, M2 = prediction only, M3 =
planning only, M4 = detection + prediction, M5 = detection + planning.

**Autonomy-B** (instance-free, paper appendix A.4) has no boxes and no trajectories; its terms
are over the occupancy query set Q of the frame (``adv3d_runner.sim.evaluate.occupancy_frames``):

* ``l_det^t = -Soft-IoU`` of the predicted occupancy against the ground truth over Q;
* ``l_pred^t`` = the foreground flow end-point error (m/s), the mean ``||f - f^||`` over the
  occupied query points;
* ``c_plan^t`` as above; lambda_pred = 1.0, lambda_plan = 0.5 (:data:`ABLATIONS_B`, the same
  names M0-M5; ``alpha``, ``beta`` and ``pred_reduction`` do not apply).

The functions here are pure: per-frame terms from plain arrays (hand-made in tests), and
:func:`episode_objective` that pulls those arrays from an ``EpisodeResult`` with the same
ground-truth rules as the episode metrics (``adv3d_runner.sim.evaluate``), from the same
:class:`~adv3d_runner.sim.evaluate.EpisodeEvaluation` when the caller passes it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Mapping, Sequence

import numpy as np

from ..errors import ConfigError
from ..metrics.comfort import plan_comfort_cost
from ..metrics.detection import IOU_THRESHOLD, detection_frame_terms
from ..metrics.occupancy import frame_terms
from ..metrics.prediction import prediction_loss

LAMBDA_PRED = 0.1
LAMBDA_PLAN = 0.5
#: How l_pred reduces the displacement error over the H waypoints: "sum" as paper Eq. 5 writes
#: it (the default), "mean" the horizon average (the form of the runs made before the protocol of docs/results.md).
PRED_REDUCTIONS = ("sum", "mean")
DEFAULT_PRED_REDUCTION = "sum"
#: The form of runs whose run.json predates the choice (they were all made with the mean).
LEGACY_PRED_REDUCTION = "mean"
LAMBDA_PRED_B = 1.0  # Autonomy-B (paper appendix A.4)


@dataclass(frozen=True)
class ObjectiveWeights:
    """Weights and form of Eq. 3-5. ``det``, ``pred``, ``plan`` multiply the three per-frame
    terms (0 switches a term off); ``alpha``/``beta`` weight true and false positives inside
    l_det; ``pred_reduction`` is how l_pred reduces over the waypoints (:data:`PRED_REDUCTIONS`:
    ``"sum"``, Eq. 5 as written, or ``"mean"``)."""

    det: float = 1.0
    pred: float = LAMBDA_PRED
    plan: float = LAMBDA_PLAN
    alpha: float = 1.0
    beta: float = 1.0
    iou_threshold: float = IOU_THRESHOLD
    pred_reduction: str = DEFAULT_PRED_REDUCTION

    def __post_init__(self) -> None:
        for k, v in self.numbers().items():
            if not np.isfinite(v) or v < 0:
                raise ConfigError(f"objective weight {k} must be a finite number >= 0, got {v}")
        if self.det == 0 and self.pred == 0 and self.plan == 0:
            raise ConfigError("the objective needs at least one of det, pred, plan > 0")
        if self.pred_reduction not in PRED_REDUCTIONS:
            raise ConfigError(f"pred_reduction must be one of {', '.join(PRED_REDUCTIONS)}, got {self.pred_reduction!r}")

    def numbers(self) -> dict[str, float]:
        """The numeric weights (every field but ``pred_reduction``)."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self) if f.name != "pred_reduction"}

    def as_dict(self) -> dict:
        return {**self.numbers(), "pred_reduction": self.pred_reduction}


#: The paper's objective ablations (supp. Table 6): which terms are on.
ABLATIONS: dict[str, ObjectiveWeights] = {
    "M0": ObjectiveWeights(),
    "M1": ObjectiveWeights(det=1.0, pred=0.0, plan=0.0),
    "M2": ObjectiveWeights(det=0.0, pred=LAMBDA_PRED, plan=0.0),
    "M3": ObjectiveWeights(det=0.0, pred=0.0, plan=LAMBDA_PLAN),
    "M4": ObjectiveWeights(det=1.0, pred=LAMBDA_PRED, plan=0.0),
    "M5": ObjectiveWeights(det=1.0, pred=0.0, plan=LAMBDA_PLAN),
}

#: Autonomy-B's objective and its ablations: the same presets with lambda_pred = 1.0.
ABLATIONS_B: dict[str, ObjectiveWeights] = {
    name: replace(w, pred=LAMBDA_PRED_B if w.pred > 0 else 0.0) for name, w in ABLATIONS.items()}


def presets_for(autonomy: str = "A") -> dict[str, ObjectiveWeights]:
    """The named presets of a stack: :data:`ABLATIONS_B` for the instance-free stacks
    (``adv3d_runner.autonomy.stacks.INSTANCE_FREE``), :data:`ABLATIONS` otherwise."""
    from ..autonomy.stacks import INSTANCE_FREE

    return ABLATIONS_B if autonomy in INSTANCE_FREE else ABLATIONS


def parse_objective(text: str | None, autonomy: str = "A") -> ObjectiveWeights:
    """``"M0"``..``"M5"``, or comma-separated ``key=value`` overrides of M0
    (``"det=1,pred=0.1,plan=0.5,alpha=1,beta=1"``), optionally after a preset
    (``"M1,beta=2"``). The presets are the stack's (:func:`presets_for`). The form of l_pred is
    not part of this text: it is its own option (``--pred-reduction``, ``AttackConfig.pred_reduction``)."""
    presets = presets_for(autonomy)
    if not text:
        return presets["M0"]
    w = presets["M0"]
    fields = set(w.numbers())
    for part in [p.strip() for p in text.split(",") if p.strip()]:
        if part.upper() in presets:
            w = presets[part.upper()]
            continue
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise ConfigError(f"--objective: expected M0..M5 or key=value with key in {sorted(fields)}, got {part!r}")
        try:
            w = replace(w, **{key: float(value)})
        except ValueError:
            raise ConfigError(f"--objective: {key} must be a number, got {value!r}") from None
    return w


# ------------------------------------------------------------------------ per-frame terms

def detection_terms(frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    iou_threshold: float = IOU_THRESHOLD, matches: Sequence | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per frame sum_TP IoU x conf and sum_FP (1 - IoU) x conf.

    Args:
        frames: T tuples (gt boxes (G, 5), detected boxes (D, 5), scores (D,)), already
            restricted to the region of interest.
        matches: the frames' ``match_frame`` at ``iou_threshold`` when the caller has them
            (``EpisodeEvaluation.matches``); made here otherwise.
    Returns:
        tp (T,), fp (T,), both >= 0.
    """
    ms = [None] * len(frames) if matches is None else matches
    terms = np.array([detection_frame_terms(g, d, s, iou_threshold, m) for (g, d, s), m in zip(frames, ms)],
                     dtype=np.float64).reshape(-1, 2)
    return np.ascontiguousarray(terms[:, 0]), np.ascontiguousarray(terms[:, 1])


def prediction_terms(pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                     reduction: str = DEFAULT_PRED_REDUCTION) -> np.ndarray:
    """Per frame l_pred (Eq. 5): mean over matched actors of the mode-averaged displacement error,
    summed over the valid waypoints (``reduction="sum"``, m x waypoints) or averaged over them
    (``"mean"``: the ADE, m); 0 for a frame without matched predictions.

    Args:
        pairs: T tuples (predictions (M, K, H, 2), true futures (M, H, 2), valid (M, H)).
        reduction: ``"sum"`` or ``"mean"`` (:data:`PRED_REDUCTIONS`).
    """
    return np.array([prediction_loss(p, g, v, reduction=reduction) if len(p) else 0.0 for p, g, v in pairs],
                    dtype=np.float64).reshape(-1)


def planning_terms(plans: Sequence[np.ndarray], dt: float = 0.1) -> np.ndarray:
    """Per frame c_plan = mean |jerk| + mean |lateral acceleration| of the plan (T,) (Eq. 5).

    Args:
        plans: T plan trajectories (P, 3) x, y, yaw (or (P, 2)) sampled every ``dt``.
    """
    return np.array([plan_comfort_cost(p, dt) for p in plans], dtype=np.float64).reshape(-1)


@dataclass
class ObjectiveValue:
    """The objective of one episode: ``total`` and its frame sums (unweighted) per term. For an
    instance-free stack ``tp`` and ``fp`` are None and ``soft_iou`` holds the frame sum of the
    occupancy Soft-IoU (``det`` = its negative)."""

    total: float
    det: float
    tp: float | None
    fp: float | None
    pred: float
    plan: float
    frames: int
    soft_iou: float | None = None
    #: terms the stack cannot provide ("det", "pred"): left out of ``total``, reported as null
    not_available: tuple[str, ...] = ()

    def components(self) -> dict:
        if self.not_available:
            out = {"det": self.det, "tp": self.tp, "fp": self.fp, "pred": self.pred, "plan": self.plan,
                   "frames": self.frames}
            for term in self.not_available:
                out.update({"det": None, "tp": None, "fp": None} if term == "det" else {term: None})
            return {**out, "not_available": list(self.not_available)}
        if self.soft_iou is not None:
            return {"det": self.det, "soft_iou": self.soft_iou, "pred": self.pred, "plan": self.plan,
                    "frames": self.frames}
        return {"det": self.det, "tp": self.tp, "fp": self.fp, "pred": self.pred, "plan": self.plan,
                "frames": self.frames}


def combine(tp: np.ndarray, fp: np.ndarray, pred: np.ndarray, plan: np.ndarray,
            weights: ObjectiveWeights = ABLATIONS["M0"]) -> ObjectiveValue:
    """Eq. 3 summed over the frames: per-frame term arrays (T,) -> :class:`ObjectiveValue`.

    Non-finite per-frame terms (a broken output) propagate to a non-finite total, which the
    searchers penalise rather than trust."""
    tp, fp, pred, plan = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (tp, fp, pred, plan))
    det = -weights.alpha * tp + weights.beta * fp
    total = weights.det * det.sum() + weights.pred * pred.sum() + weights.plan * plan.sum()
    return ObjectiveValue(float(total), float(det.sum()), float(tp.sum()), float(fp.sum()), float(pred.sum()),
                          float(plan.sum()), int(max(len(tp), len(pred), len(plan))))


def occupancy_terms(frames: Sequence[Sequence]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (Soft-IoU of occupancy, foreground flow EPE) over the frame's query set
    (:func:`adv3d_runner.metrics.occupancy.frame_terms`), (T,) each.

    Args:
        frames: T lists of :class:`~adv3d_runner.metrics.occupancy.OccupancySample`.
    """
    terms = np.array([frame_terms(list(f)) for f in frames], dtype=np.float64).reshape(-1, 2)
    return terms[:, 0], terms[:, 1]


def combine_occupancy(soft_iou: np.ndarray, epe: np.ndarray, plan: np.ndarray,
                      weights: ObjectiveWeights = ABLATIONS_B["M0"]) -> ObjectiveValue:
    """Autonomy-B's objective summed over the frames: per-frame Soft-IoU, EPE (m/s) and c_plan
    (T,) -> :class:`ObjectiveValue` (l_det = -Soft-IoU; ``alpha``/``beta`` unused)."""
    iou, epe, plan = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (soft_iou, epe, plan))
    total = weights.det * -iou.sum() + weights.pred * epe.sum() + weights.plan * plan.sum()
    return ObjectiveValue(float(total), float(-iou.sum()), None, None, float(epe.sum()), float(plan.sum()),
                          int(max(len(iou), len(epe), len(plan))), soft_iou=float(iou.sum()))


def episode_objective(result, weights: ObjectiveWeights = ABLATIONS["M0"], evaluation=None) -> ObjectiveValue:
    """The objective of an :class:`~adv3d_runner.sim.episode.EpisodeResult` (all frames); for an
    instance-free stack (its outputs carry occupancy) Autonomy-B's terms (module docstring).

    ``evaluation``: the episode's :class:`~adv3d_runner.sim.evaluate.EpisodeEvaluation` (its
    detection frames and prediction pairs) when the caller already has it, e.g. to share it
    with ``episode_metrics``; computed here otherwise.
    """
    from ..sim.evaluate import MIN_GT_POINTS, episode_evaluation

    if evaluation is None:
        evaluation = episode_evaluation(result)
    elif evaluation.min_gt_points != MIN_GT_POINTS:
        raise ValueError(f"the objective uses min_gt_points={MIN_GT_POINTS}, the evaluation has "
                         f"{evaluation.min_gt_points}")
    plan = (planning_terms(result.plans(), result.dt) if evaluation.plan_comfort is None
            else np.array([c.jerk + c.lat for c in evaluation.plan_comfort], dtype=np.float64).reshape(-1))
    if evaluation.occupancy is not None:
        iou, epe = occupancy_terms(evaluation.occupancy)
        return combine_occupancy(iou, epe, plan, weights)
    tp, fp = detection_terms(evaluation.detection, weights.iou_threshold, evaluation.matches(weights.iou_threshold))
    # l_pred is measured even when its weight is 0 (M1, M3, M5): the journal reports every term
    # unweighted, whatever the search maximised.
    pred = prediction_terms(evaluation.prediction, weights.pred_reduction)
    missing = tuple(t for t, output in (("det", "detections"), ("pred", "predictions"))
                    if output in getattr(evaluation, "not_available", ()))
    if missing:  # a stack without detections or predictions: only the terms it has count
        from dataclasses import replace

        if all(getattr(weights, t) == 0 for t in TERMS if t not in missing):
            raise ConfigError(f"the objective weighs only {', '.join(t for t in TERMS if getattr(weights, t))}, which "
                              f"this stack does not provide (not available: {', '.join(missing)}); weigh plan")
        value = combine(tp, fp, pred, plan, replace(weights, **{t: 0.0 for t in missing}))
        return replace(value, not_available=missing)
    return combine(tp, fp, pred, plan, weights)


#: The three terms of Eq. 3 in the order they are reported, with their weight's field.
TERMS = ("det", "pred", "plan")


def term_split(components: Mapping[str, float], weights: ObjectiveWeights) -> dict[str, dict[str, float]]:
    """Each term of the objective apart: ``{term: {"unweighted", "weight", "weighted"}}`` for
    det, pred, plan from a query's ``components`` (the unweighted frame sums; ``det`` already
    holds alpha and beta). ``weighted`` = weight x unweighted, so the three weighted values add
    up to the objective (without a realism penalty); the unweighted values never do, and are
    never added up. ``pred``'s unit follows ``weights.pred_reduction`` (m x waypoints summed, or
    m). A term the stack does not provide (null in ``components``) is NaN: not available."""
    out = {}
    for term in TERMS:
        raw = components.get(term)
        value = float("nan") if raw is None else float(raw)
        w = float(getattr(weights, term))
        out[term] = {"unweighted": value, "weight": w, "weighted": w * value}
    return out
