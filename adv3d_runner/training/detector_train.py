"""Training and evaluation of the BEV detector (``adv3d train detector``).

Loss (PIXOR): sigmoid focal loss (alpha 0.25, gamma 2) on the score map, normalised by the
number of positive cells, with zero weight inside "ignore" boxes; smooth-L1 on the 6 box
channels at positive cells. AdamW with a one-cycle (cosine) learning rate; augmentation: a
random left/right mirror of each frame (y -> -y, yaw -> -yaw; the grid is symmetric in y).

Evaluation (:func:`evaluate_detector`): AP and recall at BEV IoU 0.5
(:func:`adv3d_runner.metrics.detection.average_precision`, VOC all-point AP) over vehicles whose
centre is within the paper's ROI, 0-50 m ahead of the ego, and within ``lateral`` m to either
side (default 20 m: the whole width of the widest generated highway around the ego). Ground
truth = actors with >= ``min_points`` returns; detections whose best IoU with an "ignore" box is
>= 0.3 are removed first (they are neither true nor false positives: KITTI's DontCare).
"""
from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np
import torch

from ..autonomy.detector import BevDetector, DetectorConfig, PixorNet, encode_targets, voxelize
from ..autonomy.interface import Detections
from ..geometry.boxes import iou_pairwise
from ..metrics.detection import ROI_AHEAD, average_precision, grouped_average_precision
from .detector_data import DEFAULT_MIN_POINTS, FrameSet, split_gt
from .loop import one_cycle, optimiser_step, out_of_time, seeded_start

ROI_LATERAL = 20.0
IGNORE_IOU = 0.3
EVAL_THRESHOLD = 0.05  # score threshold for AP curves (the operating threshold is in the config)


def _mirror(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = points.copy()
    p[:, 1] = -p[:, 1]
    b = boxes.copy()
    b[:, 1] = -b[:, 1]
    b[:, 4] = -b[:, 4]
    return p, b


def make_batch(fs: FrameSet, idx: np.ndarray, cfg: DetectorConfig, min_points: int,
               mirror: np.ndarray | None = None) -> tuple[torch.Tensor, ...]:
    """Inputs and targets of frames ``idx``: x (B, C, nx, ny), score/weight (B, ox, oy),
    reg (B, 6, ox, oy)."""
    xs, ss, ws, rs = [], [], [], []
    for k, f in enumerate(idx):
        pts = fs.frame_points(int(f))
        boxes, npts = fs.frame_boxes(int(f))
        if mirror is not None and mirror[k]:
            pts, boxes = _mirror(pts, boxes)
        gt, ign = split_gt(boxes, npts, min_points)
        xs.append(voxelize(pts, cfg))
        s, w, r = encode_targets(gt, cfg, ign)
        ss.append(s)
        ws.append(w)
        rs.append(r)
    return tuple(torch.from_numpy(np.stack(a)) for a in (xs, ss, ws, rs))


def detector_loss(logits: torch.Tensor, box: torch.Tensor, score: torch.Tensor, weight: torch.Tensor,
                  reg: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(score loss, box loss) of a batch; logits (B, 1, ox, oy), box (B, 6, ox, oy)."""
    z = logits[:, 0]
    p = torch.sigmoid(z)
    ce = torch.nn.functional.binary_cross_entropy_with_logits(z, score, reduction="none")
    p_t = p * score + (1 - p) * (1 - score)
    a_t = alpha * score + (1 - alpha) * (1 - score)
    focal = a_t * (1 - p_t) ** gamma * ce * weight
    n_pos = score.sum().clamp(min=1.0)
    cls = focal.sum() / n_pos
    pos = score > 0.5
    if pos.any():
        diff = torch.nn.functional.smooth_l1_loss(box.permute(0, 2, 3, 1)[pos], reg.permute(0, 2, 3, 1)[pos],
                                                  beta=0.1, reduction="sum")
        box_loss = diff / n_pos
    else:
        box_loss = box.sum() * 0.0
    return cls, box_loss


def evaluate_detector(det: BevDetector, fs: FrameSet, min_points: int = DEFAULT_MIN_POINTS,
                      ahead: float = ROI_AHEAD, lateral: float = ROI_LATERAL, iou_threshold: float = 0.5,
                      detections: list[Detections] | None = None, score_threshold: float | None = EVAL_THRESHOLD,
                      box_groups: np.ndarray | None = None, groups: Sequence | None = None) -> dict:
    """AP / recall at BEV IoU ``iou_threshold`` over ``fs`` in the ROI (see module doc).

    Args:
        score_threshold: detections kept for the precision/recall curve (low, so AP sees the
            whole curve; None = the detector's operating threshold). Ignored with ``detections``.
        box_groups: (B,) a group label per box of ``fs`` (e.g. "seen" / "held_out", or the
            asset id); with ``groups`` (the labels to report) the result also holds
            ``by_group`` (:func:`adv3d_runner.metrics.detection.grouped_average_precision`:
            the same matching, per ground-truth group).
    Returns:
        dict with ap, recall, n_gt, n_det, n_tp, n_frames and the ROI parameters (+ by_group).
    """
    if detections is None:
        detections = det.detect_batch([fs.frame_points(f) for f in range(len(fs))], score_threshold=score_threshold)
    frames, grouped = [], []
    target = fs.box_points >= min_points                      # split_gt's rule, per box of fs
    for f, d in enumerate(detections):
        in_frame = fs.box_frame == f
        boxes = fs.boxes[in_frame]
        gt, ign = boxes[target[in_frame]], boxes[~target[in_frame]]
        db, ds = d.boxes, d.scores
        if len(ign) and len(db):
            keep = iou_pairwise(db, ign).max(axis=1) < IGNORE_IOU
            db, ds = db[keep], ds[keep]
        in_roi = lambda b: (b[:, 0] >= 0) & (b[:, 0] <= ahead) & (np.abs(b[:, 1]) <= lateral)  # noqa: E731
        gm, dm = in_roi(gt), in_roi(db)
        frames.append((gt[gm], db[dm], ds[dm]))
        if box_groups is not None:
            grouped.append((gt[gm], np.asarray(box_groups)[in_frame][target[in_frame]][gm], db[dm], ds[dm]))
    m = average_precision(frames, iou_threshold)
    out = m.as_dict()
    out.update(n_frames=len(fs), iou_threshold=iou_threshold, roi_ahead_m=ahead, roi_lateral_m=lateral,
               min_points=min_points)
    if box_groups is not None and groups is not None:
        out["by_group"] = grouped_average_precision(grouped, groups, iou_threshold)
    return out


def val_loss(net: PixorNet, fs: FrameSet, cfg: DetectorConfig, min_points: int, batch: int = 16,
             device="cpu") -> tuple[float, float]:
    net.eval()
    tot_c = tot_b = 0.0
    n = 0
    with torch.inference_mode():
        for k in range(0, len(fs), batch):
            idx = np.arange(k, min(k + batch, len(fs)))
            x, s, w, r = (t.to(device) for t in make_batch(fs, idx, cfg, min_points))
            logits, box = net(x)
            c, b = detector_loss(logits, box, s, w, r)
            tot_c += float(c) * len(idx)
            tot_b += float(b) * len(idx)
            n += len(idx)
    return tot_c / max(n, 1), tot_b / max(n, 1)


def train_detector(train: FrameSet, val: FrameSet | None, cfg: DetectorConfig, epochs: int = 12, batch: int = 8,
                   lr: float = 2e-3, weight_decay: float = 1e-4, seed: int = 0, min_points: int = DEFAULT_MIN_POINTS,
                   threads: int = 1, log: Callable[[str], None] = print, time_limit_s: float | None = None,
                   device="cpu") -> tuple[BevDetector, dict]:
    """Train a :class:`PixorNet` on ``train`` (on ``device``: "cpu", the shipped weights, or a
    ``torch.device``); returns the detector (on the CPU) and a history dict (per-epoch
    train/val losses, seconds, stopped_early)."""
    device, rng = seeded_start(seed, threads, device)
    net = PixorNet(cfg).to(device)
    opt, sched = one_cycle(net, lr, weight_decay, epochs, len(train), batch)
    hist = {"epoch": [], "train_score_loss": [], "train_box_loss": [], "val_score_loss": [], "val_box_loss": [],
            "seconds": [], "stopped_early": False}
    # Held-out loss per epoch on at most 120 evenly spread frames (the full held-out set is
    # used for AP at the end); keeps the per-epoch overhead small.
    val_sub = None
    if val is not None and len(val):
        val_sub = subset(val, 120)
    t_start = time.perf_counter()
    for ep in range(epochs):
        net.train()
        order = rng.permutation(len(train))
        mirror = rng.random(len(train)) < 0.5
        sc = sb = 0.0
        for k in range(0, len(order), batch):
            idx = order[k:k + batch]
            x, s, w, r = (t.to(device) for t in make_batch(train, idx, cfg, min_points, mirror[k:k + batch]))
            logits, box = net(x)
            c, b = detector_loss(logits, box, s, w, r)
            optimiser_step(net, opt, sched, c + b)
            sc += c.item() * len(idx)
            sb += b.item() * len(idx)
        hist["epoch"].append(ep + 1)
        hist["train_score_loss"].append(sc / len(train))
        hist["train_box_loss"].append(sb / len(train))
        if val_sub is not None:
            vc, vb = val_loss(net, val_sub, cfg, min_points, device=device)
        else:
            vc = vb = float("nan")
        hist["val_score_loss"].append(vc)
        hist["val_box_loss"].append(vb)
        hist["seconds"].append(time.perf_counter() - t_start)
        log(f"epoch {ep + 1}/{epochs}: train score {hist['train_score_loss'][-1]:.4f} box {hist['train_box_loss'][-1]:.4f}"
            f" | val score {vc:.4f} box {vb:.4f} | {hist['seconds'][-1]:.0f} s")
        if out_of_time(t_start, time_limit_s, ep, epochs, hist, log):
            break
    net = net.cpu().eval()
    return BevDetector(cfg, net, threads=1), hist


def subset(fs: FrameSet, n: int) -> FrameSet:
    """At most ``n`` evenly spread frames of ``fs``."""
    if len(fs) <= n:
        return fs
    parts = []
    for f in np.linspace(0, len(fs) - 1, n).astype(int):
        m = fs.box_frame == f
        parts.append(FrameSet(fs.frame_points(int(f)), np.array([0, fs.offsets[f + 1] - fs.offsets[f]], np.int64),
                              fs.boxes[m], np.zeros(int(m.sum()), np.int64), fs.box_points[m], fs.box_actor[m],
                              fs.scene_seed[f:f + 1], fs.frame_index[f:f + 1]))
    return FrameSet.concat(parts)


def plot_losses(hist: dict, path, title: str = "") -> None:
    """Loss curves PNG (train and held-out, score and box terms)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import atomic_path

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, name in ((axes[0], "score", "score (focal) loss"), (axes[1], "box", "box (smooth L1) loss")):
        ax.plot(hist["epoch"], hist[f"train_{key}_loss"], "o-", label="train")
        if np.isfinite(hist[f"val_{key}_loss"]).any():
            ax.plot(hist["epoch"], hist[f"val_{key}_loss"], "s-", label="held-out")
        ax.set_xlabel("epoch")
        ax.set_title(name)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend()
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def machine_info() -> dict:
    from ..machine import machine_info as _machine_info

    return _machine_info("torch", "numpy")
