"""Rotated-box geometry benchmark: speed of the exact IoU, and the planner's clearance
approximation (separating-axis gap) against the exact footprint distance.

    .venv/bin/python bench/boxes.py [--quick]

Prints a table and writes ``bench/results/boxes[.quick].json``.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.geometry.boxes import box_distance, box_separation, iou_pairwise  # noqa: E402


def random_boxes(rng, n, spread):
    return np.c_[rng.uniform(-spread, spread, (n, 2)), rng.uniform(3.5, 6.0, n), rng.uniform(1.6, 2.6, n),
                 rng.uniform(-np.pi, np.pi, n)]


def timed(fn, *args, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn(*args)
        best = min(best, time.process_time() - t0)
    return out, best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    print("| what | n | CPU ms | per item (us) | error vs exact |")
    print("|---|---|---|---|---|")
    for n, spread in ([(50, 30.0), (200, 60.0)] if args.quick else [(50, 30.0), (200, 60.0), (500, 100.0)]):
        a, b = random_boxes(rng, n, spread), random_boxes(rng, n, spread)
        iou, t = timed(iou_pairwise, a, b)
        rows.append({"what": "iou_pairwise", "n_pairs": n * n, "overlapping": int((iou > 0).sum()), "cpu_s": t})
        print(f"| iou_pairwise (N x N, {int((iou > 0).sum())} overlapping) | {n * n} | {1000 * t:.1f} | "
              f"{1e6 * t / (n * n):.2f} | exact |")
    m = 20000 if args.quick else 100000
    a, b = random_boxes(rng, m, 8.0), random_boxes(rng, m, 8.0)
    exact, t_exact = timed(box_distance, a, b)
    sep, t_sep = timed(box_separation, a, b)
    apart = exact > 0
    err = exact[apart] - np.maximum(sep[apart], 0.0)
    overlap_agree = float(np.mean((sep <= 0) == (exact == 0)))
    rows.append({"what": "box_distance", "n_pairs": m, "cpu_s": t_exact})
    rows.append({"what": "box_separation", "n_pairs": m, "cpu_s": t_sep, "max_underestimate_m": float(err.max()),
                 "mean_underestimate_m": float(err.mean()), "overlap_agreement": overlap_agree})
    print(f"| box_distance (exact) | {m} | {1000 * t_exact:.1f} | {1e6 * t_exact / m:.2f} | reference |")
    print(f"| box_separation (SAT gap, planner clearance) | {m} | {1000 * t_sep:.1f} | {1e6 * t_sep / m:.2f} | "
          f"underestimate mean {err.mean():.3f} m, max {err.max():.3f} m; overlap decisions agree "
          f"{100 * overlap_agree:.2f}% |")
    near = apart & (exact < 1.0)
    e_near = exact[near] - np.maximum(sep[near], 0.0)
    # highway traffic: nearly parallel vehicles (|relative yaw| < 0.2 rad)
    b2 = b.copy()
    b2[:, 4] = a[:, 4] + rng.uniform(-0.2, 0.2, m)
    ex2, sp2 = box_distance(a, b2), box_separation(a, b2)
    near2 = (ex2 > 0) & (ex2 < 1.0)
    e_par = ex2[near2] - np.maximum(sp2[near2], 0.0)
    rows.append({"what": "box_separation_within_1m", "random_yaw_max_m": float(e_near.max()),
                 "random_yaw_mean_m": float(e_near.mean()), "parallel_max_m": float(e_par.max()),
                 "parallel_mean_m": float(e_par.mean())})
    print(f"| ... pairs closer than 1 m (the buffer) | {int(near.sum())} random yaw, {int(near2.sum())} near-parallel "
          f"| | | random yaw: mean {e_near.mean():.3f} m, max {e_near.max():.3f} m; near-parallel (|dyaw| < 0.2): "
          f"mean {e_par.mean():.3f} m, max {e_par.max():.3f} m |")
    out = ROOT / "bench" / "results" / ("boxes.quick.json" if args.quick else "boxes.json")
    write_json(out, {"format": "adv3d-bench", "version": 1, "topic": "boxes",
                     "command": " ".join(["bench/boxes.py"] + sys.argv[1:]),
                     "machine": {"python": platform.python_version(), "platform": platform.platform(),
                                 "processor": platform.processor()},
                     "rows": rows})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
