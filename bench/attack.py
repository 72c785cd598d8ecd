"""Attack benchmark: searcher overhead and convergence, query throughput, and where a query's
CPU time goes.

    .venv/bin/python bench/attack.py [--quick] [--scene FILE] [--autonomy oracle|A] [--queries N]
    .venv/bin/python bench/attack.py --stages [--autonomy A] [--queries 8] [--scenes 000000,000010,000041]
    .venv/bin/python bench/attack.py --search-only [--quick]

1. Convergence on the synthetic 5-D objective (``synthetic:peak``: a bowl with a narrow peak of
   height 2 at a fixed point; ``tests/attack_synthetic.py``, the tests' analytic stand-in for the
   episode evaluator), every algorithm at budget 100 over several seeds: best value after
   10/25/50/100 queries and the searcher's own time per query (ask + tell, no simulation).
2. Throughput on a bundled scene: a closed-loop 5 s BO attack with 1 and 2 local workers
   (batch = workers); queries per minute (steady state from the journal's per-query wall times,
   and end to end including worker start-up and the LiDAR world build) and the extrapolated time
   of a 100-query attack.
3. ``--stages`` (alone): CPU seconds of one query (a 5 s episode with a decoded shape, scored and
   measured) in closed and open loop, with the plain and the incremental LiDAR (when the code has
   it), split by stage: shape decoding, the journal's realism figures (code that has them),
   BVH build, LiDAR, detector, tracker, predictor, planner,
   evaluation (objective + metrics) and the rest. One process pinned to one core, one thread per
   library; ``time.process_time`` (the machine is shared: CPU time, not wall time). The same
   seeded shapes in every configuration, interleaved query by query so that load changes hit all
   of them alike; the first query of each (workspace build) is not counted. Runs against the
   code next to it, so the same script measures an older checkout (``before`` numbers).

``--search-only``: section 1 alone, with scikit-optimize's GP optimiser (``skopt``) beside the
others (needs the ``skopt`` extra), the searcher's time per query also as CPU time.

Writes ``bench/results/attack.json`` (``attack.quick.json`` with --quick; ``attack_stages.json``
with --stages; ``attack_search.json`` with --search-only).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

if "--stages" in sys.argv:  # one core, one thread per library, before numpy and torch load
    for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_k, "1")
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.config import AttackConfig  # noqa: E402
from adv3d_runner.attack.driver import run_attack  # noqa: E402
from adv3d_runner.attack.search import make_searcher  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402
from tests.attack_synthetic import peak  # noqa: E402  (the synthetic objective lives with the tests)

CHECKPOINTS = (10, 25, 50, 100)


def synthetic_convergence(seeds: int, budget: int = 100,
                          algos: tuple[str, ...] = ("bo", "random", "grid", "blendsearch", "bruteforce")) -> dict:
    f = peak
    out = {}
    for algo in algos:
        curves, overhead, cpu = [], [], []
        for seed in range(seeds):
            cands = np.random.default_rng(seed).random((budget, 5)) if algo == "bruteforce" else None
            s = make_searcher(algo, 5, seed=seed, budget=budget, candidates=cands)
            best, vals, t, c = -np.inf, [], 0.0, 0.0
            while not s.exhausted:
                t0, c0 = time.perf_counter(), time.process_time()
                X = s.ask(1)
                t, c = t + time.perf_counter() - t0, c + time.process_time() - c0
                y = [f(x) for x in X]
                t0, c0 = time.perf_counter(), time.process_time()
                s.tell(X, y)
                t, c = t + time.perf_counter() - t0, c + time.process_time() - c0
                best = max(best, *y)
                vals.append(best)
            curves.append(vals)
            overhead.append(t / max(len(vals), 1))
            cpu.append(c / max(len(vals), 1))
        n = min(len(c) for c in curves)
        C = np.array([c[:n] for c in curves])
        out[algo] = {"best_at": {str(k): float(C[:, k - 1].mean()) for k in CHECKPOINTS if k <= n},
                     "best_std_at_end": float(C[:, -1].std()), "queries": n,
                     "searcher_ms_per_query": 1000 * float(np.mean(overhead)),
                     "searcher_cpu_ms_per_query": 1000 * float(np.mean(cpu)), "seeds": seeds,
                     "curve_mean": [float(v) for v in C.mean(axis=0)]}
    return out


def throughput(scene: str, autonomy: str, queries: int, workers: int, seconds: float) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="adv3d-bench-attack-"))
    try:
        cfg = AttackConfig([scene], algo="bo", budget=queries, batch=workers, autonomy=autonomy, seconds=seconds)
        t0 = time.perf_counter()
        run_attack(cfg, tmp / "run", workers=workers, show_progress=False)
        total = time.perf_counter() - t0
        recs = [json.loads(x) for x in (tmp / "run" / "queries.jsonl").read_text().splitlines()]
        walls = np.array([r["wall_s"] for r in recs])
        # steady state: skip each worker's first query (it builds the world and loads the stack)
        steady = walls[workers:] if len(walls) > workers else walls
        per_query = float(np.mean(steady)) / workers
        return {"workers": workers, "queries": len(recs), "end_to_end_s": total,
                "queries_per_min_end_to_end": 60 * len(recs) / total,
                "query_wall_s_mean": float(np.mean(steady)), "queries_per_min_steady": 60 / per_query,
                "first_query_s": float(walls[0]), "extrapolated_100_queries_min": 100 * per_query / 60,
                "statuses": {s: sum(r["status"] == s for r in recs) for s in ("ok", "invalid", "error")}}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


STAGES = ("decode", "realism", "bvh", "lidar", "detector", "tracker", "predictor", "planner", "evaluation")


class _StageClock:
    """CPU seconds per stage, accumulated by wrapping the functions and methods of each stage
    (module attributes looked up at call time, so the episode and the evaluator use the
    wrapped ones)."""

    def __init__(self):
        self.now = dict.fromkeys(STAGES, 0.0)
        self._undo = []

    def wrap(self, owner, name: str, stage: str) -> None:
        orig = getattr(owner, name)
        clock = self

        def timed(*a, **k):
            t0 = time.process_time()
            try:
                return orig(*a, **k)
            finally:
                clock.now[stage] += time.process_time() - t0

        setattr(owner, name, timed)
        self._undo.append((owner, name, orig))

    def restore(self) -> None:
        for owner, name, orig in reversed(self._undo):
            setattr(owner, name, orig)
        self._undo.clear()


def query_stages(scenes: list[str], autonomy: str, queries: int, seconds: float = 5.0) -> dict:
    """Section 3: CPU seconds per query by stage (see the module docstring)."""
    import dataclasses

    import adv3d_runner.attack.objective as objective_mod
    import adv3d_runner.attack.targets as targets_mod
    import adv3d_runner.sensors.lidar as lidar_mod
    import adv3d_runner.sim.evaluate as evaluate_mod
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import SceneWorkspace
    from adv3d_runner.sensors.world import LidarWorld

    has_incremental = "incremental" in {f.name for f in dataclasses.fields(QuerySettings)}
    variants = [("plain", False)] + ([("incremental", True)] if has_incremental else [])
    configs = [(loop, name, flag) for loop in ("closed", "open") for name, flag in variants]
    clock = _StageClock()
    clock.wrap(lidar_mod, "simulate_frame", "lidar")
    try:  # the query's shapes: attack.shape_models, attack.targets in older commits
        from adv3d_runner.attack.shape_models import ActorShapes

        clock.wrap(ActorShapes, "decode_query", "decode")
        clock.wrap(ActorShapes, "figures", "realism")  # the journal's per-query realism figures
    except ImportError:
        clock.wrap(targets_mod, "decode_query", "decode")
    clock.wrap(LidarWorld, "set_actor_mesh", "bvh")
    clock.wrap(evaluate_mod, "episode_evaluation", "evaluation")
    clock.wrap(evaluate_mod, "episode_metrics", "evaluation")
    clock.wrap(objective_mod, "episode_objective", "evaluation")
    wrapped_stacks = set()
    out = {"configs": {}, "scenes": [], "queries_per_scene": queries, "seconds": seconds,
           "has_incremental": has_incremental}
    per = {f"{loop}/{name}": [] for loop, name, _ in configs}
    try:
        for scene in scenes:
            units = np.random.default_rng(0).random((queries + 1, 5))
            spaces = {}
            for loop, name, flag in configs:
                kw = {"incremental": flag} if has_incremental else {}
                st = QuerySettings(autonomy=autonomy, seconds=seconds, **kw)
                key = (name, flag)
                if key not in spaces:
                    spaces[key] = SceneWorkspace(scene, st)
                    stack = spaces[key].stack
                    if id(stack) not in wrapped_stacks:
                        wrapped_stacks.add(id(stack))
                        clock.wrap(stack.detector, "detect", "detector")
                        clock.wrap(stack.tracker, "update", "tracker")
                        clock.wrap(stack.predictor, "predict", "predictor")
                        clock.wrap(stack.planner, "plan", "planner")
            results = {}
            for q, u in enumerate(units):
                for loop, name, flag in configs:
                    ws = spaces[(name, flag)]
                    clock.now = dict.fromkeys(STAGES, 0.0)
                    t0 = time.process_time()
                    res, ep = ws.evaluate(u, loop == "closed")
                    total = time.process_time() - t0
                    results.setdefault((loop, q), []).append((name, res.cost, res.metrics))
                    if q == 0:
                        continue  # first query: warm-up
                    row = {k: v for k, v in clock.now.items()}
                    row["other"] = total - sum(row.values())
                    row["total"] = total
                    row["frames"] = int(ep.frames)
                    per[f"{loop}/{name}"].append(row)
            same = all(len({(c, json.dumps(m, sort_keys=True)) for _, c, m in v}) == 1 for v in results.values())
            cache = {}
            for (name, flag), ws in spaces.items():
                for loop, c in getattr(ws, "lidar_caches", {}).items():
                    cache[f"{'closed' if loop else 'open'}/{name}"] = {"hits": c.hits, "misses": c.misses,
                                                                      "megabytes": c.nbytes / 2**20}
            out["scenes"].append({"scene": Path(scene).name, "targets": spaces[variants[0]].targets,
                                  "actors": len(spaces[variants[0]].scene.actors),
                                  "results_identical_across_variants": same, "lidar_cache": cache})
            print(f"  {Path(scene).name}: results identical across variants: {same}; cache {cache}")
    finally:
        clock.restore()
    for key, rows in per.items():
        frames = np.mean([r["frames"] for r in rows])
        out["configs"][key] = {
            "queries": len(rows),
            "cpu_s_per_query_median": float(np.median([r["total"] for r in rows])),
            "cpu_s_per_query_mean": float(np.mean([r["total"] for r in rows])),
            "s_per_query_by_stage": {k: float(np.mean([r[k] for r in rows])) for k in STAGES + ("other",)},
            "ms_per_frame_by_stage": {k: 1000 * float(np.mean([r[k] for r in rows])) / frames
                                      for k in STAGES + ("other",)},
        }
    keys = list(out["configs"])
    print(f"\nCPU per {seconds:g} s query by stage (s per query, mean over {len(per[keys[0]])} queries; "
          f"{autonomy}; one core)")
    print(f"{'stage':12s} " + " ".join(f"{k:>20s}" for k in keys))
    for stage in STAGES + ("other",):
        print(f"{stage:12s} " + " ".join(f"{out['configs'][k]['s_per_query_by_stage'][stage]:20.3f}" for k in keys))
    print(f"{'total (med)':12s} " + " ".join(f"{out['configs'][k]['cpu_s_per_query_median']:20.3f}" for k in keys))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", default=str(ROOT / "scenes/highway/highway-benchmark-000000.json.gz"))
    ap.add_argument("--autonomy", default="oracle")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--queries", type=int, default=None,
                    help="queries per throughput run (default 8, 4 with --quick; 100 = the issue's target run)")
    ap.add_argument("--stages", action="store_true", help="only section 3: CPU per query by stage")
    ap.add_argument("--search-only", action="store_true",
                    help="only section 1, every searcher including skopt (bench/results/attack_search.json)")
    ap.add_argument("--scenes", default="000000,000010,000041",
                    help="--stages: benchmark scene numbers (default 000000,000010,000041)")
    ap.add_argument("--out", default=None, help="--stages: result file (default bench/results/attack_stages.json)")
    args = ap.parse_args()
    if args.stages:
        scenes = [str(ROOT / "scenes" / "highway" / f"highway-benchmark-{n}.json.gz") for n in args.scenes.split(",")]
        t0 = time.time()
        stages = query_stages(scenes, args.autonomy, args.queries or 8, args.seconds)
        doc = {"format": "adv3d.bench", "topic": "attack_stages",
               "command": " ".join([Path(sys.executable).name] + sys.argv),
               "machine": machine_info("numpy", "torch", "embreex"), "wall_s": time.time() - t0,
               "timing": "time.process_time of one process pinned to one core, one thread per library",
               "autonomy": args.autonomy, **stages}
        out = Path(args.out) if args.out else ROOT / "bench" / "results" / "attack_stages.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"\nwrote {out}")
        return
    seeds = 2 if args.quick else 5
    nq = args.queries or (4 if args.quick else 8)
    t0 = time.time()
    algos = ("bo", "random", "grid", "blendsearch", "bruteforce") + (("skopt",) if args.search_only else ())
    conv = synthetic_convergence(seeds, algos=algos)
    print(f"\nSearch on synthetic:peak (5-D, optimum 2.0), budget 100, mean over {seeds} seeds")
    print(f"{'algorithm':12s} " + " ".join(f"{'@' + str(k):>8s}" for k in CHECKPOINTS) + f" {'ms/query':>9s} {'CPU ms':>7s}")
    for algo, r in conv.items():
        print(f"{algo:12s} " + " ".join(f"{r['best_at'].get(str(k), float('nan')):8.3f}" for k in CHECKPOINTS)
              + f" {r['searcher_ms_per_query']:9.1f} {r['searcher_cpu_ms_per_query']:7.1f}")
    if args.search_only:
        doc = {"format": "adv3d.bench", "topic": "attack_search", "command": " ".join([Path(sys.executable).name] + sys.argv),
               "machine": machine_info("numpy", "scipy", "flaml", "scikit-optimize", "scikit-learn"), "wall_s": time.time() - t0,
               "timing": "searcher_ms_per_query: perf_counter (wall); searcher_cpu_ms_per_query: time.process_time",
               "synthetic_convergence": conv}
        out = ROOT / "bench" / "results" / ("attack_search.quick.json" if args.quick else "attack_search.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"\nwrote {out}")
        return
    thr = []
    for w in (1, 2):
        thr.append(throughput(args.scene, args.autonomy, nq, w, args.seconds))
    print(f"\nClosed-loop BO attack throughput, {Path(args.scene).name}, {args.seconds:g} s episodes, "
          f"autonomy {args.autonomy}, {nq} queries")
    print(f"{'workers':>7s} {'q/min steady':>12s} {'q/min e2e':>10s} {'s/query':>8s} {'100 q (min)':>11s}")
    for r in thr:
        print(f"{r['workers']:7d} {r['queries_per_min_steady']:12.2f} {r['queries_per_min_end_to_end']:10.2f} "
              f"{r['query_wall_s_mean']:8.2f} {r['extrapolated_100_queries_min']:11.1f}")
    doc = {"format": "adv3d.bench", "topic": "attack", "command": " ".join([Path(sys.executable).name] + sys.argv),
           "machine": machine_info("numpy", "torch", "flaml"),
           "wall_s": time.time() - t0, "synthetic_convergence": conv,
           "throughput": {"scene": Path(args.scene).name, "autonomy": args.autonomy, "seconds": args.seconds,
                          "runs": thr}}
    out = ROOT / "bench" / "results" / ("attack.quick.json" if args.quick else "attack.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
