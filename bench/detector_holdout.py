"""BEV detector: AP on vehicles whose mesh was left out of training next to vehicles seen in it.

    .venv/bin/python bench/detector_holdout.py [--model LABEL=DIR ...] [--val-scenes 40] [--quick]

Every model is evaluated on the same held-out training-split scenes (seeds 900000 + [0, M),
10 frames each, actors drawing their meshes from EVERY asset of the bundled library: the frames
``adv3d train detector`` evaluates on, read from its cache), with the ground truth split by the
mesh each vehicle drew: the default hold-out (``detector_data.default_holdout``: 7 of the 38
assets) against the rest. Per group: AP@0.5 and recall in the ROI (0-50 m ahead, |y| <= 20 m,
>= 5 LiDAR returns), one matching for all boxes, false positives attributed to the vehicle they
overlap (``metrics.detection.grouped_average_precision``; ``ap_with_background_fp`` also charges
every group with the false positives that overlap no vehicle); recall at the operating score
threshold; and per held-out asset.

Default models: the hold-out model (``bench/results/detector_holdout``: trained on scenes that
never place the 7 meshes) and the shipped model (``assets/models/detector``: trained on the
whole library), so the same vehicles are compared unseen and seen. Add e.g.
``--model old=DIR`` for another model folder. Writes ``bench/results/detector_holdout.json``
(``.quick.json`` with ``--quick``: 8 scenes).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.autonomy.detector import load_detector  # noqa: E402
from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.shapes.library import library_fingerprint, load_library  # noqa: E402
from adv3d_runner.training.detector_data import VAL_SEED0, box_assets, default_holdout, make_frames  # noqa: E402
from adv3d_runner.training.detector_train import EVAL_THRESHOLD, evaluate_detector, machine_info  # noqa: E402

DEFAULT_MODELS = ("holdout=bench/results/detector_holdout", "shipped=assets/models/detector")
GROUPS = ("seen", "held_out")


def model_rows(label: str, folder: Path, val, assets: np.ndarray, holdout: list[str]) -> dict:
    """Grouped metrics of one model folder on the frames ``val`` (boxes' assets ``assets``)."""
    import json

    det = load_detector(folder)
    report_path = folder / "training_report.json"
    trained_holdout = None
    if report_path.is_file():
        rep = json.loads(report_path.read_text())
        trained_holdout = ((rep.get("data") or {}).get("holdout") or {}).get("assets")
    t0 = time.process_time()
    dets = det.detect_batch([val.frame_points(f) for f in range(len(val))], score_threshold=EVAL_THRESHOLD)
    detect_cpu = time.process_time() - t0
    groups = np.where(np.isin(assets, holdout), "held_out", "seen")
    full = evaluate_detector(det, val, detections=dets, box_groups=groups, groups=GROUPS)
    thr = det.cfg.score_threshold
    op = evaluate_detector(det, val, detections=[d.filter(d.scores >= thr) for d in dets], box_groups=groups,
                           groups=GROUPS)
    per_asset = evaluate_detector(det, val, detections=dets, box_groups=assets, groups=holdout)["by_group"]["groups"]
    return {"label": label, "folder": str(folder), "trained_without": trained_holdout,
            "ap": full["ap"], "recall": full["recall"], "n_gt": full["n_gt"],
            "groups": full["by_group"]["groups"], "n_fp_background": full["by_group"]["n_fp_background"],
            "operating_point": {"score_threshold": thr,
                                "groups": {g: {"recall": v["recall"], "n_tp": v["n_tp"], "n_fp": v["n_fp"]}
                                           for g, v in op["by_group"]["groups"].items()},
                                "n_fp_background": op["by_group"]["n_fp_background"]},
            "held_out_assets": per_asset, "detect_cpu_s": round(detect_cpu, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", action="append", default=None, metavar="LABEL=DIR",
                    help=f"model folder to evaluate (repeatable; default: {' '.join(DEFAULT_MODELS)})")
    ap.add_argument("--val-scenes", type=int, default=40)
    ap.add_argument("--frames-per-scene", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="8 held-out scenes")
    args = ap.parse_args()
    models = []
    for spec in args.model or DEFAULT_MODELS:
        label, sep, folder = spec.partition("=")
        if not sep or not label or not folder:
            ap.error(f"--model takes LABEL=DIR (got {spec!r})")
        models.append((label, Path(folder) if Path(folder).is_absolute() else ROOT / folder))
    n_val = 8 if args.quick else args.val_scenes
    lib = load_library()
    holdout = default_holdout(lib)
    t0 = time.time()
    val = make_frames(range(VAL_SEED0, VAL_SEED0 + n_val), args.frames_per_scene, library=lib, desc="held-out scenes")
    assets = box_assets(val, lib)
    rows = [model_rows(label, folder, val, assets, holdout) for label, folder in models]
    f = lambda x: "n/a" if x is None or not np.isfinite(x) else f"{x:.3f}"  # noqa: E731
    print(f"\n{len(val)} frames of {n_val} held-out scenes, every asset of the library; held-out meshes: "
          f"{', '.join(holdout)}\n")
    print("| model | held-out meshes in its training scenes | vehicles | in ROI | AP@0.5 | AP, background FP charged | "
          "recall | recall at operating threshold |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        for g in GROUPS:
            v, o = r["groups"][g], r["operating_point"]["groups"][g]
            trained_on = "no" if r["trained_without"] else "yes" if r["trained_without"] == [] else "not recorded"
            print(f"| {r['label']} | {trained_on} | {g.replace('_', ' ')} | {v['n_gt']} | "
                  f"{f(v['ap'])} | {f(v['ap_with_background_fp'])} | {f(v['recall'])} | {f(o['recall'])} |")
    print("\nper held-out asset, AP / recall (vehicles in ROI):\n")
    print("| asset | " + " | ".join(r["label"] for r in rows) + " |")
    print("|---|" + "---|" * len(rows))
    for a in holdout:
        cells = [f"{f(r['held_out_assets'][a]['ap'])} / {f(r['held_out_assets'][a]['recall'])} "
                 f"({r['held_out_assets'][a]['n_gt']})" for r in rows]
        print(f"| {a} | " + " | ".join(cells) + " |")
    doc = {"format": "adv3d-bench", "version": 1, "topic": "detector_holdout",
           "command": " ".join(["bench/detector_holdout.py"] + sys.argv[1:]), "machine": machine_info(),
           "note": "2-core VM shared with other jobs; detect_cpu_s = process CPU time of the detection pass",
           "val_seeds": [VAL_SEED0, VAL_SEED0 + n_val - 1], "frames": len(val),
           "library_fingerprint": library_fingerprint(lib), "holdout": holdout, "groups": list(GROUPS),
           "rows": rows, "wall_s": round(time.time() - t0, 1)}
    out = ROOT / "bench" / "results" / ("detector_holdout.quick.json" if args.quick else "detector_holdout.json")
    write_json(out, _finite(doc))
    print(f"\nwrote {out.relative_to(ROOT)}")
    return 0


def _finite(obj):
    """JSON without NaN (null instead)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


if __name__ == "__main__":
    raise SystemExit(main())
