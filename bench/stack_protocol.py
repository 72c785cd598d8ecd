"""The out-of-process protocol's cost per frame (docs/stack_protocol.md).

    .venv/bin/python bench/stack_protocol.py [--frames 300] [--out bench/results/stack_protocol.json]

One HDL-64E frame of ``highway-benchmark-000000`` (about 107k points, with the rig's sensor
index) is handed, ``--frames`` times, to a stack that does nothing but answer a 31-pose plan:
once in process (``PluginStack`` around the stack) and once in its own process
(``exec:python -m adv3d_runner.autonomy.remote stack_protocol:make``), alternating. The
overhead is the difference of the median wall times per frame; the target is under 2 ms.
Another frame size (130k points, the full HDL-64E turn without drops) is measured as well.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.autonomy.api import Plan, Sensors, StackInfo, StepOutput  # noqa: E402


class NullStack:
    """Answers a straight constant-speed plan: the stack's own work is next to nothing."""

    def info(self) -> StackInfo:
        return StackInfo("null", "1")

    def sensors(self) -> Sensors:
        return Sensors()

    def reset(self, episode) -> None:
        self.n = 0

    def run_step(self, frame) -> StepOutput:
        self.n += len(frame.points)
        x, y, yaw = frame.ego.pose
        s = np.arange(31) * 0.1 * frame.ego.speed
        return StepOutput(Plan(np.stack([x + s * np.cos(yaw), y + s * np.sin(yaw), np.full(31, yaw)], 1),
                               np.full(31, frame.ego.speed)))


def make() -> NullStack:
    return NullStack()


def _frame_points(n: int | None):
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sensors.lidar import simulate_frame
    from adv3d_runner.sensors.world import rig_from_scene, world_from_scene

    path = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    scene = load_scene(path)
    from adv3d_runner.sim.episode import default_library

    world = world_from_scene(scene, default_library(), scene_dir=path.parent)
    frame = simulate_frame(world, rig_from_scene(scene), scene.ego_poses()[0], np.full((len(world.actor_ids), 3), np.nan),
                           np.random.default_rng(0))
    pts = np.c_[frame.points[:, :3], np.zeros(len(frame.points))] if frame.points.shape[1] == 3 else frame.points
    if n is not None:  # repeat the frame's points up to n
        pts = np.resize(pts, (n, pts.shape[1]))
    return scene, pts.astype(np.float32)


def main() -> int:
    from adv3d_runner.autonomy.interface import EgoState, SceneContext
    from adv3d_runner.autonomy.plugins import PluginStack, build
    from adv3d_runner.machine import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "stack_protocol.json"))
    args = ap.parse_args()
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT / "bench"), str(ROOT)])
    rows = []
    for n in (None, 130_000):
        scene, pts = _frame_points(n)
        context = SceneContext.from_scene(scene)
        local = PluginStack(NullStack())
        remote, _ = build(f"exec:{sys.executable} -m adv3d_runner.autonomy.remote stack_protocol:make")
        times = {"in_process": [], "out_of_process": []}
        for stack in (local, remote):
            stack.reset(context)
        ego = EgoState(np.array(scene.ego_poses()[0], float), 25.0)
        for _ in range(args.frames):
            for name, stack in (("in_process", local), ("out_of_process", remote)):
                t = time.perf_counter()
                stack.step(pts, ego)
                times[name].append(time.perf_counter() - t)
        remote.close()
        med = {k: float(np.median(v)) * 1000 for k, v in times.items()}
        q = {k: [float(x) * 1000 for x in np.percentile(v, [25, 75])] for k, v in times.items()}
        rows.append({"points": int(len(pts)), "megabytes": round(pts.nbytes / 2**20, 2), "median_ms": med, "iqr_ms": q,
                     "overhead_ms": med["out_of_process"] - med["in_process"]})
        print(f"{len(pts):7d} points ({pts.nbytes / 2**20:.1f} MB): in process {med['in_process']:.3f} ms, "
              f"out of process {med['out_of_process']:.3f} ms (IQR {q['out_of_process'][0]:.2f}-{q['out_of_process'][1]:.2f}), "
              f"overhead {rows[-1]['overhead_ms']:.3f} ms per frame")
    doc = {"format": "adv3d-bench", "topic": "stack_protocol", "command": "python bench/stack_protocol.py "
           + " ".join(sys.argv[1:]), "machine": machine_info("numpy", "msgpack"), "frames": args.frames,
           "target_ms": 2.0, "rows": rows}
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
