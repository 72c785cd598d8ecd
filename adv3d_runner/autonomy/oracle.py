"""Oracle perception: a detector that returns the simulator's ground truth instead of detecting.

It cannot see the ground truth through ``detect(points)``; it receives it through
``observe_ground_truth(boxes_ego, n_points)`` before each frame, which
:class:`~.modular.ModularStack` forwards from the stack interface
(``AutonomyStack.observe_ground_truth``, called by the episode loop). Used by
``make_stack("oracle")`` (:mod:`.stacks`): no torch, no weights.
"""
from __future__ import annotations

import numpy as np

from .interface import Detections


class OracleDetector:
    """Ground-truth boxes of the actors hit by at least ``min_points`` LiDAR returns.

    Scores grow with the number of returns (0.5 at ``min_points``, 1.0 from 50 returns), so a
    shape that reflects fewer rays gets a lower confidence, as it would from a real detector.

    Args:
        min_points: returns an actor needs to be detected.
        max_range: m, actors whose centre is farther from the ego are not detected.
    """

    def __init__(self, min_points: int = 5, max_range: float = 100.0):
        self.min_points = int(min_points)
        self.max_range = float(max_range)
        self._boxes = np.zeros((0, 5))
        self._counts = np.zeros(0, np.int64)

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """Ground truth of the coming frame: (N, 5) boxes in the ego frame (NaN rows for absent
        actors) and (N,) returns per actor (``AutonomyStack.observe_ground_truth``)."""
        self._boxes = np.asarray(boxes_ego, dtype=np.float64).reshape(-1, 5)
        self._counts = np.asarray(n_points, dtype=np.int64).reshape(-1)

    def detect(self, points: np.ndarray) -> Detections:
        """Boxes in the ego frame; nothing when the frame has no points."""
        if len(points) == 0 or len(self._boxes) == 0:
            return Detections()
        b = self._boxes
        ok = np.isfinite(b).all(axis=1) & (self._counts >= self.min_points)
        ok &= np.hypot(np.nan_to_num(b[:, 0], nan=np.inf), np.nan_to_num(b[:, 1], nan=np.inf)) <= self.max_range
        n = self._counts[ok].astype(np.float64)
        scores = np.clip(0.5 + 0.5 * (n - self.min_points) / max(50.0 - self.min_points, 1.0), 0.5, 1.0)
        return Detections(b[ok], scores)
