"""A toy stack under test: oracle perception and a constant-velocity planner that brakes for
the nearest actor ahead in its lane (docs/tutorials/test_your_stack.md).

It uses only the public stack interface, ``adv3d_runner.autonomy.api``.
"""
from __future__ import annotations

import numpy as np

from adv3d_runner.autonomy.api import Plan, Sensors, StackInfo, StepOutput

HORIZON = 30     # plan steps of 0.1 s
GAP = 25.0       # m: brake for an actor closer than this ahead, within half a lane sideways
BRAKE = 3.0      # m/s^2


class ToyStack:
    def info(self) -> StackInfo:
        return StackInfo("toy", "1.0", provides=frozenset())  # a plan, nothing else

    def sensors(self) -> Sensors:
        return Sensors(lidar=True, ground_truth=True)  # oracle perception

    def reset(self, episode) -> None:
        self.dt = episode.dt

    def run_step(self, frame) -> StepOutput:
        ego = frame.ego
        boxes = frame.ground_truth if frame.ground_truth is not None else np.zeros((0, 5))
        boxes = boxes[np.isfinite(boxes).all(axis=1)]
        ahead = boxes[(boxes[:, 0] > 0) & (boxes[:, 0] < GAP) & (np.abs(boxes[:, 1]) < 1.8)]
        accel = -BRAKE if len(ahead) else 0.0
        t = np.arange(HORIZON + 1) * self.dt
        speed = np.maximum(ego.speed + accel * t, 0.0)
        s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * self.dt)])
        x, y, yaw = ego.pose
        traj = np.stack([x + s * np.cos(yaw), y + s * np.sin(yaw), np.full_like(s, yaw)], axis=1)
        return StepOutput(Plan(traj, speed, dt=self.dt))


def make() -> ToyStack:
    """The factory adv3d calls (``--autonomy toy_stack:make``)."""
    return ToyStack()
