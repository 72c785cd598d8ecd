"""The stack interface: what an autonomy stack under test implements (docs/stacks.md).

This module is the whole of adv3d a stack author needs: a stack is any object with the four
methods of :class:`Stack`, made by a factory that adv3d finds through the ``adv3d.stacks``
entry-point group or as ``--autonomy package.module:factory``. It follows the CARLA
Leaderboard's ``AutonomousAgent``: :meth:`Stack.sensors` declares what the stack needs,
:meth:`Stack.run_step` answers each frame.

Per episode the stack gets an :class:`Episode` (the lanes, the LiDAR rig, dt); per frame a
:class:`Frame` (the LiDAR points of every sensor with the sensor each came from, the ego's state,
the time, and ground truth only if it asked for it). It answers a :class:`StepOutput`: the plan,
and whatever else it has (detections, tracks, predictions, occupancy). What a stack does not
provide is reported as not available by the metrics and the objective, never as zero.

Versioned: :data:`STACK_API_VERSION` changes its major number only when a stack written for the
old one would break. Units: metres, seconds, radians; the map frame is the scene's; the ego
frame has +x forward, +y left, origin at the ego's footprint centre on the ground.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from .interface import DT, Detections, EgoState, Plan, Predictions, Tracks

__all__ = ["STACK_API_VERSION", "OUTPUTS", "StackInfo", "Sensors", "Lane", "LidarSensor", "Episode", "Frame",
           "StepOutput", "Stack", "EgoState", "Detections", "Tracks", "Predictions", "Plan", "DT", "remote_stack"]

#: The interface's version, "major.minor".
STACK_API_VERSION = "1.0"

#: What a stack can provide beyond its plan (the plan is always required).
OUTPUTS = ("detections", "tracks", "predictions", "occupancy")


@dataclass(frozen=True)
class StackInfo:
    """Who the stack is: every run, journal, replay, report and table records it.

    Attributes:
        name: short name (``--autonomy`` shows it).
        version: the stack's own version string.
        provides: which of :data:`OUTPUTS` its :class:`StepOutput` carries.
        fingerprint: what identifies its behaviour beyond the version (weights' hashes,
            parameters), or "".
    """

    name: str
    version: str
    provides: frozenset[str] = frozenset()
    fingerprint: str = ""

    def __post_init__(self) -> None:
        unknown = set(self.provides) - set(OUTPUTS)
        if unknown:
            raise ValueError(f"StackInfo.provides: unknown outputs {sorted(unknown)} (known: {', '.join(OUTPUTS)})")
        object.__setattr__(self, "provides", frozenset(self.provides))

    def as_dict(self) -> dict:
        return {"name": self.name, "version": self.version, "provides": sorted(self.provides),
                "fingerprint": self.fingerprint, "api": STACK_API_VERSION}


@dataclass(frozen=True)
class Sensors:
    """What a stack asks for (CARLA's ``sensors()``).

    Attributes:
        lidar: the LiDAR points (every stack under test; False only for a map-only baseline).
        ground_truth: the actors' true boxes in the ego frame each frame (oracle perception:
            a stack that asks for it is not testing perception).
    """

    lidar: bool = True
    ground_truth: bool = False


@dataclass(frozen=True)
class Lane:
    """One lane of the map. ``centerline`` (P, 2) map-frame m in driving direction, ``width``
    (P,) m; neighbour and successor ids; ``speed_limit`` m/s or None."""

    id: int
    centerline: np.ndarray
    width: np.ndarray
    left: int | None = None
    right: int | None = None
    successors: tuple[int, ...] = ()
    speed_limit: float | None = None


@dataclass(frozen=True)
class LidarSensor:
    """One LiDAR of the rig: ``model`` (e.g. ``hdl64``), ``mount`` (x, y, z, roll, pitch, yaw)
    in the ego frame (m, rad), ``channels`` (lasers) and ``columns`` (firings per turn)."""

    model: str
    mount: tuple[float, float, float, float, float, float]
    channels: int
    columns: int


@dataclass(frozen=True)
class Episode:
    """What a stack learns once per episode (:meth:`Stack.reset`)."""

    scene_id: str
    dt: float
    lanes: tuple[Lane, ...]
    rig: tuple[LidarSensor, ...] = ()


@dataclass(frozen=True)
class Frame:
    """One frame (10 Hz).

    Attributes:
        index: frame number from 0; time: s since the episode's start.
        ego: the ego's state in the map frame (pose x, y, yaw; speed; acceleration; ...).
        points: (P, 4) float32 x, y, z (m) and intensity in [0, 1], ego frame, every sensor.
        sensor: (P,) int8, the index in :attr:`Episode.rig` of the sensor of each point.
        ground_truth: (N, 5) x, y, length, width, yaw of every actor in the ego frame (NaN
            rows: absent this frame), only for a stack whose :class:`Sensors` asked for it.
        ground_truth_points: (N,) LiDAR returns on each actor (with ``ground_truth``).
    """

    index: int
    time: float
    ego: EgoState
    points: np.ndarray
    sensor: np.ndarray
    ground_truth: np.ndarray | None = None
    ground_truth_points: np.ndarray | None = None


@dataclass
class StepOutput:
    """A stack's answer to one frame. ``plan`` is required (map frame, starting at the ego's
    pose, at ``plan.dt``); the rest as the stack's :attr:`StackInfo.provides` says: detections
    (map frame), tracks, predictions (map frame), occupancy (an object with ``query(xy, t)``, see
    :class:`~adv3d_runner.autonomy.interface.OccupancyField`). ``timings``: seconds per stage,
    for the reports."""

    plan: Plan
    detections: Detections | None = None
    tracks: Tracks | None = None
    predictions: Predictions | None = None
    occupancy: object | None = None
    timings: dict[str, float] = field(default_factory=dict)


@runtime_checkable
class Stack(Protocol):
    """An autonomy stack under test."""

    def info(self) -> StackInfo:
        """Name, version, outputs and fingerprint (asked once, before the first episode)."""
        ...

    def sensors(self) -> Sensors:
        """What the stack needs each frame."""
        ...

    def reset(self, episode: Episode) -> None:
        """Start an episode: forget every state of the last one."""
        ...

    def run_step(self, frame: Frame) -> StepOutput:
        """Answer one frame."""
        ...


def remote_stack(command: list[str]) -> Stack:
    """A stack in its own process and environment, started with ``command`` (argv) and spoken
    to over the wire protocol (docs/stack_protocol.md): what a plugin's factory returns for a
    stack whose dependencies clash with adv3d's. Raises ``StackFailure`` if it cannot start."""
    from .remote import RemoteStack

    return RemoteStack(command=list(command), label="exec:" + " ".join(command))
