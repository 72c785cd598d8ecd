"""The detector network's CPU time per frame under this process's numerical configuration, and
what changes it: run natively and under ``adv3d numerics --emulate avx2 -- ...`` to compare ISAs.

    .venv/bin/python bench/detector_isa.py [--frames 30] [--out FILE]

One thread (``torch.set_num_threads(1)``, pinned to one core), the shipped 0.25 m model with its
BatchNorms folded (``load_detector``), a synthetic 100k-point frame (seeded). Reports the median
``time.thread_time`` of the network per frame for: the shipped path; ``channels_last`` tensors
(oneDNN without the per-call activation reorders); flush-to-zero of denormals
(``torch.set_flush_denormal``). Each variant's outputs are compared bit for bit with the
shipped path's. Writes JSON to ``--out`` (default: print only).
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


def median_ms(fn, frames: int) -> float:
    for _ in range(3):
        fn()
    ts = []
    for _ in range(frames):
        t = time.thread_time()
        fn()
        ts.append(time.thread_time() - t)
    return 1000.0 * float(np.median(ts))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    det = load_detector()
    rng = np.random.default_rng(0)
    n = 100_000
    pts = np.c_[rng.uniform(-20, 80, n), rng.uniform(-35, 35, n), rng.uniform(-1, 3, n), rng.uniform(0, 1, n)]
    grid = voxelize(pts.astype(np.float32), det.cfg)[None]
    ref = det._forward(grid)
    x = torch.from_numpy(np.ascontiguousarray(grid))
    net_cl = copy.deepcopy(det.inference_net).to(memory_format=torch.channels_last)

    def channels_last():
        with torch.inference_mode():
            logits, box = net_cl(x.contiguous(memory_format=torch.channels_last))
            return torch.sigmoid(logits[:, 0]).contiguous().numpy(), box.contiguous().numpy()

    def same(out) -> bool:
        return all(np.array_equal(a, b) for a, b in zip(ref, out))

    variants = {"shipped": median_ms(lambda: det._forward(grid), args.frames)}
    variants["channels_last"] = median_ms(channels_last, args.frames)
    identical = {"channels_last": same(channels_last())}
    torch.set_flush_denormal(True)
    variants["flush_denormal"] = median_ms(lambda: det._forward(grid), args.frames)
    identical["flush_denormal"] = same(det._forward(grid))
    torch.set_flush_denormal(False)
    variants["shipped_again"] = median_ms(lambda: det._forward(grid), args.frames)
    doc = {"format": "adv3d.bench", "topic": "detector_isa",
           "command": " ".join([Path(sys.executable).name, "bench/detector_isa.py"] + sys.argv[1:]),
           "machine": machine_info("numpy", "torch"), "load_average": list(os.getloadavg()),
           "torch_threads": torch.get_num_threads(), "grid": list(grid.shape),
           "timing": "median time.thread_time of the network per frame, ms", "network_ms": variants,
           "identical_to_shipped": identical}
    print(json.dumps({k: doc[k] for k in ("network_ms", "identical_to_shipped", "load_average")}, indent=1))
    if args.out:
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
