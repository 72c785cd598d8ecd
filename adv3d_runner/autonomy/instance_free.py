"""Autonomy-B: an instance-free stack, the implicit occupancy model + the sampling planner.

Per episode, :meth:`OccupancyStack.reset` forgets the sweep history and hands the scene's lane
map to the planner. Per frame (:meth:`OccupancyStack.step`): the frame's points above the
ground are kept with the ego pose (the model stacks the sweeps of the last few frames, moved
into the current ego frame); the model encodes the frame into an
:class:`~adv3d_runner.autonomy.occupancy.ImplicitField`; the planner plans on it
(:class:`~adv3d_runner.autonomy.planner.SamplingPlanner` with ``occupancy=field``: the occupancy
collision and buffer terms, lane leaders from occupancy and flow). The outputs carry no
detections, tracks or predictions, and the field as ``occupancy`` (the evaluation and the
replay writer query it afterwards).

``timings``: ``occupancy`` = the model's time in this frame (voxelising the sweeps, encoding,
and every query the planner made), ``planner`` = the rest of planning (seconds).
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from .interface import AutonomyOutputs, Detections, EgoState, Predictions, SceneContext, Tracks
from .occupancy import OccupancyModel, keep_points
from .planner import SamplingPlanner


class OccupancyStack:
    """The :class:`~adv3d_runner.autonomy.interface.AutonomyStack` of Autonomy-B.

    Args:
        model: the trained :class:`~adv3d_runner.autonomy.occupancy.OccupancyModel`.
        planner: default :class:`SamplingPlanner` with its default config.
    """

    def __init__(self, model: OccupancyModel, planner: SamplingPlanner | None = None):
        self.model = model
        self.planner = planner if planner is not None else SamplingPlanner()
        self.context: SceneContext | None = None
        self._sweeps: deque = deque(maxlen=max(model.cfg.sweep_lags) + 1)

    def reset(self, context: SceneContext) -> None:
        """New episode: forget the sweeps and the plan hysteresis; the planner takes the map."""
        self.context = context
        self._sweeps.clear()
        self.planner.reset(context.lane_map)

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """Ignored: a learned stack sees only its LiDAR."""

    def step(self, points: np.ndarray, ego_state: EgoState) -> AutonomyOutputs:
        if self.context is None:
            raise RuntimeError("OccupancyStack.reset(context) must be called before step")
        t0 = time.perf_counter()
        pts = np.asarray(points)
        self._sweeps.appendleft((keep_points(pts.reshape(-1, pts.shape[-1]) if pts.size else np.zeros((0, 3)),
                                             self.model.cfg), ego_state.pose.copy()))
        sweeps = [self._sweeps[k] if k < len(self._sweeps) else None for k in self.model.cfg.sweep_lags]
        field = self.model.encode(sweeps, ego_state.pose, ego_state.speed)
        t1 = time.perf_counter()
        plan = self.planner.plan(ego_state, occupancy=field)
        t2 = time.perf_counter()
        decode = float(self.model.timings.get("decode", 0.0))
        timings = {"occupancy": (t1 - t0) + decode, "planner": (t2 - t1) - decode}
        return AutonomyOutputs(Detections(), Tracks(), Predictions(), plan, timings, occupancy=field)
