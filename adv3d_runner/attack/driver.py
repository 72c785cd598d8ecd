"""The attack driver: ask a searcher, evaluate the queries (locally in worker processes or on a
Ray cluster), journal them, tell the searcher; then evaluate the best shape in closed loop.

The driver talks to a :class:`~adv3d_runner.attack.evaluator.QueryEvaluator` (by default the
episode evaluator, :class:`~adv3d_runner.attack.evaluator.EpisodeEvaluator`; tests plug in a
cheap analytic one) and is configured by a typed :class:`~adv3d_runner.attack.config.AttackConfig`.

Determinism: the searcher is asked for a batch of ``batch`` queries (``batch`` = the number of
workers of the *first* run, stored in run.json), the batch is evaluated in parallel, and the
results are told in query order, so completion order never matters. Each query is journalled
as soon as it finishes (``queries.jsonl`` if every lower index of its batch is already there,
else ``queries.pending.jsonl`` until they are; see :mod:`.journal`), so a kill loses only the
queries in flight while the journal stays in index order. The episode
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
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from ..errors import ConfigError, RunFailedError
from ..fileio import resolve_inside
from .config import MODES, AttackConfig, QuerySettings
from .evaluator import EpisodeEvaluator, Query, QueryEvaluator, QueryResult, run_query
from .journal import Journal, query_record, record_cost, record_unit
from .search import make_searcher

__all__ = ["MODES", "AttackConfig", "SceneRun", "check_outcome", "finalize_scene", "make_executor", "run_attack",
           "run_scene"]

#: Builds the run's evaluator from its settings (``run_attack(evaluator=...)``).
EvaluatorFactory = Callable[[QuerySettings], QueryEvaluator]


# ============================================================================ executors
# Each evaluates a batch of queries with one evaluator and yields (position in the batch,
# result) as each query finishes, so the driver can journal it at once.

class SerialExecutor:
    """Evaluates in this process (``--workers 1``)."""

    def as_completed(self, evaluator: QueryEvaluator, queries: Sequence[Query]) -> Iterator[tuple[int, QueryResult]]:
        for k, q in enumerate(queries):
            yield k, run_query(evaluator, q)

    def close(self) -> None:
        pass


class ProcessExecutor:
    """A pool of local worker processes (spawned, so torch and Embree start clean). Each
    worker builds a scene's context once and reuses it for every query of that scene."""

    def __init__(self, workers: int):
        self.pool = cf.ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"))

    def as_completed(self, evaluator: QueryEvaluator, queries: Sequence[Query]) -> Iterator[tuple[int, QueryResult]]:
        futures = {self.pool.submit(run_query, evaluator, q): k for k, q in enumerate(queries)}
        for fut in cf.as_completed(futures):
            yield futures[fut], fut.result()

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
        self._remote = ray.remote(run_query)

    def as_completed(self, evaluator: QueryEvaluator, queries: Sequence[Query]) -> Iterator[tuple[int, QueryResult]]:
        refs = {self._remote.remote(evaluator, q): k for k, q in enumerate(queries)}
        waiting = list(refs)
        while waiting:
            ready, waiting = self.ray.wait(waiting, num_returns=1)
            yield refs[ready[0]], self.ray.get(ready[0])

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


def run_scene(journal: Journal, config: AttackConfig, evaluator: QueryEvaluator, ref: str, scene_id: str, mode: str,
              executor, on_query: Callable[[SceneRun], None] | None = None) -> SceneRun:
    """Search one scene in one mode; journals every new query. Returns the outcome."""
    targets, dim = evaluator.targets(ref)
    cands = evaluator.candidates(ref, targets) if config.algo == "bruteforce" else None
    options = {"n_initial": config.n_initial} if config.algo == "bo" else {}
    searcher = make_searcher(config.algo, dim, seed=config.seed, budget=config.budget, candidates=cands, **options)
    done = journal.finished(scene_id, mode)
    run = SceneRun(scene_id, mode, targets)
    closed = mode == "closed"
    while not searcher.exhausted:
        X = searcher.ask(config.batch)
        if len(X) == 0:
            break
        first = searcher.n_told
        idx = list(range(first, first + len(X)))
        results: dict[int, dict] = {}
        todo = []
        for i, x in zip(idx, X):
            if i in done:
                rec = done[i]
                u = record_unit(rec)
                if u.shape != np.shape(x) or not np.allclose(u, x, rtol=0, atol=1e-9) or rec.get("actors") != targets:
                    raise ConfigError(f"{journal.path}: query {i} of {scene_id}/{mode} does not match this run "
                                      f"(different code or options?); use a new --out")
                results[i] = rec
                run.reused += 1
            else:
                todo.append((i, x))
        # Journal each query as it finishes: in index order into queries.jsonl (the next index
        # of the batch not yet there), anything that finishes early into the pending file.
        commit = iter(idx)
        nxt = [next(commit, None)]

        def advance() -> None:
            while nxt[0] is not None and nxt[0] in results:
                i = nxt[0]
                if i not in done or journal.is_pending(scene_id, mode, i):
                    journal.append(results[i])
                nxt[0] = next(commit, None)

        advance()
        queries = [Query(ref, np.asarray(x, dtype=np.float64).reshape(-1), closed) for _, x in todo]
        for k, out in executor.as_completed(evaluator, queries):
            i, x = todo[k]
            rec = query_record(scene_id, mode, i, targets, x, latent=out.latent, scales=out.scales,
                               dimensions=out.dimensions, cost=out.cost, components=out.components,
                               metrics=out.metrics, status=out.status, error=out.error, wall_s=out.wall_s,
                               realism=out.realism)
            results[i] = rec
            run.evaluated += 1
            if i == nxt[0]:
                advance()
            else:
                journal.append_pending(rec)
        advance()
        journal.clear_pending()
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


def finalize_scene(root: Path, config: AttackConfig, evaluator: QueryEvaluator, ref: str, run: SceneRun,
                   summary: dict) -> None:
    """Evaluate the original scene (once) and the best shape in closed loop; write the best
    meshes (glb) and the replay of that closed-loop episode under ``scenes/<id>/<mode>/``
    (:meth:`QueryEvaluator.evaluate_best`)."""
    entry = summary.setdefault("scenes", {}).setdefault(run.scene, {"ref": ref, "targets": run.targets, "modes": {}})
    m = {"best_index": run.best_index, "best_cost": run.best_cost if np.isfinite(run.best_cost) else None,
         "best_unit": run.best_unit, "n_queries": len(run.costs),
         "n_failed": int(sum(not np.isfinite(c) for c in run.costs))}
    if run.best_unit is None:
        entry["modes"][run.mode] = m
        return
    old = entry["modes"].get(run.mode) or {}
    if (old.get("best_index") == run.best_index and old.get("closed_loop_eval") and "original" in entry
            and (root / old.get("files", {}).get("replay", "missing")).exists()):
        return  # a resumed run that had already finished this scene: nothing new to simulate
    folder = f"scenes/{run.scene}/{run.mode}"
    out_dir = resolve_inside(root, folder, field="scene id", inside="the run folder")  # checked at start too
    best = evaluator.evaluate_best(
        ref, run.targets, np.asarray(run.best_unit, dtype=np.float64).reshape(-1), out_dir,
        original="original" not in entry,
        metadata={"attack": {"algo": config.algo, "mode": run.mode, "query": run.best_index, "cost": run.best_cost,
                             "seed": config.seed}})
    if best is not None:
        if best.original is not None:
            entry["original"] = best.original
        m["closed_loop_eval"] = best.closed_loop
        m["files"] = {"meshes": {str(k): f"{folder}/{v}" for k, v in best.meshes.items()},
                      "replay": f"{folder}/{best.replay}"}
    entry["modes"][run.mode] = m


def versions(evaluator: QueryEvaluator) -> dict:
    """What the run's results depend on beyond its config (stored in run.json, not compared)."""
    from .. import __version__

    return {"adv3d": __version__, "numpy": np.__version__, **evaluator.versions()}


def run_attack(config: AttackConfig, out: str | Path, *, workers: int = 1, ray_address: str | None = None,
               show_progress: bool = True, evaluator: EvaluatorFactory = EpisodeEvaluator,
               stop_after: int | None = None) -> dict:
    """Run (or resume) an attack into ``out``. Returns the summary document.

    ``evaluator``: builds the :class:`~adv3d_runner.attack.evaluator.QueryEvaluator` from the
    config's :class:`~adv3d_runner.attack.config.QuerySettings` (default: the episode evaluator).
    ``stop_after``: stop (as if killed) once this many new queries were evaluated; for tests.
    """
    from tqdm.auto import tqdm

    from ..progress import is_quiet, status

    root = Path(out)
    ev = evaluator(config.settings)
    # Everything is read and checked before anything is written: scenes (ids, content),
    # output folders of every scene, the run folder itself (Journal.start).
    ids = [ev.scene_id(ref) for ref in config.scenes]
    for sid in ids:
        resolve_inside(root, f"scenes/{sid}", field="scene id", inside="the run folder")
    digests = [ev.scene_digest(ref) for ref in config.scenes]
    journal = Journal(root)
    from .config import library_fingerprint_of

    stored = journal.start({**config.run_json(), "library_fingerprint": library_fingerprint_of(config.library),
                            "scene_ids": ids, "scene_sha256": digests, "versions": versions(ev),
                            "workers": workers, "ray_address": ray_address})
    config = config.with_batch(int(stored.get("batch", config.batch)))  # a resume keeps the first run's batches
    summary = journal.read_summary()
    summary.setdefault("scenes", {})
    summary["run"] = {"algo": config.algo, "budget": config.budget, "mode": config.mode, "seed": config.seed,
                      "objective": config.objective, "autonomy": config.autonomy}
    executor = make_executor(workers, ray_address)
    evaluated = [0]

    class _Stop(Exception):
        pass

    t_start = time.perf_counter()
    try:
        for ref, sid in zip(config.scenes, ids):
            try:
                ev.targets(ref)
            except ConfigError as exc:  # e.g. no actor in front of the ego: skip, keep going
                status(f"skipping {sid}: {exc}")
                summary["scenes"][sid] = {"ref": ref, "skipped": str(exc)}
                journal.write_summary(summary)
                continue
            for mode in config.modes:
                bar = tqdm(total=config.budget, desc=f"{sid} [{mode}]", unit="query",
                           disable=not show_progress or is_quiet(), leave=True, dynamic_ncols=True)

                def on_query(run: SceneRun, bar=bar) -> None:
                    bar.n = len(run.costs)
                    bar.set_postfix(best=f"{run.best_cost:.4g}", failed=sum(not np.isfinite(c) for c in run.costs))
                    bar.refresh()
                    evaluated[0] = run.evaluated
                    if stop_after is not None and run.evaluated >= stop_after:
                        raise _Stop

                try:
                    run = run_scene(journal, config, ev, ref, sid, mode, executor, on_query)
                finally:
                    bar.close()
                finalize_scene(root, config, ev, ref, run, summary)
                summary["wall_s"] = round(time.perf_counter() - t_start, 3)
                journal.write_summary(summary)
    except _Stop:
        pass
    finally:
        executor.close()
    return summary


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

