"""The experiment protocol of the paper's tables, stated once here and in
docs/results.md ("Protocol"); ``bench/paper_tables.py`` runs it.

* **Scenes** (:func:`select_scenes`, rule :data:`SCENE_RULE`): generated benchmark scenes from
  every traffic density (and, cycling, every layout) plus the benchmark part of the real
  scenes (``scenes/real/split.json``), one recording after the other.
* **Seeds**: every table runs ``S >= 3`` run seeds. Within a run each scene has its own search
  seed and search-episode (LiDAR-noise) seed, derived from the run seed and the scene's content
  (``AttackConfig(scene_seeds=True)``, :func:`~adv3d_runner.attack.config.scene_seed`), so
  searches differ per scene and seed.
* **Held-out evaluation** (:func:`evaluation_seeds`, :func:`heldout_evaluate`): the search
  picks its best shape on its own noise seed, so its score there is optimistic (the best of
  ``budget`` draws of that very episode). Every best shape, and the original scene, is
  re-simulated in closed loop on ``K`` evaluation seeds derived from the run seed and the scene
  (streams ``eval0``, ``eval1``, ...; never the search's seeds), and those are the numbers the
  tables report. The original and the shapes of one scene and run seed share the evaluation
  seeds, so every comparison is paired.
* **Statistics** (:mod:`adv3d_runner.metrics.stats`): a scene's value is the mean over its run
  seeds and evaluation seeds (:func:`scene_means`); tables give the mean over scenes with a
  percentile bootstrap interval over scenes, and comparisons the paired sign-flip permutation
  test on the per-scene differences (Wilcoxon and the sign test beside it).

Held-out results are kept in a :class:`HeldoutStore` (a ``.json.gz`` file keyed by scene,
what was evaluated and seed; written after every evaluation, so a killed campaign resumes
without redoing one).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from ..errors import ConfigError
from ..fileio import REPO_ROOT
from .config import QuerySettings, scene_seed

#: Default folder of the generated benchmark scenes.
HIGHWAY_DIR = REPO_ROOT / "scenes" / "highway"

SCENE_RULE = (
    "generated: the scenes of scenes/highway (ids in order) are grouped by the traffic density "
    "recorded in each scene (source.details.density); rounds k = 0, 1, ... visit the densities in "
    "the generator's order (free, light, moderate, dense, congested), and density j takes its "
    "lowest-id scene not yet chosen whose layout is LAYOUTS[(j + k) mod 4] (straight, curved, "
    "onramp, lanedrop; any layout when none is left), until N scenes; real: the benchmark part of "
    "scenes/real/split.json, one recording after the other (recordings in the file's order, each "
    "recording's scenes in the file's order: round v takes each recording's v-th scene), until R "
    "scenes. Chosen from the scene files alone, before any attack ran on them.")

#: The rule for the fresh real benchmark part (``scenes/real-fresh``), recorded in a table's
#: protocol when it has fresh scenes.
FRESH_RULE = (
    "fresh: the scenes of scenes/real-fresh/index.csv (recordings 10-18, never trained or tuned on; "
    "each recording's scenes are its egos at evenly spaced ranks of logged speed, slowest first), "
    "rounds v = 0, 1, ... visit the recordings in ascending order and recording j takes its scene "
    "of rank (j + v) mod (its scene count) not yet chosen, so every round spreads over the speed "
    "ranks, until F scenes. Chosen from the manifest alone, before any attack ran on them.")


@dataclass(frozen=True)
class SceneChoice:
    """One scene of the protocol's set.

    Attributes:
        path: the scene file, relative to the repository root when it lies inside it.
        part: ``generated``, ``real`` (the benchmark part of ``scenes/real``) or
            ``real-fresh`` (``scenes/real-fresh``).
        density, layout: the generator's (generated scenes); ``recording``: the NGSIM
            recording (real scenes).
    """

    path: str
    part: str
    density: str | None = None
    layout: str | None = None
    recording: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


def generated_catalogue(folder: str | Path = HIGHWAY_DIR) -> list[tuple[Path, str, str]]:
    """(file, density, layout) of every generated scene of a folder, in file-name order (read
    from each scene's ``source.details``; scenes without them are left out)."""
    from ..fileio import read_json

    out = []
    for path in sorted(Path(folder).glob("*.json*")):
        doc = read_json(path)
        details = ((doc.get("source") or {}).get("details") or {}) if isinstance(doc, dict) else {}
        if details.get("density") and details.get("layout"):
            out.append((path, str(details["density"]), str(details["layout"])))
    return out


def select_scenes(n_generated: int, n_real: int, *, n_fresh: int = 0, highway_dir: str | Path = HIGHWAY_DIR,
                  split_path: str | Path | None = None, fresh_dir: str | Path | None = None) -> list[SceneChoice]:
    """The protocol's scene set by :data:`SCENE_RULE`: ``n_generated`` generated scenes, then
    ``n_real`` real benchmark scenes, then ``n_fresh`` scenes of the fresh real part
    (:data:`FRESH_RULE`).

    Raises:
        ConfigError: fewer scenes exist than asked for.
    """
    from ..scene.generate import DENSITIES, LAYOUTS
    from ..scene.real import load_real_split, recording_of

    if n_generated < 0 or n_real < 0:
        raise ConfigError(f"scene counts must be >= 0, got {n_generated} generated and {n_real} real")
    out: list[SceneChoice] = []
    if n_generated:
        cat = generated_catalogue(highway_dir)
        if len(cat) < n_generated:
            raise ConfigError(f"{highway_dir} holds {len(cat)} generated scenes, {n_generated} asked for")
        taken: set[Path] = set()
        densities = list(DENSITIES)
        k = 0
        while len(out) < n_generated:
            progress = False
            for j, density in enumerate(densities):
                if len(out) == n_generated:
                    break
                pool = [c for c in cat if c[1] == density and c[0] not in taken]
                if not pool:
                    continue
                want = LAYOUTS[(j + k) % len(LAYOUTS)]
                path, dens, layout = next((c for c in pool if c[2] == want), pool[0])
                taken.add(path)
                out.append(SceneChoice(_rel(path), "generated", density=dens, layout=layout))
                progress = True
            if not progress:  # densities outside DENSITIES only: take them in id order
                rest = [c for c in cat if c[0] not in taken]
                for path, dens, layout in rest[: n_generated - len(out)]:
                    taken.add(path)
                    out.append(SceneChoice(_rel(path), "generated", density=dens, layout=layout))
            k += 1
    if n_real:
        split = load_real_split(split_path)
        by_rec: dict[int, list[Path]] = {r: [] for r in split.recordings["benchmark"]}
        for path in split.paths("benchmark"):
            by_rec.setdefault(recording_of(path.name.split(".")[0]), []).append(path)
        chosen: list[SceneChoice] = []
        v = 0
        while len(chosen) < n_real and any(len(p) > v for p in by_rec.values()):
            for rec, paths in by_rec.items():
                if v < len(paths) and len(chosen) < n_real:
                    chosen.append(SceneChoice(_rel(paths[v]), "real", recording=int(rec)))
            v += 1
        if len(chosen) < n_real:
            raise ConfigError(f"the real benchmark part holds {len(chosen)} scenes, {n_real} asked for")
        out += chosen
    if n_fresh < 0:
        raise ConfigError(f"the fresh scene count must be >= 0, got {n_fresh}")
    if n_fresh:
        out += select_fresh(n_fresh, fresh_dir)
    return out


def select_fresh(n_fresh: int, folder: str | Path | None = None) -> list[SceneChoice]:
    """``n_fresh`` scenes of the fresh real part by :data:`FRESH_RULE` (manifest
    ``<folder>/index.csv``, default ``scenes/real-fresh``).

    Raises:
        ConfigError: the part holds fewer scenes; FileFormatError: a bad manifest."""
    from ..scene.real import load_fresh_part

    part = load_fresh_part(folder)
    by_rec: dict[int, list[Path]] = {}
    for row, path in zip(part.rows, part.paths()):
        by_rec.setdefault(int(row["recording"]), []).append(path)
    if n_fresh > sum(len(p) for p in by_rec.values()):
        raise ConfigError(f"the fresh real part holds {sum(len(p) for p in by_rec.values())} scenes, "
                          f"{n_fresh} asked for")
    chosen: list[SceneChoice] = []
    taken: set[Path] = set()
    v = 0
    while len(chosen) < n_fresh:
        for j, rec in enumerate(sorted(by_rec)):
            paths = by_rec[rec]
            # rank (j + v) mod n, or the next one not yet taken
            for q in range(len(paths)):
                path = paths[(j + v + q) % len(paths)]
                if path not in taken:
                    taken.add(path)
                    chosen.append(SceneChoice(_rel(path), "real-fresh", recording=rec))
                    break
            if len(chosen) == n_fresh:
                break
        v += 1
    return chosen


def evaluation_seeds(run_seed: int, scene_digest: str, k: int) -> list[int]:
    """The ``k`` held-out evaluation seeds of a scene in a run: streams ``eval0``, ``eval1``, ...
    of :func:`~adv3d_runner.attack.config.scene_seed`, skipping any value that equals the
    search's seed or noise seed (or an earlier evaluation seed), so no evaluation ever replays
    the search's noise."""
    if k < 1:
        raise ConfigError(f"need at least one evaluation seed, got {k}")
    used = {scene_seed(run_seed, scene_digest, "search"), scene_seed(run_seed, scene_digest, "noise")}
    out: list[int] = []
    i = 0
    while len(out) < k:
        s = scene_seed(run_seed, scene_digest, f"eval{i}")
        if s not in used:
            out.append(s)
            used.add(s)
        i += 1
    return out


def _clean(x: Any) -> Any:
    """JSON-safe: non-finite floats -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x


#: Fields of :class:`QuerySettings` that an evaluation of the original scene (no shape) on a
#: given seed never reads: the search's own seeds, the shape model and its region and realism
#: knobs, and how the LiDAR is computed (``incremental``: identical results either way).
SHAPE_ONLY_FIELDS = ("seed", "scene_seeds", "shape_space", "shape_model", "vd_bound", "vd_lattice", "max_mahalanobis",
                     "class_scales", "realism_weight", "region", "incremental")


def original_settings(settings: QuerySettings) -> QuerySettings:
    """``settings`` with :data:`SHAPE_ONLY_FIELDS` at their defaults: what the original scene's
    held-out evaluation depends on (stack, targets, objective and its form, episode length,
    reactive actors, library). Settings that differ only in those fields (a table's search
    algorithms, shape models, realism presets) share the original's evaluations and the
    workspace they run on (:func:`run_heldout`)."""
    defaults = QuerySettings()
    return dataclasses.replace(settings, **{f: getattr(defaults, f) for f in SHAPE_ONLY_FIELDS
                                            if hasattr(defaults, f)})


def heldout_evaluate(ref: str, settings: QuerySettings, unit: np.ndarray | None, seed: int) -> dict[str, Any]:
    """One closed-loop evaluation of ``unit`` (None: the original scene) on ``seed``, with the
    run's settings (stack, objective and its form, shape model): ``{"seed", "cost",
    "components", "metrics"}`` (the query's result without the realism figures; JSON-safe). Runs
    in this process on its cached scene workspace (``evaluator.workspace_for``): the search's
    own when the search ran in this process (its world, background and static-hit caches), and
    for the original scene the one of :func:`original_settings`."""
    from .evaluator import workspace_for

    if unit is None:
        settings = original_settings(settings)
    u = None if unit is None else np.asarray(unit, dtype=np.float64).reshape(-1)
    res, _ = workspace_for(ref, settings).evaluate(u, closed_loop=True, seed=int(seed))
    return _clean({"seed": int(seed), "cost": res.cost, "components": res.components, "metrics": res.metrics})


def heldout_key(scene_id: str, what: str, seed: int) -> str:
    """Key of a held-out evaluation: ``scene|what|seed`` (``what``: ``original`` or the mode
    whose best shape it is)."""
    return f"{scene_id}|{what}|{int(seed)}"


def check_heldout_record(node, key: str) -> None:
    """One stored held-out evaluation: its key ``scene|what|seed`` (:func:`heldout_key`) and
    record (``seed`` equal to the key's, ``cost`` a number or null, ``components`` and
    ``metrics`` objects, ``unit`` null or a list of numbers in [0, 1]); FileFormatError naming
    the file and key."""
    from ..argtypes import SEED_MAX

    parts = key.split("|")
    if len(parts) != 3 or not parts[0] or not parts[1] or not parts[2].isdigit() or int(parts[2]) > SEED_MAX:
        node.fail("a key scene|what|seed (seed an integer)", key)
    node.object("a held-out evaluation record")
    if node["seed"].integer(lo=0, hi=SEED_MAX) != int(parts[2]):
        node["seed"].fail(f"the seed of its key ({parts[2]})", node["seed"].value)
    if node["cost"].value is not None:
        node["cost"].number()
    node.get("components", {}).object()
    node.get("metrics", {}).object()
    if node.get("unit").value is not None:
        node["unit"].numbers(min_length=1, lo=0.0, hi=1.0)


class HeldoutStore:
    """Held-out evaluations of one run folder, kept in a ``.json.gz`` file (format
    ``adv3d-heldout``, version 1: ``{"format", "version", "evaluations": {key: record}}``; a
    record is :func:`heldout_evaluate`'s plus ``unit``, the evaluated unit vector or None).
    Written atomically after every new evaluation."""

    FORMAT = "adv3d-heldout"
    VERSION = 1

    def __init__(self, path: str | Path):
        from ..fileio import read_json
        from ..validate import Node, check_header

        self.path = Path(path)
        self.evaluations: dict[str, dict] = {}
        if self.path.exists():
            doc = Node(read_json(self.path), "$", self.path)
            check_header(doc, self.FORMAT, (self.VERSION,))
            evaluations = doc["evaluations"]
            for key, rec in evaluations.object().items():
                check_heldout_record(evaluations.child(key, rec), key)
            self.evaluations = dict(evaluations.value)

    def get(self, key: str, unit: np.ndarray | None) -> dict | None:
        """The stored record of ``key`` when it evaluated the same unit vector (else None: a
        different best shape must be evaluated again)."""
        rec = self.evaluations.get(key)
        if rec is None:
            return None
        stored = rec.get("unit")
        if (stored is None) != (unit is None):
            return None
        if unit is not None and not np.allclose(np.asarray(stored, dtype=np.float64).reshape(-1),
                                                np.asarray(unit, dtype=np.float64).reshape(-1), rtol=0, atol=1e-12):
            return None
        return rec

    def put(self, key: str, unit: np.ndarray | None, record: dict) -> None:
        from ..fileio import write_json

        self.evaluations[key] = {**record, "unit": None if unit is None else
                                 np.asarray(unit, dtype=np.float64).reshape(-1).tolist()}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, {"format": self.FORMAT, "version": self.VERSION, "evaluations": self.evaluations},
                   indent=None)


@dataclass(frozen=True)
class HeldoutTask:
    """One held-out evaluation to make: scene ``ref`` (id ``scene_id``), ``what`` (original or
    a mode), its unit vector (None: original) and the evaluation seed."""

    ref: str
    scene_id: str
    what: str
    unit: tuple[float, ...] | None
    seed: int

    @property
    def key(self) -> str:
        return heldout_key(self.scene_id, self.what, self.seed)


def heldout_tasks(summary: dict, run_seed: int, k: int) -> list[HeldoutTask]:
    """The held-out evaluations a finished run needs: per attacked scene the original and each
    mode's best shape, on the scene's :func:`evaluation_seeds`. Scenes that were skipped, or
    modes without a best shape, give none."""
    from .evaluator import EpisodeEvaluator

    tasks = []
    digest_of = EpisodeEvaluator(QuerySettings()).scene_digest
    for sid, entry in summary.get("scenes", {}).items():
        if "skipped" in entry or not entry.get("modes"):
            continue
        ref = entry["ref"]
        seeds = evaluation_seeds(run_seed, digest_of(ref), k)
        units: list[tuple[str, tuple[float, ...] | None]] = [("original", None)]
        for mode, m in entry["modes"].items():
            if m.get("best_unit") is not None:
                units.append((mode, tuple(np.asarray(m["best_unit"], dtype=np.float64).reshape(-1).tolist())))
        for what, u in units:
            for s in seeds:
                tasks.append(HeldoutTask(ref, sid, what, u, s))
    return tasks


#: This process's held-out evaluations of original scenes: (scene file, :func:`original_settings`,
#: seed) -> record. Another setting of the same table evaluates the same episodes (a campaign
#: runs every setting of a run seed on each scene), so they are simulated once per process.
_ORIGINAL_RECORDS: dict[tuple, dict] = {}
#: The held-out worker processes of this process, by count: kept between :func:`run_heldout`
#: calls so that a campaign's workers import the stack and build a scene's workspace once, not
#: once per run folder.
_POOLS: dict[int, Any] = {}


def _original_key(ref: str, settings: QuerySettings, seed: int) -> tuple:
    return (str(Path(ref).resolve()), original_settings(settings), int(seed))


def heldout_pool(workers: int):
    """This process's pool of ``workers`` spawned held-out workers (one thread per numerical
    library each), started on first use and kept until the process exits."""
    import atexit
    import concurrent.futures as cf
    import multiprocessing as mp

    pool = _POOLS.get(int(workers))
    if pool is None:
        from ..machine import limit_threads, single_thread_children

        with single_thread_children():
            pool = cf.ProcessPoolExecutor(max_workers=int(workers), mp_context=mp.get_context("spawn"),
                                          initializer=limit_threads)
            for fut in [pool.submit(int, 0) for _ in range(int(workers))]:  # start them with this environment
                fut.result()
        _POOLS[int(workers)] = pool
        if len(_POOLS) == 1:
            atexit.register(lambda: [p.shutdown(cancel_futures=True) for p in _POOLS.values()])
    return pool


def run_heldout(tasks: Sequence[HeldoutTask], settings: QuerySettings, store: HeldoutStore, *, workers: int = 1,
                on_done: Callable[[HeldoutTask], None] | None = None) -> int:
    """Make every task not in ``store`` yet (in this process, or on ``workers`` processes of
    :func:`heldout_pool`) and store each result as it arrives. What was simulated already is
    not simulated again:

    * the same shape on the same scene and seed is one episode (e.g. open- and closed-loop
      searches that kept the same point): simulated once and stored under each key;
    * the original scene on a seed is simulated once per process for every setting with the
      same :func:`original_settings` (a table's algorithms, shape models or realism presets);
    * in this process, the evaluations run on the search's workspace (``evaluator.workspace_for``:
      its world and background), in worker processes on workspaces kept from earlier calls.

    Returns the number of new simulations."""
    def unit_of(t: HeldoutTask):
        return None if t.unit is None else np.asarray(t.unit)

    def ident(scene_id: str, seed, unit) -> tuple:
        return (scene_id, int(seed), None if unit is None else tuple(float(x) for x in unit))

    known = {ident(key.split("|")[0], rec["seed"], rec.get("unit")): rec for key, rec in store.evaluations.items()}
    groups: dict[tuple, list[HeldoutTask]] = {}
    for t in tasks:
        if store.get(t.key, unit_of(t)) is None:
            groups.setdefault(ident(t.scene_id, t.seed, t.unit), []).append(t)

    def put(group: list[HeldoutTask], rec: dict) -> None:
        t0 = group[0]
        if t0.unit is None:
            _ORIGINAL_RECORDS[_original_key(t0.ref, settings, t0.seed)] = rec
        for t in group:
            store.put(t.key, unit_of(t), {k: v for k, v in rec.items() if k != "unit"})
            if on_done:
                on_done(t)

    todo = []
    for key, group in groups.items():
        t0 = group[0]
        shared = _ORIGINAL_RECORDS.get(_original_key(t0.ref, settings, t0.seed)) if t0.unit is None else None
        if key in known:
            put(group, known[key])
        elif shared is not None:
            put(group, shared)
        else:
            todo.append(group)
    if workers <= 1 or len(todo) <= 1:
        for group in todo:
            t = group[0]
            put(group, heldout_evaluate(t.ref, settings, t.unit, t.seed))
        return len(todo)
    import concurrent.futures as cf

    pool = heldout_pool(int(workers))
    futures = {pool.submit(heldout_evaluate, g[0].ref, settings, g[0].unit, g[0].seed): g for g in todo}
    for fut in cf.as_completed(futures):
        put(futures[fut], fut.result())
    return len(todo)


# --------------------------------------------------------------------------- aggregation

#: The reported metrics: name -> (path into a query's metrics, scale), as the paper's Table 1
#: (AP and recall in %, ADE in m, comfort in m/s^2 and m/s^3), plus the objective.
METRICS: dict[str, tuple[tuple[str, ...], float]] = {
    "objective": (("_cost",), 1.0),
    "AP": (("detection", "ap"), 100.0),
    "Recall": (("detection", "recall"), 100.0),
    "minADE": (("prediction", "min_ade"), 1.0),
    "meanADE": (("prediction", "mean_ade"), 1.0),
    "Plan lat.": (("planning_comfort", "lat"), 1.0),
    "Plan jerk": (("planning_comfort", "jerk"), 1.0),
    "Drive lat.": (("driving_comfort", "lat"), 1.0),
    "Drive jerk": (("driving_comfort", "jerk"), 1.0),
}
#: Autonomy-B's (instance-free) metrics, as the lower block of the paper's Table 1: occupancy
#: and flow-grounded occupancy mAP and Soft-IoU in %, flow EPE in m/s, comfort as above.
METRICS_B: dict[str, tuple[tuple[str, ...], float]] = {
    "objective": (("_cost",), 1.0),
    "Occupancy mAP": (("occupancy", "map"), 100.0),
    "Occupancy Soft-IoU": (("occupancy", "soft_iou"), 100.0),
    "Flow-grounded mAP": (("occupancy", "flow_grounded_map"), 100.0),
    "Flow-grounded Soft-IoU": (("occupancy", "flow_grounded_soft_iou"), 100.0),
    "EPE": (("occupancy", "epe"), 1.0),
    **{k: v for k, v in METRICS.items() if k.startswith(("Plan", "Drive"))},
}
#: Metrics where a lower value is worse for the stack (for the others higher is worse).
LOWER_IS_WORSE = ("AP", "Recall", "Occupancy mAP", "Occupancy Soft-IoU", "Flow-grounded mAP",
                  "Flow-grounded Soft-IoU")


def metrics_for(autonomy: str) -> dict[str, tuple[tuple[str, ...], float]]:
    """The reported metrics of a stack: :data:`METRICS_B` for the instance-free stacks,
    :data:`METRICS` otherwise."""
    from ..autonomy.stacks import INSTANCE_FREE

    return METRICS_B if autonomy in INSTANCE_FREE else METRICS


def metric_value(record: dict, name: str) -> float:
    """A metric of a held-out record (NaN when absent or null), by its name in :data:`METRICS`
    or :data:`METRICS_B`."""
    path, scale = METRICS[name] if name in METRICS else METRICS_B[name]
    if path == ("_cost",):
        v = record.get("cost")
    else:
        v = record.get("metrics") or {}
        for p in path:
            v = v.get(p) if isinstance(v, dict) else None
    return float(v) * scale if isinstance(v, (int, float)) and not isinstance(v, bool) else float("nan")


def scene_means(records: Iterable[tuple[str, dict]], value: Callable[[dict], float]) -> dict[str, float]:
    """Per scene the mean of ``value(record)`` over its records (run seeds x evaluation seeds),
    non-finite values left out (NaN for a scene without any).

    Args:
        records: (scene id, record) pairs.
    """
    acc: dict[str, list[float]] = {}
    for sid, rec in records:
        acc.setdefault(sid, []).append(value(rec))
    out = {}
    for sid, vals in acc.items():
        v = np.asarray(vals, dtype=np.float64)
        v = v[np.isfinite(v)]
        out[sid] = float(v.mean()) if len(v) else float("nan")
    return out
