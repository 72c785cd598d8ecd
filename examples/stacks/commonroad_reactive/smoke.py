"""Closed-loop smoke test of adv3d_crp.CRPlanner (CommonRoad's reactive planner), run in this
folder's own venv:

    .venv/bin/python smoke.py                 # 3-lane highway, leader 40 m ahead at 20 m/s
    .venv/bin/python smoke.py --lanes 1       # one lane: it has to slow down behind the leader
    .venv/bin/python smoke.py --predictions   # the leader's future given as 2 prediction modes

Straight highway along +x, lanes 3.7 m wide and 400 m long (ids 0 = right .. 2 = left), ego on
the middle lane at 25 m/s, a leader 40 m ahead (centre to centre) on the same lane at 20 m/s.
Each step the ego is put on the plan's next state (perfect tracking) and the leader moves at
constant speed. Prints per-step time, lane, speed, gap; exits 1 on a collision.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adv3d_crp import CRPlanner, EgoInput, LaneInput, ObstacleInput, PlannerOptions  # noqa: E402

W, LENGTH, DT = 3.7, 400.0, 0.1


def highway(n_lanes: int) -> list[LaneInput]:
    xs = np.linspace(0.0, LENGTH, 81)
    lanes = []
    for i in range(n_lanes):
        lanes.append(LaneInput(id=i, centerline=np.column_stack([xs, np.full_like(xs, i * W)]), width=W,
                               left=i + 1 if i + 1 < n_lanes else None, right=i - 1 if i > 0 else None))
    return lanes


def footprint(x, y, L, Wd, yaw) -> Polygon:
    c, s = math.cos(yaw), math.sin(yaw)
    pts = [(x + c * dx - s * dy, y + s * dx + c * dy) for dx, dy in
           ((L / 2, Wd / 2), (-L / 2, Wd / 2), (-L / 2, -Wd / 2), (L / 2, -Wd / 2))]
    return Polygon(pts)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lanes", type=int, default=3)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--predictions", action="store_true")
    ap.add_argument("--horizon", type=int, default=60)
    ap.add_argument("--multiproc", action="store_true")
    ap.add_argument("--replan-every", type=int, default=1)
    ap.add_argument("--safety-margin", type=float, default=0.0)
    args = ap.parse_args()

    lanes = highway(args.lanes)
    ego_lane_y = (1 if args.lanes >= 2 else 0) * W
    ego = EgoInput(x=20.0, y=ego_lane_y, yaw=0.0, speed=25.0, acceleration=0.0, length=4.8, width=2.0,
                   wheelbase=2.9, curvature=0.0)
    lead = np.array([60.0, ego_lane_y])
    lead_v, lead_L, lead_W = 20.0, 4.8, 2.0

    p = CRPlanner(PlannerOptions(horizon_steps=args.horizon, multiproc=args.multiproc,
                                  replan_every=args.replan_every, safety_margin=args.safety_margin))
    p.reset(lanes, ego)
    print(f"reset (lanelet network, road boundary, planner): {p.reset_time_s * 1e3:.1f} ms; "
          f"lanes extended past the map edge: {p.extended}")

    collided, min_gap, min_dist = False, math.inf, math.inf
    setup_ms, plan_ms = [], []
    speeds = [ego.speed]
    ys = [ego.y]
    for k in range(args.steps):
        preds = probs = None
        if args.predictions:  # two modes: keep lane (0.8), drift half a lane left (0.2)
            t = DT * np.arange(1, 61)[:, None]
            keep = lead + t * np.array([lead_v, 0.0])
            drift = keep + np.column_stack([np.zeros(60), np.minimum(t[:, 0], 3.0) * 0.6])
            preds, probs = np.stack([keep, drift]), np.array([0.8, 0.2])
        obs = [ObstacleInput(box=(lead[0], lead[1], lead_L, lead_W, 0.0), velocity=(lead_v, 0.0),
                             predictions=preds, probabilities=probs)]
        res = p.plan(ego, obs)
        att = (res.stats.get("attempts") or [{}])[-1]
        if "t_plan" in att:
            setup_ms.append((att["t"] - att["t_plan"]) * 1e3)
            plan_ms.append(att["t_plan"] * 1e3)
        nxt = res.trajectory[1]
        kap = float(res.curvature[1])
        ego = EgoInput(x=float(nxt[0]), y=float(nxt[1]), yaw=float(nxt[2]), speed=float(res.speed[1]),
                       acceleration=float(res.acceleration[1]), length=ego.length, width=ego.width,
                       wheelbase=ego.wheelbase, curvature=kap)
        lead = lead + DT * np.array([lead_v, 0.0])
        fe = footprint(ego.x, ego.y, ego.length, ego.width, ego.yaw)
        fl = footprint(lead[0], lead[1], lead_L, lead_W, 0.0)
        dist = fe.distance(fl)
        same_lane = abs(ego.y - lead[1]) < W / 2
        gap = (lead[0] - ego.x) - (lead_L + ego.length) / 2
        if same_lane and lead[0] > ego.x:
            min_gap = min(min_gap, gap)
        min_dist = min(min_dist, dist)
        if fe.intersects(fl):
            collided = True
        speeds.append(ego.speed)
        ys.append(ego.y)
        st = res.stats
        print(f"step {k:2d}  {res.time_s * 1e3:7.1f} ms  lane {st.get('lane')}  x {ego.x:7.2f}  y {ego.y:5.2f}"
              f"  v {ego.speed:5.2f}  a {ego.acceleration:5.2f}  gap {gap:6.2f}  dist {dist:6.2f}"
              f"  samples {att.get('samples', '-')}"
              f"{'  EMERGENCY: ' + res.reason if res.emergency else ''}")

    ts = np.array(p.step_times) * 1e3
    print("\n=== summary ===")
    print(f"steps {args.steps}, lanes {args.lanes}, horizon {args.horizon} steps, predictions {args.predictions}")
    print(f"time per step ms: mean {ts.mean():.1f}  median {statistics.median(ts):.1f}  "
          f"p95 {np.percentile(ts, 95):.1f}  max {ts.max():.1f}")
    if plan_ms:
        print(f"  of which: obstacles + collision checker + planner reset {np.mean(setup_ms):.1f} ms, "
              f"ReactivePlanner.plan() {np.mean(plan_ms):.1f} ms (means over planning steps)")
    print(f"collision: {collided}")
    print(f"min bumper gap while behind the leader in its lane: {min_gap:.2f} m; "
          f"min footprint distance: {min_dist:.2f} m")
    print(f"emergency fallbacks: {p.emergency_count} {sorted(set(p.emergency_reasons))}")
    print("speed profile (every 5th step, m/s): " + " ".join(f"{v:.1f}" for v in speeds[::5]))
    print("lateral y profile (every 5th step, m): " + " ".join(f"{y:.2f}" for y in ys[::5]))
    return 1 if collided else 0


if __name__ == "__main__":
    sys.exit(main())
