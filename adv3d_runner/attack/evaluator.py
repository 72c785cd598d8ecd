"""What scores a query: the :class:`QueryEvaluator` interface the driver talks to, and its
production implementation :class:`EpisodeEvaluator` (decode the shapes, run the episode, score
it with paper Eq. 3-5 and measure it with the episode metrics).

A query (:class:`Query`) is a scene, the unit vector(s) of the attacked actors' shapes and
closed or open loop; its :class:`QueryResult` holds the journal fields. An evaluator raises
for a query that fails (:class:`~adv3d_runner.errors.InvalidQueryError` for a shape without a
surface, anything else for an error); :func:`run_query`, which the driver's executors call in
the workers, turns that into a result with status ``invalid`` / ``error`` and never raises.

Evaluators cross process boundaries (local worker processes, Ray tasks), so they hold only
small settings and are pickled with every task; the heavy per-scene state (the scene, its LiDAR
world, the stack) lives in a per-process cache (:func:`workspace_for`), built on a worker's first
query of a scene and reused for the next ones.
"""
from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from ..errors import InvalidQueryError
from .config import QuerySettings

if TYPE_CHECKING:  # pragma: no cover - annotations only
    from ..sim.episode import EpisodeResult


@dataclass(frozen=True, eq=False)
class Query:
    """One query: score these shapes on this scene.

    Attributes:
        scene: the scene reference as given to the attack (a file path).
        unit: (m * (K + 2),) float64 unit vectors of the m attacked actors, in [0, 1].
        closed_loop: the ego drives with the stack (True) or replays its log (False).
    """

    scene: str
    unit: np.ndarray
    closed_loop: bool = True


@dataclass
class QueryResult:
    """The outcome of a query: the fields of its journal line (docs/formats.md).

    Attributes:
        cost: the objective (None when the query failed). components: its unweighted frame
            sums per term. metrics: the episode metrics (without format, version and timings).
        latent, scales, dimensions: per attacked actor (m x K, m x 2, m x 3), None if not decoded
            (latent and scales also None for vertex-deformed shapes).
        realism: per attacked actor, the shape's cheap realism figures
            (:meth:`~adv3d_runner.attack.shape_models.ActorShapes.figures`), None if not decoded;
            in a closed-loop evaluation of a best shape, the full realism report.
        status: ``ok``, ``invalid`` (no surface) or ``error``. error: the message, or None.
        wall_s: seconds the evaluation took (not a result: it differs between runs).
    """

    cost: float | None = None
    components: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    latent: list | None = None
    scales: list | None = None
    dimensions: list | None = None
    realism: list | None = None
    status: str = "ok"
    error: str | None = None
    wall_s: float = 0.0

    def evaluation(self) -> dict[str, Any]:
        """``{"cost", "components", "metrics"}`` (+ ``realism`` when measured), as summary.json
        stores a closed-loop evaluation."""
        out = {"cost": self.cost, "components": self.components, "metrics": self.metrics}
        if self.realism is not None:
            out["realism"] = self.realism
        return out


@dataclass(frozen=True)
class BestEvaluation:
    """The closed-loop evaluation of a scene's best shape (and of the original scene), with the
    files written for it (names relative to the folder it was given)."""

    closed_loop: dict[str, Any]
    original: dict[str, Any] | None = None
    meshes: dict[int, str] = field(default_factory=dict)
    replay: str | None = None


@runtime_checkable
class QueryEvaluator(Protocol):
    """What the driver needs from whatever scores queries (must pickle: it goes to workers)."""

    def scene_id(self, ref: str) -> str:
        """The id of the scene ``ref`` (journal and summary key; a file-name-safe id)."""

    def scene_digest(self, ref: str) -> str:
        """The identity of the scene's content (``sha256:...``): a resume compares it, not the
        path the scene was given by."""

    def targets(self, ref: str) -> tuple[list[int], int]:
        """(attacked actor ids, query dimension) of a scene. Raises ConfigError when the scene
        has nothing to attack (the driver skips it)."""

    def candidates(self, ref: str, targets: list[int]) -> np.ndarray:
        """(C, dim) unit vectors that brute-force search enumerates."""

    def evaluate(self, query: Query) -> QueryResult:
        """Score one query. Raises InvalidQueryError (invalid shape) or any other exception
        (error); :func:`run_query` turns both into a failed result."""

    def versions(self) -> dict[str, Any]:
        """What the results depend on beyond the config (file hashes, model fingerprints)."""

    def evaluate_best(self, ref: str, targets: list[int], unit: np.ndarray, out: Path, *, original: bool,
                      metadata: dict[str, Any]) -> BestEvaluation | None:
        """Evaluate the best shape in closed loop (and the original scene when ``original``),
        writing its files into ``out``; None when this evaluator has nothing to add."""


def run_query(evaluator: QueryEvaluator, query: Query) -> QueryResult:
    """Evaluate one query (runs in a worker). Never raises: failures come back as a status
    (``invalid`` for an InvalidQueryError, ``error`` for any other exception or a non-finite
    objective), with a null cost."""
    t0 = time.perf_counter()
    try:
        out = evaluator.evaluate(query)
        if out.cost is None or not np.isfinite(out.cost):
            out = replace(out, status="error", error=f"non-finite objective {out.cost}", cost=None)
    except InvalidQueryError as exc:
        out = QueryResult(status="invalid", error=f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # noqa: BLE001 - a query must never stop the run
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        out = QueryResult(status="error", error=tb[:500])
    return replace(out, wall_s=time.perf_counter() - t0)


# ============================================================================ episodes

_STACKS: dict[str, Any] = {}
#: Memory bounds of a scene's static-hit caches (``sensors.incremental``): a whole 5 s open-loop
#: path of a 133k-ray HDL-64E with 30 actors takes about 90 MB; closed-loop episodes reuse only
#: the frames before they diverge.
OPEN_LOOP_CACHE_BYTES = 128 * 2**20
CLOSED_LOOP_CACHE_BYTES = 64 * 2**20


def stack_info_of(autonomy: str):
    """The :class:`~adv3d_runner.autonomy.api.StackInfo` of a stack: adv3d's own without
    building it, any other from this process's instance (built once)."""
    from ..autonomy.stacks import own_info

    info = own_info(autonomy)
    return info if info is not None else stack_for(autonomy).stack_info


def stack_for(autonomy: str):
    """This process's autonomy stack of that name (loaded once: a stack is reset at the start of
    every episode, so the scenes of a process share it)."""
    if autonomy not in _STACKS:
        from ..autonomy.stacks import make_stack

        _STACKS[autonomy] = make_stack(autonomy)
    return _STACKS[autonomy]


class SceneWorkspace:
    """What one process needs to evaluate queries on a scene: the scene, its LiDAR world and rig
    and its lane map (each built once), the autonomy stack, the shape space, the targets, how
    queries become their shapes (:class:`~adv3d_runner.attack.shape_models.ActorShapes`) and the
    objective weights; with ``settings.incremental``, the scene's
    :class:`~adv3d_runner.sensors.incremental.StaticRayCache` s (the attacked actors are their
    dynamic actors; one for open-loop and one for closed-loop episodes), which every episode of
    the scene shares."""

    def __init__(self, scene_path: str, settings: QuerySettings):
        from ..autonomy.interface import SceneContext
        from ..scene.schema import load_scene
        from ..sensors.incremental import StaticRayCache
        from ..sensors.world import rig_from_scene, world_from_scene
        from .shape_models import ActorShapes
        from .targets import select_targets

        self.settings = settings
        self.scene = load_scene(scene_path)
        self.space = settings.load_shape_space()
        self.world = world_from_scene(self.scene, settings.load_library(), scene_dir=Path(scene_path).parent)
        self.rig = rig_from_scene(self.scene, path=scene_path)
        self.context = SceneContext.from_scene(self.scene)
        self.stack = stack_for(settings.autonomy)
        self.targets = select_targets(self.scene, settings.actors, rank=settings.target_rank)
        self.shapes = ActorShapes(settings, self.scene, self.targets, self.space, settings.load_library())
        self.weights = settings.weights
        # The search's episode seed (LiDAR noise): the run seed, or one derived per scene.
        self.seed = settings.episode_seed(scene_digest_of(self.scene)) if settings.scene_seeds else settings.seed
        # One cache per loop: open-loop episodes all share the logged ego poses (every frame is
        # served again), closed-loop ones share only their first frames and then store frames
        # that are never served again; apart, the closed-loop churn cannot push the open-loop
        # path out of memory.
        self.lidar_caches: dict[bool, StaticRayCache] = {}
        if settings.incremental:
            dynamic = [self.world.actor_index(int(a)) for a in self.targets]
            self.lidar_caches = {False: StaticRayCache(self.world, dynamic, max_bytes=OPEN_LOOP_CACHE_BYTES),
                                 True: StaticRayCache(self.world, dynamic, max_bytes=CLOSED_LOOP_CACHE_BYTES)}

    def episode(self, overrides: dict | None, closed_loop: bool, record_points: bool = False,
                seed: int | None = None) -> "EpisodeResult":
        from ..sim.episode import run_episode

        s = self.settings
        return run_episode(self.scene, self.stack, seconds=s.seconds, closed_loop=closed_loop, reactive=s.reactive,
                           world=self.world, rig=self.rig, actor_overrides=overrides, seed=self.seed if seed is None else int(seed),
                           record_points=record_points, context=self.context,
                           lidar_cache=self.lidar_caches.get(bool(closed_loop)))

    def evaluate(self, u: np.ndarray | None, closed_loop: bool, record_points: bool = False,
                 seed: int | None = None) -> tuple[QueryResult, "EpisodeResult"]:
        """(the query's result, the episode). ``u`` None = the original scene. ``seed``: the
        episode seed (LiDAR noise) when not the search's (:attr:`seed`), e.g. a held-out
        evaluation seed (``attack.protocol``).

        The episode's detection frames and prediction pairs are computed once
        (``sim.evaluate.episode_evaluation``) for both the objective and the metrics. A decoded
        query carries its shapes' cheap realism figures; with ``realism_weight`` W > 0 the cost
        is the objective minus W times the realism penalty (``realism_constraints.realism_penalty``),
        which ``components`` holds unweighted as ``realism_penalty``. In the realistic region
        (``settings.region``) the shapes are decoded where the realism report passes
        (``ActorShapes.realistic_unit``).
        """
        from ..sim.evaluate import episode_evaluation, episode_metrics
        from .objective import episode_objective
        from .realism_constraints import realism_penalty

        info: dict[str, Any] = {}
        overrides = None
        if u is not None:
            overrides, info = self.shapes.decode_query(u)
            info["realism"] = self.shapes.figures(overrides, info)
        result = self.episode(overrides, closed_loop, record_points, seed)
        evaluation = episode_evaluation(result)
        obj = episode_objective(result, self.weights, evaluation)
        metrics = episode_metrics(result, self.scene.lanes, evaluation=evaluation)
        for k in ("format", "version", "ms_per_frame", "fps"):  # timing is not a result
            metrics.pop(k, None)
        cost, components = obj.total, obj.components()
        weight = self.settings.realism_weight
        if weight > 0 and u is not None:
            penalty = realism_penalty(info["realism"], self.shapes.reference.jsd_limit)
            components["realism_penalty"] = penalty
            cost = obj.total - weight * penalty
        return QueryResult(cost=cost, components=components, metrics=metrics, **info), result


def scene_digest_of(scene) -> str:
    """``sha256:<hex>`` of a loaded scene's canonical JSON (written compactly): the scene's
    content id, whatever file or path it came from."""
    import hashlib

    from ..fileio import dump_json

    return "sha256:" + hashlib.sha256(dump_json(scene.to_dict(), indent=None).encode()).hexdigest()


_WORKSPACES: dict[tuple[str, QuerySettings], SceneWorkspace] = {}
#: Scenes a process keeps built at once (the driver sends a scene's queries to the same worker
#: where it can; two cover a worker that moves on to a new scene while finishing another).
WORKSPACES_PER_PROCESS = 2


def workspace_for(scene_ref: str, settings: QuerySettings) -> SceneWorkspace:
    """This process's context of a scene (built on first use; the least recently used one is
    dropped beyond :data:`WORKSPACES_PER_PROCESS`, which keeps memory flat)."""
    key = (scene_ref, settings)
    ws = _WORKSPACES.pop(key, None)
    if ws is None:
        while len(_WORKSPACES) >= WORKSPACES_PER_PROCESS:
            _WORKSPACES.pop(next(iter(_WORKSPACES)))
        ws = SceneWorkspace(scene_ref, settings)
    _WORKSPACES[key] = ws  # most recently used last
    return ws


class EpisodeEvaluator:
    """The production :class:`QueryEvaluator`: decode the query's shapes into
    :class:`~adv3d_runner.sim.episode.ShapeOverride` s, run the closed- or open-loop episode
    with the run's stack, score it (paper Eq. 3-5) and measure it (episode metrics)."""

    def __init__(self, settings: QuerySettings):
        self.settings = settings

    def scene_id(self, ref: str) -> str:
        from ..scene.schema import load_scene

        return load_scene(ref).id

    def scene_digest(self, ref: str) -> str:
        """sha256 of the scene's canonical JSON (the loaded scene written compactly): the same
        scene as ``.json`` or ``.json.gz``, by any path, has the same digest."""
        from ..scene.schema import load_scene

        return scene_digest_of(load_scene(ref))

    def targets(self, ref: str) -> tuple[list[int], int]:
        from ..scene.schema import load_scene
        from .shape_models import dim_per_actor
        from .targets import select_targets

        space = self.settings.load_shape_space()
        ids = select_targets(load_scene(ref), self.settings.actors, rank=self.settings.target_rank)
        return ids, dim_per_actor(self.settings, space) * len(ids)

    def candidates(self, ref: str, targets: list[int]) -> np.ndarray:
        """Unit vectors of the shape space's library assets (scales 1): every actor takes the
        same asset (M candidates) for m = 1; for m > 1 the M^m combinations in a seeded order."""
        import itertools

        space = self.settings.load_shape_space()
        units = np.array([space.asset_unit(a) for a in space.asset_ids])
        n_actors = len(targets)
        if n_actors == 1:
            return units
        combos = np.array(list(itertools.islice(itertools.product(range(len(units)), repeat=n_actors), 100_000)))
        combos = combos[np.random.default_rng(self.settings.seed).permutation(len(combos))]
        return units[combos].reshape(len(combos), -1)

    def evaluate(self, query: Query) -> QueryResult:
        result, _ = workspace_for(query.scene, self.settings).evaluate(query.unit, query.closed_loop)
        return result

    def versions(self) -> dict[str, Any]:
        from ..autonomy.stacks import DETECTOR_MODELS

        v: dict[str, Any] = {"shape_space": self.settings.load_shape_space().content_hash}
        if self.settings.autonomy in DETECTOR_MODELS:
            v["models"] = model_fingerprints((DETECTOR_MODELS[self.settings.autonomy], "predictor"))
        elif self.settings.autonomy == "B":
            v["models"] = model_fingerprints(("occupancy",))
        if self.settings.autonomy in (*DETECTOR_MODELS, "B"):
            v["planner"] = planner_fingerprint()
        v["stack"] = stack_info_of(self.settings.autonomy).as_dict()
        return v

    def evaluate_best(self, ref: str, targets: list[int], unit: np.ndarray, out: Path, *, original: bool,
                      metadata: dict[str, Any]) -> BestEvaluation:
        """Closed-loop episodes of the original scene (when ``original``) and of the best shape;
        writes ``actor<ID>.glb`` per attacked actor and ``replay.json.gz`` (with the LiDAR
        points) of the best shape's episode into ``out``. The best shape's evaluation carries
        its full realism report per actor (``realism``); both evaluations carry CommonRoad
        CriMe's criticality figures of their episode (``criticality``,
        :func:`~adv3d_runner.sim.criticality.criticality_block`: only here, never per query)."""
        import trimesh

        from ..shapes.mesh_io import write_mesh
        from ..sim.criticality import criticality_block
        from ..sim.replay import replay_from_episode, save_replay

        ctx = workspace_for(ref, self.settings)
        first = None
        if original:
            first_result, first_episode = ctx.evaluate(None, closed_loop=True)
            first = {**first_result.evaluation(), "criticality": criticality_block(first_episode, ctx.scene.lanes)}
        u = np.asarray(unit, dtype=np.float64).reshape(-1)
        best, result = ctx.evaluate(u, closed_loop=True, record_points=True)
        best = replace(best, realism=ctx.shapes.full_reports(u))
        out.mkdir(parents=True, exist_ok=True)
        overrides, _ = ctx.shapes.decode_query(u)
        meshes = {}
        for aid, shape in overrides.items():
            name = f"actor{aid}.glb"
            write_mesh(trimesh.Trimesh(vertices=shape.vertices, faces=shape.faces, process=False), out / name)
            meshes[aid] = name
        replay = replay_from_episode(result, autonomy=self.settings.autonomy, scene_file=str(ref), meshes=meshes,
                                     metadata={**metadata, "stack": stack_info_of(self.settings.autonomy).as_dict()})
        save_replay(replay, out / "replay.json.gz")
        closed = {**best.evaluation(), "criticality": criticality_block(result, ctx.scene.lanes)}
        return BestEvaluation(closed_loop=closed, original=first, meshes=meshes, replay="replay.json.gz")


def planner_fingerprint() -> str:
    """The planner's fingerprint (:func:`adv3d_runner.autonomy.plugins.planner_fingerprint`)."""
    from ..autonomy.plugins import planner_fingerprint as fingerprint

    return fingerprint()


def model_fingerprints(models: tuple[str, ...] = ("detector", "predictor")) -> dict[str, str]:
    """The weights' fingerprints (:func:`adv3d_runner.autonomy.plugins.model_fingerprints`)."""
    from ..autonomy.plugins import model_fingerprints as fingerprints

    return fingerprints(models)
