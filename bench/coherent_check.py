"""Every background cast of whole episodes: the certified coherent cast against the reference query.

    .venv/bin/python bench/coherent_check.py [--generated 30] [--seconds 5] [--out bench/results/coherent_check.json]

Runs 5 s closed-loop Autonomy-A episodes on the first N generated benchmark scenes and on every
scene in ``scenes/real/``; each background cast (``MeshBVH._intersect_coherent``, see
``adv3d_runner/sensors/coherent.py``) is repeated with Embree's reference query on the same rays
and limits, and the distances (as bits) and faces are compared. Reports rays, differing rays,
rays cast again and the CPU time of both, per scene and in all (docs/lidar.md, "Coherent
background casts").
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402
from adv3d_runner.sensors import raycast  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generated", type=int, default=30, help="first N generated benchmark scenes")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "coherent_check.json"))
    args = ap.parse_args()

    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import world_from_scene
    from adv3d_runner.sim.episode import default_library, run_episode

    totals = {"calls": 0, "rays": 0, "differing_distance": 0, "differing_face": 0, "cast_again": 0,
              "reference_s": 0.0, "certified_s": 0.0}
    certified = raycast.MeshBVH._intersect_coherent

    def compared(self, origins, directions, tfar):
        t_ref = tfar.copy()
        a = time.thread_time()
        p_ref = self._scene.intersect(origins, directions, t_ref)
        b = time.thread_time()
        before = self.recast_rays
        prim = certified(self, origins, directions, tfar)
        totals["reference_s"] += b - a
        totals["certified_s"] += time.thread_time() - b
        totals["cast_again"] += self.recast_rays - before
        totals["calls"] += 1
        totals["rays"] += len(directions)
        totals["differing_distance"] += int((tfar.view(np.int32) != t_ref.view(np.int32)).sum())
        totals["differing_face"] += int((prim != p_ref).sum())
        return prim

    raycast.MeshBVH._intersect_coherent = compared
    stack = make_stack("A")
    paths = sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json.gz"))[:args.generated]
    paths += sorted((ROOT / "scenes" / "real").glob("*.json.gz"))
    rows = []
    for k, path in enumerate(paths, 1):
        before = dict(totals)
        scene = load_scene(path)
        run_episode(scene, stack, seconds=args.seconds, world=world_from_scene(scene, default_library()))
        row = {"scene": path.name, **{key: totals[key] - before[key] for key in totals}}
        rows.append(row)
        print(f"[{k}/{len(paths)}] {path.name:34s} rays {row['rays']:>10,d}  differing {row['differing_distance']} / "
              f"{row['differing_face']}  cast again {row['cast_again'] / max(row['rays'], 1):.1%}  "
              f"reference {row['reference_s']:.2f} s  certified {row['certified_s']:.2f} s", flush=True)
    result = {"benchmark": "coherent_check", "command": " ".join([Path(sys.executable).name] + sys.argv),
              "machine": machine_info("numpy", "embreex"), "load_average": list(os.getloadavg()),
              "seconds": args.seconds, "autonomy": "A", "totals": totals, "scenes": rows}
    write_json(Path(args.out), result)
    print(f"all: {totals}\nwrote {args.out}")
    return 0 if totals["differing_distance"] == 0 and totals["differing_face"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
