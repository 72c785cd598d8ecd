"""A modular stack (detector -> tracker -> predictor -> planner) behind :class:`AutonomyStack`.

Autonomy-A is this class with the learned BEV detector and the learned predictor plugged in;
until they exist, any object with the right method works (e.g. an oracle detector in tests, or
:class:`~.baselines.LaneFollowingPredictor`).

Per frame: the detector turns ego-frame points into ego-frame boxes; they are moved into the
map frame with the ego pose (perfect localisation), tracked, predicted and planned on. Each
stage's wall time is reported in ``AutonomyOutputs.timings`` (seconds).
"""
from __future__ import annotations

import time
from typing import Any, Protocol, Sequence

import numpy as np

from ..geometry.frames import boxes_from_frame
from .baselines import LaneFollowingPredictor
from .interface import AutonomyOutputs, Detections, EgoState, Predictions, Tracks
from .planner import SamplingPlanner
from .tracker import MultiObjectTracker


class Detector(Protocol):
    def detect(self, points: np.ndarray) -> Detections:
        """Points (P, 3|4) in the ego frame -> detections with boxes in the **ego** frame."""
        ...


class Predictor(Protocol):
    def predict(self, tracks: Tracks, lanes: Sequence[Any]) -> Predictions:
        """Map-frame tracks (+ the lane map) -> multi-modal predictions in the map frame."""
        ...


class ModularStack:
    """Detector -> :class:`MultiObjectTracker` -> predictor -> :class:`SamplingPlanner`.

    Args:
        detector: object with ``detect(points) -> Detections`` (ego frame).
        predictor: object with ``predict(tracks, lanes) -> Predictions``
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

    def reset(self) -> None:
        self.tracker.reset()
        self.planner.reset()

    def step(self, points: np.ndarray, ego_state: EgoState, lane_map: Sequence[Any]) -> AutonomyOutputs:
        timings = {}
        t0 = time.perf_counter()
        pts = np.asarray(points)
        local = self.detector.detect(pts.reshape(-1, pts.shape[-1]) if pts.size else np.zeros((0, 3)))
        dets = Detections(boxes_from_frame(local.boxes, ego_state.pose) if len(local) else np.zeros((0, 5)),
                          local.scores)
        t1 = time.perf_counter()
        tracks = self.tracker.update(dets, prior_speed=ego_state.speed if self.prior_speed else None)
        t2 = time.perf_counter()
        preds = self.predictor.predict(tracks, lane_map)
        t3 = time.perf_counter()
        plan = self.planner.plan(ego_state, lane_map, preds, tracks)
        t4 = time.perf_counter()
        timings.update(detector=t1 - t0, tracker=t2 - t1, predictor=t3 - t2, planner=t4 - t3)
        return AutonomyOutputs(dets, tracks, preds, plan, timings)
