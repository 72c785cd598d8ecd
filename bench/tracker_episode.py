"""The tracker's own CPU time inside a closed-loop Autonomy-A episode (the second of a workspace:
numba and torch warm), per frame, with the detections and tracks it handled.

    .venv/bin/python bench/tracker_episode.py [--scene highway-benchmark-000010] [--out FILE]

One process pinned to one core, one thread per library; ``time.thread_time`` around every
``MultiObjectTracker.update`` of one 5 s episode of the original scene. Run natively and under
``adv3d numerics --emulate avx2 --`` to compare numerical configurations.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack import evaluator  # noqa: E402
from adv3d_runner.attack.config import QuerySettings  # noqa: E402
from adv3d_runner.autonomy import tracker  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="highway-benchmark-000010")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    calls: list[tuple[float, int, int]] = []
    update = tracker.MultiObjectTracker.update

    def timed(self, detections, *a, **k):
        t = time.thread_time()
        out = update(self, detections, *a, **k)
        calls.append((time.thread_time() - t, len(detections.boxes), len(self._tracks)))
        return out

    tracker.MultiObjectTracker.update = timed
    ws = evaluator.workspace_for(str(ROOT / "scenes" / "highway" / f"{args.scene}.json.gz"), QuerySettings(autonomy="A"))
    ws.evaluate(None, closed_loop=True)  # warm
    calls.clear()
    t0 = time.process_time()
    ws.evaluate(None, closed_loop=True)
    episode = time.process_time() - t0
    c = np.array(calls)
    doc = {"format": "adv3d.bench", "topic": "tracker_episode",
           "command": " ".join([Path(sys.executable).name, "bench/tracker_episode.py"] + sys.argv[1:]),
           "machine": machine_info("numpy", "torch"), "load_average": list(os.getloadavg()), "scene": args.scene,
           "frames": len(c), "tracker_ms_per_frame_mean": 1000 * float(c[:, 0].mean()),
           "tracker_s_per_episode": float(c[:, 0].sum()), "episode_cpu_s": episode,
           "detections_per_frame_mean": float(c[:, 1].mean()), "tracks_per_frame_mean": float(c[:, 2].mean())}
    print(json.dumps({k: v for k, v in doc.items() if k not in ("machine", "command")}, indent=1))
    if args.out:
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
