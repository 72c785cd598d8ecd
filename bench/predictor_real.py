"""Predictors on real traffic: the held-out table of ``adv3d train predictor`` for any model
folders, on the real scenes' samples (``adv3d_runner.training.predictor_data.real_scene_samples``:
noisy boxes -> tracker -> features, recorded frames only), per part of ``scenes/real/``.

Used to compare the predictor shipped before the real-traffic tuning (generated traffic only; its folder is
``git show fa10c6e:assets/models/predictor/...``) with the one trained on generated + real
traffic. On the train part the second one has seen the very samples (a memorisation check, not
a result); the benchmark part is held out from both.

    .venv/bin/python bench/predictor_real.py [--parts benchmark,train,fresh] [--out NAME] NAME=DIR [NAME=DIR ...]

``fresh`` is ``scenes/real-fresh/`` (recordings 10-18, docs/benchmark.md), held out from every
model. Writes ``bench/results/predictor_real.json`` (``--out NAME``: ``bench/results/NAME.json``).
"""
from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", metavar="NAME=DIR", help="model folders (default shipped=assets/models/predictor)")
    ap.add_argument("--parts", default="benchmark,train", help="comma-separated: benchmark, train, fresh")
    ap.add_argument("--out", default="predictor_real", help="result file stem under bench/results/")
    args = ap.parse_args()
    if any("=" not in m for m in args.models):
        ap.error("models are given as NAME=DIR")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not parts or set(parts) - {"benchmark", "train", "fresh"}:
        ap.error("--parts takes benchmark, train and/or fresh")
    models = dict(arg.split("=", 1) for arg in args.models) or {"shipped": str(ROOT / "assets" / "models" / "predictor")}
    import torch

    torch.set_num_threads(1)
    from adv3d_runner.autonomy.predictor import load_predictor, no_reversing
    from adv3d_runner.fileio import write_json
    from adv3d_runner.scene.real import load_fresh_part, load_real_split
    from adv3d_runner.training.predictor_data import BASELINES, build_real_dataset, per_sample_metrics

    split = load_real_split()
    out = {}
    for part in parts:
        paths = load_fresh_part(split=split).paths() if part == "fresh" else split.paths(part)
        held = build_real_dataset(paths, desc=f"real {part}")
        full = held["future_valid"].all(axis=1)
        rows = {}
        for name, folder in models.items():
            model = load_predictor(folder)
            traj, probs = model.predict_local(held["features"], held["prior"], held["path"])
            # as LearnedPredictor.predict does (no reversing): what the planner receives
            m = per_sample_metrics(no_reversing(traj), probs, held["future"].astype(np.float64), held["future_valid"])
            rows[name] = m
        for b in BASELINES:
            rows[b] = held[f"{b}_metrics"]
        out[part] = {"n_samples": {"full_6s": int(full.sum()), "all": int(len(full))},
                     "min_ade": {k: {"full_6s": float(v[full, 0].mean()), "all": float(v[:, 0].mean())}
                                 for k, v in rows.items()},
                     "mean_ade": {k: {"full_6s": float(v[full, 1].mean()), "all": float(v[:, 1].mean())}
                                  for k, v in rows.items()}}
        print(f"\nreal {part} part ({int(full.sum())} samples known for 6 s, {len(full)} for >= 3 s)")
        print("| model | minADE (6 s known) | meanADE (6 s known) | minADE (>= 3 s) |")
        print("|---|---|---|---|")
        for k in rows:
            print(f"| {k} | {out[part]['min_ade'][k]['full_6s']:.3f} | {out[part]['mean_ade'][k]['full_6s']:.3f} | "
                  f"{out[part]['min_ade'][k]['all']:.3f} |")
    path = ROOT / "bench" / "results" / f"{args.out}.json"
    write_json(path, {"format": "adv3d-bench", "version": 1, "topic": "predictor_real",
                      "command": " ".join(["bench/predictor_real.py"] + sys.argv[1:]), "models": models,
                      "machine": {"python": platform.python_version(), "platform": platform.platform()},
                      "parts": out})
    print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
