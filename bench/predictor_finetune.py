"""Fine-tune the shipped predictor on more real traffic of the *train* recordings (docs/benchmark.md).

The shipped predictor (``adv3d train predictor``: 240 generated scenes + the 14 train-part scenes
of ``scenes/real/``, 20 epochs, about 46 min on the 2-core VM) saw the train recordings (1, 2,
3, 5, 8) only around 14 egos. This script starts from its weights and trains a few more epochs
on the real samples around *every* ego of the train recordings (``scenes/real/``'s train part
and ``scenes/real-train-egos/``: 47 egos), repeated ``--real-weight`` times, mixed with cached
generated training-split scenes so that generated traffic is not forgotten. Nothing of the
benchmark recordings (4, 6, 9) or the fresh ones (10-18) is trained on; the report evaluates
the generated held-out scenes and the benchmark part that was tuned on (never the fresh part:
``bench/predictor_real.py --parts fresh`` looks at that, once).

    .venv/bin/python bench/predictor_finetune.py --out runs/predictor-ft [--epochs 4] [--lr 5e-4]
        [--gen-scenes 60] [--real-weight 10] [--seed 100000]

Writes a model folder (``weights.pt``, ``config.json``, ``training_report.json`` with the command,
seeds, the SHA-256 of every real scene file and of the training arrays, and the held-out tables).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def train_recording_scenes() -> list[Path]:
    """Scene files of the train recordings: ``scenes/real/``'s train part and every file of
    ``scenes/real-train-egos/`` (each checked to come from a train recording)."""
    from adv3d_runner.errors import ConfigError
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.real import load_real_split, recording_of

    split = load_real_split()
    train = set(split.recordings["train"])
    extra = sorted((ROOT / "scenes" / "real-train-egos").glob("*.json.gz"))
    for p in extra:
        rec = recording_of(Path(str(load_scene(p).source.details["file"])).stem)
        if rec not in train:
            raise ConfigError(f"{p}: recording {rec} is not a train recording {sorted(train)}")
    return split.paths("train") + extra


def _digest(arrays: dict, keys=("features", "prior", "future", "future_valid")) -> str:
    h = hashlib.sha256()
    for k in keys:
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--init", default=str(ROOT / "assets" / "models" / "predictor"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--gen-scenes", type=int, default=60, help="generated training-split scenes (seeds SEED..)")
    ap.add_argument("--val-scenes", type=int, default=10, help="generated held-out scenes (seeds SEED + 500000000..)")
    ap.add_argument("--real-weight", type=int, default=10)
    ap.add_argument("--seed", type=int, default=100_000)
    args = ap.parse_args()
    import torch

    from adv3d_runner.autonomy.predictor import _AGENT_F, _HIST_F, _LANE_F, load_predictor, save_predictor
    from adv3d_runner.fileio import write_json
    from adv3d_runner.scene.real import load_real_split
    from adv3d_runner.training.predictor_data import (ARRAYS, BASELINES, METRIC_COLUMNS, build_dataset,
                                                      build_real_dataset, data_key, per_sample_metrics)
    from adv3d_runner.training.predictor_train import HELD_OUT_OFFSET, _held_out_table, _wta_losses

    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    real_paths = train_recording_scenes()
    gen = build_dataset(range(args.seed, args.seed + args.gen_scenes), desc="generated training scenes")
    real = build_real_dataset(real_paths, desc="real train-recording scenes")
    held = build_dataset(range(args.seed + HELD_OUT_OFFSET, args.seed + HELD_OUT_OFFSET + args.val_scenes),
                         desc="generated held-out scenes")
    held_real = build_real_dataset(load_real_split().paths("benchmark"), desc="real benchmark part (tuned on)")
    train = {k: np.concatenate([gen[k]] + [real[k]] * args.real_weight) for k in ARRAYS}
    t_data = time.perf_counter() - t0
    print(f"{len(gen['features'])} generated + {len(real['features'])} x {args.real_weight} real samples ({t_data:.0f} s)",
          flush=True)

    model = load_predictor(args.init)
    net, cfg = model.net, model.config
    tables_before = {"generated": _held_out_table(torch, net, held, cfg.num_modes, per_sample_metrics, BASELINES, METRIC_COLUMNS),
                     "real_benchmark": _held_out_table(torch, net, held_real, cfg.num_modes, per_sample_metrics, BASELINES,
                                                       METRIC_COLUMNS)}
    X, V = torch.from_numpy(train["features"]), torch.from_numpy(train["prior"])
    Y, M = torch.from_numpy(train["future"]), torch.from_numpy(train["future_valid"])
    n = len(X)
    steps = max(1, (n + args.batch - 1) // args.batch)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=args.epochs * steps, pct_start=0.1)
    g = torch.Generator().manual_seed(args.seed)
    lane_lo = _HIST_F + _AGENT_F
    lane_hi = lane_lo + 3 * _LANE_F
    curves = []
    t1 = time.perf_counter()
    for ep in range(args.epochs):
        net.train()
        perm = torch.randperm(n, generator=g)
        tot = 0.0
        for i in range(steps):
            idx = perm[i * args.batch:(i + 1) * args.batch]
            xb = X[idx].clone()
            drop = torch.rand(len(idx), generator=g) < 0.05  # lane dropout, as adv3d train predictor
            xb[drop, lane_lo:lane_hi] = 0.0
            traj, logits = net(xb, V[idx])
            reg, cls = _wta_losses(torch, traj, logits, Y[idx], M[idx])
            loss = reg + 0.5 * cls
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
            opt.step()
            sched.step()
            tot += float(loss.detach()) * len(idx)
        curves.append(tot / n)
        print(f"epoch {ep + 1}/{args.epochs}: train loss {tot / n:.3f} ({time.perf_counter() - t1:.0f} s)", flush=True)
    net.eval()
    tables = {"generated": _held_out_table(torch, net, held, cfg.num_modes, per_sample_metrics, BASELINES, METRIC_COLUMNS),
              "real_benchmark": _held_out_table(torch, net, held_real, cfg.num_modes, per_sample_metrics, BASELINES,
                                                METRIC_COLUMNS)}
    out = Path(args.out)
    save_predictor(net, cfg, out, extra={"training_report": "training_report.json"})
    report = {
        "format": "adv3d-predictor-training-report", "version": 1,
        "command": " ".join(["bench/predictor_finetune.py"] + sys.argv[1:]),
        "init": {"folder": args.init, "weights_sha256": hashlib.sha256((Path(args.init) / "weights.pt").read_bytes()).hexdigest()},
        "data": {"data_key": data_key(), "generated_train_seeds": [args.seed, args.seed + args.gen_scenes - 1],
                 "held_out_seeds": [args.seed + HELD_OUT_OFFSET, args.seed + HELD_OUT_OFFSET + args.val_scenes - 1],
                 "generated_train_samples": int(len(gen["features"])), "real_train_samples": int(len(real["features"])),
                 "real_weight": args.real_weight, "train_samples": int(n),
                 "real_train_scenes": {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in real_paths},
                 "train_arrays_sha256": _digest(train), "seconds": round(t_data, 1)},
        "training": {"epochs": args.epochs, "batch": args.batch, "lr": args.lr, "optimizer": "AdamW + one-cycle",
                     "cls_weight": 0.5, "lane_dropout": 0.05, "threads": 1, "torch_seed": args.seed,
                     "seconds": round(time.perf_counter() - t1, 1), "train_loss": curves},
        "held_out_before": tables_before, "held_out": tables,
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
                    "cpu": platform.processor() or platform.machine()},
        "notes": "held_out: generated held-out scenes and the real benchmark part that was tuned on (recordings 4, 6, 9); "
                 "the fresh part (recordings 10-18) is never read here.",
    }
    write_json(out / "training_report.json", report)
    k = f"learned_k{cfg.num_modes}"
    for name in tables:
        b, a = tables_before[name]["full_6s"]["models"], tables[name]["full_6s"]["models"]
        print(f"{name} held-out minADE (6 s known): before {b[k]['min_ade']:.3f} -> after {a[k]['min_ade']:.3f} m "
              f"(constant velocity {a['constant_velocity']['min_ade']:.3f}, lane following {a['lane_following']['min_ade']:.3f})")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
