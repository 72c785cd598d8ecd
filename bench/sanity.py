"""Sanity of the closed loop on the bundled benchmark scenes (issue 4, acceptance 5).

Every scene of ``scenes/highway/``: a 5 s closed-loop episode (actors replay their logs), the
full LiDAR simulation (the scene's 64-beam rig, library meshes) and the chosen stack. Reports
the share of scenes where the ego neither collides nor leaves the road, and the Table-1
metrics (AP / recall in the ROI, minADE / meanADE, planning and driving comfort) next to the
paper's "Original" row for Autonomy-A.

    .venv/bin/python bench/sanity.py [--quick] [--autonomy A|B|oracle] [--workers 2] [--seconds 5]

``--autonomy A`` needs the trained detector and predictor (assets/models/); without them use
``--autonomy oracle`` (ground-truth boxes of the actors the LiDAR hits + lane-following
prediction). ``--autonomy B`` (instance-free, the implicit occupancy model) reports the
occupancy metrics instead of AP and ADE (paper Table 1's lower block: occupancy mAP and
Soft-IoU, flow-grounded mAP and Soft-IoU, and the flow EPE) next to Autonomy-A's rows of the
same scenes from ``bench/results/sanity.json``. Writes
``bench/results/sanity[.<autonomy>][.quick].json``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PAPER_ORIGINAL_A = {"ap": 0.882, "recall": 0.894, "min_ade": 2.14, "mean_ade": 4.90, "plan_lat": 0.203,
                    "plan_jerk": 0.336, "drive_lat": 0.194, "drive_jerk": 0.331}
PAPER_ORIGINAL_B = {"map": 0.831, "soft_iou": 0.504, "fg_map": 0.946, "fg_soft_iou": 0.612, "plan_lat": 0.256,
                    "plan_jerk": 0.319, "drive_lat": 0.263, "drive_jerk": 0.315}

_STACK = None
_LIB = None


def _run(job: tuple[str, str, float]) -> dict:
    path, autonomy, seconds = job
    global _STACK, _LIB
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import world_from_scene
    from adv3d_runner.sim.episode import default_library, run_episode
    from adv3d_runner.sim.evaluate import episode_metrics
    from adv3d_runner.autonomy.stacks import make_stack

    if _STACK is None:
        _STACK = make_stack(autonomy)
        _LIB = default_library()
    t0 = time.perf_counter()
    scene = load_scene(path)
    world = world_from_scene(scene, _LIB)
    t1 = time.perf_counter()
    result = run_episode(scene, _STACK, seconds=seconds, world=world)
    m = episode_metrics(result, scene.lanes)
    m["world_build_s"] = t1 - t0
    m["wall_s"] = time.perf_counter() - t0
    m["plans"] = {}  # which candidate kinds were chosen (diagnosis)
    for o in result.outputs:
        lab = o.plan.label.split("/")[0] if o.plan.label else "?"
        m["plans"][lab] = m["plans"].get(lab, 0) + 1
    return m


def _mean(rows, *keys) -> float | None:
    vals = []
    for r in rows:
        v = r
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        if v is not None and np.isfinite(v):
            vals.append(v)
    return float(np.mean(vals)) if vals else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 scenes instead of 100")
    ap.add_argument("--autonomy", choices=("A", "B", "oracle", "A-lanefollow"), default="A")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    paths = sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json*"))
    if args.quick:
        paths = paths[::10]
    from adv3d_runner.autonomy.stacks import make_stack

    make_stack(args.autonomy)  # fail early (e.g. no weights) before starting workers
    jobs = [(str(p), args.autonomy, args.seconds) for p in paths]
    t0 = time.time()
    rows = []
    if args.workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.workers) as pool:
            for m in pool.imap(_run, jobs):
                rows.append(m)
                _line(m, len(rows), len(jobs))
    else:
        for job in jobs:
            rows.append(_run(job))
            _line(rows[-1], len(rows), len(jobs))
    wall = time.time() - t0
    n = len(rows)
    collided = [r["collision"]["collided"] for r in rows]
    at_fault = [r["collision"]["at_fault"] for r in rows]
    off = [r["off_road"] for r in rows]
    summary = {
        "scenes": n, "autonomy": args.autonomy, "seconds": args.seconds,
        "ok_rate": float(np.mean([not c and not o for c, o in zip(collided, off)])),
        "ok_rate_at_fault_only": float(np.mean([not c and not o for c, o in zip(at_fault, off)])),
        "collision_rate": float(np.mean(collided)), "at_fault_collision_rate": float(np.mean(at_fault)),
        "off_road_rate": float(np.mean(off)),
        "ap": _mean(rows, "detection", "ap"), "recall": _mean(rows, "detection", "recall"),
        "min_ade": _mean(rows, "prediction", "min_ade"), "mean_ade": _mean(rows, "prediction", "mean_ade"),
        "plan_lat": _mean(rows, "planning_comfort", "lat"), "plan_jerk": _mean(rows, "planning_comfort", "jerk"),
        "drive_lat": _mean(rows, "driving_comfort", "lat"), "drive_jerk": _mean(rows, "driving_comfort", "jerk"),
        "occ_map": _mean(rows, "occupancy", "map"), "occ_soft_iou": _mean(rows, "occupancy", "soft_iou"),
        "fg_map": _mean(rows, "occupancy", "flow_grounded_map"),
        "fg_soft_iou": _mean(rows, "occupancy", "flow_grounded_soft_iou"), "epe": _mean(rows, "occupancy", "epe"),
        "fps_mean": _mean(rows, "fps"), "wall_s": wall,
        "failures": [{"scene": r["scene"], "collided": r["collision"]["collided"], "at_fault": r["collision"]["at_fault"],
                      "first_frame": r["collision"]["first_frame"], "actors": r["collision"]["actors"],
                      "off_road_m": r["off_road_m"]} for r in rows if r["collision"]["collided"] or r["off_road"]],
    }
    s = summary
    f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    print(f"\n{n} scenes, {args.seconds:g} s closed loop, autonomy {args.autonomy}: "
          f"ok (no collision, on road) {100 * s['ok_rate']:.0f}% | collisions {100 * s['collision_rate']:.0f}% "
          f"(ego at fault {100 * s['at_fault_collision_rate']:.0f}%) | off road {100 * s['off_road_rate']:.0f}% | "
          f"{wall:.0f} s wall with {args.workers} workers")
    reference = None
    if args.autonomy == "B":
        reference = _reference_a([r["scene"] for r in rows])
        summary["autonomy_a_same_scenes"] = reference
        _print_b(s, reference, args)
    else:
        print("\n| | AP | recall | minADE | meanADE | plan lat | plan jerk | drive lat | drive jerk |")
        print("|---|---|---|---|---|---|---|---|---|")
        print(f"| this run ({args.autonomy}) | {f(s['ap'])} | {f(s['recall'])} | {f(s['min_ade'], 2)} | {f(s['mean_ade'], 2)} | "
              f"{f(s['plan_lat'])} | {f(s['plan_jerk'])} | {f(s['drive_lat'])} | {f(s['drive_jerk'])} |")
        p = PAPER_ORIGINAL_A
        print(f"| paper Table 1, Autonomy-A, Original | {p['ap']:.3f} | {p['recall']:.3f} | {p['min_ade']:.2f} | "
              f"{p['mean_ade']:.2f} | {p['plan_lat']:.3f} | {p['plan_jerk']:.3f} | {p['drive_lat']:.3f} | {p['drive_jerk']:.3f} |")
    for fail in s["failures"]:
        print("failure:", fail)
    from adv3d_runner.fileio import write_json

    name = "sanity" + ("" if args.autonomy == "A" else f".{args.autonomy}") + (".quick" if args.quick else "")
    out = ROOT / "bench" / "results" / f"{name}.json"
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "sanity",
                     "command": " ".join(["bench/sanity.py"] + sys.argv[1:]),
                     "machine": {"python": platform.python_version(), "platform": platform.platform(),
                                 "processor": platform.processor(), "cpus": os.cpu_count()},
                     "paper_original_autonomy_a": PAPER_ORIGINAL_A, "paper_original_autonomy_b": PAPER_ORIGINAL_B,
                     "summary": summary,
                     "rows": [{k: v for k, v in r.items() if k not in ("format", "version")} for r in rows]})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


def _reference_a(scenes: list[str]) -> dict | None:
    """Autonomy-A's sanity rows of the same scenes (bench/results/sanity.json), averaged."""
    import json

    path = ROOT / "bench" / "results" / "sanity.json"
    if not path.is_file():
        return None
    rows = [r for r in json.loads(path.read_text())["rows"] if r["scene"] in set(scenes)]
    if not rows:
        return None
    return {"source": "bench/results/sanity.json", "scenes": len(rows),
            "ok_rate": float(np.mean([not r["collision"]["collided"] and not r["off_road"] for r in rows])),
            "ap": _mean(rows, "detection", "ap"), "recall": _mean(rows, "detection", "recall"),
            "min_ade": _mean(rows, "prediction", "min_ade"), "mean_ade": _mean(rows, "prediction", "mean_ade"),
            "plan_lat": _mean(rows, "planning_comfort", "lat"), "plan_jerk": _mean(rows, "planning_comfort", "jerk"),
            "drive_lat": _mean(rows, "driving_comfort", "lat"), "drive_jerk": _mean(rows, "driving_comfort", "jerk")}


def _print_b(s: dict, ref: dict | None, args) -> None:
    f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    print("\n| | ok | occ. mAP | occ. Soft-IoU | flow-gr. mAP | flow-gr. Soft-IoU | EPE m/s | plan lat | plan jerk | "
          "drive lat | drive jerk |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| this run (B) | {100 * s['ok_rate']:.0f}% | {f(s['occ_map'])} | {f(s['occ_soft_iou'])} | {f(s['fg_map'])} | "
          f"{f(s['fg_soft_iou'])} | {f(s['epe'], 2)} | {f(s['plan_lat'])} | {f(s['plan_jerk'])} | {f(s['drive_lat'])} | "
          f"{f(s['drive_jerk'])} |")
    p = PAPER_ORIGINAL_B
    print(f"| paper Table 1, Autonomy-B, Original | - | {p['map']:.3f} | {p['soft_iou']:.3f} | {p['fg_map']:.3f} | "
          f"{p['fg_soft_iou']:.3f} | - | {p['plan_lat']:.3f} | {p['plan_jerk']:.3f} | {p['drive_lat']:.3f} | "
          f"{p['drive_jerk']:.3f} |")
    if ref:
        print(f"\nAutonomy-A on the same {ref['scenes']} scenes ({ref['source']}): ok {100 * ref['ok_rate']:.0f}% | "
              f"AP {f(ref['ap'])} recall {f(ref['recall'])} | minADE {f(ref['min_ade'], 2)} meanADE "
              f"{f(ref['mean_ade'], 2)} | plan lat {f(ref['plan_lat'])} jerk {f(ref['plan_jerk'])} | drive lat "
              f"{f(ref['drive_lat'])} jerk {f(ref['drive_jerk'])}")


def _line(m: dict, i: int, n: int) -> None:
    d, c = m["detection"], m["collision"]
    if m.get("occupancy") is not None:
        o = m["occupancy"]
        perception = (f"mAP={o['map'] and round(o['map'], 3)} softIoU={o['soft_iou'] and round(o['soft_iou'], 3)} "
                      f"EPE={o['epe'] and round(o['epe'], 2)}")
    else:
        perception = (f"AP={d['ap'] if d['ap'] is None else round(d['ap'], 3)} "
                      f"minADE={m['prediction']['min_ade'] and round(m['prediction']['min_ade'], 2)}")
    print(f"[{i}/{n}] {m['scene']:28s} coll={int(c['collided'])} fault={int(c['at_fault'])} "
          f"off={m['off_road_m']:.2f} {perception} "
          f"drive_lat={m['driving_comfort']['lat']:.3f} drive_jerk={m['driving_comfort']['jerk']:.3f} "
          f"fps={m['fps']:.1f}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
