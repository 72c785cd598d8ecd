"""``adv3d train ...``: train the learned autonomy models.

This module defines the ``train`` command group, ``adv3d train detector`` (data from
:mod:`.detector_data`, training and evaluation in :mod:`.detector_train`), ``adv3d train
predictor`` (the anchored model of :mod:`.predictor_anchored` by default, the older free one of
:mod:`.predictor_train` with ``--model free``) and ``adv3d train occupancy`` (Autonomy-B's model:
:mod:`.occupancy_data`, :mod:`.occupancy_train`). Every command takes ``--device cpu|cuda|auto``
(:mod:`.device`; cpu by default, which the shipped weights were trained on). torch is imported
inside the handlers only.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def register(subparsers) -> None:
    train = subparsers.add_parser("train", help="train the learned autonomy models (detector, predictor, occupancy)",
                                  description="Train the learned autonomy models on data the simulator makes "
                                              "from training-split scenes (never the benchmark scenes).")
    train_sub = train.add_subparsers(dest="train_command", metavar="MODEL")
    train.set_defaults(func=lambda args: (train.print_help(), 2)[1])
    add_train_detector(train_sub)
    add_train_predictor(train_sub)
    add_train_occupancy(train_sub)


def _device_option(p) -> None:
    from .device import DEVICES

    p.add_argument("--device", choices=DEVICES, default="cpu",
                   help="where to train: cpu (default; the shipped weights, reproducible byte for byte), cuda "
                        "(a GPU), auto (cuda when one is visible, else cpu)")


def add_train_detector(train_sub) -> None:
    from .. import argtypes as at
    from .seeds import TRAIN_SEED0, VAL_SEED0

    p = train_sub.add_parser(
        "detector", help="train the PIXOR-like BEV LiDAR detector",
        description="Simulate LiDAR frames of training-split scenes (seeds 100000 + [0, N)), train the BEV "
                    "detector, evaluate AP/recall at BEV IoU 0.5 on held-out scenes (seeds 900000 + [0, M)), "
                    "and write weights, config.json, training_report.json and loss_curves.png to --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenes", type=at.integer(1, VAL_SEED0 - TRAIN_SEED0), default=140,
                   help="training scenes (seeds 100000 + [0, N): below the held-out seeds)")
    p.add_argument("--val-scenes", type=at.positive_int, default=40, help="held-out evaluation scenes")
    p.add_argument("--frames-per-scene", type=at.positive_int, default=10, help="LiDAR frames per scene")
    p.add_argument("--epochs", type=at.positive_int, default=10)
    p.add_argument("--batch", type=at.positive_int, default=8)
    p.add_argument("--lr", type=at.positive, default=2e-3)
    p.add_argument("--resolution", type=at.number(0.01, 10.0), default=0.25,
                   help="BEV cell size, m (0.25: assets/models/detector; 0.4: assets/models/detector-fast, --autonomy A-fast)")
    p.add_argument("--min-points", type=at.positive_int, default=5, help="LiDAR returns for a vehicle to count as ground truth")
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--threads", type=at.positive_int, default=1, help="torch threads for training")
    p.add_argument("--time-limit", type=at.positive, default=38 * 60,
                   help="stop training after the epoch that passes this many seconds (data included); the "
                        "number of epochs then depends on the machine's load: for a reproducible model give a "
                        "limit all --epochs fit in (the report records epochs_run)")
    p.add_argument("--cache", default=None, help="frame cache folder (default ~/.cache/adv3d/detector)")
    p.add_argument("--out", default="assets/models/detector", help="model folder")
    p.add_argument("--library", default=None,
                   help="vehicle library the scenes' actors draw their meshes from (default: the bundled one; "
                        "'none': boxes)")
    p.add_argument("--holdout-assets", default="none", metavar="none|default|ID,ID,...",
                   help="vehicle meshes left out of training (training scenes never place them; held-out "
                        "scenes use every asset): 'default' = about 20%% of each class's assets "
                        "(detector_data.default_holdout), or asset ids; AP is then also reported separately "
                        "for vehicles whose mesh was seen in training and vehicles left out")
    p.add_argument("--quick", action="store_true",
                   help="small recipe for smoke tests and the resolution benchmark (24 scenes, 4 epochs)")
    _device_option(p)
    p.set_defaults(func=_train_detector)


def _train_detector(args) -> int:
    import time

    import numpy as np

    t0 = time.perf_counter()
    cpu0 = time.process_time()

    from ..autonomy.detector import DetectorConfig, save_detector
    from ..errors import ConfigError
    from ..fileio import write_json
    from ..progress import status
    from .detector_data import (TRAIN_SEED0, VAL_SEED0, box_assets, default_holdout, make_frames, resolve_holdout,
                                without_assets)
    from .detector_train import evaluate_detector, machine_info, plot_losses, subset, train_detector
    from .device import device_info, resolve_device

    device = resolve_device(getattr(args, "device", "cpu"))
    if args.quick:
        args.scenes = min(args.scenes, 24)
        args.val_scenes = min(args.val_scenes, 8)
        args.epochs = min(args.epochs, 4)
    if args.scenes < 1 or args.epochs < 1 or args.val_scenes < 0:
        raise ConfigError("--scenes and --epochs must be >= 1, --val-scenes >= 0")
    if args.scenes > VAL_SEED0 - TRAIN_SEED0:
        raise ConfigError(f"--scenes must be <= {VAL_SEED0 - TRAIN_SEED0} (held-out seeds start at {VAL_SEED0})")
    cfg = DetectorConfig(resolution=args.resolution)
    out = Path(args.out)
    status(f"detector: resolution {cfg.resolution} m, grid {cfg.grid_shape}, {args.scenes} training scenes x "
           f"{args.frames_per_scene} frames, {args.val_scenes} held-out scenes")
    train_seeds = list(range(TRAIN_SEED0, TRAIN_SEED0 + args.scenes))
    val_seeds = list(range(VAL_SEED0, VAL_SEED0 + args.val_scenes))
    t_data = time.perf_counter()
    cache_stats: dict = {}
    from ..shapes.library import library_fingerprint, resolve_library

    library = resolve_library(args.library)
    try:
        holdout = resolve_holdout(args.holdout_assets, library)
    except ConfigError as exc:  # ids the library lacks, or a class left without assets
        from ..errors import UsageError

        raise UsageError(str(exc)) from None
    # training scenes draw from the library without the held-out meshes; held-out scenes from all
    train_library = without_assets(library, holdout) if holdout else library
    if holdout:
        status(f"vehicle hold-out: {len(holdout)} of {len(library.assets)} assets never placed in training scenes: "
               + ", ".join(holdout))
    train = make_frames(train_seeds, args.frames_per_scene, library=train_library, cache_dir=args.cache,
                        desc="training scenes", stats=cache_stats)
    val = make_frames(val_seeds, args.frames_per_scene, library=library, cache_dir=args.cache,
                      desc="held-out scenes", stats=cache_stats)
    data_s = time.perf_counter() - t_data
    status(f"data: {len(train)} training frames, {len(val)} held-out frames ({data_s:.0f} s)")
    limit = None if args.time_limit is None else max(0.0, args.time_limit - (time.perf_counter() - t0))
    t_train = time.perf_counter()
    det, hist = train_detector(train, val, cfg, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed,
                               min_points=args.min_points, threads=args.threads, log=status, time_limit_s=limit,
                               device=device)
    train_s = time.perf_counter() - t_train
    t_eval = time.perf_counter()
    metrics, operating, by_vehicle = {}, {}, {}
    if len(val):
        from .detector_train import EVAL_THRESHOLD
        dets = det.detect_batch([val.frame_points(f) for f in range(len(val))], score_threshold=EVAL_THRESHOLD)
        # each ground-truth box's mesh: seen in training, or left out (the hold-out)
        assets = box_assets(val, library) if library is not None else np.full(len(val.boxes), "", dtype=str)
        seen = np.where(np.isin(assets, holdout), "held_out", "seen")
        metrics = evaluate_detector(det, val, min_points=args.min_points, detections=dets,
                                    box_groups=seen, groups=("seen", "held_out"))
        thr = cfg.score_threshold
        op = evaluate_detector(det, val, min_points=args.min_points,
                               detections=[d.filter(d.scores >= thr) for d in dets],
                               box_groups=seen, groups=("seen", "held_out"))
        operating = {"score_threshold": thr, "recall": op["recall"],
                     "precision": op["n_tp"] / op["n_det"] if op["n_det"] else None,
                     "n_det": op["n_det"], "n_tp": op["n_tp"], "n_gt": op["n_gt"], "by_group": op["by_group"]}
        per_asset = evaluate_detector(det, val, min_points=args.min_points, detections=dets, box_groups=assets,
                                      groups=sorted(set(assets.tolist())))["by_group"]
        by_vehicle = {"rule": "ground-truth boxes grouped by the asset their actor drew (held-out scenes use every "
                              "asset); per group: metrics.detection.grouped_average_precision",
                      "assets": {a: dict(g, held_out=a in holdout) for a, g in per_asset["groups"].items()}}
    train_metrics = evaluate_detector(det, subset(train, 200), min_points=args.min_points)
    eval_s = time.perf_counter() - t_eval
    status(f"held-out AP@0.5 {metrics.get('ap', float('nan')):.4f} recall {metrics.get('recall', float('nan')):.4f}"
           f" ({metrics.get('n_gt', 0)} vehicles in ROI); training frames AP {train_metrics['ap']:.4f}")
    if holdout and metrics:
        for name, g in metrics["by_group"]["groups"].items():
            status(f"  vehicles {name.replace('_', ' ')} in training: AP@0.5 {g['ap']:.4f} recall {g['recall']:.4f} "
                   f"({g['n_gt']} in ROI)")
    command = "adv3d " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv and "adv3d" in sys.argv[0] \
        else "adv3d train detector " + _args_line(args)
    recipe = {"split": "train", "train_seeds": [train_seeds[0], train_seeds[-1]],
              "val_seeds": [val_seeds[0], val_seeds[-1]] if val_seeds else [],
              "frames_per_scene": args.frames_per_scene,
              "library": args.library or "bundled benign vehicle library",
              "library_fingerprint": library_fingerprint(library) if library is not None else None,
              "actor_meshes": "drawn per actor from every asset of its class (scene.actors.assign_assets)",
              "holdout": {"assets": holdout, "n_assets": len(holdout),
                          "n_library_assets": len(library.assets) if library is not None else 0,
                          "rule": ("default_holdout: per class min(n - 1, round-half-up(0.2 n)) assets, ranked by "
                                   "sha256 of the id" if holdout and holdout == default_holdout(library)
                                   else "given ids" if holdout else "none"),
                          "training_library_fingerprint": (library_fingerprint(train_library)
                                                           if train_library is not None else None),
                          "training_scenes": "draw from the library without the held-out assets",
                          "held_out_scenes": "draw from every asset of the library"},
              "lidar": "scene rig (HDL-64E at 1.73 m) with noise and ray drop", "min_points": args.min_points,
              "train_frames": len(train), "val_frames": len(val),
              "cache": {"scenes_from_cache": cache_stats.get("cached", 0),
                        "scenes_simulated": cache_stats.get("simulated", 0),
                        "simulate_s": round(cache_stats.get("simulate_s", 0.0), 1)}}
    training = {"epochs": args.epochs, "epochs_run": len(hist["epoch"]), "time_limit_s": args.time_limit,
                "stopped_early": bool(hist["stopped_early"]), "batch": args.batch, "lr": args.lr,
                "seed": args.seed, "threads": args.threads, "optimizer": "AdamW + one-cycle cosine",
                "augmentation": "random left/right mirror", "quick": bool(args.quick)}
    save_detector(det, out, {"seed": args.seed, "data": recipe, "training": training})
    total_s = time.perf_counter() - t0
    report = {
        "format": "adv3d-detector-training-report", "version": 1,
        "command": command,
        "machine": machine_info(),
        "seconds": {"data": round(data_s, 1), "train": round(train_s, 1), "eval": round(eval_s, 1),
                    "total": round(total_s, 1), "total_cpu_of_process": round(time.process_time() - cpu0, 1)},
        "note": "wall times on a 2-core VM shared with other jobs; training uses one torch thread",
        "device": device_info(device),
        "data": recipe, "training": training, "detector": cfg.to_dict(),
        "history": hist,
        "held_out": metrics, "held_out_operating_point": operating, "held_out_by_vehicle": by_vehicle,
        "training_frames_subset": train_metrics,
        "parameters": int(sum(p.numel() for p in det.net.parameters())),
    }
    write_json(out / "training_report.json", _finite(report))
    plot_losses(hist, out / "loss_curves.png",
                title=f"BEV detector {cfg.resolution} m: held-out AP@0.5 {metrics.get('ap', float('nan')):.3f}")
    status(f"wrote {out} ({total_s / 60:.1f} min)")
    return 0


def _args_line(args) -> str:
    parts = [f"--scenes {args.scenes}", f"--val-scenes {args.val_scenes}", f"--frames-per-scene {args.frames_per_scene}",
             f"--epochs {args.epochs}", f"--resolution {args.resolution}", f"--seed {args.seed}", f"--out {args.out}"]
    if args.holdout_assets and args.holdout_assets != "none":
        parts.append(f"--holdout-assets {args.holdout_assets}")
    if args.quick:
        parts.append("--quick")
    return " ".join(parts)


def _finite(obj):
    """JSON without NaN/inf (null instead)."""
    import math
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if hasattr(obj, "item") and not isinstance(obj, (str, bytes)):
        try:
            return _finite(obj.item())
        except (ValueError, AttributeError):
            pass
    return obj


#: The anchored predictor's training defaults (``predictor_anchored.train_anchored``; a test
#: checks they are its keyword defaults), kept here so that building the parser imports nothing heavy.
ANCHORED_DEFAULTS = {"epochs": 8, "gen_scenes": 160, "val_scenes": 10, "draws": 20, "seed": 100_000, "lr": 1e-3,
                     "hidden": 256, "residual_scale": 0.25}
#: The older free predictor's (version 1, :func:`.predictor_train.train_predictor`); ``--quick`` values in brackets.
FREE_DEFAULTS = {"epochs": 20, "val_scenes": 40, "lr": 2e-3, "seed": 100_000}
#: Options that only one model kind reads (argparse dest -> kind).
_ONLY = {"gen_scenes": "anchored", "draws": "anchored", "hidden": "anchored", "residual_scale": "anchored",
         "fixed_modes": "anchored", "val_recording": "anchored",
         "scenes": "free", "modes": "free", "batch": "free", "threads": "free", "time_limit": "free", "quick": "free",
         "no_cache": "free", "no_real": "free", "real_weight": "free"}
#: A folder holding one of these is a model: ``adv3d train predictor`` refuses to overwrite it without --force.
_MODEL_FILES = ("weights.pt", "config.json")


def add_train_predictor(train_subparsers) -> None:
    """Add ``predictor`` to the ``adv3d train`` subcommand group (docs/predictor.md)."""
    from .. import argtypes as at
    from ..autonomy.names import MODEL_DIRS

    a, f = ANCHORED_DEFAULTS, FREE_DEFAULTS
    p = train_subparsers.add_parser(
        "predictor", help="train the learned multi-modal trajectory predictor (the shipped anchored kind by default)",
        description="Train the trajectory predictor. --model anchored (default; the shipped kind, config version 2): "
                    "residuals on lane-following anchors, trained on every vehicle of the real train recordings "
                    "(--real's train part) and on generated training-split scenes; --model free (version 1, the "
                    "model shipped before): generated scenes' tracks through the tracker plus the real train part, "
                    "winner-takes-all over K modes. An existing model at --out is never overwritten without --force. "
                    "See docs/predictor.md.")
    p.add_argument("--model", choices=("anchored", "free"), default="anchored",
                   help="anchored (default): the kind Autonomy-A ships; free: the older version-1 model")
    p.add_argument("--out", default=str(MODEL_DIRS["predictor"]),
                   help=f"output folder (default {MODEL_DIRS['predictor']}, the shipped model: needs --force)")
    p.add_argument("--force", action="store_true", help="overwrite a model already at --out")
    p.add_argument("--real", default=None, metavar="SPLIT_JSON",
                   help="real scenes' split manifest (default scenes/real/split.json; its scene files, the CommonRoad "
                        "US-101 recordings converted by `adv3d scenes import-commonroad`, lie next to it): the train "
                        "part is trained on, the benchmark part is evaluated only")
    p.add_argument("--epochs", type=at.positive_int, default=None,
                   help=f"epochs (default {a['epochs']}; free: {f['epochs']}, 2 with --quick)")
    p.add_argument("--val-scenes", type=at.positive_int, default=None,
                   help=f"generated held-out scenes (default {a['val_scenes']}; free: {f['val_scenes']}, 3 with --quick)")
    p.add_argument("--seed", type=at.seed, default=a["seed"],
                   help="first training scene seed (>= 100000) and torch seed")
    p.add_argument("--lr", type=at.positive, default=None, help=f"learning rate (default {a['lr']}; free: {f['lr']})")
    p.add_argument("--cache", default=None, help="data cache root (default $ADV3D_CACHE or ~/.cache/adv3d)")
    g = p.add_argument_group("anchored model (--model anchored)")
    g.add_argument("--gen-scenes", type=at.positive_int, default=None,
                   help=f"generated training scenes (default {a['gen_scenes']})")
    g.add_argument("--draws", type=at.positive_int, default=None,
                   help=f"perception-noise draws of each train recording (default {a['draws']})")
    g.add_argument("--hidden", type=at.positive_int, default=None, help=f"hidden width (default {a['hidden']})")
    g.add_argument("--residual-scale", type=at.positive, default=None,
                   help=f"scale of the residuals on the anchors, m (default {a['residual_scale']})")
    g.add_argument("--fixed-modes", default=None, metavar="K,K,...",
                   help="modes kept at their anchors (no residual)")
    g.add_argument("--val-recording", type=at.integer(0, 1000), default=None,
                   help="leave this train recording out of training and report the model on it")
    g = p.add_argument_group("free model (--model free)")
    g.add_argument("--scenes", type=at.positive_int, default=None, help="training scenes (default 240; 8 with --quick)")
    g.add_argument("--modes", type=at.integer(3, 64), default=None, help="number of modes K (>= 3; default 6)")
    g.add_argument("--batch", type=at.positive_int, default=None, help="batch size (default 512)")
    g.add_argument("--threads", type=at.positive_int, default=None,
                   help="torch threads for training (default 1: on a shared 2-core machine 2 threads were 70x slower)")
    g.add_argument("--time-limit", type=at.positive, default=None,
                   help="minutes: stop after the epoch that passes this (data included; default 40)")
    g.add_argument("--no-cache", action="store_true", help="do not read or write the sample cache")
    g.add_argument("--quick", action="store_true", help="tiny run for smoke tests (few scenes, 2 epochs)")
    g.add_argument("--no-real", action="store_true", help="train on generated scenes only")
    g.add_argument("--real-weight", type=at.integer(1, 1000), default=None,
                   help="times each real training sample is repeated (default 10)")
    _device_option(p)
    p.set_defaults(func=_train_predictor)


def _check_predictor_args(args: argparse.Namespace) -> None:
    """Options of the other model kind: UsageError."""
    from ..errors import UsageError

    for dest, kind in _ONLY.items():
        value = getattr(args, dest, None)
        if kind != args.model and value not in (None, False):
            raise UsageError(f"--{dest.replace('_', '-')} applies to --model {kind} only (this is --model {args.model})")
    if args.model == "anchored" and getattr(args, "device", "cpu") != "cpu":
        raise UsageError(f"--device {args.device}: the anchored model trains on the cpu only (one torch thread)")


def _refuse_existing_model(out: Path, force: bool) -> None:
    """UsageError naming ``out`` when a model (weights.pt or config.json) is already there and not ``force``."""
    from ..errors import UsageError

    found = [n for n in _MODEL_FILES if (out / n).exists()]
    if found and not force:
        raise UsageError(f"--out {out}: a model is already there ({', '.join(found)}); give another --out, or "
                         f"--force to overwrite it")


def _command_line() -> str:
    """The ``adv3d ...`` command line when run from the ``adv3d`` script, else ''."""
    if not sys.argv:
        return ""
    prog = Path(sys.argv[0])
    ours = prog.name.startswith("adv3d") or (prog.parent.name == "adv3d_runner" and prog.name in ("cli.py", "__main__.py"))
    return ("adv3d " + " ".join(shlex.quote(a) for a in sys.argv[1:])) if ours else ""


def _train_predictor(args: argparse.Namespace) -> int:
    """``adv3d train predictor``: check the options, then train the anchored (default) or the free model."""
    from ..errors import ConfigError, UsageError
    from ..scene.generate import check_split
    from .predictor_train import HELD_OUT_OFFSET

    _check_predictor_args(args)
    anchored = args.model == "anchored"
    d = ANCHORED_DEFAULTS if anchored else FREE_DEFAULTS
    epochs = args.epochs if args.epochs is not None else (2 if args.quick else d["epochs"])
    val = args.val_scenes if args.val_scenes is not None else (3 if args.quick else d["val_scenes"])
    lr = args.lr if args.lr is not None else d["lr"]
    if anchored:
        scenes, what = (args.gen_scenes if args.gen_scenes is not None else d["gen_scenes"]), "--gen-scenes"
    else:
        scenes, what = (args.scenes if args.scenes is not None else (8 if args.quick else 240)), "--scenes"
    if scenes < 1 or val < 1 or epochs < 1:
        raise ConfigError(f"{what}, --val-scenes and --epochs must be >= 1")
    for s in (args.seed, args.seed + scenes - 1, args.seed + HELD_OUT_OFFSET, args.seed + HELD_OUT_OFFSET + val - 1):
        try:  # --seed and the scene counts that leave the training split: before any data is made
            check_split("train", s)
        except ConfigError as exc:
            raise UsageError(f"--seed {args.seed} {what} {scenes} --val-scenes {val}: {exc}") from None
    _refuse_existing_model(Path(args.out), args.force)
    from ..scene.real import load_real_split

    split = None
    if anchored or not args.no_real:
        if args.real and not Path(args.real).is_file():
            raise UsageError(f"--real {args.real}: no split manifest there (folder {Path(args.real).parent.resolve()}); "
                             "the default is scenes/real/split.json with the converted CommonRoad US-101 scenes")
        split = load_real_split(args.real)  # checked: each scene file it lists lies next to it
    if anchored:
        return _train_anchored(args, split, epochs=epochs, gen_scenes=scenes, val_scenes=val, lr=lr)
    return _train_free(args, split, scenes=scenes, val=val, epochs=epochs, lr=lr)


def _train_anchored(args: argparse.Namespace, split, *, epochs: int, gen_scenes: int, val_scenes: int,
                    lr: float) -> int:
    import os

    from ..errors import UsageError
    from .predictor_anchored import print_report, train_anchored

    d = ANCHORED_DEFAULTS
    try:
        fixed = tuple(int(k) for k in (args.fixed_modes or "").split(",") if k.strip())
    except ValueError:
        raise UsageError(f"--fixed-modes {args.fixed_modes!r}: expected comma-separated mode numbers") from None
    kw = {"epochs": epochs, "gen_scenes": gen_scenes, "val_scenes": val_scenes,
          "draws": args.draws if args.draws is not None else d["draws"], "seed": args.seed, "lr": lr,
          "hidden": args.hidden if args.hidden is not None else d["hidden"],
          "residual_scale": args.residual_scale if args.residual_scale is not None else d["residual_scale"]}
    spelled = " ".join(["adv3d train predictor", "--out", shlex.quote(str(args.out))]
                       + [f"--{k.replace('_', '-')} {v}" for k, v in kw.items()]
                       + ([f"--val-recording {args.val_recording}"] if args.val_recording is not None else [])
                       + ([f"--fixed-modes {','.join(map(str, fixed))}"] if fixed else [])
                       + ([f"--real {shlex.quote(args.real)}"] if args.real else []))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    rep = train_anchored(args.out, **kw, val_recording=args.val_recording, fixed_modes=fixed, cache=args.cache,
                         command=_command_line() or spelled, split=split)
    print_report(rep, args.out)
    return 0


def _train_free(args: argparse.Namespace, split, *, scenes: int, val: int, epochs: int, lr: float) -> int:
    from .device import resolve_device
    from .predictor_train import train_predictor

    real_train, real_eval, real_info = [], [], None
    if split is not None:
        real_train, real_eval = split.paths("train"), split.paths("benchmark")
        if args.quick:
            real_train, real_eval = real_train[:2], real_eval[:1]
        real_info = {"split": args.real or "scenes/real/split.json", "train_recordings": list(split.recordings["train"]),
                     "held_out_recordings": list(split.recordings["benchmark"])}
    train_predictor(scenes=scenes, val_scenes=val, epochs=epochs, seed=args.seed,
                    modes=args.modes if args.modes is not None else 6,
                    batch=args.batch if args.batch is not None else 512, lr=lr,
                    threads=args.threads if args.threads is not None else 1, cache=args.cache,
                    use_cache=not args.no_cache, out=args.out, command=_command_line(),
                    time_limit_min=args.time_limit if args.time_limit is not None else 40.0,
                    real_train=real_train, real_eval=real_eval,
                    real_weight=args.real_weight if args.real_weight is not None else 10, real_info=real_info,
                    device=resolve_device(getattr(args, "device", "cpu")))
    return 0


def add_train_occupancy(train_sub) -> None:
    """Add ``occupancy`` (Autonomy-B's implicit occupancy-and-flow model) to ``adv3d train``."""
    from .. import argtypes as at

    p = train_sub.add_parser(
        "occupancy", help="train Autonomy-B's implicit occupancy-and-flow model",
        description="Simulate LiDAR sweeps of training-split scenes (seeds 100000 + [0, N)) with query points and "
                    "their ground-truth occupancy and flow from the logs, train the implicit occupancy model, "
                    "evaluate it on held-out scenes (seeds 900000 + [0, M)) and write weights, config.json, "
                    "training_report.json and loss_curves.png to --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    from .seeds import TRAIN_SEED0, VAL_SEED0

    p.add_argument("--scenes", type=at.integer(1, VAL_SEED0 - TRAIN_SEED0), default=120,
                   help="training scenes (seeds 100000 + [0, N): below the held-out seeds)")
    p.add_argument("--val-scenes", type=at.integer(0, 100_000), default=20, help="held-out scenes")
    p.add_argument("--frames-per-scene", type=at.positive_int, default=10, help="samples per scene")
    p.add_argument("--queries", type=at.integer(2, 1_000_000), default=2048, help="query points per sample")
    p.add_argument("--epochs", type=at.positive_int, default=12)
    p.add_argument("--batch", type=at.positive_int, default=8)
    p.add_argument("--lr", type=at.positive, default=2e-3)
    p.add_argument("--seed", type=at.seed, default=0)
    p.add_argument("--threads", type=at.positive_int, default=1, help="torch threads for training")
    p.add_argument("--time-limit", type=at.positive, default=30 * 60,
                   help="stop training after the epoch that passes this many seconds (data included)")
    p.add_argument("--cache", default=None, help="sample cache folder (default ~/.cache/adv3d/occupancy)")
    p.add_argument("--out", default="assets/models/occupancy", help="model folder")
    p.add_argument("--quick", action="store_true", help="tiny recipe for smoke tests (6 scenes, 2 epochs)")
    _device_option(p)
    p.set_defaults(func=_train_occupancy)


def _train_occupancy(args) -> int:
    import time

    import numpy as np

    t0 = time.perf_counter()
    cpu0 = time.process_time()

    from ..autonomy.occupancy import OccupancyConfig, save_occupancy
    from ..errors import ConfigError
    from ..fileio import write_json
    from ..machine import machine_info
    from ..progress import status
    from .device import device_info, resolve_device
    from .occupancy_data import TRAIN_SEED0, VAL_SEED0, make_samples
    from .occupancy_train import evaluate_occupancy, plot_history, train_occupancy

    device = resolve_device(args.device)
    if args.quick:
        args.scenes = min(args.scenes, 6)
        args.val_scenes = min(args.val_scenes, 2)
        args.epochs = min(args.epochs, 2)
        args.frames_per_scene = min(args.frames_per_scene, 4)
        args.queries = min(args.queries, 512)
    if args.scenes < 1 or args.epochs < 1 or args.val_scenes < 0 or args.queries < 2:
        raise ConfigError("--scenes and --epochs must be >= 1, --val-scenes >= 0, --queries >= 2")
    if args.scenes > VAL_SEED0 - TRAIN_SEED0:
        raise ConfigError(f"--scenes must be <= {VAL_SEED0 - TRAIN_SEED0} (held-out seeds start at {VAL_SEED0})")
    cfg = OccupancyConfig()
    out = Path(args.out)
    status(f"occupancy: grid {cfg.grid_shape} at {cfg.resolution} m, sweeps {list(cfg.sweep_lags)}, "
           f"{args.scenes} training scenes x {args.frames_per_scene} samples x {args.queries} queries, "
           f"{args.val_scenes} held-out scenes, device {device}")
    train_seeds = list(range(TRAIN_SEED0, TRAIN_SEED0 + args.scenes))
    val_seeds = list(range(VAL_SEED0, VAL_SEED0 + args.val_scenes))
    t_data = time.perf_counter()
    stats: dict = {}
    train = make_samples(train_seeds, args.frames_per_scene, args.queries, cfg, cache_dir=args.cache,
                         desc="training scenes", stats=stats)
    val = make_samples(val_seeds, args.frames_per_scene, args.queries, cfg, cache_dir=args.cache,
                       desc="held-out scenes", stats=stats) if val_seeds else None
    data_s = time.perf_counter() - t_data
    status(f"data: {len(train)} training samples, {0 if val is None else len(val)} held-out ({data_s:.0f} s)")
    limit = None if args.time_limit is None else max(0.0, args.time_limit - (time.perf_counter() - t0))
    t_train = time.perf_counter()
    model, hist = train_occupancy(train, val, cfg, epochs=args.epochs, batch=args.batch, lr=args.lr, seed=args.seed,
                                  threads=args.threads, device=device, log=status, time_limit_s=limit)
    train_s = time.perf_counter() - t_train
    t_eval = time.perf_counter()
    held = evaluate_occupancy(model.net, val, cfg) if val is not None and len(val) else {}
    train_metrics = evaluate_occupancy(model.net, train.subset(np.linspace(0, len(train) - 1, min(len(train), 100)).astype(int)), cfg)
    eval_s = time.perf_counter() - t_eval
    status(f"held-out mAP {held.get('map') or float('nan'):.3f} Soft-IoU {held.get('soft_iou') or float('nan'):.3f} "
           f"EPE {held.get('epe') or float('nan'):.2f} m/s; training samples mAP {train_metrics['map'] or float('nan'):.3f}")
    command = "adv3d " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv and "adv3d" in sys.argv[0] \
        else ("adv3d train occupancy " + f"--scenes {args.scenes} --val-scenes {args.val_scenes} "
              f"--frames-per-scene {args.frames_per_scene} --queries {args.queries} --epochs {args.epochs} "
              f"--seed {args.seed} --device {args.device} --out {args.out}" + (" --quick" if args.quick else ""))
    recipe = {"split": "train", "train_seeds": [train_seeds[0], train_seeds[-1]],
              "val_seeds": [val_seeds[0], val_seeds[-1]] if val_seeds else [],
              "frames_per_scene": args.frames_per_scene, "queries_per_sample": args.queries,
              "library": "bundled benign vehicle library",
              "lidar": "scene rig (HDL-64E at 1.73 m) with noise and ray drop, sweeps at the logged ego poses",
              "train_samples": len(train), "val_samples": 0 if val is None else len(val),
              "cache": {"scenes_from_cache": stats.get("cached", 0), "scenes_simulated": stats.get("simulated", 0),
                        "simulate_s": round(stats.get("simulate_s", 0.0), 1)}}
    training = {"epochs": args.epochs, "epochs_run": len(hist["epoch"]), "batch": args.batch, "lr": args.lr,
                "seed": args.seed, "threads": args.threads, "optimizer": "AdamW + one-cycle cosine",
                "augmentation": "random left/right mirror, sweep dropout", "quick": bool(args.quick)}
    save_occupancy(model, out, {"seed": args.seed, "data": recipe, "training": training})
    total_s = time.perf_counter() - t0
    report = {
        "format": "adv3d-occupancy-training-report", "version": 1,
        "command": command,
        "machine": machine_info("torch", "numpy"),
        "device": device_info(device),
        "seconds": {"data": round(data_s, 1), "train": round(train_s, 1), "eval": round(eval_s, 1),
                    "total": round(total_s, 1), "total_cpu_of_process": round(time.process_time() - cpu0, 1)},
        "note": "wall times on a 2-core VM shared with other jobs; training uses --threads torch threads",
        "data": recipe, "training": training, "occupancy": cfg.to_dict(),
        "history": hist, "held_out": held, "training_samples_subset": train_metrics,
        "parameters": int(sum(p.numel() for p in model.net.parameters())),
    }
    write_json(out / "training_report.json", _finite(report))
    plot_history(hist, out / "loss_curves.png",
                 title=f"implicit occupancy: held-out Soft-IoU {held.get('soft_iou') or float('nan'):.3f}, "
                       f"EPE {held.get('epe') or float('nan'):.2f} m/s ({device}, {train_s / 60:.1f} min)")
    status(f"wrote {out} ({total_s / 60:.1f} min)")
    return 0
