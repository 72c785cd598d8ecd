"""Attack benchmark: searcher overhead and convergence, and query throughput on a real scene.

    .venv/bin/python bench/attack.py [--quick] [--scene FILE] [--autonomy oracle|A] [--queries N]

1. Convergence on the synthetic 5-D objective (``synthetic:peak``: a bowl with a narrow peak of
   height 2 at a fixed point; ``tests/attack_synthetic.py``, the tests' analytic stand-in for the
   episode evaluator), every algorithm at budget 100 over several seeds: best value after
   10/25/50/100 queries and the searcher's own time per query (ask + tell, no simulation).
2. Throughput on a bundled scene: a closed-loop 5 s BO attack with 1 and 2 local workers;
   queries per minute (steady state from the journal's per-query wall times, and end to end
   including worker start-up and the LiDAR world build) and the extrapolated time of a
   100-query attack.

Writes ``bench/results/attack.json`` (``attack.quick.json`` with --quick).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.config import AttackConfig  # noqa: E402
from adv3d_runner.attack.driver import run_attack  # noqa: E402
from adv3d_runner.attack.search import make_searcher  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402
from tests.attack_synthetic import peak  # noqa: E402  (the synthetic objective lives with the tests)

CHECKPOINTS = (10, 25, 50, 100)


def synthetic_convergence(seeds: int, budget: int = 100) -> dict:
    f = peak
    out = {}
    for algo in ("bo", "random", "grid", "blendsearch", "bruteforce"):
        curves, overhead = [], []
        for seed in range(seeds):
            cands = np.random.default_rng(seed).random((budget, 5)) if algo == "bruteforce" else None
            s = make_searcher(algo, 5, seed=seed, budget=budget, candidates=cands)
            best, vals, t = -np.inf, [], 0.0
            while not s.exhausted:
                t0 = time.perf_counter()
                X = s.ask(1)
                t += time.perf_counter() - t0
                y = [f(x) for x in X]
                t0 = time.perf_counter()
                s.tell(X, y)
                t += time.perf_counter() - t0
                best = max(best, *y)
                vals.append(best)
            curves.append(vals)
            overhead.append(t / max(len(vals), 1))
        n = min(len(c) for c in curves)
        C = np.array([c[:n] for c in curves])
        out[algo] = {"best_at": {str(k): float(C[:, k - 1].mean()) for k in CHECKPOINTS if k <= n},
                     "best_std_at_end": float(C[:, -1].std()), "queries": n,
                     "searcher_ms_per_query": 1000 * float(np.mean(overhead)), "seeds": seeds,
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", default=str(ROOT / "scenes/highway/highway-benchmark-000000.json.gz"))
    ap.add_argument("--autonomy", default="oracle")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--queries", type=int, default=None,
                    help="queries per throughput run (default 8, 4 with --quick; 100 = the issue's target run)")
    args = ap.parse_args()
    seeds = 2 if args.quick else 5
    nq = args.queries or (4 if args.quick else 8)
    t0 = time.time()
    conv = synthetic_convergence(seeds)
    print(f"\nSearch on synthetic:peak (5-D, optimum 2.0), budget 100, mean over {seeds} seeds")
    print(f"{'algorithm':12s} " + " ".join(f"{'@' + str(k):>8s}" for k in CHECKPOINTS) + f" {'ms/query':>9s}")
    for algo, r in conv.items():
        print(f"{algo:12s} " + " ".join(f"{r['best_at'].get(str(k), float('nan')):8.3f}" for k in CHECKPOINTS)
              + f" {r['searcher_ms_per_query']:9.1f}")
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
