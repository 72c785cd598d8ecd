"""Review in Blender: time to load a 200-frame review with LiDAR points, and per-frame
scrubbing cost.

    .venv/bin/python bench/blender_review.py [--quick] [--replay PATH]

Part 1, a real replay file: ``adv3d simulate`` of a bundled highway scene for 20 s (200 frames)
with ``--points`` (written to a temporary folder unless ``--replay`` names one), loaded through
the Review panel's operator (``adv3d.review_load``: read + validate the JSON and the points
file, convert, build objects and keyframes, show frame 0), timed end to end and by step; then
loaded again as the modal operator does it (``jobs.Job`` sliced ``jobs.SLICE_S`` per timer
tick): total time, steps, and the longest slice (how long the UI is held at most). The
"error" column: max |shown point (world, + origin) - ``Replay.points_in_map``| over the frames
visited (m; float32 + 1 cm quantisation of the file).

Part 2, the engine alone on synthetic episodes (seeded): 20 actors (2 adversarial), N points
per frame, 15 detections, 90 predicted trajectories of 30 points and a 50-point plan per frame;
``review.build_review`` and ``scene.frame_set`` over the timeline, error = max |shown points -
that frame's points|.
Writes bench/results/blender_review.json (``--quick``: blender_review.quick.json; part 1 is
then a 50-frame replay).
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


def simulate_replay(folder: Path, seconds: float) -> Path:
    """``adv3d simulate`` a bundled highway scene with points -> folder/replay.json.gz."""
    import subprocess

    scene = sorted((REPO / "scenes" / "highway").glob("*.json.gz"))[0]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "--quiet", "simulate", str(scene), "--seconds",
                    str(seconds), "--autonomy", "oracle", "--points", "--out", str(folder)], check=True, env=env)
    return folder / "replay.json.gz"


def real_replay(path: Path, step: int) -> dict:
    """Load ``path`` through the Review operator; time the steps; scrub."""
    import bpy

    import blender_addon
    from adv3d_runner.sim.replay import load_replay
    from blender_addon import ops_review, review

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    scene = bpy.context.scene
    t0 = time.perf_counter()
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    total_s = time.perf_counter() - t0
    # the same steps again, one by one
    t = time.perf_counter()
    replay = load_replay(path)
    read_s = time.perf_counter() - t
    t = time.perf_counter()
    data, origin = ops_review.replay_to_review(replay, path.parent)
    convert_s = time.perf_counter() - t
    t = time.perf_counter()
    review.build_review(scene, data)
    build_s = time.perf_counter() - t
    bpy.data.collections[review.REVIEW_COLLECTION]["adv3d_origin"] = [float(origin[0]), float(origin[1])]
    lidar = bpy.data.objects["review lidar"]
    times, err = [], 0.0
    for f in range(0, replay.n_frames, step):
        t = time.perf_counter()
        scene.frame_set(f)
        times.append(1e3 * (time.perf_counter() - t))
        co = np.empty(len(lidar.data.vertices) * 3, np.float32)
        lidar.data.vertices.foreach_get("co", co)
        m = np.array(lidar.matrix_world)
        world = co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3] + [origin[0], origin[1], 0.0]
        err = max(err, float(np.abs(world - replay.points_in_map(f)).max()))
    # the modal operator's work, sliced as its timer does (jobs.SLICE_S per tick): how long the
    # UI is held at most, and the whole load this way
    from blender_addon import jobs

    job = jobs.Job("Load review", ops_review.load_review_steps(scene, path))
    t = time.perf_counter()
    ticks = 0
    while job.run_slice() == jobs.RUNNING:
        ticks += 1
    modal_s = time.perf_counter() - t
    assert job.state == jobs.DONE, job.error
    blender_addon.unregister()
    n_points = int(sum(len(p) for p in replay.points))
    return {"replay": str(path), "frames": replay.n_frames, "points_total": n_points,
            "points_per_frame_mean": n_points / max(1, replay.n_frames),
            "json_mb": path.stat().st_size / 1e6, "points_mb": ops_review_points_mb(path),
            "load_total_s": total_s, "read_validate_s": read_s, "convert_s": convert_s, "build_s": build_s,
            "frame_set_median_ms": float(np.median(times)), "frame_set_p95_ms": float(np.percentile(times, 95)),
            "max_point_error_m": err, "modal_total_s": modal_s, "modal_ticks": ticks + 1, "modal_steps": job.n_steps,
            "modal_max_step_s": job.max_step_s, "modal_max_step_cpu_s": job.max_step_cpu_s,
            "modal_slowest_step_after": job.slowest, "modal_max_slice_s": job.max_slice_s,
            "load_average_1min": os.getloadavg()[0]}


def ops_review_points_mb(path: Path) -> float:
    from adv3d_runner.sim.replay import points_path

    p = points_path(path)
    return p.stat().st_size / 1e6 if p.exists() else 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--replay", type=Path, default=None,
                        help="replay file for part 1 (default: simulate one into a temporary folder)")
    args = parser.parse_args()
    import tempfile

    import bpy

    with tempfile.TemporaryDirectory() as tmp:
        path = args.replay or simulate_replay(Path(tmp) / "sim", 5.0 if args.quick else args.frames / 10)
        real = real_replay(path, 5 if args.quick else 2)
    print(f"real replay: {real['frames']} frames, {real['points_per_frame_mean']:.0f} points/frame "
          f"({real['json_mb']:.1f} MB json.gz + {real['points_mb']:.1f} MB npz)")
    print(f"  load through adv3d.review_load: {real['load_total_s']:.2f} s  "
          f"(read+validate {real['read_validate_s']:.2f} s, "
          f"convert {real['convert_s']:.3f} s, build {real['build_s']:.3f} s)")
    print(f"  frame_set median / p95: {real['frame_set_median_ms']:.1f} / {real['frame_set_p95_ms']:.1f} ms, "
          f"max point error {real['max_point_error_m']:.1e} m")
    print(f"  modal load: {real['modal_total_s']:.2f} s in {real['modal_steps']} steps / {real['modal_ticks']} timer "
          f"ticks; UI held at most {1e3 * real['modal_max_slice_s']:.0f} ms (longest step "
          f"{1e3 * real['modal_max_step_s']:.0f} ms wall, {1e3 * real['modal_max_step_cpu_s']:.0f} ms CPU, after "
          f"'{real['modal_slowest_step_after']}'; load average {real['load_average_1min']:.1f})")

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
        "real_replay": real, "rows": rows,
        "target": "load a 200-frame review with points <= 10 s (real_replay.load_total_s), the UI never held "
                  ">= 0.5 s (real_replay.modal_max_slice_s)",
    }, indent=1) + "\n")
    print(f"wrote {out.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
