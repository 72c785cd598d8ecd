"""The attack driver: ask a searcher, evaluate the queries (locally in worker processes or on a
Ray cluster), journal them, tell the searcher; then evaluate the best shape in closed loop.

Determinism: the searcher is asked for a batch of ``batch`` queries (``batch`` = the number of
workers of the *first* run, stored in run.json), the batch is evaluated in parallel, and the
results are journalled and told in query order, so completion order never matters. The episode
seed is the run seed for every query (common random numbers: two queries differ only by their
shapes). A resumed run replays the same asks and takes the journalled result of every query
that is already there (checking that the journalled unit vector is the one asked), so it
neither redoes work nor changes the outcome.

A query that fails (no surface: ``EmptySurfaceError``; any other exception in decoding or
simulation) is journalled with status ``invalid`` / ``error`` and a null cost, which the
searcher penalises; the run goes on.

Modes (paper Table 1): ``closed`` attacks with the ego driven by the stack; ``open`` attacks
with the ego replaying its log and then evaluates the found shape in closed loop; ``both``
runs the two attacks one after the other.

Scenes named ``synthetic:NAME`` are cheap analytic objectives (:data:`SYNTHETIC`) over the same
unit cube, with an invalid region, for tests and benchmarks of the machinery without the
simulator.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ConfigError, InvalidQueryError
from .journal import Journal, query_record, record_cost, record_unit
from .objective import parse_objective
from .search import make_searcher

MODES = ("closed", "open", "both")
PER_ACTOR = 5  # K + 2 for the paper's K = 3; taken from the shape space for real scenes


@dataclass
class AttackConfig:
    """Everything that determines an attack's results (stored in run.json)."""

    scenes: list[str]
    algo: str = "bo"
    budget: int = 100
    actors: int = 1
    mode: str = "closed"
    seconds: float = 5.0
    seed: int = 0
    objective: str = "M0"
    autonomy: str = "A"
    reactive: bool = False
    batch: int = 1
    n_initial: int = 11
    shape_space: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.budget < 1:
            raise ConfigError(f"--budget must be >= 1, got {self.budget}")
        if self.seconds <= 0:
            raise ConfigError(f"--seconds must be > 0, got {self.seconds}")
        if self.batch < 1:
            raise ConfigError(f"batch (workers) must be >= 1, got {self.batch}")
        parse_objective(self.objective)  # validate early

    @property
    def modes(self) -> list[str]:
        return ["open", "closed"] if self.mode == "both" else [self.mode]


# ============================================================================ synthetic scenes

def _synthetic_peak(u: np.ndarray) -> float:
    """5-D: a smooth bowl with a narrow peak (height 2, width 0.05) at a fixed point."""
    c = np.array([0.73, 0.21, 0.58, 0.87, 0.34])
    d2 = float(np.sum((u[:5] - c) ** 2))
    return -d2 + 2.0 * np.exp(-d2 / (2 * 0.05**2))


SYNTHETIC: dict[str, Callable[[np.ndarray], float]] = {"peak": _synthetic_peak}
SYNTHETIC_INVALID = 0.95  # u[0] above this is an "empty surface"; u[1] above it a "simulation error"


def _synthetic_evaluate(name: str, u: np.ndarray) -> dict:
    if name not in SYNTHETIC:
        raise ConfigError(f"unknown synthetic scene {name!r}; choose one of {', '.join(SYNTHETIC)}")
    from ..errors import EmptySurfaceError

    if u[0] > SYNTHETIC_INVALID:
        raise EmptySurfaceError("synthetic: no surface")
    if u[1] > SYNTHETIC_INVALID:
        raise RuntimeError("synthetic: simulation error")
    v = SYNTHETIC[name](u)
    return {"cost": v, "components": {"synthetic": v}, "metrics": {}}


# ============================================================================ worker side

_CONTEXTS: dict[tuple, "SceneContext"] = {}


class SceneContext:
    """What one process needs to evaluate queries on a scene: the scene, its LiDAR world (built
    once), the autonomy stack, the shape space, the targets and the objective weights."""

    def __init__(self, scene_path: str, cfg: dict):
        from ..scene.schema import load_scene
        from ..shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace
        from ..sim.episode import default_library
        from ..autonomy.stacks import make_stack
        from ..sensors.world import world_from_scene
        from .targets import select_targets

        self.cfg = cfg
        self.scene = load_scene(scene_path)
        self.space = ShapeSpace.load(cfg.get("shape_space") or DEFAULT_SHAPE_SPACE)
        self.world = world_from_scene(self.scene, default_library(), scene_dir=Path(scene_path).parent)
        self.stack = make_stack(cfg["autonomy"])
        self.targets = select_targets(self.scene, cfg["actors"])
        self.weights = parse_objective(cfg["objective"])

    def episode(self, overrides: dict | None, closed_loop: bool, record_points: bool = False):
        from ..sim.episode import run_episode

        return run_episode(self.scene, self.stack, seconds=self.cfg["seconds"], closed_loop=closed_loop,
                           reactive=self.cfg["reactive"], world=self.world, actor_overrides=overrides,
                           seed=self.cfg["seed"], record_points=record_points)

    def evaluate(self, u: np.ndarray | None, closed_loop: bool, record_points: bool = False):
        """(fields for the journal record, EpisodeResult). ``u`` None = the original scene."""
        from ..sim.evaluate import episode_metrics
        from .objective import episode_objective
        from .targets import decode_query

        info: dict[str, Any] = {}
        overrides = None
        if u is not None:
            overrides, info = decode_query(self.space, u, self.targets)
        result = self.episode(overrides, closed_loop, record_points)
        obj = episode_objective(result, self.weights)
        metrics = episode_metrics(result, self.scene.lanes)
        for k in ("format", "version", "ms_per_frame", "fps"):  # timing is not a result
            metrics.pop(k, None)
        return {"cost": obj.total, "components": obj.components(), "metrics": metrics, **info}, result


def context_for(scene_ref: str, cfg: dict) -> SceneContext:
    key = (scene_ref, cfg["autonomy"], cfg["actors"], cfg["objective"], cfg["seconds"], cfg["seed"],
           cfg["reactive"], cfg.get("shape_space"))
    if key not in _CONTEXTS:
        _CONTEXTS.clear()  # one scene at a time per worker keeps memory flat
        _CONTEXTS[key] = SceneContext(scene_ref, cfg)
    return _CONTEXTS[key]


def evaluate_task(task: dict) -> dict:
    """Evaluate one query (runs in a worker). Never raises: failures come back as a status.

    Args:
        task: {"scene": path or "synthetic:NAME", "cfg": AttackConfig as dict, "unit": list,
            "closed_loop": bool}.
    Returns:
        {"status", "error", "cost", "components", "metrics", "latent", "scales",
        "dimensions", "wall_s"}.
    """
    t0 = time.perf_counter()
    u = np.asarray(task["unit"], dtype=np.float64)
    out: dict[str, Any] = {"status": "ok", "error": None, "cost": None, "components": {}, "metrics": {},
                           "latent": None, "scales": None, "dimensions": None}
    try:
        ref = task["scene"]
        if ref.startswith("synthetic:"):
            out.update(_synthetic_evaluate(ref.split(":", 1)[1], u))
        else:
            fields_, _ = context_for(ref, task["cfg"]).evaluate(u, task["closed_loop"])
            out.update(fields_)
        if out["cost"] is None or not np.isfinite(out["cost"]):
            out.update(status="error", error=f"non-finite objective {out['cost']}", cost=None)
    except InvalidQueryError as exc:
        out.update(status="invalid", error=f"{type(exc).__name__}: {exc}", cost=None)
    except Exception as exc:  # noqa: BLE001 - a query must never stop the run
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        out.update(status="error", error=tb[:500], cost=None)
    out["wall_s"] = time.perf_counter() - t0
    return out


# ============================================================================ executors

class SerialExecutor:
    """Evaluates in this process (``--workers 1``)."""

    def map(self, fn, tasks: Sequence[dict]) -> list[dict]:
        return [fn(t) for t in tasks]

    def close(self) -> None:
        pass


class ProcessExecutor:
    """A pool of local worker processes (spawned, so torch and Embree start clean). Each
    worker builds a scene's context once and reuses it for every query of that scene."""

    def __init__(self, workers: int):
        self.pool = cf.ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"))

    def map(self, fn, tasks: Sequence[dict]) -> list[dict]:
        return list(self.pool.map(fn, tasks))  # results in task order whatever finishes first

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayExecutor:
    """Queries as Ray tasks on an existing cluster (``ray.init(address=...)``)."""

    def __init__(self, address: str):
        try:
            import ray
        except ImportError as exc:  # pragma: no cover - optional extra
            raise ConfigError("--ray-address needs Ray: pip install 'adv3d[ray]'") from exc
        self.ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            ray.init(address=address, log_to_driver=False, ignore_reinit_error=True)
        self._remote = ray.remote(evaluate_task)

    def map(self, fn, tasks: Sequence[dict]) -> list[dict]:
        if fn is not evaluate_task:
            return [fn(t) for t in tasks]
        return list(self.ray.get([self._remote.remote(t) for t in tasks]))

    def close(self) -> None:
        if self._own:
            self.ray.shutdown()


def make_executor(workers: int = 1, ray_address: str | None = None):
    if ray_address:
        return RayExecutor(ray_address)
    if int(workers) > 1:
        return ProcessExecutor(int(workers))
    return SerialExecutor()


# ============================================================================ driver

@dataclass
class SceneRun:
    """Outcome of the search on one scene and mode."""

    scene: str
    mode: str
    targets: list[int]
    costs: list[float] = field(default_factory=list)
    best_index: int = -1
    best_cost: float = float("-inf")
    best_unit: list | None = None
    evaluated: int = 0
    reused: int = 0


def scene_ids(refs: Sequence[str]) -> list[str]:
    """Scene ids (read from the files; ``synthetic:NAME`` stays as it is)."""
    from ..scene.schema import load_scene

    return [r if r.startswith("synthetic:") else load_scene(r).id for r in refs]


def scene_targets(ref: str, cfg: dict) -> tuple[list[int], int]:
    """(target actor ids, query dimension) of a scene."""
    if ref.startswith("synthetic:"):
        ids = list(range(cfg["actors"]))
        return ids, PER_ACTOR * len(ids)
    from ..scene.schema import load_scene
    from ..shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace
    from .targets import select_targets

    space = ShapeSpace.load(cfg.get("shape_space") or DEFAULT_SHAPE_SPACE)
    ids = select_targets(load_scene(ref), cfg["actors"])
    return ids, space.dim * len(ids)


def bruteforce_candidates(cfg: dict, n_actors: int) -> np.ndarray:
    """Unit vectors of the shape space's library assets (scales 1): every actor takes the same
    asset (M candidates) for m = 1; for m > 1 the M^m combinations in a seeded order."""
    import itertools

    from ..shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

    space = ShapeSpace.load(cfg.get("shape_space") or DEFAULT_SHAPE_SPACE)
    units = np.array([space.asset_unit(a) for a in space.asset_ids])
    if n_actors == 1:
        return units
    combos = np.array(list(itertools.islice(itertools.product(range(len(units)), repeat=n_actors), 100_000)))
    combos = combos[np.random.default_rng(cfg["seed"]).permutation(len(combos))]
    return units[combos].reshape(len(combos), -1)


def run_scene(journal: Journal, cfg: dict, ref: str, scene_id: str, mode: str, executor,
              on_query: Callable[[SceneRun], None] | None = None, evaluate: Callable = evaluate_task) -> SceneRun:
    """Search one scene in one mode; journals every new query. Returns the outcome."""
    targets, dim = scene_targets(ref, cfg)
    cands = None
    if cfg["algo"] == "bruteforce":
        if ref.startswith("synthetic:"):
            cands = np.random.default_rng(cfg["seed"]).random((50, dim))
        else:
            cands = bruteforce_candidates(cfg, len(targets))
    options = {"n_initial": cfg["n_initial"]} if cfg["algo"] == "bo" else {}
    searcher = make_searcher(cfg["algo"], dim, seed=cfg["seed"], budget=cfg["budget"], candidates=cands, **options)
    done = journal.finished(scene_id, mode)
    run = SceneRun(scene_id, mode, targets)
    closed = mode == "closed"
    while not searcher.exhausted:
        X = searcher.ask(cfg["batch"])
        if len(X) == 0:
            break
        first = searcher.n_told
        idx = list(range(first, first + len(X)))
        results: dict[int, dict] = {}
        todo = []
        for i, x in zip(idx, X):
            if i in done:
                rec = done[i]
                if not np.allclose(record_unit(rec), x, rtol=0, atol=1e-9) or rec.get("actors") != targets:
                    raise ConfigError(f"{journal.path}: query {i} of {scene_id}/{mode} does not match this run "
                                      f"(different code or options?); use a new --out")
                results[i] = rec
                run.reused += 1
            else:
                todo.append((i, x))
        tasks = [{"scene": ref, "cfg": cfg, "unit": x.tolist(), "closed_loop": closed} for _, x in todo]
        for (i, x), out in zip(todo, executor.map(evaluate, tasks)):
            rec = query_record(scene_id, mode, i, targets, x, latent=out.get("latent"), scales=out.get("scales"),
                               dimensions=out.get("dimensions"), cost=out.get("cost"),
                               components=out.get("components"), metrics=out.get("metrics"),
                               status=out["status"], error=out.get("error"), wall_s=out.get("wall_s", 0.0))
            journal.append(rec)
            results[i] = rec
            run.evaluated += 1
        y = [record_cost(results[i]) for i in idx]
        searcher.tell(X, y)
        for i in idx:
            c = record_cost(results[i])
            run.costs.append(c)
            if np.isfinite(c) and c > run.best_cost:
                run.best_cost, run.best_index, run.best_unit = c, i, results[i]["unit"]
        if on_query is not None:
            on_query(run)
    return run


def finalize_scene(root: Path, cfg: dict, ref: str, run: SceneRun, summary: dict) -> None:
    """Evaluate the original scene (once) and the best shape in closed loop; write the best
    meshes (glb) and the replay of that closed-loop episode under ``scenes/<id>/<mode>/``."""
    entry = summary.setdefault("scenes", {}).setdefault(run.scene, {"ref": ref, "targets": run.targets, "modes": {}})
    m = {"best_index": run.best_index, "best_cost": run.best_cost if np.isfinite(run.best_cost) else None,
         "best_unit": run.best_unit, "n_queries": len(run.costs),
         "n_failed": int(sum(not np.isfinite(c) for c in run.costs))}
    if ref.startswith("synthetic:") or run.best_unit is None:
        entry["modes"][run.mode] = m
        return
    old = entry["modes"].get(run.mode) or {}
    if (old.get("best_index") == run.best_index and old.get("closed_loop_eval") and "original" in entry
            and (root / old.get("files", {}).get("replay", "missing")).exists()):
        return  # a resumed run that had already finished this scene: nothing new to simulate
    from ..shapes.mesh_io import write_mesh
    from ..sim.replay import replay_from_episode, save_replay
    from .targets import decode_query

    ctx = context_for(ref, cfg)
    if "original" not in entry:
        fields_, _ = ctx.evaluate(None, closed_loop=True)
        entry["original"] = {"cost": fields_["cost"], "components": fields_["components"], "metrics": fields_["metrics"]}
    u = np.asarray(run.best_unit, dtype=np.float64).reshape(-1)
    fields_, result = ctx.evaluate(u, closed_loop=True, record_points=True)
    out = root / "scenes" / run.scene / run.mode
    out.mkdir(parents=True, exist_ok=True)
    overrides, _ = decode_query(ctx.space, u, run.targets)
    import trimesh

    meshes = {}
    for aid, (v, f, _) in overrides.items():
        name = f"actor{aid}.glb"
        write_mesh(trimesh.Trimesh(vertices=v, faces=f, process=False), out / name)
        meshes[aid] = name
    replay = replay_from_episode(result, autonomy=cfg["autonomy"], scene_file=str(ref), meshes=meshes,
                                 metadata={"attack": {"algo": cfg["algo"], "mode": run.mode, "query": run.best_index,
                                                      "cost": run.best_cost, "seed": cfg["seed"]}})
    save_replay(replay, out / "replay.json.gz")
    m["closed_loop_eval"] = {"cost": fields_["cost"], "components": fields_["components"], "metrics": fields_["metrics"]}
    m["files"] = {"meshes": {str(k): f"scenes/{run.scene}/{run.mode}/{v}" for k, v in meshes.items()},
                  "replay": f"scenes/{run.scene}/{run.mode}/replay.json.gz"}
    entry["modes"][run.mode] = m


def versions(cfg: dict) -> dict:
    from .. import __version__

    v = {"adv3d": __version__, "numpy": np.__version__}
    if not all(s.startswith("synthetic:") for s in cfg["scenes"]):
        from ..shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

        v["shape_space"] = ShapeSpace.load(cfg.get("shape_space") or DEFAULT_SHAPE_SPACE).content_hash
        if cfg["autonomy"] == "A":
            v["models"] = model_fingerprints()
    return v


def model_fingerprints() -> dict[str, str]:
    """sha256 (first 16 hex digits) of every file under assets/models/{detector,predictor}: a
    run's results depend on the weights, which may be retrained between runs."""
    import hashlib

    from ..fileio import REPO_ROOT

    out = {}
    for sub in ("detector", "predictor"):
        d = REPO_ROOT / "assets" / "models" / sub
        if not d.is_dir():
            continue
        h = hashlib.sha256()
        for f in sorted(p for p in d.rglob("*") if p.is_file() and p.suffix in (".pt", ".json", ".safetensors")):
            h.update(f.relative_to(d).as_posix().encode())
            h.update(f.read_bytes())
        out[sub] = h.hexdigest()[:16]
    return out


def run_attack(config: AttackConfig, out: str | Path, *, workers: int = 1, ray_address: str | None = None,
               show_progress: bool = True, evaluate: Callable = evaluate_task,
               stop_after: int | None = None) -> dict:
    """Run (or resume) an attack into ``out``. Returns the summary document.

    ``stop_after``: stop (as if killed) once this many new queries were evaluated; for tests.
    """
    from tqdm.auto import tqdm

    from ..progress import is_quiet, status

    root = Path(out)
    cfg = asdict(config)
    ids = scene_ids(cfg["scenes"])
    journal = Journal(root)
    stored = journal.start({**cfg, "scene_ids": ids, "versions": versions(cfg), "workers": workers,
                            "ray_address": ray_address})
    cfg["batch"] = int(stored.get("batch", cfg["batch"]))  # a resume keeps the first run's batches
    summary = journal.read_summary()
    summary.setdefault("scenes", {})
    summary["run"] = {"algo": cfg["algo"], "budget": cfg["budget"], "mode": cfg["mode"], "seed": cfg["seed"],
                      "objective": cfg["objective"], "autonomy": cfg["autonomy"]}
    executor = make_executor(workers, ray_address)
    evaluated = [0]

    class _Stop(Exception):
        pass

    t_start = time.perf_counter()
    try:
        for ref, sid in zip(cfg["scenes"], ids):
            try:
                scene_targets(ref, cfg)
            except ConfigError as exc:  # e.g. no actor in front of the ego: skip, keep going
                status(f"skipping {sid}: {exc}")
                summary["scenes"][sid] = {"ref": ref, "skipped": str(exc)}
                journal.write_summary(summary)
                continue
            for mode in config.modes:
                bar = tqdm(total=cfg["budget"], desc=f"{sid} [{mode}]", unit="query", disable=not show_progress or is_quiet(),
                           leave=True, dynamic_ncols=True)

                def on_query(run: SceneRun, bar=bar) -> None:
                    bar.n = len(run.costs)
                    bar.set_postfix(best=f"{run.best_cost:.4g}", failed=sum(not np.isfinite(c) for c in run.costs))
                    bar.refresh()
                    evaluated[0] = run.evaluated
                    if stop_after is not None and run.evaluated >= stop_after:
                        raise _Stop

                try:
                    run = run_scene(journal, cfg, ref, sid, mode, executor, on_query, evaluate)
                finally:
                    bar.close()
                finalize_scene(root, cfg, ref, run, summary)
                summary["wall_s"] = round(time.perf_counter() - t_start, 3)
                journal.write_summary(summary)
    except _Stop:
        pass
    finally:
        executor.close()
    return summary
