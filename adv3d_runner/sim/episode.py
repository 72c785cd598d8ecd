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

The loop is an :class:`Episode` in three parts: setup (its constructor: checks, log windows,
traffic model, substituted meshes, ``stack.reset``), :meth:`Episode.step` (one frame) and
:meth:`Episode.finish` (the actor poses of the prediction horizon after the episode, the
:class:`EpisodeResult`). Recorders (:mod:`.recorders`) are its callbacks: wall times and the
points of every frame are recorded by them, not by the loop. :func:`run_episode` runs the three
parts with the usual recorders.

Shapes can be substituted (the attack): ``actor_overrides = {actor_id: ShapeOverride(vertices,
faces, dimensions)}`` replaces the actor's mesh in the world for this episode only (one BVH
built per new mesh, the benign mesh is given back afterwards) and its ground-truth box takes the
new ``dimensions`` (L, W, H), which the detection metrics and the reactive traffic use.

Randomness: LiDAR noise and ray drop come from ``numpy.random.default_rng(seed)``; nothing else
draws random numbers, so the same scene, stack, overrides and seed give the same episode.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from ..autonomy.interface import PREDICTION_STEPS, AutonomyOutputs, EgoState, SceneContext
from ..errors import ConfigError
from ..geometry.frames import boxes_to_frame
from ..scene.schema import MAX_FRAMES
from .recorders import STAGES, EpisodeFrame, PointRecorder, Recorder, TimingRecorder

__all__ = ["STAGES", "Episode", "EpisodeResult", "ShapeOverride", "default_library", "run_episode"]


@dataclass(frozen=True, eq=False)
class ShapeOverride:
    """A substituted actor shape for one episode, checked once here.

    The mesh is in the actor's local frame (origin at the footprint centre on the ground, +x
    front); the actor's ground-truth box takes ``dimensions``. The arrays are read-only copies.

    Attributes:
        vertices: (V, 3) float64, metres.
        faces: (F, 3) int64 indices into ``vertices``.
        dimensions: (3,) float64 L, W, H, metres (> 0).

    Raises:
        ConfigError: arrays of the wrong shape, non-finite vertices or dimensions, a dimension
            <= 0, or a face index outside the vertices.
    """

    vertices: np.ndarray
    faces: np.ndarray
    dimensions: np.ndarray

    def __post_init__(self) -> None:
        try:
            v = np.array(self.vertices, dtype=np.float64).reshape(-1, 3)
            f = np.array(self.faces, dtype=np.int64).reshape(-1, 3)
            d = np.array(self.dimensions, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"a shape override needs vertices (V,3), faces (F,3), dimensions (3,): {exc}") from None
        if not np.all(np.isfinite(v)) or not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise ConfigError("shape override: non-finite vertices or non-positive dimensions")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise ConfigError("shape override: face index out of range")
        for name, a in (("vertices", v), ("faces", f), ("dimensions", d)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)


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
            index into ``actor_ids``, -1 background) when ``record_points``
            (:class:`~adv3d_runner.sim.recorders.PointRecorder`).
        timings: stage -> (T,) seconds (:data:`STAGES`;
            :class:`~adv3d_runner.sim.recorders.TimingRecorder`).
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


def _episode_frames(scene, seconds: float, closed_loop: bool, start_frame: int) -> int:
    """T = round(seconds / dt), checked against the scene.

    Raises:
        ConfigError: no frame, an open-loop episode past the ego log, or a start outside the scene.
    """
    T = int(round(seconds / float(scene.dt)))
    if T < 1:
        raise ConfigError(f"an episode needs at least one frame (seconds={seconds})")
    if T > MAX_FRAMES:  # the replay contract's bound; also bounds every per-frame array of the episode
        raise ConfigError(f"--seconds {seconds:g} at the scene's dt of {float(scene.dt):g} s is {T} frames; an "
                          f"episode has at most {MAX_FRAMES}")
    if not closed_loop and start_frame + T > scene.frames:
        raise ConfigError(f"open loop needs the ego log for frames {start_frame}..{start_frame + T - 1}, "
                          f"the scene has {scene.frames}")
    if start_frame < 0 or start_frame >= scene.frames:
        raise ConfigError(f"start_frame {start_frame} outside the scene's {scene.frames} frames")
    return T


def _substituted_dimensions(scene, ids: np.ndarray, to_world: np.ndarray,
                            overrides: Mapping[int, ShapeOverride]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) actor L, W, H with the overrides' dimensions, and (N,) bool: substituted.

    Raises:
        ConfigError: an override names an actor not in the scene (or not in the world), or is
            not a :class:`ShapeOverride`.
    """
    dims = scene.actor_dimensions().copy()
    adversarial = np.zeros(len(ids), bool)
    index = {int(a): i for i, a in enumerate(ids)}
    for aid, spec in overrides.items():
        if int(aid) not in index or to_world[index[int(aid)]] < 0:
            raise ConfigError(f"actor_overrides: actor {aid} is not in scene {scene.id}")
        if not isinstance(spec, ShapeOverride):
            raise ConfigError(f"actor_overrides[{aid}] must be a ShapeOverride, got {type(spec).__name__}")
        dims[index[int(aid)]] = spec.dimensions
        adversarial[index[int(aid)]] = True
    return dims, adversarial


class Episode:
    """One episode, stepped frame by frame: setup (the constructor), :meth:`step`, :meth:`finish`.

    The constructor checks the arguments (see :func:`run_episode`, which takes the same ones),
    cuts the logs to the episode, builds the traffic model, puts the substituted meshes into the
    world and resets the stack. :meth:`step` simulates the next frame and hands it to every
    recorder; after the last frame :meth:`finish` gives the world its benign meshes back and
    returns the :class:`EpisodeResult` (recorders add to it). Call :meth:`close` (idempotent)
    when stopping early, so that the world gets its meshes back.

    Attributes:
        frames: T. k: frames simulated so far. scene, stack, world, rig: as given.
        label_to_actor: (W + 1,) int64, a LiDAR label (world actor row; W = background) -> the
            scene actor's index, -1 for the background or a world actor not in the scene.
    """

    def __init__(self, scene, stack, *, seconds: float = 5.0, closed_loop: bool = True, reactive: bool = False,
                 world=None, rig=None, library: Any = "default",
                 actor_overrides: Mapping[int, ShapeOverride] | None = None, seed: int = 0,
                 start_frame: int = 0, lidar_noise: bool = True, recorders: Sequence[Recorder] = (),
                 context: SceneContext | None = None, lidar_cache=None):
        from ..sensors.world import rig_from_scene, world_from_scene

        dt = float(scene.dt)
        T = _episode_frames(scene, seconds, closed_loop, start_frame)
        H = PREDICTION_STEPS
        if world is None:
            world = world_from_scene(scene, default_library() if library == "default" else library)
        if rig is None:
            rig = rig_from_scene(scene)
        self.scene, self.stack, self.world, self.rig = scene, stack, world, rig
        self.dt, self.frames, self.horizon = dt, T, H
        self.closed_loop, self.reactive, self.seed = bool(closed_loop), bool(reactive), int(seed)
        self.start_frame, self.lidar_noise = int(start_frame), bool(lidar_noise)
        self.recorders = list(recorders)
        self.lidar_cache = lidar_cache

        ids = np.array(scene.actor_ids, dtype=np.int64)
        n = len(ids)
        # world rows <-> scene actors (a caller's world may order or hold actors differently)
        world_ids = list(world.actor_ids)
        row_of = {a: i for i, a in enumerate(world_ids)}
        to_world = np.array([row_of.get(int(a), -1) for a in ids], dtype=np.int64)
        overrides = dict(actor_overrides or {})
        dims, adversarial = _substituted_dimensions(scene, ids, to_world, overrides)
        self.ids, self.dims, self.adversarial, self.overrides = ids, dims, adversarial, overrides
        self.n_world, self.to_world, self.have = len(world_ids), to_world, to_world >= 0
        self.label_to_actor = np.full(len(world_ids) + 1, -1, np.int64)
        self.label_to_actor[to_world[self.have]] = np.flatnonzero(self.have)

        # Logged poses of the episode plus the prediction horizon after it.
        all_poses, _ = scene.all_actor_poses()
        self.log = _log_window(all_poses, start_frame, T + H)                      # (N, T+H, 3)
        speeds_all = np.array([scene.actor_speeds(int(a)) for a in ids]).reshape(n, scene.frames)
        log_speeds = _log_window(speeds_all, start_frame, T + H)                   # (N, T+H)
        self.ego_log = scene.ego_poses()
        self.ego_log_speed = scene.ego_speeds()
        self.ego_log_accel = scene.ego_accelerations()
        L, W = float(scene.ego.dimensions[0]), float(scene.ego.dimensions[1])

        self.ego = self._ego_from_log(0)
        self.traffic = None
        if reactive:
            from .reactive import ReactiveTraffic

            self.traffic = ReactiveTraffic(scene, self.log, log_speeds, dims[:, 0], dims[:, 1], self.ego.pose,
                                           self.ego.speed, (L, W), dt)

        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.actor_poses = np.full((T + H, n, 3), np.nan)
        self.ego_poses, self.ego_speeds, self.ego_accels = np.zeros((T, 3)), np.zeros(T), np.zeros(T)
        self.n_points = np.zeros(T, np.int64)
        self.actor_points = np.zeros((T, n), np.int64)
        self.outputs: list[AutonomyOutputs] = []
        self._world_poses = np.full((len(world_ids), 3), np.nan)

        self._meshes_set = True
        try:
            for aid, spec in overrides.items():
                world.set_actor_mesh(int(aid), spec.vertices, spec.faces)
            context = context if context is not None else SceneContext.from_scene(scene)
            stack.reset(replace(context, rig=self.rig))  # a plugin stack is told the rig (docs/stacks.md)
        except BaseException:  # a failed setup must not leave the adversarial meshes in the world
            self.close()
            raise

    def _ego_from_log(self, k: int) -> EgoState:
        """The logged ego at episode frame k (acceleration: ``Scene.ego_accelerations``)."""
        scene, dt = self.scene, self.dt
        f = self.start_frame + k
        return EgoState(self.ego_log[f], float(self.ego_log_speed[f]), acceleration=float(self.ego_log_accel[f]),
                        time=k * dt,
                        length=float(scene.ego.dimensions[0]), width=float(scene.ego.dimensions[1]),
                        wheelbase=float(scene.ego.wheelbase))

    @property
    def done(self) -> bool:
        """All T frames are simulated."""
        return self.k >= self.frames

    def step(self) -> EpisodeFrame:
        """Simulate frame k (LiDAR, stack, ego and actor motion) and hand it to the recorders."""
        from ..sensors.kernels import count_labels
        from ..sensors.lidar import simulate_frame

        if self.done:
            raise RuntimeError(f"the episode already has its {self.frames} frames")
        k, stack, dims, ego = self.k, self.stack, self.dims, self.ego
        t_start = time.perf_counter()
        if not self.closed_loop and k > 0:
            ego = self._ego_from_log(k)
        poses_k = self.traffic.poses() if self.traffic is not None else self.log[:, k]
        self.actor_poses[k] = poses_k
        world_poses, to_world, have = self._world_poses, self.to_world, self.have
        world_poses[:] = np.nan
        world_poses[to_world[have]] = poses_k[have]
        t0 = time.perf_counter()
        frame = simulate_frame(self.world, self.rig, ego.pose, world_poses, self.rng if self.lidar_noise else None,
                               cache=self.lidar_cache)
        t1 = time.perf_counter()
        counts_world = count_labels(frame.label, self.n_world + 1)
        if counts_world.size == 0:
            counts_world = np.bincount(frame.label[frame.label >= 0], minlength=self.n_world + 1)
        counts = np.where(have, counts_world[np.maximum(to_world, 0)], 0)
        self.actor_points[k] = counts
        self.n_points[k] = len(frame.points)
        gt = np.c_[poses_k[:, :2], dims[:, :2], poses_k[:, 2]]
        stack.observe_ground_truth(boxes_to_frame(gt, ego.pose), counts)
        observe_frame = getattr(stack, "observe_lidar_frame", None)
        if observe_frame is not None:  # a plugin stack gets each point's sensor
            observe_frame(frame)
        out = stack.step(frame.points, ego)
        self.outputs.append(out)
        self.ego_poses[k], self.ego_speeds[k], self.ego_accels[k] = ego.pose, ego.speed, ego.acceleration
        t2 = time.perf_counter()
        if self.traffic is not None:
            self.traffic.step(ego.pose, ego.speed)
        t3 = time.perf_counter()
        self.ego = _follow(out, ego, k + 1, self.dt) if self.closed_loop else ego
        self.k = k + 1
        seconds = {name: float(out.timings.get(name, 0.0))
                   for name in ("detector", "tracker", "predictor", "occupancy", "planner")}
        seconds.update(lidar=t1 - t0, traffic=t3 - t2, total=time.perf_counter() - t_start)
        record = EpisodeFrame(k, ego, poses_k, frame, counts, out, seconds)
        for recorder in self.recorders:
            recorder.on_frame(self, record)
        return record

    def close(self) -> None:
        """Give the substituted actors their benign meshes back (idempotent)."""
        if self._meshes_set:
            self._meshes_set = False
            for aid in self.overrides:
                self.world.reset_actor_mesh(int(aid))

    def finish(self) -> EpisodeResult:
        """The result, after the last frame: the actor poses of the prediction horizon after the
        episode are added and every recorder's ``on_finish`` sees the result."""
        if not self.done:
            raise RuntimeError(f"finish after {self.k} of {self.frames} frames")
        self.close()
        T, H, dt, scene = self.frames, self.horizon, self.dt, self.scene
        actor_poses, traffic = self.actor_poses, self.traffic
        # Actor poses after the episode: the ground truth for the last predictions.
        if traffic is None:
            actor_poses[T:] = np.transpose(self.log[:, T:], (1, 0, 2))
        else:
            plan = self.outputs[-1].plan
            last = self.ego
            for h in range(H):
                actor_poses[T + h] = traffic.poses()
                traffic.step(last.pose, last.speed)
                f = self.start_frame + T + h + 1
                if not self.closed_loop and f < scene.frames:
                    pose, speed = self.ego_log[f], float(self.ego_log_speed[f])
                else:  # the ego at T + h + 1 is (h + 2) dt along the plan made at T - 1
                    pose, speed = _extrapolate(plan, (h + 2) * dt, dt)
                last = EgoState(pose, speed)
        result = EpisodeResult(scene.id, self.start_frame, dt, self.closed_loop, self.reactive, self.seed, self.ids,
                               [a.cls for a in scene.actors], self.dims, self.adversarial,
                               np.asarray(scene.ego.dimensions, float), self.ego_poses, self.ego_speeds,
                               self.ego_accels, actor_poses, self.n_points, self.actor_points, self.outputs)
        for recorder in self.recorders:
            recorder.on_finish(self, result)
        return result


def run_episode(scene, stack, *, seconds: float = 5.0, closed_loop: bool = True, reactive: bool = False,
                world=None, rig=None, library: Any = "default",
                actor_overrides: Mapping[int, ShapeOverride] | None = None,
                seed: int = 0, start_frame: int = 0, record_points: bool = False, progress: bool = False,
                lidar_noise: bool = True, context: SceneContext | None = None, lidar_cache=None) -> EpisodeResult:
    """Run one episode of ``seconds`` at the scene's dt (10 Hz): :class:`Episode` setup, steps
    and finish, with a :class:`~adv3d_runner.sim.recorders.TimingRecorder` (and a
    :class:`~adv3d_runner.sim.recorders.PointRecorder` when ``record_points``).

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
        actor_overrides: {actor_id: :class:`ShapeOverride`} shapes used for this episode only.
        seed: seeds the LiDAR noise and ray drop.
        start_frame: first scene frame of the episode.
        record_points: keep every frame's points (for replay files).
        progress: show a progress bar.
        lidar_noise: False = ideal LiDAR (no range noise, no ray drop).
        context: the scene's :class:`~adv3d_runner.autonomy.interface.SceneContext` (its lane
            map) for ``stack.reset``; built from ``scene`` when None. Pass one to reuse the lane
            map across episodes of the same scene (an attack builds it once per scene).
        lidar_cache: a :class:`~adv3d_runner.sensors.incremental.StaticRayCache` of ``world``
            and ``rig`` whose dynamic actors are the substituted ones: frames whose ego and
            actor poses were simulated before reuse the hits of everything else (identical
            results; an attack keeps one per scene).

    Raises:
        ConfigError: the scene is too short for an open-loop episode, or an override names an
            unknown actor or is not a :class:`ShapeOverride`.
    """
    recorders: list[Recorder] = [TimingRecorder()]
    if record_points:
        recorders.append(PointRecorder())
    episode = Episode(scene, stack, seconds=seconds, closed_loop=closed_loop, reactive=reactive, world=world,
                      rig=rig, library=library, actor_overrides=actor_overrides, seed=seed,
                      start_frame=start_frame, lidar_noise=lidar_noise, recorders=recorders,
                      context=context, lidar_cache=lidar_cache)
    steps = range(episode.frames)
    if progress:
        from ..progress import progress as bar

        steps = bar(steps, desc=f"simulate {scene.id}", total=episode.frames, unit="frame")
    try:
        for _ in steps:
            episode.step()
    finally:
        episode.close()
    return episode.finish()


def _follow(out: AutonomyOutputs, ego: EgoState, k: int, dt: float) -> EgoState:
    """Perfect control: the state ``dt`` along the chosen plan."""
    plan = out.plan
    if len(plan.trajectory) >= 2 and abs(plan.dt - dt) < 1e-9:
        acc = float(plan.acceleration[0]) if plan.acceleration is not None and len(plan.acceleration) else 0.0
        curv = float(plan.curvature[0]) if plan.curvature is not None and len(plan.curvature) else 0.0
        pose, speed = plan.trajectory[1], float(plan.speed[1])
    else:
        from ..dynamics.bicycle import advance_on_trajectory

        pose, speed = advance_on_trajectory(plan.trajectory, plan.speed, dt=dt, plan_dt=plan.dt)
        acc, curv = (speed - ego.speed) / dt, 0.0
    return EgoState(pose, speed, acceleration=acc, curvature=curv, time=k * dt, length=ego.length,
                    width=ego.width, wheelbase=ego.wheelbase)


def _extrapolate(plan, t: float, dt: float) -> tuple[np.ndarray, float]:
    """The ego t s along a plan, continuing at constant speed and heading past its end."""
    traj, v = plan.trajectory, plan.speed
    end = (len(traj) - 1) * plan.dt
    if t <= end:
        from ..dynamics.bicycle import advance_on_trajectory

        return advance_on_trajectory(traj, v, dt=t, plan_dt=plan.dt)
    last = traj[-1]
    dist = float(v[-1]) * (t - end)
    return np.array([last[0] + dist * np.cos(last[2]), last[1] + dist * np.sin(last[2]), last[2]]), float(v[-1])
