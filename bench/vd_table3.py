"""The paper's Table 3 on our benchmark: the latent attack against the vertex-deformation (VD)
baseline at l-infinity bounds 0.1, 0.2, 0.5 and 1.0 m, same searcher, same budget; attack
strength and JSD side by side (paper Table 3, docs/realism.md).

    .venv/bin/python bench/vd_table3.py --scenes 10 --budget 100 --seconds 5 --workers 2   # the campaign
    .venv/bin/python bench/vd_table3.py --smoke                                           # 1 scene, budget 4, 3 s

Runs ``adv3d attack`` (``run_attack``) once per row into ``--work`` (resumable: a killed
campaign continues where it stopped), then writes the combined ``adv3d report`` of all rows
(``--work``/report.md: Table 1 with the JSD column is the paper's Table 3) and a JSON table
(``--out``, default bench/results/vd_table3.json; ``--smoke``: vd_table3_smoke.json) with, per
row and over scenes, the closed-loop AP, recall, minADE, driving jerk, the objective gain over
the original scene and the best shapes' JSD. The paper's own rows are from one scenario
(main Table 3) and a 100-triangle template (supplementary Table 8); see docs/realism.md.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def rows_of(summary: dict) -> dict[str, list]:
    """Per scene: original and best closed-loop figures."""
    out: dict[str, list] = {"original": [], "best": []}
    for sid, entry in sorted(summary.get("scenes", {}).items()):
        m = (entry.get("modes") or {}).get("closed") or {}
        ev = m.get("closed_loop_eval")
        if not ev or "original" not in entry:
            continue
        out["original"].append((sid, entry["original"]))
        out["best"].append((sid, ev))
    return out


def _figures(ev: dict) -> dict:
    met = ev["metrics"]
    return {"objective": ev["cost"], "ap": 100 * met["detection"]["ap"], "recall": 100 * met["detection"]["recall"],
            "min_ade": met["prediction"]["min_ade"], "drive_jerk": met["driving_comfort"]["jerk"],
            "plan_jerk": met["planning_comfort"]["jerk"]}


def _mean(values: list[float]) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


def _add_cpu(work: Path, seconds: float) -> float:
    """CPU seconds of this process added to the total of every run of this work folder (a
    resumed campaign keeps counting; ``work``/cpu_s.json)."""
    path = work / "cpu_s.json"
    total = (json.loads(path.read_text())["cpu_s"] if path.exists() else 0.0) + seconds
    work.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"cpu_s": round(total, 1)}) + "\n")
    return round(total, 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=10, help="the first N benchmark scenes (default 10)")
    parser.add_argument("--scene", action="append", default=None, help="explicit scene files (repeatable)")
    parser.add_argument("--budget", type=int, default=100)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--algo", default="bo", choices=("bo", "random", "blendsearch"))
    parser.add_argument("--n-initial", type=int, default=11)
    parser.add_argument("--autonomy", default="A")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bounds", default="0.1,0.2,0.5,1.0", help="VD l-infinity bounds in m")
    parser.add_argument("--pred-reduction", default="sum", choices=("sum", "mean"),
                        help="the objective's prediction term over the waypoints: sum (Eq. 5, the default) or "
                             "mean (the form before issue 18, which the kept sweep of 2026-11-23 used)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--work", default=None, help="run folders (default runs/vd_table3[_smoke])")
    parser.add_argument("--out", default=None, help="JSON (default bench/results/vd_table3[_smoke].json)")
    parser.add_argument("--smoke", action="store_true", help="1 scene, budget 4 (BO: 2 initial), 3 s episodes")
    args = parser.parse_args()
    if args.smoke:
        args.scenes, args.budget, args.seconds, args.n_initial = 1, 4, 3.0, 2
    suffix = "_smoke" if args.smoke else ""
    work = Path(args.work or REPO / "runs" / f"vd_table3{suffix}")
    out = Path(args.out or REPO / "bench" / "results" / f"vd_table3{suffix}.json")

    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.driver import run_attack
    from adv3d_runner.attack.report import write_report

    scenes = args.scene or [f"scenes/highway/highway-benchmark-{i:06d}.json.gz" for i in range(args.scenes)]
    bounds = [float(b) for b in args.bounds.split(",")]
    rows = {f"VD {b:g} m": {"shape_model": "vd", "vd_bound": b} for b in bounds}
    rows["Adv3D (latent)"] = {}
    t_cpu, t_wall = time.process_time(), time.perf_counter()
    table: dict[str, dict] = {}
    folders = []
    for name, knobs in rows.items():
        folder = work / name.split(" (")[0].replace(" ", "_").replace(".", "p")
        cfg = AttackConfig(scenes, algo=args.algo, budget=args.budget, seconds=args.seconds, seed=args.seed,
                           pred_reduction=args.pred_reduction,
                           autonomy=args.autonomy, n_initial=args.n_initial, batch=args.workers, **knobs)
        print(f"[{name}] attack -> {folder}", flush=True)
        summary = run_attack(cfg, folder, workers=args.workers, show_progress=False)
        folders.append(folder)
        per = rows_of(summary)
        if "Original" not in table and per["original"]:
            figs = [_figures(o) for _, o in per["original"]]
            table["Original"] = {k: _mean([f[k] for f in figs]) for k in figs[0]} | {"jsd": None}
        figs = [_figures(ev) for _, ev in per["best"]]
        gains = [ev["cost"] - o["cost"] for (_, ev), (_, o) in zip(per["best"], per["original"])]
        jsd = [max(r["jsd"] for r in ev["realism"]) for _, ev in per["best"]]
        best = {sid: [{k: r.get(k) for k in ("jsd", "nearest_asset", "nearest_chamfer_m", "dimensions_m",
                                               "dimension_class", "flags", "max_displacement_m", "mahalanobis")}
                      for r in ev["realism"]] for sid, ev in per["best"]}
        table[name] = {k: _mean([f[k] for f in figs]) for k in figs[0]} | {
            "best_shapes": best,
            "objective_gain": _mean(gains), "jsd": _mean(jsd), "jsd_max": float(np.max(jsd)) if jsd else None,
            "scenes": len(figs), "queries": int(sum(m["n_queries"] for e in summary["scenes"].values()
                                                    for m in (e.get("modes") or {}).values()))}
    report = write_report(folders, work / "report.md")
    result = {
        "smoke": bool(args.smoke),
        "note": ("SMOKE RUN: 1 scene, budget 4, 3 s episodes; proves the pipeline, not a result" if args.smoke
                 else "campaign"),
        "command": "python bench/vd_table3.py " + " ".join(sys.argv[1:]),
        "scenes": len(scenes), "budget": args.budget, "seconds": args.seconds, "algo": args.algo,
        "pred_reduction": args.pred_reduction,
        "autonomy": args.autonomy, "seed": args.seed, "rows": table, "report": str(report),
        "cpu_s_this_process": round(time.process_time() - t_cpu, 1), "wall_s": round(time.perf_counter() - t_wall, 1),
        "cpu_s_total": _add_cpu(work, time.process_time() - t_cpu),
        "machine": {"platform": platform.platform(), "note": "2-core machine shared with other jobs"},
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'':16s} {'AP':>6s} {'Recall':>6s} {'minADE':>7s} {'Jerk':>6s} {'gain':>7s} {'JSD':>6s}")
    for name, r in table.items():
        jsd = "-" if r.get("jsd") is None else f"{r['jsd']:.3f}"
        gain = "-" if "objective_gain" not in r else f"{r['objective_gain']:+.2f}"
        print(f"{name:16s} {r['ap']:6.1f} {r['recall']:6.1f} {r['min_ade']:7.3f} {r['drive_jerk']:6.3f} {gain:>7s} {jsd:>6s}")
    print(f"wrote {out} and {report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
