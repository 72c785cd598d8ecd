"""Planner benchmark: closed-loop ego on the bundled benchmark scenes with oracle perception.

The ego re-plans every 0.1 s with :class:`SamplingPlanner` and follows its plan exactly
(perfect control); actors replay their logs. Perception and prediction are replaced by an
oracle (ground-truth boxes; future = the logged future as one mode, or constant velocity with
``--predictor cv``), so this isolates the planner. ``--predictor tracked`` runs the whole
non-learned chain instead: ground-truth boxes with noise (0.2 m, 0.03 rad, 5 % dropped) ->
``MultiObjectTracker`` -> ``LaneFollowingPredictor`` (3 modes) -> planner: collisions, leaving the road, comfort (the
paper's Table 1 columns), and milliseconds per plan.

    .venv/bin/python bench/planner.py [--quick] [--seconds 5] [--predictor log|cv]

Prints a table and writes ``bench/results/planner[.quick].json``.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.autonomy.baselines import LaneFollowingPredictor  # noqa: E402
from adv3d_runner.autonomy.interface import Detections, EgoState, Predictions, Tracks  # noqa: E402
from adv3d_runner.autonomy.tracker import MultiObjectTracker  # noqa: E402
from adv3d_runner.autonomy.planner import SamplingPlanner  # noqa: E402
from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.metrics.comfort import collisions, driving_comfort, planning_comfort  # noqa: E402
from adv3d_runner.scene import lanes as lanegeo  # noqa: E402
from adv3d_runner.scene.lanemap import LaneMap  # noqa: E402
from adv3d_runner.scene.schema import load_scene  # noqa: E402

DT = 0.1
H = 60


def oracle_inputs(poses, valid, dims, k, predictor):
    """Tracks and one-mode predictions of the actors valid at frame k."""
    idx = np.flatnonzero(valid[:, k])
    n = len(idx)
    boxes = np.c_[poses[idx, k, :2], dims[idx, :2], poses[idx, k, 2]]
    fut = np.empty((n, H, 2))
    T = poses.shape[1]
    for r, i in enumerate(idx):
        if predictor == "cv":
            # finite difference of the log (backward; forward at an actor's first frame)
            if k > 0 and valid[i, k - 1]:
                vel = (poses[i, k, :2] - poses[i, k - 1, :2]) / DT
            elif k + 1 < T and valid[i, k + 1]:
                vel = (poses[i, k + 1, :2] - poses[i, k, :2]) / DT
            else:
                vel = np.zeros(2)
            fut[r] = poses[i, k, :2] + np.arange(1, H + 1)[:, None] * DT * vel
        else:
            last = k
            for h in range(H):
                f = k + 1 + h
                if f < T and valid[i, f]:
                    last = f
                fut[r, h] = poses[i, last, :2]
    tracks = Tracks(idx, boxes, np.zeros((n, 2)), np.ones(n), np.zeros(n, np.int64), np.zeros((n, 1, 3)),
                    np.ones((n, 1), bool))
    return tracks, Predictions(idx, fut[:, None], np.ones((n, 1)))


def off_road(scene, ego_boxes) -> float:
    """Largest distance (m) of the ego centre outside every lane strip over the episode."""
    worst = 0.0
    for b in ego_boxes:
        best = np.inf
        for lane in scene.lanes:
            s, d, _ = lanegeo.project(lane.centerline, b[:2])
            total = lanegeo.length(lane.centerline)
            half = 0.5 * float(lanegeo.width_at(lane.centerline, lane.width, np.clip(s, 0, total)))
            best = min(best, np.hypot(max(abs(d) - half, 0.0), max(0.0, -s, s - total)))
        worst = max(worst, best)
    return worst


def run_scene(path: Path, seconds: float, predictor: str) -> dict:
    scene = load_scene(path)
    poses, valid = scene.all_actor_poses()
    dims = scene.actor_dimensions()
    ego_log = scene.ego_poses()
    L, W = float(scene.ego.dimensions[0]), float(scene.ego.dimensions[1])
    ego = EgoState(ego_log[0], float(scene.ego_speeds()[0]), length=L, width=W, wheelbase=scene.ego.wheelbase)
    lane_map = LaneMap.from_scene(scene)
    planner = SamplingPlanner()
    tracker, lfp = MultiObjectTracker(), LaneFollowingPredictor()
    planner.reset(lane_map)
    lfp.reset(lane_map)
    rng = np.random.default_rng(0)
    steps = int(round(seconds / DT))
    ego_boxes, act_boxes, act_valid, plans, ms = [], [], [], [], []
    for k in range(steps):
        if predictor == "tracked":
            idx = np.flatnonzero(valid[:, k] & (rng.random(len(dims)) > 0.05))
            noisy = np.c_[poses[idx, k, :2] + rng.normal(0, 0.2, (len(idx), 2)), dims[idx, :2],
                          poses[idx, k, 2] + rng.normal(0, 0.03, len(idx))]
            tracks = tracker.update(Detections(noisy, np.full(len(idx), 0.9)), prior_speed=ego.speed)
            preds = lfp.predict(tracks)
        else:
            tracks, preds = oracle_inputs(poses, valid, dims, k, predictor)
        t0 = time.process_time()
        plan = planner.plan(ego, preds, tracks)
        ms.append(1000 * (time.process_time() - t0))
        ego_boxes.append(ego.box)
        ab = np.c_[np.nan_to_num(poses[:, k, :2]), dims[:, :2], np.nan_to_num(poses[:, k, 2])]
        act_boxes.append(ab)
        act_valid.append(valid[:, k])
        plans.append(plan.trajectory)
        ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]), length=L,
                       width=W, wheelbase=scene.ego.wheelbase, time=(k + 1) * DT)
    ego_boxes = np.array(ego_boxes)
    rep = collisions(ego_boxes, np.array(act_boxes).reshape(steps, -1, 5), np.array(act_valid))
    at_fault = False
    if rep.collided:  # an actor driving into the ego from behind is not the ego's fault
        k = rep.first_frame
        e = ego_boxes[k]
        for i in rep.actors:
            rel = act_boxes[k][i, :2] - e[:2]
            lon = rel[0] * np.cos(e[4]) + rel[1] * np.sin(e[4])
            at_fault |= lon > 0
    traj = np.c_[ego_boxes[:, :2], ego_boxes[:, 4]]
    dc, pc = driving_comfort(traj), planning_comfort(plans)
    return {"scene": scene.id, "collided": rep.collided, "at_fault": bool(at_fault), "min_distance": rep.min_distance,
            "off_road_m": off_road(scene, ego_boxes), "drive_lat": dc.lat, "drive_jerk": dc.jerk,
            "plan_lat": pc.lat, "plan_jerk": pc.jerk, "ms_per_plan": float(np.mean(ms)),
            "progress_m": float(np.hypot(*(ego_boxes[-1, :2] - ego_boxes[0, :2])))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 scenes instead of 100")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--predictor", choices=("log", "cv", "tracked"), default="log")
    args = ap.parse_args()
    paths = sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json*"))
    if args.quick:
        paths = paths[::10]
    rows = []
    for p in paths:
        rows.append(run_scene(p, args.seconds, args.predictor))
        r = rows[-1]
        print(f"{r['scene']:28s} coll={int(r['collided'])} fault={int(r['at_fault'])} off={r['off_road_m']:.2f} "
              f"lat={r['drive_lat']:.3f} jerk={r['drive_jerk']:.3f} plan_lat={r['plan_lat']:.3f} "
              f"plan_jerk={r['plan_jerk']:.3f} ms={r['ms_per_plan']:.1f}", flush=True)
    n = len(rows)
    summary = {
        "scenes": n,
        "collision_rate": float(np.mean([r["collided"] for r in rows])),
        "at_fault_collision_rate": float(np.mean([r["at_fault"] for r in rows])),
        "off_road_rate": float(np.mean([r["off_road_m"] > 0.0 for r in rows])),
        "ok_rate": float(np.mean([not r["at_fault"] and r["off_road_m"] == 0.0 for r in rows])),
        **{k: float(np.mean([r[k] for r in rows])) for k in ("plan_lat", "plan_jerk", "drive_lat", "drive_jerk",
                                                              "ms_per_plan")},
    }
    print("\n| scenes | ok (no at-fault collision, on road) | collisions (any) | plan lat | plan jerk | drive lat | "
          "drive jerk | ms/plan |")
    print("|---|---|---|---|---|---|---|---|")
    s = summary
    print(f"| {n} | {100 * s['ok_rate']:.0f}% | {100 * s['collision_rate']:.0f}% | {s['plan_lat']:.3f} | "
          f"{s['plan_jerk']:.3f} | {s['drive_lat']:.3f} | {s['drive_jerk']:.3f} | {s['ms_per_plan']:.1f} |")
    print("paper Table 1 (Original, Autonomy-A): plan lat 0.203, plan jerk 0.336, drive lat 0.194, drive jerk 0.331")
    suffix = "" if args.predictor == "log" else f".{args.predictor}"
    out = ROOT / "bench" / "results" / f"planner{suffix}{'.quick' if args.quick else ''}.json"
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "planner",
                     "command": " ".join(["bench/planner.py"] + sys.argv[1:]),
                     "machine": {"python": platform.python_version(), "platform": platform.platform(),
                                 "processor": platform.processor()},
                     "summary": summary, "rows": rows})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
