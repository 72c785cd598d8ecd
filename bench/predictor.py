"""Predictor benchmark: time per frame against accuracy for the learned predictor and the two
baselines, end to end in the map frame (noisy ground-truth detections -> tracker -> predict).

Scenes are training-split scenes with seeds used neither for training nor for the training
report's held-out set (900 000 100 + i), so the numbers are out of sample. Every 5th frame from
frame 10 is predicted; each track matched to a ground-truth actor (<= 3 m) is scored over the
6 s horizon (steps where the actor is known).

    .venv/bin/python bench/predictor.py [--quick] [--scenes N]

Prints a table and writes bench/results/predictor[.quick].json.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

SEED0 = 900_000_100


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 scenes")
    ap.add_argument("--scenes", type=int, default=None)
    args = ap.parse_args()
    n_scenes = args.scenes or (3 if args.quick else 12)

    import torch

    torch.set_num_threads(1)
    from adv3d_runner.autonomy.baselines import ConstantVelocityPredictor, LaneFollowingPredictor
    from adv3d_runner.autonomy.predictor import load_predictor
    from adv3d_runner.metrics.prediction import prediction_metrics
    from adv3d_runner.scene.generate import generate_scene
    from adv3d_runner.scene.lanemap import LaneMap
    from adv3d_runner.training.predictor_data import tracked_evaluation_frames

    learned = load_predictor(threads=1)
    models = {"constant_velocity": ConstantVelocityPredictor(), "lane_following": LaneFollowingPredictor(),
              f"learned_k{learned.num_modes}": learned}
    preds = {k: [] for k in models}
    times = {k: [] for k in models}
    tracks_per_frame = []
    gts, vals = [], []
    for i in range(n_scenes):
        seed = SEED0 + i
        scene = generate_scene(seed, "train")
        lane_map = LaneMap.from_scene(scene)
        for model in models.values():
            model.reset(lane_map)
        frames = tracked_evaluation_frames(scene, np.random.default_rng(seed), frames=range(scene.frames - 60),
                                           every=5, miss=0.05)
        for _, tracks, rows, future, future_valid in frames:
            tracks_per_frame.append(len(tracks))
            for name, model in models.items():
                t0 = time.perf_counter()
                p = model.predict(tracks)
                times[name].append(time.perf_counter() - t0)
                preds[name].append(p.trajectories[rows])
            gts.append(future)
            vals.append(future_valid)
    gt, val = np.concatenate(gts), np.concatenate(vals)
    rows = []
    for name in models:
        m = prediction_metrics(np.concatenate(preds[name]), gt, val)
        t = np.asarray(times[name]) * 1e3
        rows.append({"model": name, "modes": int(np.concatenate(preds[name]).shape[1]),
                     "ms_per_frame_mean": float(t.mean()), "ms_per_frame_p95": float(np.percentile(t, 95)),
                     **m.as_dict()})
    print(f"{n_scenes} scenes, {len(tracks_per_frame)} frames, {np.mean(tracks_per_frame):.1f} tracks/frame "
          f"(max {max(tracks_per_frame)}), {rows[0]['n_actors']} scored track-frames, 1 thread")
    print(f"{'model':<20}{'K':>3}{'ms/frame':>10}{'p95 ms':>9}{'minADE':>9}{'meanADE':>9}{'minFDE':>9}{'meanFDE':>9}")
    for r in rows:
        print(f"{r['model']:<20}{r['modes']:>3}{r['ms_per_frame_mean']:>10.2f}{r['ms_per_frame_p95']:>9.2f}"
              f"{r['min_ade']:>9.3f}{r['mean_ade']:>9.3f}{r['min_fde']:>9.3f}{r['mean_fde']:>9.3f}")
    out = ROOT / "bench" / "results" / f"predictor{'.quick' if args.quick else ''}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"format": "adv3d-bench", "topic": "predictor", "command": "python bench/predictor.py " + " ".join(sys.argv[1:]),
           "machine": {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
                       "cpu": platform.processor() or platform.machine(), "threads": 1},
           "scenes": [SEED0, SEED0 + n_scenes - 1], "frames": len(tracks_per_frame),
           "tracks_per_frame_mean": float(np.mean(tracks_per_frame)), "results": rows}
    out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
