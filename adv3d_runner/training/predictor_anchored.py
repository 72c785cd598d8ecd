"""The anchored predictor: residuals on lane-following anchors, trained on every vehicle of the
*train* recordings and on generated traffic (docs/predictor.md, "The anchored predictor").

Each of the K = 6 modes starts from its own anchor: the track moves along its lane path
(:func:`~adv3d_runner.autonomy.predictor.lane_paths`, lateral offset kept) from its tracked
speed with a fixed acceleration (``ANCHOR_ACCELS``: keep the speed, +-0.4 and +-1.0 m/s^2, brake
at 2 m/s^2 to a stop). The network (the shipped architecture) adds residuals to the anchors and
gives the mode probabilities; its trajectory head starts at zero, so the untrained model *is*
the anchor set, and the anchor set with the speed factors of :class:`LaneFollowingPredictor`
would be that baseline.

Data (nothing of the benchmark recordings 4, 6, 9 or the fresh ones 10-18 is trained on):

* **real**: every vehicle of each train recording (``scenes/real/split.json``'s train part; one
  scene per recording, the one with the most recorded frames, since the CommonRoad variants of
  a recording share its traffic), the ego included and no detection range
  (:func:`~.predictor_data.recording_samples`), ``--draws`` independent perception-noise draws;
* **generated**: ``--gen-scenes`` training-split scenes (seeds ``SEED ..``).

Validation (how the settings were chosen): ``--val-recording R`` leaves train recording R out of
the training data and reports the model on its vehicles (draw 0) beside the anchors alone and
both baselines. The fresh part is never read here.

    adv3d train predictor --out DIR [--val-recording R] [--epochs 8] [--gen-scenes 160]
        [--draws 20] [--residual-scale 0.25] [--seed 100000] [--force]

(``python -m adv3d_runner.training.predictor_anchored ARGS`` is the same command: :func:`main`
parses ARGS with ``adv3d train predictor``'s parser and runs its handler with ``--model
anchored``; the options, their defaults and the refusal to overwrite a model at ``--out``
without ``--force`` are those of :mod:`.cli`.)

Writes ``weights.pt`` + ``config.json`` (:func:`~adv3d_runner.autonomy.predictor.load_predictor`)
and ``training_report.json`` (the command, the SHA-256 of every real scene file and of the
training arrays, the loss curves, held-out tables). Same seed, same weights on one machine
(one torch thread).
"""
from __future__ import annotations

import argparse
import hashlib
import platform
import sys
import time
from pathlib import Path

import numpy as np

ANCHOR_SCALES = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
ANCHOR_ACCELS = (0.0, 0.4, -0.4, 1.0, -1.0, -2.0)     # m/s^2, chosen on the train recordings
REPO = Path(__file__).resolve().parents[2]


def train_recording_files(split=None) -> dict[int, Path]:
    """{train recording: the scene file of ``scenes/real/`` with its most recorded frames}."""
    from ..scene import load_scene
    from ..scene.real import load_real_split, recording_of

    split = split or load_real_split()
    best: dict[int, tuple[int, Path]] = {}
    for path in split.paths("train"):
        rec = recording_of(path.name.split(".json")[0])
        n = int(load_scene(path).source.details.get("recorded_frames", 0))
        if rec not in best or n > best[rec][0]:
            best[rec] = (n, path)
    return {rec: p for rec, (n, p) in sorted(best.items())}


def recording_dataset(files: dict[int, Path], draws: int, cache: str | Path | None = None) -> dict[str, np.ndarray]:
    """Samples of every vehicle of each recording's scene, ``draws`` noise draws each (cached per
    file and draw under the predictor data cache); a ``recording`` column is added."""
    from ..scene import load_scene
    from .predictor_data import ARRAYS, _empty, cache_dir, load_samples, real_cache_name, recording_samples, save_samples

    folder = cache_dir(cache)
    parts = []
    for rec, path in files.items():
        scene = None
        for draw in range(draws):
            cpath = folder / real_cache_name(path).replace(".npz", f"-all-d{draw:03d}.npz")
            arrays = None
            if cpath.is_file():
                try:
                    arrays = load_samples(cpath)
                except Exception:  # a broken cache entry is rebuilt, never trusted
                    arrays = None
            if arrays is None:
                scene = scene or load_scene(path)
                arrays = recording_samples(scene, draw)
                save_samples(cpath, arrays)
            arrays = {k: arrays[k] for k in ARRAYS}
            arrays["recording"] = np.full(len(arrays["features"]), rec, np.int64)
            parts.append(arrays)
    if not parts:
        out = _empty()
        out["recording"] = np.zeros(0, np.int64)
        return out
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _digest(arrays: dict, keys=("features", "prior", "path", "future", "future_valid")) -> str:
    h = hashlib.sha256()
    for k in keys:
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def _anchors(arrays: dict, cfg) -> np.ndarray:
    from ..autonomy.predictor import anchor_speed, anchor_trajectories

    out = np.empty((len(arrays["features"]), cfg.num_modes, cfg.steps, 2), np.float32)
    for i in range(0, len(out), 8192):
        sl = slice(i, i + 8192)
        out[sl] = anchor_trajectories(arrays["path"][sl], anchor_speed(arrays["features"][sl]), cfg.anchor_scales,
                                      cfg.anchor_accels, cfg.steps, cfg.dt)
    return out


def evaluate(model, arrays: dict) -> dict:
    """minADE etc. of ``model`` (a LearnedPredictor), of its anchors alone and of both baselines
    on ``arrays`` (outputs as the planner gets them: no reversing), for samples known for 6 s
    (``full_6s``) and for >= 3 s (``all``)."""
    from ..autonomy.predictor import no_reversing
    from .predictor_data import BASELINES, per_sample_metrics

    if len(arrays["features"]) == 0:
        return {"n_samples": {"full_6s": 0, "all": 0}}
    fut = arrays["future"].astype(np.float64)
    val = arrays["future_valid"]
    traj, probs = model.predict_local(arrays["features"], arrays["prior"], arrays["path"])
    K = model.config.num_modes
    rows = {f"learned_k{K}": per_sample_metrics(no_reversing(traj), probs, fut, val)}
    if model.config.anchored:
        anchors = model.base(arrays["features"], arrays["prior"], arrays["path"]).astype(np.float64)
        rows[f"anchors_k{K}"] = per_sample_metrics(anchors, np.full((len(fut), K), 1.0 / K), fut, val)
    for b in BASELINES:
        rows[b] = arrays[f"{b}_metrics"]
    full = val.all(axis=1)
    cols = ("min_ade", "mean_ade", "min_fde", "mean_fde", "top1_ade", "top1_fde")
    out = {"n_samples": {"full_6s": int(full.sum()), "all": int(len(full))}}
    for sub, mask in (("full_6s", full), ("all", np.ones(len(full), bool))):
        out[sub] = {name: {c: (float(m[mask, j].mean()) if mask.any() else None) for j, c in enumerate(cols)}
                    for name, m in rows.items()}
    return out


def train_anchored(out: str | Path, *, epochs: int = 8, gen_scenes: int = 160, val_scenes: int = 10, draws: int = 20,
                   seed: int = 100_000, batch: int = 512, lr: float = 1e-3, hidden: int = 256, layers: int = 3,
                   residual_scale: float = 0.25, cls_weight: float = 0.5, lane_dropout: float = 0.05,
                   val_recording: int | None = None, fixed_modes: tuple[int, ...] = (), cache: str | Path | None = None,
                   command: str = "", split=None) -> dict:
    """Train the anchored predictor (module docstring) and write it to ``out``; returns the report.

    ``split``: the real scenes' split (:class:`~adv3d_runner.scene.real.RealSplit`; default
    ``scenes/real/split.json``). ``out`` is written over: the caller (``adv3d train predictor``)
    refuses an existing model without ``--force``.

    ``fixed_modes``: modes whose residuals stay zero (their rows of the trajectory head are zero
    and get no gradient), so that they are their anchors exactly."""
    import torch

    from ..autonomy.predictor import (NUM_FEATURES, LearnedPredictor, PredictorConfig,
                                      build_net, save_predictor)
    from ..errors import ConfigError
    from ..fileio import write_json
    from ..scene.real import load_real_split
    from .predictor_data import ARRAYS, build_dataset, build_real_dataset, data_key
    from .predictor_train import HELD_OUT_OFFSET, train_epoch

    torch.manual_seed(seed)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    split = split or load_real_split()
    files = train_recording_files(split)
    if val_recording is not None and val_recording not in files:
        raise ConfigError(f"--val-recording {val_recording} is not a train recording {sorted(files)}")
    train_files = {r: p for r, p in files.items() if r != val_recording}
    real = recording_dataset(train_files, draws, cache)
    gen = build_dataset(range(seed, seed + gen_scenes), cache, desc="generated training scenes")
    held = build_dataset(range(seed + HELD_OUT_OFFSET, seed + HELD_OUT_OFFSET + val_scenes), cache,
                         desc="generated held-out scenes")
    held_sets = {"generated": held,
                 "real_benchmark_tuned_on": build_real_dataset(split.paths("benchmark"), cache,
                                                               desc="real benchmark part (tuned on)")}
    if val_recording is not None:
        held_sets[f"validation_recording_{val_recording}"] = recording_dataset({val_recording: files[val_recording]}, 1, cache)
    train = {k: np.concatenate([gen[k], real[k]]) for k in ARRAYS}
    t_data = time.perf_counter() - t0
    print(f"{len(gen['features'])} generated + {len(real['features'])} real samples ({t_data:.0f} s)", flush=True)

    cfg = PredictorConfig(num_features=NUM_FEATURES, num_modes=len(ANCHOR_ACCELS), hidden=hidden, layers=layers,
                          residual_scale=residual_scale, anchor_scales=ANCHOR_SCALES, anchor_accels=ANCHOR_ACCELS)
    net = build_net(cfg)
    if fixed_modes:
        if not all(0 <= k < cfg.num_modes for k in fixed_modes):
            raise ConfigError(f"--fixed-modes: modes are 0..{cfg.num_modes - 1}")
        keep = torch.ones(cfg.num_modes, cfg.steps * 2)
        keep[list(fixed_modes)] = 0.0
        keep = keep.reshape(-1)
        net.traj.weight.register_hook(lambda grad: grad * keep[:, None])
        net.traj.bias.register_hook(lambda grad: grad * keep)
    X = torch.from_numpy(train["features"])
    A = torch.from_numpy(_anchors(train, cfg))
    Y = torch.from_numpy(train["future"])
    M = torch.from_numpy(train["future_valid"])
    n = len(X)
    steps = max(1, (n + batch - 1) // batch)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=epochs * steps, pct_start=0.1)
    g = torch.Generator().manual_seed(seed)
    curves: dict[str, list] = {"epoch": [], "train_loss": [], "train_reg_ade": [], "train_cls": []}
    for name in held_sets:
        curves[f"{name}_min_ade"] = []
    t1 = time.perf_counter()
    for ep in range(epochs):
        net.train()
        tot, reg_sum, cls_sum = train_epoch(torch, net, opt, sched, g, X, A, Y, M, batch=batch,
                                            lane_dropout=lane_dropout, cls_weight=cls_weight)
        net.eval()
        model = LearnedPredictor(net, cfg)
        curves["epoch"].append(ep + 1)
        curves["train_loss"].append(tot)
        curves["train_reg_ade"].append(reg_sum)
        curves["train_cls"].append(cls_sum)
        msg = []
        for name, arrays in held_sets.items():
            ev = evaluate(model, arrays)
            v = ev["all"][f"learned_k{cfg.num_modes}"]["min_ade"] if ev["n_samples"]["all"] else None
            curves[f"{name}_min_ade"].append(v)
            msg.append(f"{name} {v:.3f}" if v is not None else f"{name} -")
        print(f"epoch {ep + 1}/{epochs}: loss {tot:.3f} ade {reg_sum:.3f} | minADE (>= 3 s) " + ", ".join(msg)
              + f" ({time.perf_counter() - t1:.0f} s)", flush=True)
    t_train = time.perf_counter() - t1
    model = LearnedPredictor(net.eval(), cfg)
    tables = {name: evaluate(model, arrays) for name, arrays in held_sets.items()}
    out = Path(out)
    save_predictor(net, cfg, out, extra={"training_report": "training_report.json"})
    report = {
        "format": "adv3d-predictor-training-report", "version": 1,
        "command": command or " ".join(["python -m adv3d_runner.training.predictor_anchored"] + sys.argv[1:]),
        "model": "anchored: residuals on lane-following anchors (docs/predictor.md)",
        "data": {"data_key": data_key(),
                 "real": {"recordings": sorted(train_files), "validation_recording": val_recording, "draws": draws,
                          "samples": int(len(real["features"])),
                          "scenes": {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in train_files.values()}},
                 "generated_train_seeds": [seed, seed + gen_scenes - 1], "generated_samples": int(len(gen["features"])),
                 "held_out_seeds": [seed + HELD_OUT_OFFSET, seed + HELD_OUT_OFFSET + val_scenes - 1],
                 "train_samples": int(n), "train_arrays_sha256": _digest(train), "seconds": round(t_data, 1)},
        "training": {"epochs": epochs, "batch": batch, "lr": lr, "optimizer": "AdamW (weight decay 1e-4) + one-cycle",
                     "cls_weight": cls_weight, "lane_dropout": lane_dropout, "threads": 1, "torch_seed": seed,
                     "hidden": hidden, "layers": layers, "residual_scale": residual_scale,
                     "fixed_modes": list(fixed_modes),
                     "anchor_scales": list(ANCHOR_SCALES), "anchor_accels": list(ANCHOR_ACCELS),
                     "seconds": round(t_train, 1), "weights_sha256": None},
        "curves": curves,
        "held_out": tables,
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
                    "cpu": platform.processor() or platform.machine()},
        "notes": "held_out: generated held-out scenes, the real benchmark part that was tuned on (recordings 4, 6, 9; "
                 "samples around its egos) and, with --val-recording, every vehicle of the left-out train recording; "
                 "the fresh part (recordings 10-18) is never read here.",
    }
    report["training"]["weights_sha256"] = hashlib.sha256((out / "weights.pt").read_bytes()).hexdigest()
    write_json(out / "training_report.json", report)
    return report


def print_report(rep: dict, out: str | Path) -> None:
    """Print each held-out table's minADE (>= 3 s) per model, then the output folder."""
    for name, t in rep["held_out"].items():
        if not t["n_samples"]["all"]:
            continue
        row = " ".join(f"{m} {v['min_ade']:.3f}" for m, v in t["all"].items())
        print(f"{name} (>= 3 s, {t['n_samples']['all']} samples): {row}")
    print(f"wrote {out}")


def main(argv: list[str] | None = None) -> int:
    """``adv3d train predictor --model anchored ARGV`` (the one training command; docs/predictor.md):
    the same options, defaults and refusals; a usage error returns 2, another error 1."""
    from ..errors import Adv3dError, UsageError
    from .cli import add_train_predictor

    prog = "python -m adv3d_runner.training.predictor_anchored"
    ap = argparse.ArgumentParser(prog=prog)
    add_train_predictor(ap.add_subparsers(dest="train_command"))
    args = ap.parse_args(["predictor", *(sys.argv[1:] if argv is None else argv), "--model", "anchored"])
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except Adv3dError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
