"""Campaign benchmark: wall time of the paper's Table 1 protocol on N scenes, extrapolated to 100.

    .venv/bin/python bench/campaign.py [--scenes 3] [--budget 4] [--workers 1,2]
                                       [--ray-address ADDR --ray-workers 1,2] [--seconds 5]

The Table 1 protocol on one scene is ``adv3d attack SCENE --mode both --budget 100 --seconds 5
--autonomy A``: an open-loop and a closed-loop attack (2 x budget episodes), then three
closed-loop episodes (the original scene, the best open-loop shape, the best closed-loop shape).
Here the first N benchmark scenes are attacked with a small budget B, once per worker count
(local processes, and Ray workers on an existing cluster with ``--ray-address``), and the run's
wall time T is measured end to end (worker start-up, scene builds, every query, every
best-shape episode, the files).

Extrapolation. With E = N (2 B + 3) episodes in the run and T0 the time to the first result
(start-up), the wall time per episode at that worker count is (T - T0) / E, so

    T(100 scenes, budget 100) = T0 + 100 x (2 x 100 + 3) x (T - T0) / E.

It assumes the benchmark scenes cost about what the measured ones do (10-36 actors), that an
episode of a late query costs what an early one does (BO's own time grows with the queries
told: ~35 ms per query averaged over 100, ``bench/attack.py``), and that the workers stay busy
(the driver runs the scenes concurrently; with W workers and N >= W scenes every worker has a
scene). Runs with different worker counts must give the same journal (checked here).

The same with CPU time (local runs: this process and its worker processes): core-hours of the
protocol = 100 x (2 x 100 + 3) x C / E for C CPU seconds of the run; on W otherwise idle cores
the wall time is about core-hours / W (the driver's own work is small).

Writes ``bench/results/campaign.json`` (``--out``). The machine is shared: wall times include other jobs'
load (the load average is recorded), which the CPU-time extrapolation does not.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # as the adv3d command
    os.environ.setdefault(_k, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.config import AttackConfig  # noqa: E402
from adv3d_runner.attack.driver import run_attack  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402

PROTOCOL_SCENES, PROTOCOL_BUDGET = 100, 100


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the local workers)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run_once(scenes: list[str], budget: int, seconds: float, autonomy: str, workers: int | None,
             ray_address: str | None, keep: Path) -> dict:
    cfg = AttackConfig(scenes, algo="bo", budget=budget, mode="both", seconds=seconds, autonomy=autonomy,
                       n_initial=min(11, max(2, budget // 2)))
    tag = f"ray{workers}" if ray_address else f"local{workers}"
    out = keep / tag
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()
    c0, t0 = _cpu_s(), time.perf_counter()
    first = []

    def watch() -> None:  # time to the first journal line (start-up)
        path = out / "queries.jsonl"
        while not first:
            if path.exists() and path.stat().st_size > 0:
                first.append(time.perf_counter() - t0)
                return
            time.sleep(0.05)

    import threading

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    run_attack(cfg, out, workers=workers, ray_address=ray_address, show_progress=False)
    wall = time.perf_counter() - t0
    cpu = _cpu_s() - c0
    first.append(wall)
    lines = (out / "queries.jsonl").read_text().splitlines()
    n_scenes = len(scenes)
    episodes = n_scenes * (2 * budget + 3)
    t_first = first[0]
    per_episode = (wall - t_first) / episodes
    extrapolated = t_first + PROTOCOL_SCENES * (2 * PROTOCOL_BUDGET + 3) * per_episode
    return {"executor": "ray" if ray_address else "local", "workers": workers, "scenes": n_scenes, "budget": budget,
            "queries": len(lines), "episodes": episodes, "wall_s": wall, "first_result_s": t_first,
            "wall_s_per_episode": per_episode,
            "cpu_s": None if ray_address else cpu, "cpu_s_per_episode": None if ray_address else cpu / episodes,
            "load_average_before": list(load0), "load_average_after": list(os.getloadavg()),
            "extrapolated_100_scenes_h": extrapolated / 3600,
            "extrapolated_100_scenes_core_h": None if ray_address else
            PROTOCOL_SCENES * (2 * PROTOCOL_BUDGET + 3) * cpu / episodes / 3600,
            "journal": [line[:line.rindex(',"wall_s"')] for line in lines]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3, help="the first N benchmark scenes (default 3)")
    ap.add_argument("--budget", type=int, default=4, help="queries per scene and mode (default 4)")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--autonomy", default="A")
    ap.add_argument("--workers", default="1,2", help="local worker counts (default 1,2; empty: none)")
    ap.add_argument("--ray-address", default=None, help="an existing Ray cluster (ray start --head ...)")
    ap.add_argument("--ray-workers", default="1,2", help="Ray worker counts (default 1,2)")
    ap.add_argument("--keep", default=None, help="keep the run folders here (default: a temporary folder)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "campaign.json"),
                    help="result file (default bench/results/campaign.json)")
    args = ap.parse_args()
    scenes = [str(p) for p in sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json.gz"))[:args.scenes]]
    keep = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="adv3d-campaign-"))
    plan = [(int(w), None) for w in args.workers.split(",") if w]
    if args.ray_address:
        plan += [(int(w), args.ray_address) for w in args.ray_workers.split(",") if w]
    rows = []
    t0 = time.time()
    try:
        for workers, address in plan:
            row = run_once(scenes, args.budget, args.seconds, args.autonomy, workers, address, keep)
            rows.append(row)
            print(f"{row['executor']:5s} workers {workers}: {row['queries']} queries + {3 * row['scenes']} best-shape "
                  f"episodes in {row['wall_s']:.1f} s wall (first result after {row['first_result_s']:.1f} s), "
                  f"{row['wall_s_per_episode']:.2f} s/episode -> 100 scenes: {row['extrapolated_100_scenes_h']:.2f} h",
                  flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(keep, ignore_errors=True)
    same = all(r["journal"] == rows[0]["journal"] for r in rows)
    base = next((r for r in rows if r["executor"] == "local" and r["workers"] == 1), rows[0])
    print(f"\nTable 1 protocol (mode both, BO), {len(scenes)} scenes x budget {args.budget}, {args.seconds:g} s "
          f"episodes, autonomy {args.autonomy}; journals identical across runs: {same}")
    print(f"{'executor':8s} {'workers':>7s} {'wall s':>8s} {'s/episode':>9s} {'speed-up':>8s} {'100 scenes h':>12s} "
          f"{'CPU s/episode':>13s} {'core-h':>7s}")
    for r in rows:
        cpu = "" if r["cpu_s_per_episode"] is None else f"{r['cpu_s_per_episode']:13.2f} " \
                                                       f"{r['extrapolated_100_scenes_core_h']:7.1f}"
        print(f"{r['executor']:8s} {r['workers']:7d} {r['wall_s']:8.1f} {r['wall_s_per_episode']:9.2f} "
              f"{base['wall_s_per_episode'] / r['wall_s_per_episode']:8.2f} {r['extrapolated_100_scenes_h']:12.2f} {cpu}")
    for r in rows:
        r.pop("journal")
    doc = {"format": "adv3d.bench", "topic": "campaign", "command": " ".join([Path(sys.executable).name] + sys.argv),
           "machine": machine_info("numpy", "torch", "embreex", "ray"), "wall_s": time.time() - t0,
           "scenes": [Path(s).name for s in scenes], "protocol": "adv3d attack SCENES --algo bo --mode both",
           "formula": "T(100) = T0 + 100 * (2 * 100 + 3) * (T - T0) / (N * (2 * B + 3))",
           "journals_identical": same, "runs": rows}
    out = Path(args.out)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
