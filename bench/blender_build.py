"""Build shape space in Blender: how long the modal Build takes and how long it holds the UI.

    .venv/bin/python bench/blender_build.py [--resolution 64] [--no-compare]

Runs the add-on's Build job (``blender_addon.ops_shapes.build_steps``: the runner's stepwise
``build_shape_space_steps`` over the shipped library's shape-space assets, then the atomic
write) sliced as the modal operator slices it (``jobs.SLICE_S`` of work per timer tick) and
reports wall and CPU time, the number of steps and timer ticks, the longest step and the longest
slice (the longest time Blender's UI waits). Unless ``--no-compare``, the runner's one-call
``build_shape_space`` builds the same space too: its time (the cost of slicing) and whether the
bytes are the same. Writes bench/results/blender_build.json.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--no-compare", action="store_true", help="skip the one-call build")
    args = parser.parse_args()

    import bpy

    import blender_addon
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.shapes.shape_space import build_shape_space
    from blender_addon import jobs, ops_shapes

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    library = load_library()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "space.npz"
        job = jobs.Job("Build shape space", ops_shapes.build_steps(library, str(out),
                                                                   {"k": 3, "resolution": args.resolution}))
        ticks, slices = 0, []
        t0, c0 = time.perf_counter(), time.process_time()
        while True:
            t = time.perf_counter()
            state = job.run_slice()
            slices.append(time.perf_counter() - t)
            ticks += 1
            if state != jobs.RUNNING:
                break
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        assert job.state == jobs.DONE, job.error
        digest = hashlib.sha256(out.read_bytes()).hexdigest()
    blender_addon.unregister()
    result = {"resolution": args.resolution, "assets": len(job.result.asset_ids), "wall_s": wall, "cpu_s": cpu,
              "steps": job.n_steps, "ticks": ticks, "max_step_s": job.max_step_s, "max_step_cpu_s": job.max_step_cpu_s,
              "slowest_step_after": job.slowest, "max_slice_s": max(slices),
              "median_slice_ms": 1e3 * sorted(slices)[len(slices) // 2], "sha256": digest}
    print(f"modal Build, {result['assets']} assets at {args.resolution}^3: {wall:.1f} s wall, {cpu:.1f} s CPU, "
          f"{job.n_steps} steps in {ticks} timer ticks; UI held at most {1e3 * max(slices):.0f} ms "
          f"(longest step {1e3 * job.max_step_s:.0f} ms wall after '{job.slowest}', most CPU in one step "
          f"{1e3 * job.max_step_cpu_s:.0f} ms; median slice {result['median_slice_ms']:.0f} ms)")
    if not args.no_compare:
        t0, c0 = time.perf_counter(), time.process_time()
        space = build_shape_space(library, resolution=args.resolution, k=3, progress=False)
        result["one_call"] = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                              "same_bytes": hashlib.sha256(space.to_bytes()).hexdigest() == digest}
        print(f"one-call build_shape_space: {result['one_call']['wall_s']:.1f} s wall, "
              f"{result['one_call']['cpu_s']:.1f} s CPU, same bytes: {result['one_call']['same_bytes']}")
    path = REPO / "bench" / "results" / "blender_build.json"
    path.write_text(json.dumps({
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "blender": bpy.app.version_string, "cpu_count": os.cpu_count(),
                    "load_average_1min_at_end": os.getloadavg()[0],
                    "note": "2-core machine shared with other jobs: wall times include waiting for a core"},
        "build": result,
        "target": "the UI never held for 0.5 s or more (build.max_slice_s)",
    }, indent=1) + "\n")
    print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
