"""Recorders: callbacks around the episode loop (:class:`~adv3d_runner.sim.episode.Episode`).

After every step the episode hands each recorder an :class:`EpisodeFrame` (``on_frame``); when
it finishes it hands them the :class:`~adv3d_runner.sim.episode.EpisodeResult`
(``on_finish``), to which a recorder adds what it recorded. The loop itself keeps only what
every episode needs (poses, autonomy outputs, return counts); anything optional or not a result
(wall times, the points of every frame) is a recorder, after nuPlan's simulation callbacks.
``run_episode`` always uses :class:`TimingRecorder` and, with ``record_points``,
:class:`PointRecorder`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..autonomy.interface import AutonomyOutputs, EgoState

if TYPE_CHECKING:  # pragma: no cover - annotations only
    from ..sensors.lidar import LidarFrame
    from .episode import Episode, EpisodeResult

#: Stages of :attr:`~adv3d_runner.sim.episode.EpisodeResult.timings` (seconds per frame).
STAGES = ("lidar", "detector", "tracker", "predictor", "occupancy", "planner", "traffic", "total")


@dataclass(frozen=True, eq=False)
class EpisodeFrame:
    """What one step of an episode produced (map frame, metres, radians, seconds).

    Attributes:
        index: k, the frame's number in the episode (0 .. T-1).
        ego: the ego state the stack saw at frame k.
        actor_poses: (N, 3) x, y, yaw of the scene's actors at frame k (NaN rows: absent).
        lidar: the simulated LiDAR frame (ego frame; ``label`` indexes the world's actors).
        actor_points: (N,) LiDAR returns on each scene actor.
        outputs: the stack's outputs of frame k.
        seconds: stage -> wall time of this frame (:data:`STAGES`).
    """

    index: int
    ego: EgoState
    actor_poses: np.ndarray
    lidar: "LidarFrame"
    actor_points: np.ndarray
    outputs: AutonomyOutputs
    seconds: dict[str, float]


class Recorder(Protocol):
    """A callback of the episode loop."""

    def on_frame(self, episode: "Episode", frame: EpisodeFrame) -> None:
        """Called once per frame, in order, after the frame's step."""

    def on_finish(self, episode: "Episode", result: "EpisodeResult") -> None:
        """Called once with the finished result; may add what was recorded to it."""


class TimingRecorder:
    """Wall time per stage and frame -> ``result.timings`` (stage -> (T,) seconds)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []

    def on_frame(self, episode: "Episode", frame: EpisodeFrame) -> None:
        self.rows.append(frame.seconds)

    def on_finish(self, episode: "Episode", result: "EpisodeResult") -> None:
        result.timings = {s: np.array([float(r.get(s, 0.0)) for r in self.rows], dtype=np.float64).reshape(-1)
                          for s in STAGES}


class PointRecorder:
    """Every frame's LiDAR points -> ``result.points``: T float32 arrays (P, 5) x, y, z (ego
    frame), intensity, label (index of the scene actor hit, -1 background), for replay files."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []

    def on_frame(self, episode: "Episode", frame: EpisodeFrame) -> None:
        # labels as scene actor indices (-1 background)
        back = episode.label_to_actor
        lab = back[np.where(frame.lidar.label >= 0, frame.lidar.label, len(back) - 1)]
        self.points.append(np.c_[frame.lidar.points, lab.astype(np.float32)].astype(np.float32))

    def on_finish(self, episode: "Episode", result: "EpisodeResult") -> None:
        result.points = self.points
