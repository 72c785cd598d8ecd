"""Autonomy-A's planner on a recorded scene, for the regression test of
``tests/test_planner_occupancy.py`` (imports only what every version of the planner has, so
``tests/data/planner_a_plans.npz`` can be made with code that has no Autonomy-B: a tree of main
made by ``git archive main adv3d_runner scenes/highway/highway-benchmark-000010.json.gz``, this file
copied to its ``tests/``, then ``PYTHONPATH=<that tree> python <that tree>/tests/planner_regression.py OUT.npz``).

The ego starts at its logged pose on benchmark scene 10 and follows its own plans for 30
frames (perfect control); the actors replay their logs and are given to the planner as tracks
with their true 60-step futures (one mode): everything but the planner is fixed by the scene file.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "highway" / "highway-benchmark-000010.json.gz"
FRAMES = 30


def a_plans(scene_path: Path = SCENE, frames: int = FRAMES) -> np.ndarray:
    """(frames, 51, 4) x, y, yaw, speed of every chosen plan."""
    from adv3d_runner.autonomy.interface import EgoState, Predictions, Tracks
    from adv3d_runner.autonomy.planner import SamplingPlanner
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.lanemap import LaneMap

    scene = load_scene(scene_path)
    poses, valid = scene.all_actor_poses()
    dims = scene.actor_dimensions()
    planner = SamplingPlanner()
    planner.reset(LaneMap.from_scene(scene))
    ego0 = scene.ego_poses()[0]
    ego = EgoState(ego0, float(scene.ego_speeds()[0]), length=float(scene.ego.dimensions[0]),
                   width=float(scene.ego.dimensions[1]), wheelbase=float(scene.ego.wheelbase))
    out = []
    for k in range(frames):
        ok = valid[:, k] & (np.hypot(*(poses[:, k, :2] - ego.pose[:2]).T) < 100.0)
        ok &= np.all(valid[:, k + 1:k + 61], axis=1)
        ids = np.flatnonzero(ok)
        boxes = np.c_[poses[ids, k, :2], dims[ids, :2], poses[ids, k, 2]]
        n = len(ids)
        tracks = Tracks(ids, boxes, np.zeros((n, 2)), np.ones(n), np.zeros(n, np.int64), np.zeros((n, 1, 3)),
                        np.ones((n, 1), bool))
        preds = Predictions(ids, poses[ids, k + 1:k + 61, :2][:, None], np.ones((n, 1)))
        plan = planner.plan(ego, preds, tracks)
        out.append(np.c_[plan.trajectory, plan.speed])
        ego = EgoState(plan.trajectory[1], float(plan.speed[1]), acceleration=float(plan.acceleration[0]),
                       curvature=float(plan.curvature[0]), time=(k + 1) * 0.1, length=ego.length, width=ego.width,
                       wheelbase=ego.wheelbase)
    return np.stack(out)


if __name__ == "__main__":
    np.savez_compressed(sys.argv[1], plans=a_plans())
