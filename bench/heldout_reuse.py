"""Cost of the experiment protocol's held-out evaluations for the settings of one table on one
scene and run seed, as a campaign makes them (``protocol.run_heldout``, one run folder per
setting, one call after another in one process).

    .venv/bin/python bench/heldout_reuse.py [--root CHECKOUT] [--table 5] [--workers 1] [--out FILE]

Each setting evaluates the original scene and its best shape (a seeded random unit vector per
setting: the search is not run) in closed loop on the scene's 3 held-out seeds
(``protocol.evaluation_seeds``). ``--table 5`` has 6 settings that differ only in the search
algorithm, ``--table 3`` a latent setting and 5 vertex-deformation bounds. Reports the
simulations made and the CPU seconds of this process and its workers (``getrusage``, after the
workers exit), and checks
that every stored record equals the one of ``--compare`` (a result file of another checkout, on
the fields both write) when given. Runs the code of ``--root`` (default this checkout), so the same script measures
an older commit.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
ap.add_argument("--table", type=int, choices=(3, 5), default=5)
ap.add_argument("--workers", type=int, default=1)
ap.add_argument("--autonomy", default="A")
ap.add_argument("--seconds", type=float, default=5.0)
ap.add_argument("--scene", default="highway-benchmark-000000")
ap.add_argument("--compare", type=Path, default=None, help="result file whose records must be equal")
ap.add_argument("--out", type=Path, default=None)
args = ap.parse_args()
ROOT = args.root.resolve()
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from adv3d_runner.attack.config import QuerySettings  # noqa: E402
from adv3d_runner.attack.evaluator import EpisodeEvaluator  # noqa: E402
from adv3d_runner.attack.protocol import HeldoutStore, HeldoutTask, evaluation_seeds, run_heldout  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402


def cpu() -> float:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def main() -> int:
    scene = str(ROOT / "scenes" / "highway" / f"{args.scene}.json.gz")
    base = QuerySettings(autonomy=args.autonomy, seconds=args.seconds, seed=0, scene_seeds=True)
    if args.table == 5:
        settings = {name: base for name in ("bo", "grid", "random", "blendsearch", "bruteforce", "skopt")}
    else:
        settings = {"latent": base, **{f"vd{b:g}": QuerySettings(**{**base.__dict__, "shape_model": "vd", "vd_bound": b})
                                       for b in (0.05, 0.1, 0.2, 0.5, 1.0)}}
    digest = EpisodeEvaluator(base).scene_digest(scene)
    seeds = evaluation_seeds(0, digest, 3)
    from adv3d_runner.attack.shape_models import dim_per_actor

    t0, c0 = time.perf_counter(), cpu()
    made, records = {}, {}
    with tempfile.TemporaryDirectory(prefix="adv3d-heldout-") as tmp:
        for k, (name, s) in enumerate(settings.items()):
            dim = dim_per_actor(s, s.load_shape_space())
            unit = tuple(np.random.default_rng(k).random(dim).tolist())
            tasks = [HeldoutTask(scene, args.scene, what, u, seed) for what, u in (("original", None), ("closed", unit))
                     for seed in seeds]
            store = HeldoutStore(Path(tmp) / f"{name}.json.gz")
            made[name] = run_heldout(tasks, s, store, workers=args.workers)
            records[name] = store.evaluations
            print(f"{name:12s} {made[name]} simulations", flush=True)
    from adv3d_runner.attack import protocol

    for pool in getattr(protocol, "_POOLS", {}).values():  # kept workers: reaped, so their CPU time counts
        pool.shutdown(wait=True)
    doc = {"format": "adv3d.bench", "topic": "heldout_reuse",
           "command": " ".join([Path(sys.executable).name, "bench/heldout_reuse.py"] + sys.argv[1:]),
           "code": str(ROOT), "machine": machine_info("numpy", "torch"), "load_average": list(os.getloadavg()),
           "table": args.table, "workers": args.workers, "autonomy": args.autonomy, "seconds": args.seconds,
           "scene": args.scene, "eval_seeds": seeds, "simulations": made, "simulations_total": sum(made.values()),
           "cpu_s": cpu() - c0, "wall_s": time.perf_counter() - t0,
           "timing": "CPU s of this process and its worker processes (getrusage SELF + CHILDREN)",
           "records": records}
    if args.compare:
        other = json.loads(args.compare.read_text())["records"]
        def same(a: dict, b: dict) -> bool:  # on the fields both versions write (newer code adds metrics)
            if isinstance(a, dict) and isinstance(b, dict):
                return all(same(a[k], b[k]) for k in a.keys() & b.keys() if a[k] is not None and b[k] is not None)
            return a == b

        doc["records_equal_to"] = {"file": str(args.compare), "equal": all(
            records[n].keys() == other[n].keys() and same(records[n], other[n]) for n in records)}
        print("records equal to", args.compare, doc["records_equal_to"]["equal"])
    print(f"total {doc['simulations_total']} simulations, {doc['cpu_s']:.1f} CPU-s, {doc['wall_s']:.0f} s wall")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
