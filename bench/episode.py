"""Episode speed by stage, and detector input resolution against AP and milliseconds.

(a) A 5 s closed-loop episode (50 frames) on benchmark scenes with the scene's 64-beam rig
    (Velodyne HDL-64E, 133k rays/frame) and library meshes, pinned to ONE core (torch 1 thread,
    OMP 1 thread). Per frame: CPU time (``time.thread_time``) of each stage (LiDAR, detector,
    tracker, predictor, planner, the rest of the loop) and frames per second of the whole loop.
    The machine is shared with other jobs, so CPU time is what we report (wall time too).
(b) The BEV detector at several input resolutions (cell sizes): ms per frame on the episode's
    LiDAR frames and, for each resolution a trained model exists for, AP / recall at IoU 0.5 in
    the ROI over open-loop episodes of the same scenes. Models are looked up as
    ``assets/models/detector`` (its config's resolution) and ``assets/models/detector-<res>``.

(c) ``--autonomy B``: Autonomy-B's per-frame CPU time on one core, its ``occupancy`` stage
    (the implicit model: voxelising the stacked sweeps, encoding, and every query the planner
    makes, measured with the model's own clock) and the rest of its planner, next to Autonomy-A's
    detector + tracker + predictor measured on the same scenes in the same process (the
    bar docs/occupancy.md sets: B's model is no slower than A's three stages together).

    .venv/bin/python bench/episode.py [--quick] [--autonomy A|B|oracle|A-fast] [--out FILE]

Writes ``bench/results/episode[.quick].json`` (``episode.B[.quick].json`` for B).
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
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core, before Embree/torch start pools

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import adv3d_runner.sensors.lidar as lidar_mod  # noqa: E402
from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.scene import load_scene  # noqa: E402
from adv3d_runner.sensors.world import world_from_scene  # noqa: E402
from adv3d_runner.sim.episode import default_library, run_episode  # noqa: E402
from adv3d_runner.sim.evaluate import episode_metrics  # noqa: E402
from adv3d_runner.autonomy.stacks import make_stack  # noqa: E402

CLOCK = time.thread_time
STAGES = ("lidar", "detector", "tracker", "predictor", "occupancy", "planner")
SCENES = ("highway-benchmark-000010", "highway-benchmark-000013", "highway-benchmark-000041")
RESOLUTIONS = (0.2, 0.25, 0.4, 0.5)


class _Timer:
    """Accumulates CPU seconds per stage for the current frame."""

    def __init__(self):
        self.now = {s: 0.0 for s in STAGES}
        self.queries: list[int] = []  # Autonomy-B: occupancy queries per frame

    def wrap(self, obj, method: str, stage: str):
        """A proxy of ``obj`` whose ``method`` is timed (other attributes pass through)."""
        timer = self

        class Proxy:
            def __getattr__(self, name):
                return getattr(obj, name)

        def timed(*a, **k):
            t0 = CLOCK()
            try:
                return getattr(obj, method)(*a, **k)
            finally:
                timer.now[stage] += CLOCK() - t0

        proxy = Proxy()
        setattr(proxy, method, timed)
        return proxy


def _instrument(stack, timer: _Timer) -> None:
    if hasattr(stack, "model"):  # Autonomy-B: the implicit model and the planner
        model = stack.model
        model.clock = CLOCK  # its decode time (the planner's queries) on the same clock
        stack.model = timer.wrap(model, "encode", "occupancy")
        planner = stack.planner

        def plan(*a, **k):
            t0 = CLOCK()
            try:
                return planner.plan(*a, **k)
            finally:
                decode = float(model.timings.get("decode", 0.0))
                timer.now["planner"] += CLOCK() - t0 - decode
                timer.now["occupancy"] += decode
                timer.queries.append(int(model.timings.get("queries", 0)))

        class Proxy:
            def __getattr__(self, name):
                return getattr(planner, name)

        proxy = Proxy()
        proxy.plan = plan
        stack.planner = proxy
        return
    stack.detector = timer.wrap(stack.detector, "detect", "detector")
    stack.tracker = timer.wrap(stack.tracker, "update", "tracker")
    stack.predictor = timer.wrap(stack.predictor, "predict", "predictor")
    stack.planner = timer.wrap(stack.planner, "plan", "planner")


def stage_times(scene, world, stack) -> dict:
    """One 5 s closed-loop episode with per-frame CPU time per stage."""
    timer = _Timer()
    _instrument(stack, timer)
    frames = []
    orig = lidar_mod.simulate_frame

    def timed_lidar(*a, **k):
        # a new frame starts with its LiDAR: close the previous frame's record
        if any(timer.now.values()):
            frames.append(dict(timer.now))
        for s in STAGES:
            timer.now[s] = 0.0
        t0 = CLOCK()
        try:
            return orig(*a, **k)
        finally:
            timer.now["lidar"] += CLOCK() - t0

    lidar_mod.simulate_frame = timed_lidar
    try:
        c0, w0 = CLOCK(), time.perf_counter()
        result = run_episode(scene, stack, seconds=5.0, world=world)
        cpu, wall = CLOCK() - c0, time.perf_counter() - w0
    finally:
        lidar_mod.simulate_frame = orig
    frames.append(dict(timer.now))
    per = {s: float(np.mean([f[s] for f in frames])) for s in STAGES}
    T = result.frames
    per["other"] = cpu / T - sum(per.values())
    return {"scene": scene.id, "frames": T, "actors": len(scene.actors), "points_per_frame": float(result.n_points.mean()),
            "queries_per_frame": float(np.mean(timer.queries)) if timer.queries else None,
            "ms_cpu": {k: 1000 * v for k, v in per.items()}, "ms_cpu_total": 1000 * cpu / T,
            "fps_cpu": T / cpu, "ms_wall_total": 1000 * wall / T, "fps_wall": T / wall,
            "ms_wall_by_stage_episode_timer": {k: float(1000 * np.mean(v)) for k, v in result.timings.items()},
            "result": result}


def _detector_for(res: float):
    """(detector, trained) at this resolution: a trained model when one exists for it, else the
    default model with its resolution overridden (weights trained at another cell size: AP not
    meaningful), else an untrained network (timing only)."""
    try:
        from adv3d_runner.autonomy.detector import DEFAULT_MODEL_DIR, BevDetector, DetectorConfig, load_detector, model_info
    except ImportError:
        return None, "no detector module"
    for folder in (Path(DEFAULT_MODEL_DIR), Path(DEFAULT_MODEL_DIR).parent / f"detector-{res:g}"):
        if (folder / "config.json").is_file():
            try:
                if abs(float(model_info(folder)["detector"]["resolution"]) - res) < 1e-9:
                    return load_detector(folder, threads=1), "trained"
            except (KeyError, TypeError, ValueError):
                pass
    return BevDetector(DetectorConfig(resolution=res), threads=1), "untrained (timing only)"


def detector_table(scenes_worlds, episodes, quick: bool) -> list[dict]:
    from adv3d_runner.autonomy.modular import ModularStack
    from adv3d_runner.autonomy.baselines import LaneFollowingPredictor

    rows = []
    frames = [p[:, :4] for ep in episodes for p in ep.points]
    frames = frames[:: (2 if quick else 3)]
    for res in RESOLUTIONS:
        det, kind = _detector_for(res)
        if det is None:
            rows.append({"resolution": res, "model": kind})
            continue
        det.detect(frames[0])  # warm-up
        t = []
        for p in frames:
            c0 = CLOCK()
            det.detect(p)
            t.append(CLOCK() - c0)
        row = {"resolution": res, "grid": list(det.cfg.grid_shape) if hasattr(det.cfg, "grid_shape") else None,
               "model": kind, "ms_cpu_median": 1000 * float(np.median(t)), "ms_cpu_mean": 1000 * float(np.mean(t)),
               "frames_timed": len(t), "ap": None, "recall": None}
        if kind == "trained":
            gt_det = []
            for scene, world in scenes_worlds:
                stack = ModularStack(det, LaneFollowingPredictor())
                r = run_episode(scene, stack, seconds=5.0, closed_loop=False, world=world)
                gt_det.append(episode_metrics(r, scene.lanes)["detection"])
            n_gt = sum(d["n_gt"] for d in gt_det)
            row["ap"] = float(np.mean([d["ap"] for d in gt_det if d["ap"] is not None]))
            row["recall"] = float(sum(d["recall"] * d["n_gt"] for d in gt_det if d["recall"] is not None) / max(n_gt, 1))
        rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one scene")
    ap.add_argument("--autonomy", choices=("A", "B", "oracle", "A-lanefollow", "A-fast"), default=None,
                    help="default: A when its weights exist, else A-lanefollow (learned detector), else oracle; "
                         "B: Autonomy-B with Autonomy-A's stages measured alongside")
    ap.add_argument("--out", default=None,
                    help="result file of (a)+(b) (default bench/results/episode[.quick].json), so that a "
                         "rerun keeps the kept one")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    autonomy = args.autonomy
    if autonomy is None:  # the most learned stack that is available
        for autonomy in ("A", "A-lanefollow", "oracle"):
            try:
                make_stack(autonomy)
                break
            except Exception as exc:  # noqa: BLE001 - report and fall back
                print(f"{autonomy} not available: {exc}")
    names = SCENES[:1] if args.quick else SCENES
    if autonomy == "B":
        return bench_b(names, args.quick)
    lib = default_library()
    rows, worlds, episodes = [], [], []
    for name in names:
        scene = load_scene(ROOT / "scenes" / "highway" / f"{name}.json.gz")
        c0 = CLOCK()
        world = world_from_scene(scene, lib)
        build = CLOCK() - c0
        stack = make_stack(autonomy)
        # warm-up (imports, torch, caches); its frames feed the detector timing of (b)
        frames_run = run_episode(scene, stack, seconds=2.0, world=world, closed_loop=False, record_points=True)
        r = stage_times(scene, world, stack)
        r["world_build_ms_cpu"] = 1000 * build
        r.pop("result")
        episodes.append(frames_run)
        worlds.append((scene, world))
        rows.append(r)
        ms = r["ms_cpu"]
        print(f"{name}: {r['actors']} actors, {r['points_per_frame']:.0f} points/frame | " +
              " ".join(f"{s} {ms[s]:.1f}" for s in (*STAGES, "other")) +
              f" | total {r['ms_cpu_total']:.1f} ms CPU = {r['fps_cpu']:.1f} frames/s (wall {r['fps_wall']:.1f}/s)",
              flush=True)
    mean = {s: float(np.mean([r["ms_cpu"][s] for r in rows])) for s in (*STAGES, "other")}
    total = float(np.mean([r["ms_cpu_total"] for r in rows]))
    print(f"\n(a) 5 s closed-loop episode, HDL-64E, autonomy {autonomy}, one core, CPU ms per frame "
          f"(mean of {len(rows)} scenes)\n")
    print("| " + " | ".join((*STAGES, "other", "total", "frames/s")) + " |")
    print("|" + "---|" * (len(STAGES) + 3))
    print("| " + " | ".join(f"{mean[s]:.1f}" for s in (*STAGES, "other")) + f" | {total:.1f} | {1000 / total:.1f} |")
    det_rows = detector_table(worlds, episodes, args.quick)
    print("\n(b) detector input resolution (CPU ms per frame on the episodes' frames, one thread)\n")
    print("| cell m | grid | model | ms median | AP@0.5 (ROI) | recall |")
    print("|---|---|---|---|---|---|")
    for d in det_rows:
        f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
        print(f"| {d['resolution']} | {d.get('grid')} | {d['model']} | {f(d.get('ms_cpu_median'), 1)} | "
              f"{f(d.get('ap'))} | {f(d.get('recall'))} |")
    # AP against resolution needs one trained model per resolution: bench/detector.py
    # (docs/detector.md) trains them with a quick recipe; show its table next to ours.
    h7 = ROOT / "bench" / "results" / "detector.json"
    h7_rows = []
    if h7.exists():
        import json

        h7_rows = json.loads(h7.read_text()).get("resolution_rows", [])
        print("\nfrom bench/results/detector.json (bench/detector.py: one model per resolution, held-out AP@0.5)\n")
        print("| model | cell m | AP | recall | ms median |")
        print("|---|---|---|---|---|")
        for d in h7_rows:
            print(f"| {d.get('model')} | {d.get('resolution')} | {d.get('ap', float('nan')):.3f} | "
                  f"{d.get('recall', float('nan')):.3f} | {d.get('ms_median', float('nan')):.1f} |")
    out = Path(args.out).resolve() if args.out else ROOT / "bench" / "results" / f"episode{'.quick' if args.quick else ''}.json"
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "episode",
                     "command": " ".join(["bench/episode.py"] + sys.argv[1:]),
                     "machine": _machine(torch),
                     "timing": "CPU time of the (single) thread, time.thread_time",
                     "autonomy": autonomy, "stages_ms_cpu_mean": mean, "total_ms_cpu_mean": total,
                     "fps_cpu_mean": 1000 / total, "rows": rows, "detector_resolution": det_rows,
                     "detector_resolution_from_bench_detector": h7_rows})
    print(f"wrote {out}")
    return 0


def _machine(torch) -> dict:
    """The result files' ``machine`` record (Python, platform, CPUs, torch threads, load)."""
    return {"python": platform.python_version(), "platform": platform.platform(),
            "processor": platform.processor(), "cpus": os.cpu_count(),
            "cores_used": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "torch_threads": torch.get_num_threads(),
            "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None}


def bench_b(names, quick: bool) -> int:
    """(c): Autonomy-B's stages and Autonomy-A's on the same scenes, one core."""
    import torch

    lib = default_library()
    rows = {"B": [], "A": []}
    for name in names:
        scene = load_scene(ROOT / "scenes" / "highway" / f"{name}.json.gz")
        world = world_from_scene(scene, lib)
        for autonomy in ("B", "A"):
            stack = make_stack(autonomy)
            run_episode(scene, stack, seconds=1.0, world=world)  # warm-up (imports, torch, caches)
            r = stage_times(scene, world, stack)
            r.pop("result")
            rows[autonomy].append(r)
            ms = r["ms_cpu"]
            print(f"{name} {autonomy}: " + " ".join(f"{k} {ms[k]:.1f}" for k in (*STAGES, "other")) +
                  f" | total {r['ms_cpu_total']:.1f} ms CPU", flush=True)
    mean = {a: {k: float(np.mean([r["ms_cpu"][k] for r in rs])) for k in (*STAGES, "other")} for a, rs in rows.items()}
    a_pp = mean["A"]["detector"] + mean["A"]["tracker"] + mean["A"]["predictor"]
    b_occ = mean["B"]["occupancy"]
    print(f"\n(c) 5 s closed-loop episode, one core, CPU ms per frame (mean of {len(names)} scenes)\n")
    print("| stack | perception + prediction | of which | planner | lidar | total |")
    print("|---|---|---|---|---|---|")
    print(f"| Autonomy-A | {a_pp:.1f} | detector {mean['A']['detector']:.1f}, tracker {mean['A']['tracker']:.1f}, "
          f"predictor {mean['A']['predictor']:.1f} | {mean['A']['planner']:.1f} | {mean['A']['lidar']:.1f} | "
          f"{float(np.mean([r['ms_cpu_total'] for r in rows['A']])):.1f} |")
    print(f"| Autonomy-B | {b_occ:.1f} | occupancy model (input, encoder, planner's queries) | {mean['B']['planner']:.1f} | "
          f"{mean['B']['lidar']:.1f} | {float(np.mean([r['ms_cpu_total'] for r in rows['B']])):.1f} |")
    print(f"\nB's occupancy model / A's detector + tracker + predictor: {b_occ / a_pp:.2f}")
    out = ROOT / "bench" / "results" / f"episode.B{'.quick' if quick else ''}.json"
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "episode-autonomy-b",
                     "command": " ".join(["bench/episode.py"] + sys.argv[1:]),
                     "machine": _machine(torch),
                     "timing": "CPU time of the (single) thread, time.thread_time; machine shared with other jobs",
                     "stages_ms_cpu_mean": mean, "a_detector_tracker_predictor_ms": a_pp, "b_occupancy_ms": b_occ,
                     "b_over_a": b_occ / a_pp, "rows": rows})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
