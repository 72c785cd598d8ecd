"""The detector's and the metrics' compiled loops (docs/detector.md) against another commit, per frame.

    .venv/bin/python bench/detector_kernels.py --base COMMIT [--seconds 5] [--repeats 3]

Records the LiDAR frames and the episode results of one closed-loop Autonomy-A query on each
of ``highway-benchmark-000000``, ``-000010`` and ``-000041`` (this code), then replays them
through this code and through ``COMMIT``'s package (``git archive`` into a temporary folder,
imported under another name, so both run in this process), interleaved frame by frame in
alternating order, and reports CPU time of this thread (``time.thread_time``; one core, one
thread per library) per frame:

* ``voxelize``: the BEV grid of the frame's points;
* ``network``: the torch forward of the shipped model (this code only: unchanged);
* ``decode``: candidates, boxes and rotated NMS from the network's outputs;
* ``objective + metrics``: ``episode_evaluation`` + ``episode_objective`` + ``episode_metrics``
  of the episode (the attack's per-query scoring), divided by its frames.

Checks that both versions give the same bytes (grids, detections; objective and metrics as
JSON). Writes ``bench/results/detector_kernels.json``.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import limit_threads, machine_info  # noqa: E402

SCENES = ("000000", "000010", "000041")
BASE_PKG = "adv3d_base_pkg"


def base_package(commit: str):
    """``commit``'s ``adv3d_runner`` imported as :data:`BASE_PKG` (its imports are relative)."""
    tmp = Path(tempfile.mkdtemp(prefix="adv3d-base-"))
    tar = subprocess.run(["git", "archive", commit, "adv3d_runner"], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tmp)], input=tar, check=True)
    (tmp / "adv3d_runner").rename(tmp / BASE_PKG)
    sys.path.insert(0, str(tmp))
    return {m: importlib.import_module(f"{BASE_PKG}.{m}") for m in ("autonomy.detector", "sim.evaluate", "attack.objective")}


def this_package():
    return {m: importlib.import_module(f"adv3d_runner.{m}") for m in ("autonomy.detector", "sim.evaluate", "attack.objective")}


def record(seconds: float):
    """Frames (points) and episodes (result, lanes, weights) of one closed-loop query per scene."""
    import adv3d_runner.sim.evaluate as ev
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import SceneWorkspace

    frames, episodes = [], []
    orig_eval = ev.episode_evaluation
    for scene in SCENES:
        ws = SceneWorkspace(str(ROOT / "scenes" / "highway" / f"highway-benchmark-{scene}.json.gz"),
                            QuerySettings(autonomy="A", seconds=seconds))
        det = ws.stack.detector
        orig_detect = det.detect

        def grab(points, *a, **k):
            frames.append(np.array(points))
            return orig_detect(points, *a, **k)

        def grab_eval(result, *a, **k):
            episodes.append((result, ws.scene.lanes, ws.weights))
            return orig_eval(result, *a, **k)

        det.detect, ev.episode_evaluation = grab, grab_eval
        try:
            ws.evaluate(np.random.default_rng(1).random(5), True)
        finally:
            del det.detect
            ev.episode_evaluation = orig_eval
    return frames, episodes, det


def score_episode(pkg, result, lanes, weights) -> str:
    ev, obj = pkg["sim.evaluate"], pkg["attack.objective"]
    e = ev.episode_evaluation(result)
    o = obj.episode_objective(result, weights, e)
    m = ev.episode_metrics(result, lanes, evaluation=e)
    for k in ("format", "version", "ms_per_frame", "fps"):
        m.pop(k, None)
    return json.dumps([o.total, o.components(), m], sort_keys=True, default=repr)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="commit whose detector / boxes / metrics are compared")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--repeats", type=int, default=3, help="timed passes over the recorded frames")
    args = ap.parse_args()
    limit_threads()
    frames, episodes, det = record(args.seconds)
    pkgs = {"base": base_package(args.base), "this": this_package()}
    cfg = det.cfg
    stages = ("voxelize", "network", "decode", "objective + metrics")
    t = {name: {s: [] for s in stages} for name in pkgs}
    differ = dict.fromkeys(("voxelize", "decode", "objective + metrics"), 0)
    clock = time.thread_time
    for rep in range(args.repeats + 1):  # pass 0: warm-up (compilation, caches), not counted
        for j, pts in enumerate(frames):
            names = ("base", "this") if (j + rep) % 2 else ("this", "base")
            out = {}
            for name in names:
                D = pkgs[name]["autonomy.detector"]
                t0 = clock()
                grid = D.voxelize(pts, cfg)
                t1 = clock()
                score, box = det._forward(grid[None])
                t2 = clock()
                d = D.decode(score[0], box[0], cfg)
                t3 = clock()
                out[name] = (grid.tobytes(), d.boxes.tobytes() + d.scores.tobytes())
                if rep:
                    for s, v in zip(stages, (t1 - t0, t2 - t1, t3 - t2)):
                        t[name][s].append(v)
            differ["voxelize"] += out["base"][0] != out["this"][0]
            differ["decode"] += out["base"][1] != out["this"][1]
        for j, (result, lanes, weights) in enumerate(episodes):
            names = ("base", "this") if (j + rep) % 2 else ("this", "base")
            got = {}
            for name in names:
                t0 = clock()
                got[name] = score_episode(pkgs[name], result, lanes, weights)
                if rep:
                    t[name]["objective + metrics"].append((clock() - t0) / result.frames)
            differ["objective + metrics"] += got["base"] != got["this"]

    def summary(v):
        return {"mean": 1e3 * float(np.mean(v)), "median": 1e3 * float(np.median(v))}

    doc = {"format": "adv3d.bench", "topic": "detector_kernels",
           "command": " ".join([Path(sys.executable).name] + sys.argv), "machine": machine_info("numpy", "torch", "numba"),
           "base": args.base, "scenes": [f"highway-benchmark-{s}" for s in SCENES], "seconds": args.seconds,
           "frames": len(frames), "episodes": len(episodes), "repeats": args.repeats,
           "differing_passes": differ,
           "ms_per_frame": {name: {s: summary(v) for s, v in t[name].items()} for name in t},
           "ms_per_frame_total_mean": {name: 1e3 * sum(float(np.mean(v)) for v in t[name].values()) for name in t}}
    out = ROOT / "bench" / "results" / "detector_kernels.json"
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps({k: doc[k] for k in ("frames", "differing_passes", "ms_per_frame", "ms_per_frame_total_mean")}, indent=1))
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
