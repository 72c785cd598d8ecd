"""Training of the learned predictor (``adv3d train predictor``, parsed in :mod:`.cli`): make
data from training-split scenes (:mod:`.predictor_data`), train
:class:`~adv3d_runner.autonomy.predictor.PredictorNet`, evaluate it against the baselines on
held-out training-split scenes, and write the model and its report.

Seeds: training scenes ``seed .. seed + scenes - 1`` (``--seed`` >= 100 000, the generator's
training split); held-out scenes ``seed + HELD_OUT_OFFSET ..`` (same split, disjoint seeds).
The benchmark scenes (``scenes/highway/``) are never used.

Real traffic: the recorded scenes of the *train* part of ``scenes/real/split.json`` (NGSIM
US-101 recordings) join the training data, each sample repeated ``real_weight`` times (they are
~1 % of the samples otherwise); the *benchmark* part (other recordings) is only evaluated, in a
separate held-out table (``held_out_real``). Nothing is selected on either held-out set: the
model of the last epoch is kept.

Outputs in ``--out`` (default ``assets/models/predictor``): ``weights.pt`` + ``config.json``
(:func:`~adv3d_runner.autonomy.predictor.load_predictor`), ``training_report.json`` (loss curves, held-out metrics of
the model and both baselines, times, the exact command) and ``loss_curves.png``.
"""
from __future__ import annotations

import platform
import time
from pathlib import Path
from typing import Sequence

import numpy as np

HELD_OUT_OFFSET = 500_000_000
REPORT_FORMAT = "adv3d-predictor-training-report"
REPORT_VERSION = 1


def _wta_losses(torch, traj, logits, fut, fval):
    """Winner-takes-all: ADE of every mode (B, K) over valid steps, regression on the best mode
    and cross-entropy of the logits towards it."""
    err = torch.sqrt(((traj - fut[:, None]) ** 2).sum(-1) + 1e-6)            # (B, K, T)
    w = fval[:, None].float()
    ade = (err * w).sum(-1) / w.sum(-1).clamp(min=1.0)                       # (B, K)
    best = ade.detach().argmin(dim=1)
    reg = ade.gather(1, best[:, None]).mean()
    cls = torch.nn.functional.cross_entropy(logits, best)
    return reg, cls


def train_epoch(torch, net, opt, sched, gen, X, cond, Y, M, *, batch: int, lane_dropout: float,
                cls_weight: float, device: str = "cpu") -> tuple[float, float, float]:
    """One epoch of winner-takes-all training over shuffled batches of the samples.

    X (N, F) features, cond (N, ...) the net's second input (the prior of the free model, the
    anchors of the anchored one), Y (N, T, 2) futures, M (N, T) their valid steps. Returns the
    mean per sample of the loss, the best mode's ADE (m) and the mode-classification loss.
    """
    from ..autonomy.predictor import _AGENT_F, _HIST_F, _LANE_F

    n = len(X)
    lane_lo = _HIST_F + _AGENT_F
    lane_hi = lane_lo + 3 * _LANE_F
    perm = torch.randperm(n, generator=gen).to(device)
    tot = reg_sum = cls_sum = 0.0
    for i in range(max(1, (n + batch - 1) // batch)):
        idx = perm[i * batch:(i + 1) * batch]
        xb = X[idx].clone()
        # lane dropout: some samples see no map, so the model has a sensible no-lane fallback
        drop = (torch.rand(len(idx), generator=gen) < lane_dropout).to(device)
        xb[drop, lane_lo:lane_hi] = 0.0
        traj, logits = net(xb, cond[idx])
        reg, cls = _wta_losses(torch, traj, logits, Y[idx], M[idx])
        loss = reg + cls_weight * cls
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
        opt.step()
        sched.step()
        k = len(idx)
        tot += float(loss.detach()) * k
        reg_sum += float(reg.detach()) * k
        cls_sum += float(cls.detach()) * k
    return tot / n, reg_sum / n, cls_sum / n


def train_predictor(scenes: int = 240, val_scenes: int = 40, epochs: int = 20, seed: int = 100_000,
                    modes: int = 6, batch: int = 512, lr: float = 2e-3, threads: int = 1,
                    cache: str | None = None, use_cache: bool = True, out: str | Path | None = None,
                    command: str = "", cls_weight: float = 0.5, lane_dropout: float = 0.05,
                    time_limit_min: float | None = 40.0, real_train: Sequence[str | Path] = (),
                    real_eval: Sequence[str | Path] = (), real_weight: int = 10,
                    real_info: dict | None = None, device="cpu") -> dict:
    """Train and evaluate the predictor; write weights, config, report and curves to ``out``.
    ``device``: "cpu" (the shipped weights) or a ``torch.device`` (training only; the
    evaluation and the saved weights are on the CPU).

    ``real_train``: real scene files added to the training data (each sample ``real_weight``
    times); ``real_eval``: real scene files evaluated as a second held-out set (never trained
    on); ``real_info``: what to record about them in the report (split, recordings).
    Returns the report dict (also written as ``training_report.json``).
    """
    import torch

    from ..errors import ConfigError
    from ..fileio import write_json
    from ..progress import progress, status
    from ..scene.generate import check_split
    from ..autonomy.predictor import (DEFAULT_MODEL_DIR, NUM_FEATURES, PredictorConfig,
                            build_net, save_predictor)
    from .device import device_info
    from .predictor_data import (ARRAYS, BASELINES, METRIC_COLUMNS, build_dataset, build_real_dataset, data_key,
                                 per_sample_metrics)

    out = Path(out) if out is not None else DEFAULT_MODEL_DIR
    for s in (seed, seed + scenes - 1, seed + HELD_OUT_OFFSET, seed + HELD_OUT_OFFSET + val_scenes - 1):
        check_split("train", s)
    if seed + scenes > seed + HELD_OUT_OFFSET:
        raise ConfigError("too many training scenes: they would reach the held-out seeds")
    torch.manual_seed(seed)
    torch.set_num_threads(max(1, threads))
    device = torch.device(device)
    t0 = time.perf_counter()
    data_stats: dict = {}
    train = build_dataset(range(seed, seed + scenes), cache, use_cache, desc="training scenes", stats=data_stats)
    held = build_dataset(range(seed + HELD_OUT_OFFSET, seed + HELD_OUT_OFFSET + val_scenes), cache, use_cache,
                         desc="held-out scenes", stats=data_stats)
    if real_weight < 1:
        raise ConfigError("--real-weight must be >= 1")
    n_generated = len(train["features"])
    real_stats: dict = {}
    real = build_real_dataset(real_train, cache, use_cache, desc="real training scenes", stats=real_stats) \
        if real_train else None
    held_real = build_real_dataset(real_eval, cache, use_cache, desc="real held-out scenes", stats=real_stats) \
        if real_eval else None
    n_real = 0 if real is None else len(real["features"])
    if n_real:  # repeated so that real traffic is not drowned by ~100x more generated samples
        train = {k: np.concatenate([train[k]] + [real[k]] * real_weight) for k in ARRAYS}
    t_data = time.perf_counter() - t0
    if len(train["features"]) == 0 or len(held["features"]) == 0:
        raise ConfigError("no training or held-out samples were made; use more scenes")
    status(f"{n_generated} generated + {n_real} x {real_weight} real training samples, {len(held['features'])} "
           f"generated held-out samples, {0 if held_real is None else len(held_real['features'])} real held-out "
           f"samples ({t_data:.0f} s)")

    # the curves track the headline subset: held-out samples whose actor is known for all 6 s
    full_mask = held["future_valid"].all(axis=1)
    held_full = {k: v[full_mask] for k, v in held.items()}
    cfg = PredictorConfig(num_features=NUM_FEATURES, num_modes=modes)
    net = build_net(cfg).to(device)
    X = torch.from_numpy(train["features"]).to(device)
    V = torch.from_numpy(train["prior"]).to(device)
    Y = torch.from_numpy(train["future"]).to(device)
    M = torch.from_numpy(train["future_valid"]).to(device)
    n = len(X)
    steps_per_epoch = max(1, (n + batch - 1) // batch)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=epochs * steps_per_epoch, pct_start=0.1)
    gen = torch.Generator().manual_seed(seed)
    curves = {"epoch": [], "train_loss": [], "train_reg_ade": [], "train_cls": [], "val_min_ade": [], "val_loss": []}
    t1 = time.perf_counter()
    stopped_early = False
    for ep in progress(range(epochs), desc="epochs", unit="epoch"):
        if time_limit_min is not None and ep > 0 and time.perf_counter() - t0 > 60.0 * time_limit_min:
            stopped_early = True  # the time budget is spent: keep the model of the last epoch
            status(f"time limit of {time_limit_min} min reached after {ep} epochs")
            break
        net.train()
        tot, reg_sum, cls_sum = train_epoch(torch, net, opt, sched, gen, X, V, Y, M, batch=batch,
                                            lane_dropout=lane_dropout, cls_weight=cls_weight, device=device)
        vm, vl = _evaluate(torch, net, held_full, cls_weight, device)
        curves["epoch"].append(ep + 1)
        curves["train_loss"].append(tot)
        curves["train_reg_ade"].append(reg_sum)
        curves["train_cls"].append(cls_sum)
        curves["val_min_ade"].append(vm)
        curves["val_loss"].append(vl)
        status(f"epoch {ep + 1}/{epochs}: train loss {tot:.3f} (best-mode ADE {reg_sum:.3f} m), "
               f"held-out minADE {vm:.3f} m")
    t_train = time.perf_counter() - t1

    # held-out evaluation: the same samples for every model (on the CPU, as the weights ship)
    net = net.cpu().eval()
    table = _held_out_table(torch, net, held, modes, per_sample_metrics, BASELINES, METRIC_COLUMNS)
    table_real = None if held_real is None or len(held_real["features"]) == 0 else \
        _held_out_table(torch, net, held_real, modes, per_sample_metrics, BASELINES, METRIC_COLUMNS)
    full = held["future_valid"].all(axis=1)
    res = table["full_6s"]["models"]
    beats = res[f"learned_k{modes}"]["min_ade"] < res["constant_velocity"]["min_ade"]

    report = {
        "format": REPORT_FORMAT, "version": REPORT_VERSION,
        "command": command or (f"adv3d train predictor --scenes {scenes} --val-scenes {val_scenes} --epochs {epochs} "
                               f"--seed {seed} --modes {modes} --batch {batch} --lr {lr} --out {out}"),
        "data": {"train_seeds": [seed, seed + scenes - 1], "held_out_seeds": [seed + HELD_OUT_OFFSET, seed + HELD_OUT_OFFSET + val_scenes - 1],
                 "split": "train (generator seed namespace disjoint from the benchmark)",
                 "train_samples": int(n), "generated_train_samples": int(n_generated),
                 "held_out_samples": int(len(full)), "data_key": data_key(),
                 "seconds": round(t_data, 1), "scenes_generated": data_stats["generated"],
                 "scenes_from_cache": data_stats["cached"],
                 "real": dict(real_info or {}, train_scenes=[Path(p).name for p in real_train],
                              held_out_scenes=[Path(p).name for p in real_eval], train_samples=int(n_real),
                              weight=int(real_weight),
                              held_out_samples=0 if held_real is None else int(len(held_real["features"])),
                              scenes_generated=real_stats.get("generated", 0),
                              scenes_from_cache=real_stats.get("cached", 0))},
        "training": {"epochs": epochs, "batch": batch, "lr": lr, "optimizer": "AdamW + one-cycle", "cls_weight": cls_weight,
                     "lane_dropout": lane_dropout, "threads": threads, "device": device_info(device),
                     "seconds": round(t_train, 1),
                     "epochs_run": len(curves["epoch"]), "stopped_by_time_limit": stopped_early,
                     "parameters": int(sum(p.numel() for p in net.parameters()))},
        "curves": curves,
        "held_out": table,
        "held_out_real": table_real,
        "beats_constant_velocity_min_ade": bool(beats),
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
                    "cpu": platform.processor() or platform.machine()},
        "notes": "metrics over 6 s at 10 Hz; 'full_6s' = samples whose actor is known for the whole 6 s, 'all' = "
                 ">= 3 s known (averaged over known steps). Baselines have K = 3 modes; learned_top3 = the learned "
                 "model's 3 most probable modes. held_out = generated held-out scenes; held_out_real = the real "
                 "benchmark part (recorded frames only), never trained on.",
    }
    save_predictor(net, cfg, out, extra={"training_report": "training_report.json"})
    write_json(out / "training_report.json", report)
    _plot(out / "loss_curves.png", curves, res, modes)
    for name, tab in (("generated", table), ("real", table_real)):
        if tab is None:
            continue
        r = tab["full_6s"]["models"] if tab["full_6s"]["n_samples"] else tab["all"]["models"]
        sub = "full 6 s" if tab["full_6s"]["n_samples"] else ">= 3 s"
        status(f"{name} held-out ({sub}, {tab['full_6s']['n_samples'] or tab['all']['n_samples']} samples): minADE "
               f"learned {r[f'learned_k{modes}']['min_ade']:.3f} m, top-3 {r['learned_top3']['min_ade']:.3f} m, "
               f"constant velocity {r['constant_velocity']['min_ade']:.3f} m, lane following "
               f"{r['lane_following']['min_ade']:.3f} m")
    status(f"wrote {out}")
    return report


def _held_out_table(torch, net, held: dict, modes: int, per_sample_metrics, baselines, columns) -> dict:
    """Metrics of the model, its 3 most probable modes and the baselines on the same samples:
    {"full_6s" | "all": {"n_samples", "models": {name: {column: mean}}}}."""
    net.eval()
    with torch.inference_mode():
        traj, logits = net(torch.from_numpy(held["features"]), torch.from_numpy(held["prior"]))
        probs = torch.softmax(logits, -1).numpy().astype(np.float64)
        traj = traj.numpy().astype(np.float64)
    fut = held["future"].astype(np.float64)
    fval = held["future_valid"]
    learned = per_sample_metrics(traj, probs, fut, fval)
    top3 = np.argsort(-probs, axis=1)[:, :3]
    learned3 = per_sample_metrics(np.take_along_axis(traj, top3[:, :, None, None], axis=1),
                                  np.take_along_axis(probs, top3, axis=1), fut, fval)
    full = fval.all(axis=1)
    table = {}
    for subset, mask in (("full_6s", full), ("all", np.ones(len(full), bool))):
        rows = {f"learned_k{modes}": learned[mask], "learned_top3": learned3[mask]}
        for b in baselines:
            rows[b] = held[f"{b}_metrics"][mask]
        table[subset] = {"n_samples": int(mask.sum()),
                         "models": {name: {c: (float(np.nanmean(v[:, j])) if len(v) else None)
                                           for j, c in enumerate(columns)} for name, v in rows.items()}}
    return table


def _evaluate(torch, net, held, cls_weight, device="cpu") -> tuple[float, float]:
    """Held-out minADE (mean over samples) and loss."""
    net.eval()
    with torch.inference_mode():
        traj, logits = net(torch.from_numpy(held["features"]).to(device), torch.from_numpy(held["prior"]).to(device))
        fut = torch.from_numpy(held["future"]).to(device)
        fval = torch.from_numpy(held["future_valid"]).to(device)
        reg, cls = _wta_losses(torch, traj, logits, fut, fval)
    return float(reg), float(reg + cls_weight * cls)


def _plot(path: Path, curves: dict, res: dict, modes: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import atomic_path

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ep = curves["epoch"]
    ax[0].plot(ep, curves["train_loss"], label="train loss (ADE + 0.5 CE)")
    ax[0].plot(ep, curves["val_loss"], label="held-out loss (6 s known)")
    ax[0].plot(ep, curves["train_cls"], label="train mode CE", ls=":")
    ax[0].set_xlabel("epoch")
    ax[0].set_title("loss")
    ax[0].legend()
    ax[1].plot(ep, curves["train_reg_ade"], label="train best-mode ADE")
    ax[1].plot(ep, curves["val_min_ade"], label=f"held-out minADE (K={modes}, 6 s)")
    ax[1].axhline(res["constant_velocity"]["min_ade"], color="r", ls="--", label="constant velocity (K=3, 6 s)")
    ax[1].axhline(res["lane_following"]["min_ade"], color="g", ls="--", label="lane following (K=3, 6 s)")
    ax[1].set_xlabel("epoch")
    ax[1].set_ylabel("m")
    ax[1].set_title("minADE over 6 s")
    ax[1].legend()
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
