"""The one interface every autonomy stack under test implements, and the data it exchanges.

Per episode the loop calls, in this order (nuPlan's ``initialize()`` pattern: the map is handed
over once, never per frame):

1. ``AutonomyStack.reset(context)`` with a :class:`SceneContext`: the scene's
   :class:`~adv3d_runner.scene.lanemap.LaneMap` (built from the scene's lanes when the episode
   starts; every stage reads this one object), dt and scene id. The stack forgets every state
   of the previous episode and passes the map to whatever reads it (planner, predictor).
2. Per frame (10 Hz): ``observe_ground_truth(boxes_ego, n_points)`` (the simulator's ground
   truth of the coming frame; a no-op for every stack except those with an oracle detector),
   then ``step(points, ego_state) -> AutonomyOutputs``.

Frames: LiDAR points come in the **ego frame** (origin at the ego's footprint centre on the
ground, x forward, y left, z up). Every output (detections, tracks, predictions, plan) is in
the scene's **map frame**; a stack converts with the ego pose (perfect localisation). Units: m,
s, rad, m/s. Boxes are ``(x, y, length, width, yaw)`` footprints (see
:mod:`adv3d_runner.geometry.boxes`).

All containers validate their shapes on construction and are numpy-only (the Blender add-on and
the replay writer can use them without torch).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator, Protocol, Sequence, runtime_checkable

import numpy as np

from ..scene.lanemap import LaneMap

DT = 0.1
PREDICTION_STEPS = 60  # 6 s at 10 Hz (paper appendix)
NUM_MODES = 3


def _f64(a: Any, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.size == 0:
        arr = arr.reshape((0,) + shape_tail)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(f"{name} must have shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    return arr


@dataclass
class EgoState:
    """The ego vehicle at one instant (map frame).

    Attributes:
        pose: (3,) x, y (m), yaw (rad) of the footprint centre.
        speed: m/s (>= 0).
        acceleration: m/s^2 (longitudinal; used for jerk continuity by the planner).
        curvature: 1/m, current path curvature (0 when unknown).
        time: s since the start of the episode.
        length, width: footprint, m.
        wheelbase: m.
    """

    pose: np.ndarray
    speed: float
    acceleration: float = 0.0
    curvature: float = 0.0
    time: float = 0.0
    length: float = 4.8
    width: float = 2.0
    wheelbase: float = 2.9

    def __post_init__(self) -> None:
        self.pose = np.asarray(self.pose, dtype=np.float64).reshape(3)
        self.speed = max(float(self.speed), 0.0)

    @property
    def box(self) -> np.ndarray:
        """(5,) footprint box."""
        return np.array([self.pose[0], self.pose[1], self.length, self.width, self.pose[2]])


@dataclass
class Detection:
    """One detected vehicle: ``box`` (5,) map frame, ``score`` confidence in [0, 1]."""

    box: np.ndarray
    score: float


@dataclass
class Detections:
    """Detections of one frame.

    Attributes:
        boxes: (N, 5) float64, x, y, length, width, yaw in the map frame.
        scores: (N,) float64 confidences in [0, 1].
    """

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.boxes = _f64(self.boxes, (5,), "Detections.boxes")
        self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if len(self.scores) != len(self.boxes):
            raise ValueError(f"{len(self.boxes)} boxes but {len(self.scores)} scores")

    def __len__(self) -> int:
        return len(self.boxes)

    def __getitem__(self, i: int) -> Detection:
        return Detection(self.boxes[i].copy(), float(self.scores[i]))

    def __iter__(self) -> Iterator[Detection]:
        return (self[i] for i in range(len(self)))

    @classmethod
    def from_list(cls, dets: Sequence[Detection]) -> "Detections":
        if not dets:
            return cls()
        return cls(np.stack([d.box for d in dets]), np.array([d.score for d in dets]))

    def filter(self, mask: np.ndarray) -> "Detections":
        m = np.asarray(mask, bool)
        return Detections(self.boxes[m], self.scores[m])


@dataclass
class Tracks:
    """Confirmed tracks output by the tracker for one frame (map frame).

    Attributes:
        ids: (N,) int64 track ids, unique within an episode.
        boxes: (N, 5) filtered boxes at the current time.
        velocities: (N, 2) m/s (vx, vy).
        scores: (N,) latest detection confidence.
        misses: (N,) int, consecutive frames without a matching detection (0 = seen now).
        history: (N, H, 3) past x, y, yaw (oldest first, the last entry is the current state).
        history_valid: (N, H) bool, False before the track existed.
    """

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    velocities: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    misses: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 1, 3)))
    history_valid: np.ndarray = field(default_factory=lambda: np.zeros((0, 1), bool))

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        n = len(self.ids)
        self.boxes = _f64(self.boxes, (5,), "Tracks.boxes")
        self.velocities = _f64(self.velocities, (2,), "Tracks.velocities")
        self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        self.misses = np.asarray(self.misses, dtype=np.int64).reshape(-1)
        self.history = np.asarray(self.history, dtype=np.float64)
        if self.history.ndim != 3 or self.history.shape[-1] != 3:
            if self.history.size:
                raise ValueError(f"Tracks.history must be (N, H, 3), got {self.history.shape}")
            self.history = np.zeros((n, 0, 3))
        self.history_valid = np.asarray(self.history_valid, bool).reshape(self.history.shape[:2])
        for name in ("boxes", "velocities", "scores", "misses", "history"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Tracks.{name} has {len(getattr(self, name))} rows for {n} ids")

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class Predictions:
    """Multi-modal future trajectories of tracked actors (map frame).

    Attributes:
        track_ids: (N,) int64, the :class:`Tracks` id each row belongs to.
        trajectories: (N, K, H, 2) positions (m) at t + dt, ..., t + H dt (default H = 60: 6 s).
        probabilities: (N, K) mode probabilities (rows sum to 1).
        dt: s between steps.
    """

    track_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    trajectories: np.ndarray = field(default_factory=lambda: np.zeros((0, NUM_MODES, PREDICTION_STEPS, 2)))
    probabilities: np.ndarray = field(default_factory=lambda: np.zeros((0, NUM_MODES)))
    dt: float = DT

    def __post_init__(self) -> None:
        self.track_ids = np.asarray(self.track_ids, dtype=np.int64).reshape(-1)
        self.trajectories = np.asarray(self.trajectories, dtype=np.float64)
        if self.trajectories.ndim != 4 or self.trajectories.shape[-1] != 2:
            raise ValueError(f"Predictions.trajectories must be (N, K, H, 2), got {self.trajectories.shape}")
        n, k = self.trajectories.shape[:2]
        self.probabilities = np.asarray(self.probabilities, dtype=np.float64).reshape(n, k)
        if len(self.track_ids) != n:
            raise ValueError(f"{n} trajectories for {len(self.track_ids)} track ids")

    def __len__(self) -> int:
        return len(self.track_ids)

    @property
    def num_modes(self) -> int:
        return self.trajectories.shape[1]

    @property
    def horizon(self) -> int:
        return self.trajectories.shape[2]


@dataclass
class Plan:
    """The chosen ego plan (map frame).

    Attributes:
        trajectory: (T, 3) x, y, yaw (wrapped to [-pi, pi)) at t, t + dt, ..., t + (T - 1) dt;
            index 0 is the current pose.
        speed: (T,) m/s along the trajectory.
        acceleration: (T - 1,) m/s^2 per step; curvature: (T - 1,) 1/m per step (the controls of
            the kinematic bicycle rollout).
        dt: s.
        cost: total cost of the chosen candidate; cost_terms: weighted per-term costs of it
            (see ``adv3d_runner.autonomy.planner.scorer``); label: which candidate it was.
    """

    trajectory: np.ndarray
    speed: np.ndarray
    acceleration: np.ndarray | None = None
    curvature: np.ndarray | None = None
    dt: float = DT
    cost: float = 0.0
    cost_terms: dict[str, float] = field(default_factory=dict)
    label: str = ""

    def __post_init__(self) -> None:
        self.trajectory = _f64(self.trajectory, (3,), "Plan.trajectory")
        self.speed = np.asarray(self.speed, dtype=np.float64).reshape(-1)
        if len(self.speed) != len(self.trajectory):
            raise ValueError("Plan.speed must have one value per trajectory pose")


@runtime_checkable
class OccupancyField(Protocol):
    """An instance-free stack's perception and prediction of one frame (Autonomy-B): occupancy
    and flow queried at any BEV point and future time, lazily (the evaluation and the replay
    writer query it after the frame; the stack's own planner queries it during the frame).

    Attributes:
        pose: (3,) the frame's ego pose (map frame). horizon: s, queries cover t in [0, horizon].
    """

    pose: np.ndarray
    horizon: float

    def query(self, xy: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame points xy (Q, 2) at times t (Q,) s after the frame -> occupancy
        probability (Q,) in [0, 1] and backward flow (Q, 2) m/s in the map frame
        (:mod:`adv3d_runner.metrics.occupancy`)."""
        ...


@dataclass
class AutonomyOutputs:
    """Everything a stack produces in one frame; ``timings`` holds seconds per stage
    (e.g. ``{"detector": 0.02, "tracker": 0.001, ...}``). An instance-free stack (Autonomy-B)
    has no detections, tracks or predictions (empty) and gives its ``occupancy`` field instead;
    it is None for instance-based stacks."""

    detections: Detections
    tracks: Tracks
    predictions: Predictions
    plan: Plan
    timings: dict[str, float] = field(default_factory=dict)
    occupancy: OccupancyField | None = None
    #: What the stack provided this frame ("plan" and any of ``api.OUTPUTS``); None: adv3d's own
    #: stacks, which provide detections, tracks and predictions, or occupancy.
    provided: frozenset[str] | None = None


@dataclass(frozen=True)
class SceneContext:
    """What a stack learns about the scene once per episode (``AutonomyStack.reset``).

    Attributes:
        lane_map: the scene's lanes with their prepared geometry (built once per scene; every
            stage of the stack reads this one object).
        dt: s between frames.
        scene_id: the scene's id ("" when unknown).
    """

    lane_map: LaneMap
    dt: float = DT
    scene_id: str = ""
    rig: Any = None  # the LiDAR rig (sensors.lidar.LidarRig), set by the episode loop

    @classmethod
    def from_scene(cls, scene: Any) -> "SceneContext":
        """The context of a loaded :class:`~adv3d_runner.scene.schema.Scene`."""
        return cls(LaneMap.from_scene(scene), float(scene.dt), str(scene.id))

    @classmethod
    def from_lanes(cls, lanes: Sequence[Any], dt: float = DT, scene_id: str = "") -> "SceneContext":
        """A context from bare lanes (tests, benchmarks without a scene file)."""
        return cls(LaneMap(lanes), float(dt), scene_id)


@runtime_checkable
class AutonomyStack(Protocol):
    """A LiDAR autonomy stack under test (closed loop, 10 Hz)."""

    def reset(self, context: SceneContext) -> None:
        """Start an episode in the scene ``context`` describes: forget all state (tracks,
        histories, plan hysteresis) and take the scene's lane map for the whole episode."""

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """The simulator's ground truth of the coming frame, given before each :meth:`step`.

        Only an oracle-perception stack uses it (its detector returns these boxes instead of
        detecting); every other stack must accept the call and ignore it.

        Args:
            boxes_ego: (N, 5) x, y, length, width, yaw of every scene actor in the **ego**
                frame (NaN rows for actors absent this frame).
            n_points: (N,) int, LiDAR returns on each actor in this frame.
        """

    def step(self, points: np.ndarray, ego_state: EgoState) -> AutonomyOutputs:
        """Process one frame.

        Args:
            points: (P, 3) or (P, 4) float32/64 LiDAR points x, y, z (m) [, intensity] in the
                ego frame; P may be 0.
            ego_state: the ego's current state in the map frame.
        """
        ...
