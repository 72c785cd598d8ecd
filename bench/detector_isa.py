"""The detector network's CPU time per frame under this process's numerical configuration, and
what changes it: run natively and under ``adv3d numerics --emulate avx2 -- ...`` to compare ISAs.

    .venv/bin/python bench/detector_isa.py [--frames 30] [--out FILE]

One thread (``torch.set_num_threads(1)``, pinned to one core), the shipped 0.25 m model with its
BatchNorms folded (``load_detector``), a synthetic 100k-point frame (seeded). Reports the median
``time.thread_time`` of the network per frame for: the shipped path (what ``BevDetector``
runs: ``blocked_forward`` where it gives ``flat_forward``'s bits); ``flat_forward`` (plain NCHW
tensors, oneDNN reordering each convolution's input, weights and output every call);
``channels_last`` tensors; flush-to-zero of denormals (``torch.set_flush_denormal``); the
``bfloat16`` precision option. The variants are timed in turns (``--frames`` rounds, each
variant once per round), so they share the machine's load. Each variant's outputs are compared
bit for bit with the shipped path's. Writes JSON to ``--out`` (default: print only).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.autonomy.detector import load_detector, voxelize  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402


def median_ms(fns: dict, frames: int) -> dict:
    """Median ``time.thread_time`` (ms) of each function of ``fns``, called in turns."""
    for fn in fns.values():
        for _ in range(3):
            fn()
    ts: dict = {k: [] for k in fns}
    for _ in range(frames):
        for k, fn in fns.items():
            t = time.thread_time()
            fn()
            ts[k].append(time.thread_time() - t)
    return {k: 1000.0 * float(np.median(v)) for k, v in ts.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    det = load_detector()
    det.blocked_after = 0  # the blocked layout's check at the first call
    rng = np.random.default_rng(0)
    n = 100_000
    pts = np.c_[rng.uniform(-20, 80, n), rng.uniform(-35, 35, n), rng.uniform(-1, 3, n), rng.uniform(0, 1, n)]
    grid = voxelize(pts.astype(np.float32), det.cfg)[None]
    ref = det._forward(grid)
    runs_blocked = det._runner(tuple(grid.shape)) is not det._flat[1]
    x = torch.from_numpy(np.ascontiguousarray(grid))
    net_cl = copy.deepcopy(det.inference_net).to(memory_format=torch.channels_last)

    def channels_last():
        with torch.inference_mode():
            logits, box = net_cl(x.contiguous(memory_format=torch.channels_last))
            return torch.sigmoid(logits[:, 0]).contiguous().numpy(), box.contiguous().numpy()

    def same(out) -> bool:
        return all(np.array_equal(a, b) for a, b in zip(ref, out))

    from adv3d_runner.autonomy.detector import flat_forward

    flat = flat_forward(det.inference_net)
    half = load_detector(precision="bfloat16")

    def plain():
        with torch.inference_mode():
            logits, box = flat(x)
            return torch.sigmoid(logits[:, 0]).numpy(), box.numpy()

    variants = median_ms({"shipped": lambda: det._forward(grid), "flat_forward": plain,
                          "channels_last": channels_last, "bfloat16": lambda: half._forward(grid)}, args.frames)
    identical = {"flat_forward": same(plain()), "channels_last": same(channels_last()),
                 "bfloat16": same(half._forward(grid))}
    torch.set_flush_denormal(True)
    variants.update({f"{k}_flush_denormal": v for k, v in median_ms({"shipped": lambda: det._forward(grid)},
                                                                      args.frames).items()})
    identical["shipped_flush_denormal"] = same(det._forward(grid))
    torch.set_flush_denormal(False)
    doc = {"format": "adv3d.bench", "topic": "detector_isa",
           "command": " ".join([Path(sys.executable).name, "bench/detector_isa.py"] + sys.argv[1:]),
           "machine": machine_info("numpy", "torch"), "load_average": list(os.getloadavg()),
           "torch_threads": torch.get_num_threads(), "grid": list(grid.shape),
           "shipped_runs_blocked_forward": runs_blocked,
           "timing": "median time.thread_time of the network per frame, ms", "network_ms": variants,
           "identical_to_shipped": identical}
    print(json.dumps({k: doc[k] for k in ("network_ms", "identical_to_shipped", "load_average")}, indent=1))
    if args.out:
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
