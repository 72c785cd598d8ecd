"""BEV detector: input resolution (cell size) against AP and milliseconds per frame.

    .venv/bin/python bench/detector.py [--quick] [--no-train]

Pinned to ONE core (torch 1 thread, OMP 1 thread), as the detector runs inside the episode.

(a) For each cell size in ``RESOLUTIONS`` a model trained with the SAME short recipe
    (``adv3d train detector --quick``: 24 training scenes x 10 frames, 4 epochs; cached under
    ``~/.cache/adv3d/detector-bench/res-<r>``, trained here unless ``--no-train``), plus the
    shipped model (``assets/models/detector``, full recipe, see its training_report.json) and any
    full-recipe model at another cell size found as ``~/.cache/adv3d/detector-bench/full-<r>``
    (made with ``adv3d train detector --resolution R --out ...``; not trained by this script).
    Each is evaluated on the same held-out training-split scenes (seeds 900000 + [0, M)):
    AP / recall at BEV IoU 0.5, vehicles 0-50 m ahead and |y| <= 20 m with >= 5 LiDAR returns
    (``adv3d_runner.training.detector_train.evaluate_detector``, detections above 0.05), and
    timed per frame at the model's operating score threshold: CPU time (``time.thread_time``)
    of the whole ``detect`` call and of its steps (median over the frames).
(b) The shipped model on bundled benchmark scenes (evaluation only, never trained on):
    AP / recall on 5 frames of each of the first N benchmark scenes.

Functions :func:`time_detector` and :func:`resolution_rows` can be imported by the episode
benchmark. Writes ``bench/results/detector[.quick].json`` with machine info and the command.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.autonomy.detector import DEFAULT_MODEL_DIR, BevDetector, load_detector, model_info  # noqa: E402
from adv3d_runner.training.detector_data import VAL_SEED0, FrameSet, make_frames, simulate_scene_frames  # noqa: E402
from adv3d_runner.training.detector_train import EVAL_THRESHOLD, evaluate_detector, machine_info  # noqa: E402
from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.progress import set_quiet  # noqa: E402

RESOLUTIONS = (0.2, 0.25, 0.4)
CLOCK = time.thread_time
BENCH_CACHE = Path.home() / ".cache" / "adv3d" / "detector-bench"


def time_detector(det: BevDetector, frames: list[np.ndarray], warmup: int = 2) -> dict:
    """CPU ms per frame of ``det.detect`` (median and mean) and its steps (median).

    Args:
        det: a detector (set to one thread by the caller / ``load_detector``).
        frames: (P, 3|4) ego-frame point arrays.
    """
    det.clock = CLOCK  # per-step CPU time too
    for p in frames[:warmup]:
        det.detect(p)
    total, steps = [], {"voxelize": [], "network": [], "decode": []}
    for p in frames:
        c0 = CLOCK()
        det.detect(p)
        total.append(CLOCK() - c0)
        for k in steps:
            steps[k].append(det.timings.get(k, 0.0))
    out = {"ms_median": 1000 * float(np.median(total)), "ms_mean": 1000 * float(np.mean(total)),
           "frames": len(total)}
    out.update({f"ms_{k}_median": 1000 * float(np.median(v)) for k, v in steps.items()})
    return out


def _train_quick(res: float, out: Path) -> float:
    cmd = [sys.executable, "-m", "adv3d_runner.cli", "--quiet", "train", "detector", "--quick",
           "--resolution", f"{res:g}", "--out", str(out)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return time.perf_counter() - t0


def resolution_rows(val: FrameSet, models: list[tuple[str, Path]]) -> list[dict]:
    """AP/recall on ``val`` and CPU ms per frame for each (label, model folder)."""
    frames = [val.frame_points(f) for f in range(len(val))]
    rows = []
    for label, folder in models:
        det = load_detector(folder, threads=1)
        info = model_info(folder)
        report = folder / "training_report.json"
        train_min = None
        if report.is_file():
            import json
            train_min = round(json.loads(report.read_text())["seconds"]["total"] / 60, 1)
        dets = [det.detect(p, score_threshold=EVAL_THRESHOLD) for p in frames]  # AP: the whole PR curve
        m = evaluate_detector(det, val, detections=dets)
        t = time_detector(det, frames[:: max(1, len(frames) // 60)])
        rows.append({"model": label, "resolution": det.cfg.resolution, "grid": list(det.cfg.grid_shape),
                     "recipe": "quick" if info.get("training", {}).get("quick") else "full",
                     "train_frames": info.get("data", {}).get("train_frames"),
                     "epochs": info.get("training", {}).get("epochs_run"), "train_minutes_wall": train_min,
                     "ap": m["ap"], "recall": m["recall"], "n_gt": m["n_gt"], **t})
    return rows


def benchmark_scene_frames(n_scenes: int, frames_per_scene: int = 5) -> FrameSet:
    """Frames of the first ``n_scenes`` bundled benchmark scenes (evaluation only)."""
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import rig_from_scene, world_from_scene
    from adv3d_runner.shapes.library import load_library

    lib = load_library()
    sets = []
    for path in sorted((ROOT / "scenes" / "highway").glob("*.json.gz"))[:n_scenes]:
        scene = load_scene(path)
        frames = np.linspace(0, min(scene.frames, 50) - 1, frames_per_scene).astype(int)  # the 5 s episodes
        sets.append(simulate_scene_frames(scene, world_from_scene(scene, lib), rig_from_scene(scene), frames,
                                          seed=int(scene.source.details.get("seed", 0)) if scene.source.details else 0))
    return FrameSet.concat(sets)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer held-out and benchmark scenes")
    ap.add_argument("--no-train", action="store_true", help="use only models already trained")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    set_quiet(True)
    n_val = 10 if args.quick else 30
    val = make_frames(range(VAL_SEED0, VAL_SEED0 + n_val), 10)
    models, train_s = [], {}
    for res in RESOLUTIONS:
        folder = BENCH_CACHE / f"res-{res:g}"
        if not (folder / "config.json").is_file():
            if args.no_train:
                continue
            print(f"training the quick model at {res:g} m ...", flush=True)
            train_s[res] = _train_quick(res, folder)
        models.append((f"quick {res:g} m", folder))
    for folder in sorted(BENCH_CACHE.glob("full-*")):  # optional full-recipe models at other cell sizes
        if (folder / "config.json").is_file():
            models.append((f"full {folder.name[5:]} m", folder))
    if (DEFAULT_MODEL_DIR / "config.json").is_file():
        models.append(("shipped", DEFAULT_MODEL_DIR))
    rows = resolution_rows(val, models)
    print(f"\n(a) resolution vs AP and CPU ms per frame (one thread), {len(val)} held-out frames "
          f"({n_val} scenes), ROI 0-50 m ahead, |y| <= 20 m\n")
    print("| model | cell m | grid | recipe | AP@0.5 | recall | ms/frame (median CPU) | voxelize | network | decode | frames/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['model']} | {r['resolution']:g} | {r['grid'][0]}x{r['grid'][1]} | {r['recipe']} "
              f"({r['train_frames']} frames, {r['epochs']} ep, {r['train_minutes_wall']} min) | {r['ap']:.3f} | {r['recall']:.3f} | "
              f"{r['ms_median']:.1f} | {r['ms_voxelize_median']:.1f} | {r['ms_network_median']:.1f} | "
              f"{r['ms_decode_median']:.1f} | {1000 / r['ms_median']:.0f} |")
    bench_rows = []
    if (DEFAULT_MODEL_DIR / "config.json").is_file():
        n_b = 10 if args.quick else 30
        fs = benchmark_scene_frames(n_b)
        det = load_detector(DEFAULT_MODEL_DIR, threads=1)
        m = evaluate_detector(det, fs)
        bench_rows.append({"model": "shipped", "scenes": n_b, "frames": len(fs), **m})
        print(f"\n(b) shipped model on {n_b} bundled benchmark scenes x 5 frames (first 5 s; evaluation only): "
              f"AP@0.5 {m['ap']:.3f}, recall {m['recall']:.3f} ({m['n_gt']} vehicles in ROI)")
    out = ROOT / "bench" / "results" / ("detector.quick.json" if args.quick else "detector.json")
    write_json(out, {"command": "python bench/detector.py" + (" --quick" if args.quick else "")
                     + (" --no-train" if args.no_train else ""),
                     "machine": machine_info(), "pinned_cores": 1, "val_seeds": [VAL_SEED0, VAL_SEED0 + n_val - 1],
                     "quick_train_seconds": {f"{k:g}": v for k, v in train_s.items()},
                     "resolution_rows": rows, "benchmark_scenes": bench_rows})
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
