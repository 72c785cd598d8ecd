"""Thread settings and torch inference options against the stack's time per frame.

    .venv/bin/python bench/threads.py [--repeats 3] [--scene highway-benchmark-000010]

The LiDAR frames and ego states of one 5 s closed-loop Autonomy-A episode are recorded once;
then, for each configuration, a fresh process (the thread settings must be in place before
numpy and torch load) replays them through the stack (detector, tracker, predictor, planner)
``--repeats`` times and reports per stage the CPU time of the whole process
(``time.process_time``: every thread's time, so threads that spin show up) and the wall time,
per frame, and whether its outputs (detections, plans) are the same bits as the default's.

Configurations: one thread per library (the default of the ``adv3d`` command and of attack
workers); torch with 2 threads; the environment unset (OpenBLAS and OpenMP start one thread
per core) with the detector's 1 thread (the previous default) and with torch's own default;
``torch.no_grad`` instead of ``torch.inference_mode``; ``channels_last``; ``torch.jit.trace``;
``torch.compile``.

Writes ``bench/results/threads.json``. The machine is shared (the load average is recorded):
threads that wait for a core another job holds burn CPU spinning, which is what one sees here.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ONE = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
CONFIGS = {
    "one thread (default)": {"env": ONE, "torch_threads": 1},
    "torch 2 threads": {"env": ONE, "torch_threads": 2},
    "env unset, torch 1 thread (before)": {"env": None, "torch_threads": 1},
    "env unset, torch default threads": {"env": None, "torch_threads": None},
    "one thread, no_grad": {"env": ONE, "torch_threads": 1, "option": "no_grad"},
    "one thread, channels_last": {"env": ONE, "torch_threads": 1, "option": "channels_last"},
    "one thread, jit.trace": {"env": ONE, "torch_threads": 1, "option": "jit_trace"},
    "one thread, torch.compile": {"env": ONE, "torch_threads": 1, "option": "compile"},
}
STAGES = ("detector", "tracker", "predictor", "planner")


def record(scene_name: str, path: Path) -> None:
    """One closed-loop episode's points and ego states -> ``path`` (npz)."""
    import numpy as np

    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sim.episode import run_episode

    scene = load_scene(ROOT / "scenes" / "highway" / f"{scene_name}.json.gz")
    r = run_episode(scene, make_stack("A"), seconds=5.0, record_points=True)
    np.savez(path, ego_poses=r.ego_poses, ego_speeds=r.ego_speeds, ego_accels=r.ego_accels,
             **{f"points{k}": p[:, :4] for k, p in enumerate(r.points)})


def child(name: str, inputs: Path, repeats: int, scene_name: str) -> dict:
    cfg = CONFIGS[name]
    import numpy as np
    import torch

    from adv3d_runner.autonomy.interface import EgoState, SceneContext
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene import load_scene

    option = cfg.get("option")
    stack = make_stack("A")
    det = stack.detector
    det.threads = cfg["torch_threads"]
    stack.predictor.threads = cfg["torch_threads"]
    if option == "no_grad":
        torch.inference_mode = torch.no_grad
    elif option in ("channels_last", "jit_trace", "compile"):
        example = torch.zeros((1, det.cfg.in_channels) + det.cfg.grid_shape)
        if option == "channels_last":
            net = det.inference_net.to(memory_format=torch.channels_last)
            forward = net.forward
            det.inference_net.forward = lambda x: forward(x.contiguous(memory_format=torch.channels_last))
        elif option == "jit_trace":
            with torch.inference_mode():
                det.inference_net = torch.jit.trace(det.inference_net, example)
        else:
            det.inference_net = torch.compile(det.inference_net)
            with torch.inference_mode():
                det.inference_net(example)  # compile outside the timing
    scene = load_scene(ROOT / "scenes" / "highway" / f"{scene_name}.json.gz")
    context = SceneContext.from_scene(scene)
    data = np.load(inputs)
    T = len(data["ego_poses"])
    frames = [data[f"points{k}"] for k in range(T)]
    egos = [EgoState(data["ego_poses"][k], float(data["ego_speeds"][k]), acceleration=float(data["ego_accels"][k]),
                     time=0.1 * k, length=float(scene.ego.dimensions[0]), width=float(scene.ego.dimensions[1]),
                     wheelbase=float(scene.ego.wheelbase)) for k in range(T)]

    clocks = {s: [0.0, 0.0] for s in STAGES}

    def wrap(obj, method, stage):
        orig = getattr(obj, method)

        def timed(*a, **k):
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return orig(*a, **k)
            finally:
                clocks[stage][0] += time.process_time() - c0
                clocks[stage][1] += time.perf_counter() - w0

        setattr(obj, method, timed)

    wrap(stack.detector, "detect", "detector")
    wrap(stack.tracker, "update", "tracker")
    wrap(stack.predictor, "predict", "predictor")
    wrap(stack.planner, "plan", "planner")
    digest = hashlib.sha256()
    per_rep = []
    for rep in range(repeats + 1):  # the first replay warms up
        for s in STAGES:
            clocks[s] = [0.0, 0.0]
        stack.reset(context)
        c0, w0 = time.process_time(), time.perf_counter()
        for k in range(T):
            out = stack.step(frames[k], egos[k])
            if rep == 0:
                digest.update(np.ascontiguousarray(out.detections.boxes).tobytes())
                digest.update(np.ascontiguousarray(out.detections.scores).tobytes())
                digest.update(np.ascontiguousarray(out.plan.trajectory).tobytes())
        total = (time.process_time() - c0, time.perf_counter() - w0)
        if rep:
            per_rep.append({"cpu": {s: 1000 * clocks[s][0] / T for s in STAGES} | {"total": 1000 * total[0] / T},
                            "wall": {s: 1000 * clocks[s][1] / T for s in STAGES} | {"total": 1000 * total[1] / T}})
    med = {kind: {s: float(np.median([r[kind][s] for r in per_rep])) for s in STAGES + ("total",)}
           for kind in ("cpu", "wall")}
    return {"config": name, "torch_threads": torch.get_num_threads(), "frames": T, "repeats": repeats,
            "env": {k: os.environ.get(k) for k in ONE}, "ms_per_frame_cpu": med["cpu"],
            "ms_per_frame_wall": med["wall"], "outputs_sha256": digest.hexdigest()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scene", default="highway-benchmark-000010")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--inputs", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    if args.child:
        print(json.dumps(child(args.child, Path(args.inputs), args.repeats, args.scene)))
        return
    from adv3d_runner.machine import machine_info

    t0 = time.time()
    rows = []
    with tempfile.TemporaryDirectory(prefix="adv3d-threads-") as tmp:
        inputs = Path(tmp) / "episode.npz"
        record(args.scene, inputs)
        for name, cfg in CONFIGS.items():
            env = {k: v for k, v in os.environ.items() if k not in ONE}
            env.update(cfg["env"] or {})
            env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
            load = os.getloadavg()
            proc = subprocess.run([sys.executable, __file__, "--child", name, "--inputs", str(inputs),
                                   "--repeats", str(args.repeats), "--scene", args.scene],
                                  env=env, capture_output=True, text=True)
            if proc.returncode != 0:
                rows.append({"config": name, "error": proc.stderr.strip().splitlines()[-1][:300]})
                print(f"{name}: failed: {rows[-1]['error']}", flush=True)
                continue
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["load_average_before"] = list(load)
            rows.append(row)
            print(f"{name}: {row['ms_per_frame_cpu']['total']:.1f} ms CPU / frame", flush=True)
    ref = rows[0].get("outputs_sha256")
    print(f"\nStack time per frame ({args.scene}, 50 frames, median of {args.repeats} replays), ms: CPU (all threads) / wall")
    print(f"{'configuration':38s} {'detector':>13s} {'predictor':>13s} {'planner':>13s} {'total':>13s} {'same bits':>9s}")
    for r in rows:
        if "error" in r:
            print(f"{r['config']:38s} failed")
            continue
        r["identical_to_default"] = r["outputs_sha256"] == ref
        c, w = r["ms_per_frame_cpu"], r["ms_per_frame_wall"]
        print(f"{r['config']:38s} " + " ".join(f"{c[s]:6.1f} /{w[s]:5.1f}" for s in ("detector", "predictor", "planner", "total"))
              + f" {str(r['identical_to_default']):>9s}")
    doc = {"format": "adv3d.bench", "topic": "threads", "command": " ".join([Path(sys.executable).name] + sys.argv),
           "machine": machine_info("numpy", "torch"), "wall_s": time.time() - t0, "scene": args.scene, "rows": rows}
    out = ROOT / "bench" / "results" / "threads.json"
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
