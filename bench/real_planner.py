"""The planner on real traffic without the LiDAR (docs/autonomy.md, real traffic): the harness its comfort limits were
tuned with, on the *train* part of ``scenes/real/`` only.

Per scene, 5 s in closed loop (actors replay their logs, perfect control): ground-truth boxes of
the actors within 80 m with noise (centre 0.15 m, yaw 0.02 rad, 5 % missed) -> the tracker
(Autonomy-A's settings) -> a learned predictor -> :class:`SamplingPlanner` with a given config.
About 20x cheaper than ``bench/sanity.py`` (no ray casting, no detector), so a config costs
~20 s of CPU for the 14 scenes. Reports driving comfort (mean and peak |jerk|, mean |lateral
acceleration|), planning jerk, collisions (at fault: the first contact is with an actor ahead),
progress against the logged driver, slowest speed and hardest braking.

    .venv/bin/python bench/real_planner.py [--part train] [--predictor DIR] [--config JSON] [--name NAME]

``--config`` overrides fields: ``{"proposals": {...}, "weights": {...}, "planner": {...}}``
(e.g. the limits before the real-traffic tuning: ``{"proposals": {"max_jerk": 4, "max_release_jerk": 10,
"max_brake_jerk": 4, "leader_speed_window": 0.1}}``). Writes
``bench/results/real_planner.<NAME>.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DT = 0.1
NOISE = {"pos_std": 0.15, "yaw_std": 0.02, "miss": 0.05, "range": 80.0}


def run_scene(path: Path, config, predictor, seconds: float = 5.0, seed: int = 0) -> dict:
    from adv3d_runner.autonomy.interface import Detections, EgoState
    from adv3d_runner.autonomy.planner import SamplingPlanner
    from adv3d_runner.autonomy.stacks import TRACK_MIN_SCORE
    from adv3d_runner.autonomy.tracker import MultiObjectTracker, TrackerConfig
    from adv3d_runner.metrics.comfort import collisions, driving_comfort, planning_comfort
    from adv3d_runner.scene.lanemap import LaneMap
    from adv3d_runner.scene.schema import load_scene

    scene = load_scene(path)
    poses, valid = scene.all_actor_poses()
    dims = scene.actor_dimensions()
    log, log_v = scene.ego_poses(), scene.ego_speeds()
    L, W = float(scene.ego.dimensions[0]), float(scene.ego.dimensions[1])
    ego = EgoState(log[0], float(log_v[0]), length=L, width=W, wheelbase=scene.ego.wheelbase)
    lane_map = LaneMap.from_scene(scene)
    planner = SamplingPlanner(config)
    planner.reset(lane_map)
    predictor.reset(lane_map)
    tracker = MultiObjectTracker(TrackerConfig(min_score=TRACK_MIN_SCORE))
    rng = np.random.default_rng(seed)
    T = int(round(seconds / DT))
    ego_boxes, act_boxes, act_valid, plans, speeds, accels = [], [], [], [], [], []
    for k in range(T):
        near = valid[:, k] & (np.hypot(*(np.nan_to_num(poses[:, k, :2]) - ego.pose[:2]).T) < NOISE["range"])
        idx = np.flatnonzero(near & (rng.random(len(dims)) > NOISE["miss"]))
        det = np.c_[poses[idx, k, :2] + rng.normal(0, NOISE["pos_std"], (len(idx), 2)), dims[idx, :2],
                    poses[idx, k, 2] + rng.normal(0, NOISE["yaw_std"], len(idx))]
        tracks = tracker.update(Detections(det, np.full(len(idx), 0.9)), prior_speed=ego.speed)
        plan = planner.plan(ego, predictor.predict(tracks), tracks)
        ego_boxes.append(ego.box)
        speeds.append(ego.speed)
        accels.append(ego.acceleration)
        act_boxes.append(np.c_[np.nan_to_num(poses[:, k, :2]), dims[:, :2], np.nan_to_num(poses[:, k, 2])])
        act_valid.append(valid[:, k])
        plans.append(plan.trajectory)
        ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]), length=L,
                       width=W, wheelbase=scene.ego.wheelbase, time=(k + 1) * DT)
    eb = np.array(ego_boxes)
    ab = np.array(act_boxes).reshape(T, -1, 5)
    rep = collisions(eb, ab, np.array(act_valid))
    fault = False
    if rep.collided:
        e = eb[rep.first_frame]
        for i in rep.actors:
            rel = ab[rep.first_frame, i, :2] - e[:2]
            fault |= bool(rel[0] * np.cos(e[4]) + rel[1] * np.sin(e[4]) > 0)
    dc, pc = driving_comfort(eb[:, [0, 1, 4]], DT), planning_comfort(plans, DT)
    driven = float(np.sum(np.hypot(*np.diff(eb[:, :2], axis=0).T)))
    logged = float(np.sum(np.hypot(*np.diff(log[:T, :2], axis=0).T)))
    return {"scene": scene.id, "collided": bool(rep.collided), "at_fault": fault, "drive_jerk": dc.jerk,
            "drive_peak_jerk": dc.max_jerk, "drive_lat": dc.lat, "plan_jerk": pc.jerk,
            "progress_ratio": driven / logged, "min_speed": float(min(speeds)), "min_accel": float(min(accels))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="train", choices=("train", "benchmark"))
    ap.add_argument("--predictor", default=None, help="predictor folder (default: the shipped one)")
    ap.add_argument("--config", default="{}", help="JSON overrides of the planner config")
    ap.add_argument("--name", default="default", help="result name: bench/results/real_planner.NAME.json")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from adv3d_runner.autonomy.planner import PlannerConfig
    from adv3d_runner.errors import ConfigError
    from adv3d_runner.autonomy.predictor import DEFAULT_MODEL_DIR, load_predictor
    from adv3d_runner.fileio import write_json
    from adv3d_runner.scene.real import load_real_split

    try:
        over = json.loads(args.config)
        config = PlannerConfig.from_overrides(over, "--config")
    except json.JSONDecodeError as exc:
        ap.error(f"--config: not JSON ({exc.msg}, column {exc.colno})")
    except ConfigError as exc:
        ap.error(str(exc))
    predictor = load_predictor(args.predictor or DEFAULT_MODEL_DIR)
    t0 = time.process_time()
    rows = []
    for path in load_real_split().paths(args.part):
        r = run_scene(path, config, predictor)
        rows.append(r)
        print(f"{r['scene']:32s} coll={int(r['collided'])}{'F' if r['at_fault'] else ' '} jerk={r['drive_jerk']:.2f} "
              f"peak={r['drive_peak_jerk']:.1f} lat={r['drive_lat']:.2f} plan_jerk={r['plan_jerk']:.2f} "
              f"progress={r['progress_ratio']:.2f} vmin={r['min_speed']:.1f} amin={r['min_accel']:.1f}", flush=True)
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    summary = {"scenes": len(rows), "drive_jerk": mean("drive_jerk"), "drive_peak_jerk": mean("drive_peak_jerk"),
               "drive_peak_jerk_max": float(max(r["drive_peak_jerk"] for r in rows)), "drive_lat": mean("drive_lat"),
               "plan_jerk": mean("plan_jerk"), "collisions": int(sum(r["collided"] for r in rows)),
               "at_fault_collisions": int(sum(r["at_fault"] for r in rows)),
               "progress_ratio_min": float(min(r["progress_ratio"] for r in rows)),
               "min_accel_min": float(min(r["min_accel"] for r in rows)), "cpu_s": time.process_time() - t0}
    print(f"\n{args.part} part, {args.name}: drive jerk {summary['drive_jerk']:.3f} (peak mean "
          f"{summary['drive_peak_jerk']:.2f}, max {summary['drive_peak_jerk_max']:.1f}), plan jerk "
          f"{summary['plan_jerk']:.3f}, lat {summary['drive_lat']:.3f}, collisions {summary['collisions']} "
          f"(at fault {summary['at_fault_collisions']}), progress vs log min {summary['progress_ratio_min']:.2f}, "
          f"hardest braking {summary['min_accel_min']:.1f} m/s^2; {summary['cpu_s']:.0f} s CPU")
    out = ROOT / "bench" / "results" / f"real_planner.{args.name}.json"
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "real_planner",
                     "command": " ".join(["bench/real_planner.py"] + sys.argv[1:]), "part": args.part,
                     "predictor": str(args.predictor or "assets/models/predictor"), "config_overrides": over,
                     "noise": NOISE, "machine": {"python": platform.python_version(), "platform": platform.platform()},
                     "summary": summary, "rows": rows})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
