"""Review engine in Blender: time to build a 200-frame review with LiDAR points, and per-frame
scrubbing cost, as the point count grows.

    .venv/bin/python bench/blender_review.py [--quick]

Synthetic episode (seeded): 20 actors (2 adversarial), N points per frame, 15 detections,
90 predicted trajectories of 30 points and a 50-point plan per frame. Measures
``review.build_review`` (objects + keyframes; the per-frame geometry is written lazily by the
frame handler) and ``scene.frame_set`` over the timeline. The "error" column checks that the
points shown after a frame change are exactly that frame's points (max |difference|, m).
The replay *file* reading is not included: its format is not defined yet.
Writes bench/results/blender_review.json (``--quick``: blender_review.quick.json).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def episode(frames: int, n_points: int, seed: int):
    from blender_addon import review

    rng = np.random.default_rng(seed)
    ego = np.stack([np.arange(frames) * 1.0, np.zeros(frames), np.zeros(frames)], axis=1)
    pts = [(rng.random((n_points, 3)) * [100, 40, 3]).astype(np.float32) for _ in range(frames)]
    actors = [review.ReviewActor(i, np.stack([10 + 5 * i + 0.9 * np.arange(frames), np.full(frames, 3.5),
                                              np.zeros(frames)], axis=1), np.array([4.5, 1.8, 1.5]),
                                 adversarial=i < 2) for i in range(20)]
    dets = [np.column_stack([rng.random((15, 2)) * 50, np.zeros(15), np.tile([4.5, 1.8, 1.5], (15, 1)),
                             rng.random(15)]) for _ in range(frames)]
    preds = [rng.random((90, 30, 2)) * 50 for _ in range(frames)]
    plan = [np.column_stack([np.linspace(0, 50, 50), np.zeros(50)]) for _ in range(frames)]
    return review.ReviewData(ego, np.array([4.8, 1.9, 1.55]), actors, pts, dets, preds, plan)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--frames", type=int, default=200)
    args = parser.parse_args()
    import bpy

    import blender_addon
    from blender_addon import review

    sizes = [10_000, 120_000] if args.quick else [10_000, 60_000, 120_000, 250_000]
    rows = []
    for n in sizes:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        blender_addon.register()
        data = episode(args.frames, n, seed=0)
        scene = bpy.context.scene
        t0 = time.perf_counter()
        review.build_review(scene, data)
        build_s = time.perf_counter() - t0
        times, err = [], 0.0
        for f in range(0, args.frames, 5 if args.quick else 2):
            t = time.perf_counter()
            scene.frame_set(f)
            times.append(1e3 * (time.perf_counter() - t))
            mesh = bpy.data.objects["review lidar"].data
            co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            err = max(err, float(np.abs(co.reshape(-1, 3) - data.points[f]).max()))
        rows.append({"points_per_frame": n, "frames": args.frames, "build_s": build_s,
                     "frame_set_median_ms": float(np.median(times)), "frame_set_p95_ms": float(np.percentile(times, 95)),
                     "max_point_error_m": err})
        blender_addon.unregister()
    print(f"{'points/frame':>12s} {'frames':>6s} {'build s':>8s} {'frame_set ms (median / p95)':>28s} {'max err m':>10s}")
    for r in rows:
        print(f"{r['points_per_frame']:12d} {r['frames']:6d} {r['build_s']:8.2f} "
              f"{r['frame_set_median_ms']:15.1f} / {r['frame_set_p95_ms']:6.1f}     {r['max_point_error_m']:10.1e}")
    out = REPO / "bench" / "results" / ("blender_review.quick.json" if args.quick else "blender_review.json")
    out.write_text(json.dumps({
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "blender": bpy.app.version_string, "cpu_count": os.cpu_count()},
        "rows": rows, "target": "load a 200-frame review with points <= 10 s (Blender side)",
    }, indent=1) + "\n")
    print(f"wrote {out.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
