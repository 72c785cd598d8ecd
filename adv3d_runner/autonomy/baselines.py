"""Non-learned baselines that share the learned models' interfaces.

:class:`ConstantVelocityPredictor` turns :class:`~.interface.Tracks` into
:class:`~.interface.Predictions` by extrapolating each track's Kalman velocity. It is the
reference a learned predictor must beat (its minADE over 6 s must be lower,
docs/predictor.md), and lets the episode loop run before any model is trained.
:class:`LaneFollowingPredictor` follows the lane graph instead (a stronger non-learned
baseline, and a sensible fallback for the planner).

Every predictor takes the scene's :class:`~adv3d_runner.scene.lanemap.LaneMap` once per
episode through ``reset(lane_map)`` and then predicts with ``predict(tracks)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scene.lanemap import LaneMap
from .interface import DT, PREDICTION_STEPS, Predictions, Tracks


@dataclass(frozen=True)
class ConstantVelocityPredictor:
    """Constant-velocity extrapolation with K speed-scaled modes.

    Attributes:
        speed_factors: one mode per factor, each extrapolating ``factor x velocity`` (the first
            is plain constant velocity).
        probabilities: mode probabilities (same length, normalised on use).
        steps: horizon in steps of ``dt`` (60 = 6 s).
        along_heading: extrapolate only the velocity component along the track's heading
            (the box yaw); False uses the full Kalman velocity.
    """

    speed_factors: tuple[float, ...] = (1.0, 0.8, 1.15)  # K = 3 modes, as the paper's stack
    probabilities: tuple[float, ...] = (0.6, 0.2, 0.2)
    steps: int = PREDICTION_STEPS
    dt: float = DT
    along_heading: bool = True

    def __post_init__(self) -> None:
        if len(self.speed_factors) != len(self.probabilities) or not self.speed_factors:
            raise ValueError("need one probability per speed factor")

    def reset(self, lane_map: LaneMap | None = None) -> None:
        """Nothing to do: constant velocity ignores the lanes (kept so every predictor has the
        same interface)."""

    def predict(self, tracks: Tracks) -> Predictions:
        """(N,) tracks -> Predictions with trajectories (N, K, steps, 2) at t + dt .. t + steps dt."""
        n = len(tracks)
        f = np.asarray(self.speed_factors, dtype=np.float64)
        p = np.asarray(self.probabilities, dtype=np.float64)
        t = np.arange(1, self.steps + 1) * self.dt  # (H,)
        vel = np.nan_to_num(np.asarray(tracks.velocities, dtype=np.float64).reshape(n, 2))
        boxes = np.asarray(tracks.boxes, dtype=np.float64).reshape(n, 5)
        xy = boxes[:, :2]
        if self.along_heading:
            # vehicles do not move sideways: keep the speed along the box heading only, which
            # removes the lateral velocity noise a young track has (0.2 m position noise at
            # 10 Hz is ~3 m/s of lateral velocity noise, i.e. a 15 m drift over 5 s)
            h = np.c_[np.cos(boxes[:, 4]), np.sin(boxes[:, 4])]
            vel = np.sum(vel * h, axis=1, keepdims=True) * h
        traj = xy[:, None, None, :] + f[None, :, None, None] * t[None, None, :, None] * vel[:, None, None, :]
        probs = np.broadcast_to(p / p.sum(), (n, len(p))).copy()
        return Predictions(tracks.ids.copy(), traj, probs, self.dt)



@dataclass
class LaneFollowingPredictor:
    """Lane-following extrapolation: each track keeps its lane (through successors), its lateral
    offset in the lane and its speed along its heading; K modes scale that speed.

    A track further than ``max_off_lane`` m outside every lane strip (or heading against every
    lane) falls back to constant velocity along its heading. Unlike plain constant velocity,
    a small heading error does not turn into a lane intrusion seconds later, which is what a
    planner downstream needs from a non-learned predictor on highways.

    Each lane's whole-lane corridor comes from the lane map
    (:meth:`~adv3d_runner.scene.lanemap.LaneMap.lane_corridor`, built once per map).

    Attributes:
        speed_factors, probabilities, steps, dt: as :class:`ConstantVelocityPredictor`.
        max_off_lane: m outside the nearest lane strip beyond which a track is not lane-bound.
        lane_map: the map given to :meth:`reset` (None before).
    """

    speed_factors: tuple[float, ...] = (1.0, 0.8, 1.15)
    probabilities: tuple[float, ...] = (0.6, 0.2, 0.2)
    steps: int = PREDICTION_STEPS
    dt: float = DT
    max_off_lane: float = 1.0
    lane_map: LaneMap | None = field(default=None, init=False, repr=False, compare=False)

    def reset(self, lane_map: LaneMap) -> None:
        """Predict on ``lane_map`` until the next reset."""
        self.lane_map = lane_map

    def predict(self, tracks: Tracks) -> Predictions:
        """(N,) tracks -> Predictions (N, K, steps, 2) along the lanes of the map given to
        :meth:`reset`."""
        lanes = self.lane_map
        if lanes is None:
            raise RuntimeError("LaneFollowingPredictor.reset(lane_map) must be called before predict")
        cv = ConstantVelocityPredictor(self.speed_factors, self.probabilities, self.steps, self.dt, along_heading=True)
        out = cv.predict(tracks)
        n = len(tracks)
        if n == 0 or not len(lanes):
            return out
        f = np.asarray(self.speed_factors, dtype=np.float64)
        t = np.arange(1, self.steps + 1) * self.dt
        boxes = np.asarray(tracks.boxes, dtype=np.float64)
        vel = np.nan_to_num(np.asarray(tracks.velocities, dtype=np.float64))
        ok = np.all(np.isfinite(boxes), axis=1)
        lane_ids = np.full(n, -1, np.int64)
        lane_ids[ok], _, d = lanes.locate_many(boxes[ok][:, [0, 1, 4]])
        reach = float(f.max()) * self.steps * self.dt
        for lid in np.unique(lane_ids[lane_ids >= 0]):
            rows = np.flatnonzero(lane_ids == lid)
            # the whole lane, then reach m (the fastest mode's travel) + a 10 m margin of successors
            cs = lanes.lane_corridor(int(lid), lanes.lane_length(int(lid)) + reach + 10.0)
            s0, d0 = cs.project(0, boxes[rows, :2])
            half = 0.5 * cs.width_at(np.zeros(len(rows), int), s0)
            lane_bound = np.abs(d0) - half <= self.max_off_lane  # the rest keep constant velocity
            heading = np.c_[np.cos(boxes[rows, 4]), np.sin(boxes[rows, 4])]
            speed = np.maximum(np.sum(vel[rows] * heading, axis=1), 0.0)
            s = s0[:, None, None] + f[None, :, None] * speed[:, None, None] * t[None, None, :]  # (R, K, H)
            xy = cs.pose_at(np.zeros(s.shape, int), s, np.broadcast_to(d0[:, None, None], s.shape))[..., :2]
            out.trajectories[rows[lane_bound]] = xy[lane_bound]
        return out
