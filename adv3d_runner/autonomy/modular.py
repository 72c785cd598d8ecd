"""A modular stack (detector -> tracker -> predictor -> planner) behind :class:`AutonomyStack`.

Autonomy-A is this class with the learned BEV detector and the learned predictor plugged in
(:func:`~.stacks.make_stack`); any object with the right methods works (e.g. the oracle detector
of :mod:`.oracle`, or :class:`~.baselines.LaneFollowingPredictor`).

Per episode, :meth:`ModularStack.reset` hands the scene's lane map to the predictor and the
planner (they keep no lane geometry of their own). Per frame: the detector turns ego-frame points
into ego-frame boxes; they are moved into the map frame with the ego pose (perfect
localisation), tracked, predicted and planned on. Each stage's wall time is reported in
``AutonomyOutputs.timings`` (seconds).
"""
from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from ..geometry.frames import boxes_from_frame
from ..scene.lanemap import LaneMap
from .baselines import LaneFollowingPredictor
from .interface import AutonomyOutputs, Detections, EgoState, Predictions, SceneContext, Tracks
from .planner import SamplingPlanner
from .tracker import MultiObjectTracker


class Detector(Protocol):
    def detect(self, points: np.ndarray) -> Detections:
        """Points (P, 3|4) in the ego frame -> detections with boxes in the **ego** frame."""
        ...


class GroundTruthDetector(Detector, Protocol):
    """A detector that also takes the simulator's ground truth (the oracle). Optional: the stack
    forwards ``observe_ground_truth`` only to detectors that have it."""

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """(N, 5) ego-frame boxes (NaN rows: absent actors) and (N,) LiDAR returns per actor."""
        ...


class Predictor(Protocol):
    def reset(self, lane_map: LaneMap) -> None:
        """Take the scene's lane map for the coming episode."""
        ...

    def predict(self, tracks: Tracks) -> Predictions:
        """Map-frame tracks -> multi-modal predictions in the map frame."""
        ...


class ModularStack:
    """Detector -> :class:`MultiObjectTracker` -> predictor -> :class:`SamplingPlanner`.

    Args:
        detector: object with ``detect(points) -> Detections`` (ego frame), and optionally
            ``observe_ground_truth(boxes_ego, n_points)`` (:class:`GroundTruthDetector`).
        predictor: object with ``reset(lane_map)`` and ``predict(tracks) -> Predictions``
            (default :class:`LaneFollowingPredictor`).
        tracker, planner: defaults are built with their default configs.
        prior_speed: start new tracks at the ego's speed (see ``MultiObjectTracker.update``).
    """

    def __init__(self, detector: Detector, predictor: Predictor | None = None,
                 tracker: MultiObjectTracker | None = None, planner: SamplingPlanner | None = None,
                 prior_speed: bool = True):
        self.detector = detector
        self.predictor = predictor if predictor is not None else LaneFollowingPredictor()
        self.tracker = tracker if tracker is not None else MultiObjectTracker()
        self.planner = planner if planner is not None else SamplingPlanner()
        self.prior_speed = prior_speed
        self.context: SceneContext | None = None

    def reset(self, context: SceneContext) -> None:
        """New episode in ``context``'s scene: clear the tracks and the plan hysteresis, and hand
        the lane map to the predictor and the planner."""
        self.context = context
        self.tracker.reset()
        self.predictor.reset(context.lane_map)
        self.planner.reset(context.lane_map)

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """Forwarded to the detector when it takes ground truth (the oracle); ignored otherwise."""
        observe = getattr(self.detector, "observe_ground_truth", None)
        if observe is not None:
            observe(boxes_ego, n_points)

    def step(self, points: np.ndarray, ego_state: EgoState) -> AutonomyOutputs:
        if self.context is None:
            raise RuntimeError("ModularStack.reset(context) must be called before step")
        timings = {}
        t0 = time.perf_counter()
        pts = np.asarray(points)
        local = self.detector.detect(pts.reshape(-1, pts.shape[-1]) if pts.size else np.zeros((0, 3)))
        dets = Detections(boxes_from_frame(local.boxes, ego_state.pose) if len(local) else np.zeros((0, 5)),
                          local.scores)
        t1 = time.perf_counter()
        tracks = self.tracker.update(dets, prior_speed=ego_state.speed if self.prior_speed else None)
        t2 = time.perf_counter()
        preds = self.predictor.predict(tracks)
        t3 = time.perf_counter()
        plan = self.planner.plan(ego_state, preds, tracks)
        t4 = time.perf_counter()
        timings.update(detector=t1 - t0, tracker=t2 - t1, predictor=t3 - t2, planner=t4 - t3)
        return AutonomyOutputs(dets, tracks, preds, plan, timings)
