"""The attack driver: ask the searchers, evaluate their queries on workers (local processes or
Ray actors on a cluster), journal them, tell the searchers; then evaluate each scene's best
shape in closed loop.

The driver talks to a :class:`~adv3d_runner.attack.evaluator.QueryEvaluator` (by default the
episode evaluator, :class:`~adv3d_runner.attack.evaluator.EpisodeEvaluator`; tests plug in a
cheap analytic one) and is configured by a typed :class:`~adv3d_runner.attack.config.AttackConfig`.

Scheduling. Every scene and mode is its own search (searcher, batches, best shape). The searches
of a run are worked on **concurrently**: whenever a worker is free and no asked query is
waiting, the next search (in the order of the command: scenes, then modes) is opened, so a run
with many scenes keeps every worker busy, and one scene's queries go to the worker that already
built that scene (its LiDAR world, lane map and static-hit cache). The closed-loop evaluation of
a search's best shape (and of the original scene) is a task on the workers too; its files come
back to the driver, which writes every file of the run.

Determinism: a search asks ``batch`` queries at a time (``--batch``, stored in run.json: a
parameter of its own, so the results do not depend on the number of workers), the batch is
evaluated in parallel, and the results are told in query order, so completion order never
matters. Each query is journalled as soon as it finishes: into ``queries.jsonl`` when every
lower index of its batch is already there, else into ``queries.pending.jsonl`` until they are
(see :mod:`.journal`), so a kill loses only the queries in flight and each search's lines stay
in index order. On local worker processes the worker itself appends its query's record to the
pending file (fsync) before the result leaves it (:func:`durable_query`): a finished query is
durable before it travels to the driver, so a kill of the driver and its workers never loses a
query whose worker had written it (docs/reliability.md, "Crash and resume"). Searches worked on concurrently interleave their lines; when the run is
complete the journal is rewritten, atomically, in the canonical order (scenes as given, modes,
query index), so a finished run's ``queries.jsonl`` is the same bytes (up to wall times) for any
number of workers, and for a run that was killed and resumed. The episode seed is the same
for every query of a scene (common random numbers: two queries differ only by their shapes):
the run seed, or with ``scene_seeds`` a seed derived from it and the scene's content, as is then
the searcher's (``config.scene_seed``; both recorded in summary.json). A resumed run
replays the same asks and takes the journalled result of every query that is already there
(checking that the journalled unit vector is the one asked), so it neither redoes work nor
changes the outcome.

A query that fails (no surface: ``EmptySurfaceError``; any other exception in decoding or
simulation) is journalled with status ``invalid`` / ``error`` and a null cost, which the
searcher penalises; the run goes on.

Modes (paper Table 1): ``closed`` attacks with the ego driven by the stack; ``open`` attacks
with the ego replaying its log and then evaluates the found shape in closed loop; ``both``
runs the two attacks (two independent searches) on each scene.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ConfigError, RunFailedError, StackFailure
from ..fileio import resolve_inside
from .config import MODES, AttackConfig, QuerySettings
from .evaluator import BestEvaluation, EpisodeEvaluator, Query, QueryEvaluator, QueryResult, run_query
from .journal import Journal, query_record, record_cost, record_unit
from .search import check_search_memory, make_searcher

__all__ = ["MODES", "AttackConfig", "SceneRun", "check_outcome", "make_executor", "run_attack"]

#: Builds the run's evaluator from its settings (``run_attack(evaluator=...)``).
EvaluatorFactory = Callable[[QuerySettings], QueryEvaluator]


# ============================================================================ executors
# An executor runs tasks on ``slots`` workers: ``submit(slot, fn, *args)`` returns a
# concurrent.futures.Future. Each worker is one long-lived process that keeps the scenes it has
# built (``evaluator.workspace_for``), which is why a task is sent to a chosen worker.

def worker_setup() -> None:
    """Runs first in every worker process: one thread per numerical library (the parallelism is
    the workers; see :func:`adv3d_runner.machine.single_thread_env`)."""
    from ..machine import limit_threads

    limit_threads()


class SerialExecutor:
    """Evaluates in this process (``--workers 1``)."""

    slots = 1
    #: whether a query's task writes its record to the run's pending file itself
    #: (:func:`durable_query`): not here, where the driver writes it the moment the task returns
    writes_pending = False

    def submit(self, slot: int, fn: Callable, *args) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller like a pool would
            future.set_exception(exc)
        return future

    def close(self) -> None:
        pass


class ProcessExecutor:
    """``workers`` local worker processes (spawned, so torch and Embree start clean), each its
    own single-process pool so that a task can go to the worker holding its scene. A worker
    writes each query's record to the run's pending file before returning it
    (:func:`durable_query`)."""

    writes_pending = True

    def __init__(self, workers: int):
        from ..machine import single_thread_children

        ctx = mp.get_context("spawn")
        with single_thread_children():
            self.pools = [cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=worker_setup)
                          for _ in range(int(workers))]
            for pool in self.pools:  # start them now, with this environment
                pool.submit(int, 0).result()
        self.slots = len(self.pools)

    def submit(self, slot: int, fn: Callable, *args) -> cf.Future:
        return self.pools[slot].submit(fn, *args)

    def close(self) -> None:
        for pool in self.pools:
            pool.shutdown(wait=True, cancel_futures=True)


class _RayWorker:
    """A Ray actor: one worker process of the cluster that keeps its scenes between tasks."""

    def __init__(self):
        worker_setup()

    def call(self, fn: Callable, *args):
        return fn(*args)


class RayExecutor:
    """Ray actors on an existing cluster (``ray.init(address=...)``), one per worker, each
    holding one CPU; ``workers`` None = one per CPU of the cluster. The actors may run on other
    machines, without the run folder: the driver writes each record when the result arrives."""

    writes_pending = False

    def __init__(self, address: str, workers: int | None = None):
        try:
            import ray
        except ImportError as exc:  # pragma: no cover - optional extra
            raise ConfigError("--ray-address needs Ray: pip install 'adv3d[ray]'") from exc
        from ..machine import single_thread_env

        self.ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            ray.init(address=address, log_to_driver=False, ignore_reinit_error=True)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        n = cpus if workers is None else min(int(workers), cpus)
        if n < 1:
            raise ConfigError(f"the Ray cluster at {address} has no CPU to run on")
        # The workers import the code from the driver's import path where a node has it (a
        # shared or identical checkout; else the node's installed adv3d), one thread each.
        path = os.pathsep.join(p for p in sys.path if p and os.path.isdir(p))
        env = {**single_thread_env(), "PYTHONPATH": path}
        actor = ray.remote(num_cpus=1, runtime_env={"env_vars": env})(_RayWorker)
        self.actors = [actor.remote() for _ in range(n)]
        self.slots = n

    def submit(self, slot: int, fn: Callable, *args) -> cf.Future:
        return self.actors[slot].call.remote(fn, *args).future()

    def close(self) -> None:
        for a in self.actors:
            self.ray.kill(a)
        if self._own:
            self.ray.shutdown()


def make_executor(workers: int | None = 1, ray_address: str | None = None):
    """Ray actors on the cluster at ``ray_address`` (``workers`` of them, None = one per CPU),
    else ``workers`` local processes (in this process for 1)."""
    if ray_address:
        return RayExecutor(ray_address, workers)
    if workers is not None and int(workers) > 1:
        return ProcessExecutor(int(workers))
    return SerialExecutor()


def best_task(evaluator: QueryEvaluator, ref: str, targets: list[int], unit: np.ndarray, original: bool,
              metadata: dict) -> tuple[BestEvaluation | None, dict[str, bytes]]:
    """:meth:`QueryEvaluator.evaluate_best` on a worker: its files are written to a temporary
    folder and returned (name relative to that folder -> bytes) for the driver to write."""
    with tempfile.TemporaryDirectory(prefix="adv3d-best-") as tmp:
        best = evaluator.evaluate_best(ref, targets, unit, Path(tmp), original=original, metadata=metadata)
        files = {p.relative_to(tmp).as_posix(): p.read_bytes() for p in sorted(Path(tmp).rglob("*")) if p.is_file()}
    return best, files


@dataclass(frozen=True)
class PendingLine:
    """Where and as what a worker journals its query: the run's pending file and the record's
    scene, mode, index and attacked actors."""

    path: str
    scene: str
    mode: str
    index: int
    actors: tuple[int, ...]


def query_line(scene: str, mode: str, index: int, actors: Sequence[int], unit: np.ndarray, out: QueryResult) -> dict:
    """The journal record of a query's result (:func:`~.journal.query_record`)."""
    return query_record(scene, mode, index, list(actors), unit, latent=out.latent, scales=out.scales,
                        dimensions=out.dimensions, cost=out.cost, components=out.components, metrics=out.metrics,
                        status=out.status, error=out.error, wall_s=out.wall_s, realism=out.realism)


def durable_query(evaluator: QueryEvaluator, query: Query, line: PendingLine) -> QueryResult:
    """:func:`run_query` on a local worker process, then the query's record appended to the
    run's pending file (one write, fsync) before the result is returned: the result is durable
    before it leaves the worker, so it is never only in memory on its way to the driver (pickled,
    piped, waiting for the driver's turn on a loaded machine). The driver then moves it to
    ``queries.jsonl`` in index order as before (:meth:`_Search.result`); a kill leaves it in the
    pending file, which a resume reads."""
    from . import journal

    out = run_query(evaluator, query)
    rec = query_line(line.scene, line.mode, line.index, line.actors, query.unit, out)
    journal._append(Path(line.path), journal._line(rec))
    return out


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
    seeds: dict | None = None  # {"search_seed", "noise_seed"} of a run with scene_seeds


class _Search:
    """One scene and mode: its searcher, the batch in flight and the outcome so far."""

    def __init__(self, journal: Journal, config: AttackConfig, evaluator: QueryEvaluator, ref: str, scene_id: str,
                 mode: str, targets: list[int], dim: int):
        self.ref, self.scene_id, self.mode = ref, scene_id, mode
        self.config, self.journal, self.evaluator, self.dim = config, journal, evaluator, dim
        self.run = SceneRun(scene_id, mode, targets)
        self.searcher = None
        self.done: dict[int, dict] = {}
        self.X: np.ndarray | None = None
        self.results: dict[int, dict] = {}
        self.waiting = 0  # queries of the current batch not back yet
        self.order: list[int] = []  # indices of the current batch not yet in queries.jsonl
        self.bar = None
        #: whether a worker may still append to the pending file (a query task running on a
        #: worker that writes its own record: :func:`durable_query`); the file is emptied only
        #: when none can, so no durable line is cut away (set by :func:`run_attack`)
        self.workers_writing: Callable[[], bool] = lambda: False

    def start(self) -> None:
        """Build the searcher and read what the journal already holds (when the search opens)."""
        config = self.config
        cands = self.evaluator.candidates(self.ref, self.run.targets) if config.algo == "bruteforce" else None
        options = {"n_initial": config.n_initial} if config.algo in ("bo", "skopt") else {}
        seed = config.seed
        if config.scene_seeds:  # this scene's own search sequence and LiDAR noise (config.scene_seed)
            digest = self.evaluator.scene_digest(self.ref)
            self.run.seeds = {"search_seed": config.search_seed(digest),
                              "noise_seed": config.settings.episode_seed(digest)}
            seed = self.run.seeds["search_seed"]
        self.searcher = make_searcher(config.algo, self.dim, seed=seed, budget=config.budget,
                                      candidates=cands, **options)
        self.done = self.journal.finished(self.scene_id, self.mode)

    def ask(self) -> list[tuple[int, Query]]:
        """The next batch's queries that are not in the journal; batches that are all journalled
        (a resumed run) are told at once. [] when the search is over."""
        while not self.searcher.exhausted:
            X = self.searcher.ask(self.config.batch)
            if len(X) == 0:
                break
            first = self.searcher.n_told
            self.X, self.results, todo = X, {}, []
            self.order = list(range(first, first + len(X)))  # journal order of the batch
            for i, x in zip(range(first, first + len(X)), X):
                if i in self.done:
                    rec = self.done[i]
                    u = record_unit(rec)
                    if (u.shape != np.shape(x) or not np.allclose(u, x, rtol=0, atol=1e-9)
                            or rec.get("actors") != self.run.targets):
                        raise ConfigError(f"{self.journal.where(self.scene_id, self.mode, i)}: query {i} of "
                                          f"{self.scene_id}/{self.mode} does not match this run (its point or "
                                          f"actors are not what the search asks at that index: different code, "
                                          f"options, or numerical libraries, or an edited line; a search resumes "
                                          f"only where its journal was written); use a new --out")
                    self.results[i] = rec
                    self.run.reused += 1
                else:
                    todo.append((i, Query(self.ref, np.asarray(x, dtype=np.float64).reshape(-1),
                                          self.mode == "closed")))
            self.commit()  # a resumed batch: its pending records move to the journal in order
            if todo:
                self.waiting = len(todo)
                return todo
            self.clear_pending()
            self.tell()
        unasked = sorted(i for i in self.done if i >= self.searcher.n_told)
        if unasked:  # the search ended before these indices: records it never asked for
            i = unasked[0]
            raise ConfigError(f"{self.journal.where(self.scene_id, self.mode, i)}: query {i} of "
                              f"{self.scene_id}/{self.mode} was never asked: the search ended after "
                              f"{self.searcher.n_told} queries; use a new --out")
        return []

    def result(self, i: int, x: np.ndarray, out: QueryResult, written: bool = False) -> bool:
        """Journal query ``i`` now: into ``queries.jsonl`` when it is the batch's next index not
        yet there (with the finished ones after it), else into the pending file until its turn
        (``written``: its worker has put it there already, :func:`durable_query`). True when its
        batch is complete (and told)."""
        rec = query_line(self.scene_id, self.mode, i, self.run.targets, x, out)
        self.results[i] = rec
        self.run.evaluated += 1
        self.waiting -= 1
        if self.order and self.order[0] == i:
            self.commit()
        elif written:
            self.journal.note_pending(rec)
        else:
            self.journal.append_pending(rec)
        if self.waiting == 0:
            self.commit()
            self.clear_pending()
            self.tell()
            return True
        return False

    def clear_pending(self) -> None:
        """Empty the pending file when no search has a record waiting there and no worker may
        still append one (:meth:`~.journal.Journal.clear_pending`)."""
        if not self.workers_writing():
            self.journal.clear_pending()

    def commit(self) -> None:
        """Append the batch's finished queries to ``queries.jsonl`` in index order, up to the
        first one not finished (a record already journalled by an earlier run is not repeated;
        one from the pending file is moved)."""
        while self.order and self.order[0] in self.results:
            i = self.order.pop(0)
            if i not in self.done or self.journal.is_pending(self.scene_id, self.mode, i):
                self.journal.append(self.results[i])

    def tell(self) -> None:
        idx = sorted(self.results)
        self.searcher.tell(self.X, [record_cost(self.results[i]) for i in idx])
        for i in idx:
            c = record_cost(self.results[i])
            self.run.costs.append(c)
            if np.isfinite(c) and c > self.run.best_cost:
                self.run.best_cost, self.run.best_index, self.run.best_unit = c, i, self.results[i]["unit"]
        if self.bar is not None:
            self.bar.n = len(self.run.costs)
            self.bar.set_postfix(best=f"{self.run.best_cost:.4g}",
                                 failed=sum(not np.isfinite(c) for c in self.run.costs))
            self.bar.refresh()


def _mode_entry(run: SceneRun) -> dict:
    return {"best_index": run.best_index, "best_cost": run.best_cost if np.isfinite(run.best_cost) else None,
            "best_unit": run.best_unit, "n_queries": len(run.costs),
            "n_failed": int(sum(not np.isfinite(c) for c in run.costs)), **(run.seeds or {})}


def _needs_best(root: Path, run: SceneRun, entry: dict) -> bool:
    """False for a resumed run that had already evaluated this search's best shape."""
    old = entry["modes"].get(run.mode) or {}
    return not (old.get("best_index") == run.best_index and old.get("closed_loop_eval") and "original" in entry
                and (root / old.get("files", {}).get("replay", "missing")).exists())


def _write_files(root: Path, folder: str, files: dict[str, bytes]) -> None:
    from ..fileio import atomic_write_bytes

    out_dir = resolve_inside(root, folder, field="scene id", inside="the run folder")  # checked at start too
    for name, data in files.items():
        target = resolve_inside(out_dir, name, field="best-shape file", inside="the run folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(target, data)


def _ordered_summary(summary: dict, config: AttackConfig, ids: list[str]) -> dict:
    """The summary with its scenes in the command's order and modes in run order, whatever order
    they finished in."""
    scenes = summary.get("scenes", {})
    ordered = {}
    for sid in ids + [s for s in scenes if s not in ids]:
        if sid in scenes and sid not in ordered:
            entry = dict(scenes[sid])
            if isinstance(entry.get("modes"), dict):
                modes = entry["modes"]
                entry["modes"] = {m: modes[m] for m in list(config.modes) + list(modes) if m in modes}
            ordered[sid] = entry
    return {**summary, "scenes": ordered}


def versions(evaluator: QueryEvaluator) -> dict:
    """What the run's results depend on beyond its config (stored in run.json, not compared)."""
    from .. import __version__
    from ..machine import numerical_config

    return {"adv3d": __version__, "numpy": np.__version__, **evaluator.versions(), "numerics": numerical_config()}


def stored_batch(out: str | Path) -> int | None:
    """The batch size of the run already in ``out`` (None when there is none)."""
    from ..fileio import read_json

    path = Path(out) / "run.json"
    if not path.exists():
        return None
    doc = read_json(path)
    batch = doc.get("batch") if isinstance(doc, dict) else None
    return int(batch) if isinstance(batch, int) and not isinstance(batch, bool) else None


def run_attack(config: AttackConfig, out: str | Path, *, workers: int | None = 1, ray_address: str | None = None,
               show_progress: bool = True, evaluator: EvaluatorFactory = EpisodeEvaluator,
               stop_after: int | None = None, incremental: bool = True) -> dict:
    """Run (or resume) an attack into ``out``. Returns the summary document.

    ``workers``: local worker processes (1 = this process), or with ``ray_address`` the number
    of Ray actors (None = one per CPU of the cluster). The results do not depend on it.
    ``evaluator``: builds the :class:`~adv3d_runner.attack.evaluator.QueryEvaluator` from the
    config's :class:`~adv3d_runner.attack.config.QuerySettings` (default: the episode evaluator).
    ``stop_after``: stop (as if killed) once this many new queries were evaluated; for tests.
    ``incremental``: reuse the static LiDAR hits between the queries of a scene
    (``QuerySettings.incremental``; identical results, faster).
    """
    from tqdm.auto import tqdm

    from ..progress import is_quiet, note, status

    from .config import library_fingerprint_of

    root = Path(out)
    settings = replace(config.settings, incremental=bool(incremental))
    ev = evaluator(settings)
    # Everything is read and checked before anything is written: scenes (ids, content),
    # output folders of every scene, the run folder itself (Journal.start).
    ids = [ev.scene_id(ref) for ref in config.scenes]
    for sid in ids:
        resolve_inside(root, f"scenes/{sid}", field="scene id", inside="the run folder")
    digests = [ev.scene_digest(ref) for ref in config.scenes]
    # each scene's targets and search dimension, and the search's memory (the dimension is the
    # shape space's or the lattice's per actor): a search too big for memory is refused here
    plans: list[tuple[list[int], int] | ConfigError] = []
    for ref, sid in zip(config.scenes, ids):
        try:
            targets, dim = ev.targets(ref)
        except ConfigError as exc:  # e.g. no actor in front of the ego: skipped below, the run goes on
            plans.append(exc)
            continue
        check_search_memory(config.algo, dim, config.budget, config.n_initial, config.batch,
                            what=f"{sid}: --actors {config.actors} ({len(targets)} attacked, {dim // max(1, len(targets))} "
                                 "dimensions each)")
        plans.append((targets, dim))
    journal = Journal(root)
    stored = journal.start({**config.run_json(), "library_fingerprint": library_fingerprint_of(config.library),
                            "scene_ids": ids, "scene_sha256": digests, "versions": versions(ev),
                            "workers": workers, "ray_address": ray_address})
    config = config.with_batch(int(stored.get("batch", config.batch)))
    summary = journal.read_summary()
    summary.setdefault("scenes", {})
    summary["run"] = {"algo": config.algo, "budget": config.budget, "mode": config.mode, "seed": config.seed,
                      "objective": config.objective, "pred_reduction": config.pred_reduction,
                      "autonomy": config.autonomy}
    if config.scene_seeds:
        summary["run"]["scene_seeds"] = True

    # every search of the run, in canonical order (skipped scenes recorded as such)
    pending: list[_Search] = []
    for ref, sid, plan in zip(config.scenes, ids, plans):
        if isinstance(plan, ConfigError):  # e.g. no actor in front of the ego: skip, keep going
            note(f"skipping {sid}: {plan}")  # with -q too: the run covers fewer scenes
            summary["scenes"][sid] = {"ref": ref, "skipped": str(plan)}
            continue
        targets, dim = plan
        for mode in config.modes:
            pending.append(_Search(journal, config, ev, ref, sid, mode, targets, dim))
    for search in pending:
        search.workers_writing = lambda: writes_pending() and any(item != "best" for _, item, _ in running.values())
    journal.write_summary(_ordered_summary(summary, config, ids))
    original_claimed: set[str] = set()

    executor = None  # started with the first task (a finished run that is resumed needs none)
    free: list[int] = []
    affinity: dict[str, int] = {}            # scene ref -> the worker that last worked on it
    ready: list[tuple[_Search, Any]] = []     # (search, (i, query)) or (search, "best")
    running: dict[cf.Future, tuple[_Search, Any, int]] = {}
    evaluated = 0
    t_start = time.perf_counter()
    stopped = False

    def open_next() -> bool:
        if not pending:
            return False
        search = pending.pop(0)
        search.bar = tqdm(total=config.budget, desc=f"{search.scene_id} [{search.mode}]", unit="query",
                          disable=not show_progress or is_quiet(), leave=True, dynamic_ncols=True)
        search.start()
        advance(search)
        return True

    def advance(search: _Search) -> None:
        """Queue the search's next batch, or its best-shape evaluation when it is over."""
        todo = search.ask()
        if todo:
            ready.extend((search, item) for item in todo)
            return
        entry = summary["scenes"].setdefault(search.scene_id, {"ref": search.ref, "targets": search.run.targets,
                                                               "modes": {}})
        if search.run.best_unit is None or not _needs_best(root, search.run, entry):
            finish(search, None, {})
        else:
            ready.append((search, "best"))

    def finish(search: _Search, best: BestEvaluation | None, files: dict[str, bytes]) -> None:
        run = search.run
        entry = summary["scenes"].setdefault(run.scene, {"ref": search.ref, "targets": run.targets, "modes": {}})
        m = _mode_entry(run)
        if run.best_unit is not None and best is None and not _needs_best(root, run, entry):
            m = {**entry["modes"][run.mode], **m}  # resumed: keep the evaluation already there
        folder = f"scenes/{run.scene}/{run.mode}"
        if best is not None:
            _write_files(root, folder, files)
            if best.original is not None:
                entry["original"] = best.original
            m["closed_loop_eval"] = best.closed_loop
            m["files"] = {"meshes": {str(k): f"{folder}/{v}" for k, v in best.meshes.items()},
                          "replay": f"{folder}/{best.replay}"}
        entry["modes"][run.mode] = m
        summary["wall_s"] = round(time.perf_counter() - t_start, 3)
        journal.write_summary(_ordered_summary(summary, config, ids))
        if search.bar is not None:
            search.bar.close()

    def task_of(search: _Search, item) -> tuple[Callable, tuple]:
        if item == "best":
            run = search.run
            # the original scene is simulated once per scene, by the first best-shape run of it
            original = "original" not in summary["scenes"][run.scene] and run.scene not in original_claimed
            original_claimed.add(run.scene)
            meta = {"attack": {"algo": config.algo, "mode": run.mode, "query": run.best_index, "cost": run.best_cost,
                               "seed": config.seed}}
            return best_task, (ev, search.ref, run.targets, np.asarray(run.best_unit, dtype=np.float64).reshape(-1),
                               original, meta)
        if writes_pending():
            line = PendingLine(str(journal.pending_path), search.scene_id, search.mode, int(item[0]),
                               tuple(int(a) for a in search.run.targets))
            return durable_query, (ev, item[1], line)
        return run_query, (ev, item[1])

    def writes_pending() -> bool:
        """Whether the executor's workers journal their queries in the pending file themselves."""
        return bool(getattr(executor, "writes_pending", False))

    def dispatch() -> None:
        nonlocal executor
        while free or executor is None:
            if not ready and not open_next():
                return
            if not ready:
                continue
            if executor is None:
                executor = make_executor(workers, ray_address)
                free.extend(range(executor.slots))
            # a free worker takes a task of a scene it already holds, else the oldest task
            pick = None
            for w in free:
                pick = next((k for k, (srch, _) in enumerate(ready) if affinity.get(srch.ref) == w), None)
                if pick is not None:
                    break
            if pick is None:
                w = free[0]
                pick = next((k for k, (srch, _) in enumerate(ready) if affinity.get(srch.ref) not in free), 0)
            search, item = ready.pop(pick)
            free.remove(w)
            affinity[search.ref] = w
            fn, args = task_of(search, item)
            running[executor.submit(w, fn, *args)] = (search, item, w)

    try:
        dispatch()
        while running:
            done, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
            for fut in sorted(done, key=lambda f: running[f][2]):
                search, item, w = running.pop(fut)
                free.append(w)
                free.sort()
                if item == "best":
                    try:
                        best, files = fut.result()
                    except StackFailure as exc:  # the stack under test broke: the search's results stand
                        note(f"note: {search.scene_id} [{search.mode}]: the best shape's closed-loop evaluation "
                             f"failed ({exc}); a resume tries it again")
                        best, files = None, {}
                    finish(search, best, files)
                    continue
                i, query = item
                batch_done = search.result(i, query.unit, fut.result(), written=writes_pending())
                evaluated += 1
                if stop_after is not None and evaluated >= stop_after:
                    raise _Stop
                if batch_done:
                    advance(search)
            dispatch()
    except _Stop:
        stopped = True
    finally:
        for fut in running:
            fut.cancel()
        if executor is not None:
            executor.close()
        for search in pending:
            if search.bar is not None:
                search.bar.close()
    if not stopped:
        journal.canonicalize([(sid, mode) for sid in ids for mode in config.modes])
    journal.close()
    return _ordered_summary(summary, config, ids)


class _Stop(Exception):
    pass


def check_outcome(summary: dict, records: Sequence[dict]) -> None:
    """Raise ``RunFailedError`` saying why when a run produced nothing: every scene skipped, or
    a scene and mode whose every query failed (the most frequent errors are quoted)."""
    from collections import Counter

    scenes = summary.get("scenes", {})
    attacked = {sid: e for sid, e in scenes.items() if "skipped" not in e}
    if scenes and not attacked:
        reasons = "; ".join(f"{sid}: {e['skipped']}" for sid, e in scenes.items())
        raise RunFailedError(f"nothing was attacked: every scene was skipped ({reasons})")
    problems = []
    for sid, entry in attacked.items():
        for mode, m in entry.get("modes", {}).items():
            n = m.get("n_queries", 0)
            if n and m.get("n_failed", 0) == n:
                errors = Counter(r.get("error") or r.get("status") for r in records
                                 if r.get("scene") == sid and r.get("mode") == mode and r.get("status") != "ok")
                top = "; ".join(f"{c} x {msg}" for msg, c in errors.most_common(3))
                problems.append(f"{sid} [{mode}]: all {n} queries failed ({top})")
    if problems:
        raise RunFailedError("every query failed: " + " | ".join(problems))
