"""What the detector's ways of running its network cost per query, and whether they change
results: Autonomy-A closed-loop queries with each variant, side by side in one process.

    .venv/bin/python bench/detector_variants.py [--queries 3] [--scenes 000000,000010,000041] [--out FILE]

Variants: ``flat`` (``flat_forward``: plain NCHW tensors, as before the blocked layout),
``shipped`` (what ``load_detector`` gives: ``blocked_forward`` where it gives the same bits) and
``bfloat16`` (the precision option, other results). One process pinned to one core, one thread
per library (as ``bench/attack.py --stages``). Per scene, one workspace per variant
(``SceneWorkspace``, static-hit cache on, so none reuses another's LiDAR cache) evaluates the
same ``--queries`` + 1 seeded shapes (5 s, closed loop), the variants in turns, so they share the
machine's load; the first query of each is not counted. Records per variant the median CPU
seconds per query (``time.process_time``), the detector's CPU per query and its network's per
frame (``time.thread_time``), and per query whether each variant's result (objective, metrics)
equals ``flat``'s. Writes JSON to ``--out`` (default: print only).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import machine_info  # noqa: E402

VARIANTS = ("flat", "shipped", "bfloat16")


def main() -> int:
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import SceneWorkspace

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=3)
    ap.add_argument("--scenes", default="000000,000010,000041")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    load = list(os.getloadavg())
    rows = {p: [] for p in VARIANTS}
    same: dict[str, list[bool]] = {p: [] for p in VARIANTS[1:]}
    for sc in args.scenes.split(","):
        scene = str(ROOT / "scenes" / "highway" / f"highway-benchmark-{sc}.json.gz")
        spaces = {}
        for p in VARIANTS:
            ws = SceneWorkspace(scene, QuerySettings(autonomy="A", seconds=5.0, incremental=True))
            det = ws.stack.detector
            det.blocked = p != "flat"
            det.precision = "bfloat16" if p == "bfloat16" else "float32"
            det.clock = staticmethod(time.thread_time)
            spent = {"detector": 0.0, "network": 0.0, "frames": 0}
            detect = det.detect

            def timed(points, *a, _detect=detect, _det=det, _spent=spent, **k):
                t0 = time.process_time()
                try:
                    return _detect(points, *a, **k)
                finally:
                    _spent["detector"] += time.process_time() - t0
                    _spent["network"] += _det.timings.get("network", 0.0)
                    _spent["frames"] += 1

            det.detect = timed
            spaces[p] = (ws, spent)
        units = np.random.default_rng(0).random((args.queries + 1, 5))
        for q, u in enumerate(units):
            got = {}
            for p, (ws, spent) in spaces.items():
                spent.update(detector=0.0, network=0.0, frames=0)
                t0 = time.process_time()
                res, _ = ws.evaluate(u, True)
                total = time.process_time() - t0
                got[p] = json.dumps([res.cost, res.metrics], sort_keys=True, default=str)
                if q:
                    rows[p].append({"scene": sc, "cpu_s": total, "detector_s": spent["detector"],
                                    "network_ms_per_frame": 1000 * spent["network"] / max(spent["frames"], 1)})
            if q:
                for p in same:
                    same[p].append(got[p] == got["flat"])
        print(f"  {sc}: done", flush=True)
    out = {p: {"queries": len(r), "cpu_s_per_query_median": float(np.median([x["cpu_s"] for x in r])),
               "detector_s_per_query_mean": float(np.mean([x["detector_s"] for x in r])),
               "network_ms_per_frame_median": float(np.median([x["network_ms_per_frame"] for x in r])),
               "per_query": r} for p, r in rows.items()}
    doc = {"format": "adv3d.bench", "topic": "detector_variants",
           "command": " ".join([Path(sys.executable).name, "bench/detector_variants.py"] + sys.argv[1:]),
           "machine": machine_info("numpy", "torch"), "load_average_at_start": load,
           "load_average_at_end": list(os.getloadavg()),
           "timing": "time.process_time per query, one process pinned to one core, one thread per library",
           "variants": out, "results_equal_to_flat_per_query": same}
    for p in VARIANTS:
        o = out[p]
        print(f"{p:9s} median {o['cpu_s_per_query_median']:.3f} CPU-s/query, detector {o['detector_s_per_query_mean']:.3f} "
              f"s/query, network {o['network_ms_per_frame_median']:.2f} ms/frame")
    for p, eq in same.items():
        print(f"{p}: results equal to flat's in {sum(eq)} of {len(eq)} queries")
    print(f"load {load[0]:.1f}")
    if args.out:
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
