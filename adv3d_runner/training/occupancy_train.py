"""Training and evaluation of Autonomy-B's occupancy model (``adv3d train occupancy``).

Loss per sample's query points (:mod:`.occupancy_data`): binary cross-entropy of the occupancy
logits, plus ``flow_weight`` x the smooth-L1 (beta 1 m/s) flow error over the occupied query
points whose flow is known. AdamW with a one-cycle (cosine) learning rate. Augmentation: a
random left/right mirror (y -> -y on the grid, the queries and the flow; the grid is symmetric
in y) and sweep dropout (the older sweeps zeroed, as in an episode's first frames).

Evaluation (:func:`evaluate_occupancy`) on held-out samples: mAP, Soft-IoU and foreground
EPE of :mod:`adv3d_runner.metrics.occupancy` over the samples' query points, plus the losses. These queries are half near actors, so these numbers are not the episode
metrics (``sim.evaluate``, on a fixed grid): they track training.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from ..autonomy.occupancy import OccupancyConfig, OccupancyModel, OccupancyNet
from ..metrics.occupancy import occupancy_ap, soft_iou
from .loop import one_cycle, optimiser_step, out_of_time, seeded_start
from .occupancy_data import SampleSet, decode_grid

FLOW_WEIGHT = 0.4
DROP_OLDER = 0.1   # probability that every sweep but the current one is missing (episode start)
DROP_OLDEST = 0.15  # probability that only the oldest sweep is missing


def make_batch(s: SampleSet, idx: np.ndarray, cfg: OccupancyConfig, rng: np.random.Generator | None = None
               ) -> tuple[torch.Tensor, ...]:
    """Tensors of samples ``idx``: x (B, C, nx, ny), queries (B, Q, 3), speed (B,), occupied
    (B, Q), flow (B, Q, 2), flow mask (B, Q). With ``rng``: mirror and sweep dropout."""
    x = decode_grid(s.grids[idx], cfg)
    q = s.queries[idx].copy()
    f = s.flow[idx].copy()
    if rng is not None:
        mirror = rng.random(len(idx)) < 0.5
        x[mirror] = x[mirror][..., ::-1]
        q[mirror, :, 1] *= -1.0
        f[mirror, :, 1] *= -1.0
        per = cfg.channels_per_sweep
        u = rng.random(len(idx))
        x[u < DROP_OLDER, per:] = 0.0
        x[(u >= DROP_OLDER) & (u < DROP_OLDER + DROP_OLDEST), -per:] = 0.0
    mask = s.occupied[idx] & s.flow_valid[idx]
    return (torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(q), torch.from_numpy(s.speed[idx]),
            torch.from_numpy(s.occupied[idx].astype(np.float32)), torch.from_numpy(f), torch.from_numpy(mask))


def occupancy_loss(logit: torch.Tensor, flow: torch.Tensor, occ: torch.Tensor, flow_true: torch.Tensor,
                   mask: torch.Tensor, flow_weight: float = FLOW_WEIGHT) -> tuple[torch.Tensor, torch.Tensor]:
    """(occupancy BCE, flow smooth-L1) of a batch (see module docstring)."""
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logit, occ)
    if mask.any():
        fl = torch.nn.functional.smooth_l1_loss(flow[mask], flow_true[mask], beta=1.0, reduction="sum") / mask.sum()
    else:
        fl = flow.sum() * 0.0
    return bce, flow_weight * fl


def predict(net: OccupancyNet, s: SampleSet, cfg: OccupancyConfig, device, batch: int = 16
            ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Occupancy probabilities (S, Q), flows (S, Q, 2) and the mean losses over ``s``."""
    net.eval()
    occ, flow, lb, lf = [], [], 0.0, 0.0
    with torch.inference_mode():
        for k in range(0, len(s), batch):
            idx = np.arange(k, min(k + batch, len(s)))
            x, q, v, o, f, m = (t.to(device) for t in make_batch(s, idx, cfg))
            logit, fl = net(x, q, v)
            b, c = occupancy_loss(logit, fl, o, f, m)
            lb += float(b) * len(idx)
            lf += float(c) * len(idx)
            occ.append(torch.sigmoid(logit).cpu().numpy())
            flow.append(fl.cpu().numpy())
    n = max(len(s), 1)
    return np.concatenate(occ), np.concatenate(flow), lb / n, lf / n


def evaluate_occupancy(net: OccupancyNet, s: SampleSet, cfg: OccupancyConfig, device="cpu") -> dict:
    """Held-out metrics over the samples' query points (see module docstring): mAP and
    Soft-IoU (per query time step, averaged over the steps), foreground EPE (m/s) and the
    losses. The flow-grounded metrics need the actors' boxes before each query time, which the
    samples do not keep: they are measured on episodes (``sim.evaluate``)."""
    occ, flow, lb, lf = predict(net, s, cfg, device)
    o = s.occupied.reshape(-1)
    p = occ.reshape(-1)
    m = (s.occupied & s.flow_valid).reshape(-1)
    d = flow.reshape(-1, 2) - s.flow.reshape(-1, 2)
    err = np.hypot(d[:, 0], d[:, 1])
    t = np.rint(s.queries[..., 2].reshape(-1) / cfg.dt).astype(int)
    a = np.array([(occupancy_ap(o[t == k], p[t == k]), soft_iou(o[t == k], p[t == k])) for k in np.unique(t)],
                 dtype=np.float64).reshape(-1, 2)
    mean = lambda c: float(np.nanmean(a[:, c])) if np.isfinite(a[:, c]).any() else None  # noqa: E731
    return {"samples": len(s), "queries": int(len(o)), "occupied": int(o.sum()), "bce": lb, "flow_loss": lf,
            "map": mean(0), "soft_iou": mean(1), "epe": float(err[m].mean()) if m.any() else None}


def train_occupancy(train: SampleSet, val: SampleSet | None, cfg: OccupancyConfig, epochs: int = 12,
                    batch: int = 8, lr: float = 2e-3, weight_decay: float = 1e-4, seed: int = 0,
                    threads: int = 1, device="cpu", log: Callable[[str], None] = print,
                    time_limit_s: float | None = None) -> tuple[OccupancyModel, dict]:
    """Train an :class:`OccupancyNet` on ``train``; returns the model (on the CPU) and a history
    dict (per-epoch train/held-out losses and held-out EPE/Soft-IoU, seconds, stopped_early)."""
    device, rng = seeded_start(seed, threads, device)
    net = OccupancyNet(cfg).to(device)
    opt, sched = one_cycle(net, lr, weight_decay, epochs, len(train), batch)
    hist = {"epoch": [], "train_bce": [], "train_flow": [], "val_bce": [], "val_flow": [], "val_soft_iou": [],
            "val_epe": [], "seconds": [], "stopped_early": False}
    val_sub = val.subset(np.linspace(0, len(val) - 1, min(len(val), 60)).astype(int)) if val is not None and len(val) else None
    t_start = time.perf_counter()
    for ep in range(epochs):
        net.train()
        order = rng.permutation(len(train))
        sb = sf = 0.0
        for k in range(0, len(order), batch):
            idx = np.sort(order[k:k + batch])
            x, q, v, o, f, m = (t.to(device) for t in make_batch(train, idx, cfg, rng))
            logit, fl = net(x, q, v)
            b, c = occupancy_loss(logit, fl, o, f, m)
            optimiser_step(net, opt, sched, b + c)
            sb += b.item() * len(idx)
            sf += c.item() * len(idx)
        hist["epoch"].append(ep + 1)
        hist["train_bce"].append(sb / len(train))
        hist["train_flow"].append(sf / len(train))
        if val_sub is not None:
            ev = evaluate_occupancy(net, val_sub, cfg, device)
            vb, vf, vi, ve = ev["bce"], ev["flow_loss"], ev["soft_iou"], ev["epe"]
        else:
            vb = vf = vi = ve = float("nan")
        hist["val_bce"].append(vb)
        hist["val_flow"].append(vf)
        hist["val_soft_iou"].append(vi)
        hist["val_epe"].append(ve)
        hist["seconds"].append(time.perf_counter() - t_start)
        log(f"epoch {ep + 1}/{epochs}: train bce {hist['train_bce'][-1]:.4f} flow {hist['train_flow'][-1]:.4f} | "
            f"held-out bce {vb:.4f} flow {vf:.4f} soft-IoU {vi:.3f} EPE {ve:.2f} m/s | {hist['seconds'][-1]:.0f} s")
        if out_of_time(t_start, time_limit_s, ep, epochs, hist, log):
            break
    net = net.cpu().eval()
    return OccupancyModel(cfg, net, threads=1), hist


def plot_history(hist: dict, path, title: str = "") -> None:
    """Loss curves PNG: occupancy BCE and flow loss (train, held-out), held-out Soft-IoU and EPE."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import atomic_path

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    ep = hist["epoch"]
    for ax, key, name in ((axes[0], "bce", "occupancy BCE"), (axes[1], "flow", f"flow loss ({FLOW_WEIGHT} x smooth L1)")):
        ax.plot(ep, hist[f"train_{key}"], "o-", label="train")
        if np.isfinite(np.asarray(hist[f"val_{key}"], dtype=float)).any():
            ax.plot(ep, hist[f"val_{key}"], "s-", label="held-out")
        ax.set_title(name)
        ax.set_yscale("log")
    axes[2].plot(ep, hist["val_soft_iou"], "s-", color="C2", label="held-out Soft-IoU")
    ax2 = axes[2].twinx()
    ax2.plot(ep, hist["val_epe"], "^-", color="C3", label="held-out EPE (m/s)")
    axes[2].set_title("held-out Soft-IoU (left), EPE m/s (right)")
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[0].legend()
    axes[1].legend()
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
