"""What the detector's and the occupancy model's training loops share (``detector_train``,
``occupancy_train``): the seeded start, AdamW with a one-cycle cosine learning rate, one
clipped optimiser step, and the wall-clock time limit between epochs.

Each function does exactly what both loops did inline, in the same order (the same torch and
numpy draws), so a seed gives the same weights as before the loops shared them. The predictor's
loop (``predictor_train``) has its own schedule and clipping and does not use these.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import torch

GRAD_CLIP = 10.0   # max gradient norm of one step
PCT_START = 0.15   # fraction of the steps spent warming the learning rate up


def seeded_start(seed: int, threads: int, device) -> tuple[torch.device, np.random.Generator]:
    """Seed torch (the network's initial weights, drawn next), set its CPU threads, and return
    the device and the numpy generator of the loop's own draws (order, augmentation)."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    return torch.device(device), np.random.default_rng([seed, 7])


def one_cycle(net: torch.nn.Module, lr: float, weight_decay: float, epochs: int, n_train: int, batch: int
              ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    """AdamW on ``net`` and a one-cycle cosine schedule over ``epochs`` x ceil(n_train / batch)
    steps peaking at ``lr``."""
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    steps_per_epoch = max(1, math.ceil(n_train / batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=epochs * steps_per_epoch,
                                                pct_start=PCT_START, anneal_strategy="cos")
    return opt, sched


def optimiser_step(net: torch.nn.Module, opt: torch.optim.Optimizer,
                   sched: torch.optim.lr_scheduler.LRScheduler, loss: torch.Tensor) -> None:
    """Backpropagate ``loss``, clip the gradient norm to :data:`GRAD_CLIP`, step the optimiser
    and the schedule."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), GRAD_CLIP)
    opt.step()
    sched.step()


def out_of_time(t_start: float, time_limit_s: float | None, epoch: int, epochs: int, hist: dict,
                log: Callable[[str], None]) -> bool:
    """True (and ``hist["stopped_early"]`` set, a line logged) when the time limit is spent
    after ``epoch`` (0-based) and epochs remain."""
    if time_limit_s is not None and time.perf_counter() - t_start > time_limit_s and epoch + 1 < epochs:
        hist["stopped_early"] = True
        log(f"time limit {time_limit_s:.0f} s reached: stopping after epoch {epoch + 1}")
        return True
    return False
