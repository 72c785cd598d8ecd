"""The fresh real benchmark part over LiDAR-noise seeds, next to the generated benchmark and the
paper's row (docs/benchmark.md).

Reads the per-seed files of ``bench/sanity.py --sets real --real-part fresh --seed S --name
sanity.real-fresh.<STACK>.seedS`` and prints, per stack, every seed's summary, the mean and the
spread (min-max over seeds) of each column, the targets of docs/benchmark.md per seed, and the
generated benchmark's row (``--generated FILE``, a ``bench/sanity.py --sets generated`` result)
and the paper's "Original" row.

    .venv/bin/python bench/fresh_table.py [--stacks A,B] [--seeds 0-4] [--generated bench/results/sanity.json]
        [--out bench/results/sanity.real-fresh.table.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
#: docs/benchmark.md, "Rule of the looks"
FRESH_TARGETS = {"at_fault_collisions_max": 0, "drive_jerk_max": 1.0, "progress_ratio_min": 0.8, "min_ade_max": 1.8}
COLUMNS = ("ok_rate", "collisions", "at_fault_collisions", "ap", "recall", "min_ade", "min_ade_recorded", "mean_ade",
           "occ_map", "occ_soft_iou", "fg_map", "fg_soft_iou", "epe", "plan_lat", "plan_jerk", "drive_lat", "drive_jerk", "drive_peak_jerk_max",
           "progress_ratio_mean", "progress_ratio_min")


def seeds_of(text: str) -> list[int]:
    """``0-4`` or ``0,1,2`` -> [0, 1, 2, ...]."""
    if "-" in text:
        a, b = text.split("-", 1)
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def targets(s: dict, rows: list[dict]) -> dict:
    """docs/benchmark.md's targets on one seed's real summary."""
    t = FRESH_TARGETS
    below = sorted((r["scene"], round(r["ego"]["progress_ratio"], 3)) for r in rows
                   if r["ego"]["progress_ratio"] is not None and r["ego"]["progress_ratio"] < t["progress_ratio_min"])
    out = {"at_fault_collisions": s["at_fault_collisions"] <= t["at_fault_collisions_max"],
           "drive_jerk": s["drive_jerk"] is not None and s["drive_jerk"] <= t["drive_jerk_max"],
           "progress": not below, "progress_below": below}
    if s.get("min_ade") is not None:
        out["min_ade"] = s["min_ade"] <= t["min_ade_max"]
        out["min_ade_recorded"] = s.get("min_ade_recorded") is not None and s["min_ade_recorded"] <= t["min_ade_max"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stacks", default="A,B")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--generated", default=str(RESULTS / "sanity.json"))
    ap.add_argument("--out", default=str(RESULTS / "sanity.real-fresh.table.json"))
    args = ap.parse_args()
    doc = {"format": "adv3d-bench", "version": 1, "topic": "sanity-fresh-table",
           "command": " ".join(["bench/fresh_table.py"] + sys.argv[1:]), "targets": FRESH_TARGETS, "stacks": {}}
    f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    for stack in [s for s in args.stacks.split(",") if s]:
        per_seed = {}
        for seed in seeds_of(args.seeds):
            path = RESULTS / f"sanity.real-fresh.{stack}.seed{seed}.json"
            if not path.is_file():
                print(f"{stack}: no {path.name}, left out")
                continue
            d = json.loads(path.read_text())
            s, rows = d["real"]["summary"], d["real"]["rows"]
            per_seed[seed] = {"file": path.name, "machine": d["machine"].get("processor") or d["machine"]["platform"],
                              "stack": d.get("stack"), "summary": {c: s.get(c) for c in COLUMNS},
                              "scenes": s["scenes"], "targets": targets(s, rows)}
        if not per_seed:
            continue
        agg = {}
        for c in COLUMNS:
            vals = [p["summary"][c] for p in per_seed.values() if p["summary"][c] is not None]
            if vals:
                agg[c] = {"mean": float(np.mean(vals)), "min": float(np.min(vals)), "max": float(np.max(vals))}
        doc["stacks"][stack] = {"seeds": per_seed, "over_seeds": agg}
        print(f"\nAutonomy-{stack}, fresh part, seeds {sorted(per_seed)}")
        print("| seed | scenes | ok | collisions (at fault) | AP / occ. mAP | minADE (rec.) | drive jerk | peak jerk max | "
              "progress mean (min) | targets failed |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for seed, p in per_seed.items():
            s, t = p["summary"], p["targets"]
            failed = [k for k, v in t.items() if v is False]
            print(f"| {seed} | {p['scenes']} | {100 * s['ok_rate']:.0f}% | {s['collisions']} ({s['at_fault_collisions']}) | "
                  f"{f(s['ap'] if s['ap'] is not None else s['occ_map'])} | {f(s['min_ade'], 2)} ({f(s['min_ade_recorded'], 2)}) | "
                  f"{f(s['drive_jerk'])} | {f(s['drive_peak_jerk_max'], 2)} | {f(s['progress_ratio_mean'], 2)} "
                  f"({f(s['progress_ratio_min'], 2)}) | {', '.join(failed) or '-'} |")
    gen = Path(args.generated)
    if gen.is_file():
        g = json.loads(gen.read_text())
        doc["generated"] = {"file": str(gen.relative_to(ROOT)) if gen.is_relative_to(ROOT) else str(gen),
                            "summary": {c: g["summary"].get(c) for c in COLUMNS}}
        doc["paper_original_autonomy_a"] = g.get("paper_original_autonomy_a")
        doc["paper_original_autonomy_b"] = g.get("paper_original_autonomy_b")
    out = Path(args.out)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
