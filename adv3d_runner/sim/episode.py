"""The episode loop: simulated LiDAR -> autonomy stack -> ego motion, at 10 Hz.

Per frame k (time k dt from ``start_frame``):

1. the ego pose: closed loop, where the ego's previous plan took it (perfect control: the next
   state is ``plan.trajectory[1]`` with ``plan.speed[1]``, paper appendix); open loop, the
   ego's logged pose;
2. the actor poses: their logged poses (replay), or the IDM/MOBIL traffic model reacting to the
   ego (``reactive=True``, :mod:`.reactive`);
3. one LiDAR frame from the scene's rig at the ego pose (:func:`~adv3d_runner.sensors.lidar.simulate_frame`
   on a :class:`~adv3d_runner.sensors.world.LidarWorld` built once, never per frame);
4. ``stack.observe_ground_truth(boxes_ego, n_points)``, then ``stack.step(points, ego_state)``
   (the stack got the scene's lane map once, from ``stack.reset(SceneContext)``); the outputs
   are recorded.

Shapes can be substituted (the attack): ``actor_overrides = {actor_id: (vertices, faces,
dimensions)}`` replaces the actor's mesh in the world for this episode only (one BVH built per
new mesh, the benign mesh is given back afterwards) and its ground-truth box takes the new
``dimensions`` (L, W, H), which the detection metrics and the reactive traffic use.

Randomness: LiDAR noise and ray drop come from ``numpy.random.default_rng(seed)``; nothing else
draws random numbers, so the same scene, stack, overrides and seed give the same episode.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..autonomy.interface import PREDICTION_STEPS, AutonomyOutputs, EgoState, SceneContext
from ..errors import ConfigError
from ..metrics.boxes import boxes_to_frame

#: Stages of :attr:`EpisodeResult.timings` (seconds per frame).
STAGES = ("lidar", "detector", "tracker", "predictor", "planner", "traffic", "total")


@dataclass
class EpisodeResult:
    """Everything an episode produced (map frame, metres, radians, seconds).

    T = ``frames`` simulated frames; H = ``PREDICTION_STEPS`` (60) more frames of actor poses
    after the episode serve as the prediction ground truth (the log when replaying, the traffic
    model continued with the ego on its last plan when reactive); N actors in ``scene.actors``
    order.

    Attributes:
        scene_id, start_frame, dt, closed_loop, reactive, seed: how it was run.
        actor_ids: (N,) int64. actor_classes: N class names. actor_dimensions: (N, 3) L, W, H
            (substituted shapes' dimensions included). adversarial: (N,) bool, shape substituted.
        ego_dimensions: (3,). ego_poses: (T, 3). ego_speeds, ego_accels: (T,).
        actor_poses: (T + H, N, 3), NaN where an actor is absent.
        n_points: (T,) LiDAR returns per frame. actor_points: (T, N) returns on each actor.
        outputs: T :class:`AutonomyOutputs`.
        points: None, or T float32 arrays (P, 5) x, y, z (ego frame), intensity, label (actor
            index into ``actor_ids``, -1 background) when ``record_points``.
        timings: stage -> (T,) seconds (:data:`STAGES`).
    """

    scene_id: str
    start_frame: int
    dt: float
    closed_loop: bool
    reactive: bool
    seed: int
    actor_ids: np.ndarray
    actor_classes: list[str]
    actor_dimensions: np.ndarray
    adversarial: np.ndarray
    ego_dimensions: np.ndarray
    ego_poses: np.ndarray
    ego_speeds: np.ndarray
    ego_accels: np.ndarray
    actor_poses: np.ndarray
    n_points: np.ndarray
    actor_points: np.ndarray
    outputs: list[AutonomyOutputs]
    points: list[np.ndarray] | None = None
    timings: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return len(self.ego_poses)

    @property
    def actor_valid(self) -> np.ndarray:
        """(T + H, N) bool."""
        return np.isfinite(self.actor_poses).all(axis=-1)

    def gt_boxes(self, k: int) -> np.ndarray:
        """(N, 5) ground-truth boxes of frame k (NaN rows for absent actors)."""
        p = self.actor_poses[k]
        return np.c_[p[:, :2], self.actor_dimensions[:, :2], p[:, 2]]

    def ego_boxes(self) -> np.ndarray:
        """(T, 5) ego footprints."""
        L, W = self.ego_dimensions[:2]
        return np.c_[self.ego_poses[:, :2], np.full(self.frames, L), np.full(self.frames, W), self.ego_poses[:, 2]]

    def plans(self) -> list[np.ndarray]:
        """The chosen plan of every frame, (P, 3) each."""
        return [o.plan.trajectory for o in self.outputs]


def _log_window(values: np.ndarray, start: int, count: int) -> np.ndarray:
    """Frames start .. start+count-1 of a (N, F, ...) array, NaN-padded past its end."""
    out = np.full((values.shape[0], count) + values.shape[2:], np.nan)
    avail = max(0, min(count, values.shape[1] - start))
    out[:, :avail] = values[:, start:start + avail]
    return out


def default_library():
    """The bundled vehicle library, or None when it is not there (actors become boxes)."""
    from ..fileio import REPO_ROOT

    path = REPO_ROOT / "assets" / "vehicles" / "library.json"
    if not path.exists():
        return None
    from ..shapes.library import load_library

    return load_library(path)


def run_episode(scene, stack, *, seconds: float = 5.0, closed_loop: bool = True, reactive: bool = False,
                world=None, rig=None, library: Any = "default",
                actor_overrides: Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
                seed: int = 0, start_frame: int = 0, record_points: bool = False, progress: bool = False,
                lidar_noise: bool = True) -> EpisodeResult:
    """Run one episode of ``seconds`` at the scene's dt (10 Hz).

    Args:
        scene: a loaded :class:`~adv3d_runner.scene.schema.Scene`.
        stack: an :class:`~adv3d_runner.autonomy.interface.AutonomyStack` (reset here first).
        seconds: episode length; T = round(seconds / dt) frames.
        closed_loop: True, the ego follows its own plans; False, it replays its log.
        reactive: actors follow IDM/MOBIL around the ego instead of replaying their logs.
        world: a prebuilt :class:`~adv3d_runner.sensors.world.LidarWorld` of this scene (built
            from ``library`` when None). Reuse it across episodes: building it is the slow part.
        rig: a prebuilt :class:`~adv3d_runner.sensors.lidar.LidarRig` (default: the scene's).
        library: vehicle library for building the world (``"default"``: the bundled one; None:
            boxes).
        actor_overrides: {actor_id: (vertices (V, 3), faces (F, 3), dimensions (L, W, H))}
            shapes in the actor's local frame (origin at the footprint centre on the ground,
            +x front) used for this episode only.
        seed: seeds the LiDAR noise and ray drop.
        start_frame: first scene frame of the episode.
        record_points: keep every frame's points (for replay files).
        progress: show a progress bar.
        lidar_noise: False = ideal LiDAR (no range noise, no ray drop).

    Raises:
        ConfigError: the scene is too short for an open-loop episode, or an override names an
            unknown actor or has a malformed mesh.
    """
    from ..sensors.lidar import simulate_frame
    from ..sensors.world import rig_from_scene, world_from_scene

    dt = float(scene.dt)
    T = int(round(seconds / dt))
    if T < 1:
        raise ConfigError(f"an episode needs at least one frame (seconds={seconds})")
    if not closed_loop and start_frame + T > scene.frames:
        raise ConfigError(f"open loop needs the ego log for frames {start_frame}..{start_frame + T - 1}, "
                          f"the scene has {scene.frames}")
    if start_frame < 0 or start_frame >= scene.frames:
        raise ConfigError(f"start_frame {start_frame} outside the scene's {scene.frames} frames")
    H = PREDICTION_STEPS
    if world is None:
        world = world_from_scene(scene, default_library() if library == "default" else library)
    if rig is None:
        rig = rig_from_scene(scene)

    ids = np.array(scene.actor_ids, dtype=np.int64)
    n = len(ids)
    dims = scene.actor_dimensions().copy()
    adversarial = np.zeros(n, bool)
    # world rows <-> scene actors (a caller's world may order or hold actors differently)
    world_ids = list(world.actor_ids)
    row_of = {a: i for i, a in enumerate(world_ids)}
    to_world = np.array([row_of.get(int(a), -1) for a in ids], dtype=np.int64)
    overrides = dict(actor_overrides or {})
    index = {int(a): i for i, a in enumerate(ids)}
    for aid, spec in overrides.items():
        if int(aid) not in index or int(aid) not in row_of:
            raise ConfigError(f"actor_overrides: actor {aid} is not in scene {scene.id}")
        try:
            v, f, d = spec
            v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
            f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
            d = np.asarray(d, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"actor_overrides[{aid}] must be (vertices (V,3), faces (F,3), dimensions (3,)): {exc}") from None
        if not np.all(np.isfinite(v)) or not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise ConfigError(f"actor_overrides[{aid}]: non-finite vertices or non-positive dimensions")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise ConfigError(f"actor_overrides[{aid}]: face index out of range")
        dims[index[int(aid)]] = d
        adversarial[index[int(aid)]] = True

    # Logged poses of the episode plus the prediction horizon after it.
    all_poses, _ = scene.all_actor_poses()
    log = _log_window(all_poses, start_frame, T + H)                      # (N, T+H, 3)
    speeds_all = np.array([scene.actor_speeds(int(a)) for a in ids]).reshape(n, -1)
    log_speeds = _log_window(speeds_all, start_frame, T + H)              # (N, T+H)
    ego_log = scene.ego_poses()
    ego_log_speed = scene.ego_speeds()
    L, W = float(scene.ego.dimensions[0]), float(scene.ego.dimensions[1])

    def ego_from_log(k: int) -> EgoState:
        f = start_frame + k
        a = (ego_log_speed[f + 1] - ego_log_speed[f]) / dt if f + 1 < scene.frames else \
            (ego_log_speed[f] - ego_log_speed[f - 1]) / dt if f > 0 else 0.0
        return EgoState(ego_log[f], float(ego_log_speed[f]), acceleration=float(a), time=k * dt,
                        length=L, width=W, wheelbase=float(scene.ego.wheelbase))

    ego = ego_from_log(0)
    traffic = None
    if reactive:
        from .reactive import ReactiveTraffic

        traffic = ReactiveTraffic(scene, log, log_speeds, dims[:, 0], dims[:, 1], ego.pose, ego.speed, (L, W), dt)

    rng = np.random.default_rng(seed)
    actor_poses = np.full((T + H, n, 3), np.nan)
    ego_poses, ego_speeds, ego_accels = np.zeros((T, 3)), np.zeros(T), np.zeros(T)
    n_points = np.zeros(T, np.int64)
    actor_points = np.zeros((T, n), np.int64)
    outputs: list[AutonomyOutputs] = []
    points_log: list[np.ndarray] | None = [] if record_points else None
    timings = {s: np.zeros(T) for s in STAGES}
    world_poses = np.full((len(world_ids), 3), np.nan)
    have = to_world >= 0

    for aid, (v, f, _) in overrides.items():
        world.set_actor_mesh(int(aid), np.asarray(v, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3))
    stack.reset(SceneContext.from_scene(scene))
    steps = range(T)
    if progress:
        from ..progress import progress as bar

        steps = bar(steps, desc=f"simulate {scene.id}", total=T, unit="frame")
    try:
        for k in steps:
            t_start = time.perf_counter()
            if not closed_loop and k > 0:
                ego = ego_from_log(k)
            poses_k = traffic.poses() if traffic is not None else log[:, k]
            actor_poses[k] = poses_k
            world_poses[:] = np.nan
            world_poses[to_world[have]] = poses_k[have]
            t0 = time.perf_counter()
            frame = simulate_frame(world, rig, ego.pose, world_poses, rng if lidar_noise else None)
            t1 = time.perf_counter()
            timings["lidar"][k] = t1 - t0
            counts_world = np.bincount(frame.label[frame.label >= 0], minlength=len(world_ids) + 1)
            counts = np.where(have, counts_world[np.maximum(to_world, 0)], 0)
            actor_points[k] = counts
            n_points[k] = len(frame.points)
            gt = np.c_[poses_k[:, :2], dims[:, :2], poses_k[:, 2]]
            stack.observe_ground_truth(boxes_to_frame(gt, ego.pose), counts)
            out = stack.step(frame.points, ego)
            outputs.append(out)
            for name in ("detector", "tracker", "predictor", "planner"):
                timings[name][k] = float(out.timings.get(name, 0.0))
            if points_log is not None:
                # labels as scene actor indices (-1 background)
                back = np.full(len(world_ids) + 1, -1, np.int64)
                back[to_world[have]] = np.flatnonzero(have)
                lab = back[np.where(frame.label >= 0, frame.label, len(world_ids))]
                points_log.append(np.c_[frame.points, lab.astype(np.float32)].astype(np.float32))
            ego_poses[k], ego_speeds[k], ego_accels[k] = ego.pose, ego.speed, ego.acceleration
            t2 = time.perf_counter()
            if traffic is not None:
                traffic.step(ego.pose, ego.speed)
            timings["traffic"][k] = time.perf_counter() - t2
            if closed_loop:
                ego = _follow(out, ego, k + 1, dt)
            timings["total"][k] = time.perf_counter() - t_start
    finally:
        for aid in overrides:
            world.reset_actor_mesh(int(aid))

    # Actor poses after the episode: the ground truth for the last predictions.
    if traffic is None:
        actor_poses[T:] = np.transpose(log[:, T:], (1, 0, 2))
    else:
        plan = outputs[-1].plan
        last = ego
        for h in range(H):
            actor_poses[T + h] = traffic.poses()
            traffic.step(last.pose, last.speed)
            f = start_frame + T + h + 1
            if not closed_loop and f < scene.frames:
                pose, speed = ego_log[f], float(ego_log_speed[f])
            else:  # the ego at T + h + 1 is (h + 2) dt along the plan made at T - 1
                pose, speed = _extrapolate(plan, (h + 2) * dt, dt)
            last = EgoState(pose, speed)
    return EpisodeResult(scene.id, int(start_frame), dt, bool(closed_loop), bool(reactive), int(seed), ids,
                         [a.cls for a in scene.actors], dims, adversarial, np.asarray(scene.ego.dimensions, float),
                         ego_poses, ego_speeds, ego_accels, actor_poses, n_points, actor_points, outputs,
                         points_log, timings)


def _follow(out: AutonomyOutputs, ego: EgoState, k: int, dt: float) -> EgoState:
    """Perfect control: the state ``dt`` along the chosen plan."""
    plan = out.plan
    if len(plan.trajectory) >= 2 and abs(plan.dt - dt) < 1e-9:
        acc = float(plan.acceleration[0]) if plan.acceleration is not None and len(plan.acceleration) else 0.0
        curv = float(plan.curvature[0]) if plan.curvature is not None and len(plan.curvature) else 0.0
        pose, speed = plan.trajectory[1], float(plan.speed[1])
    else:
        from .kinematics import advance_on_trajectory

        pose, speed = advance_on_trajectory(plan.trajectory, plan.speed, dt=dt, plan_dt=plan.dt)
        acc, curv = (speed - ego.speed) / dt, 0.0
    return EgoState(pose, speed, acceleration=acc, curvature=curv, time=k * dt, length=ego.length,
                    width=ego.width, wheelbase=ego.wheelbase)


def _extrapolate(plan, t: float, dt: float) -> tuple[np.ndarray, float]:
    """The ego t s along a plan, continuing at constant speed and heading past its end."""
    traj, v = plan.trajectory, plan.speed
    end = (len(traj) - 1) * plan.dt
    if t <= end:
        from .kinematics import advance_on_trajectory

        return advance_on_trajectory(traj, v, dt=t, plan_dt=plan.dt)
    last = traj[-1]
    dist = float(v[-1]) * (t - end)
    return np.array([last[0] + dist * np.cos(last[2]), last[1] + dist * np.sin(last[2]), last[2]]), float(v[-1])
