"""Scene benchmarks: background mesh resolution (speed against geometric error) and the
generator's time and file size per density.

    .venv/bin/python bench/scenes.py [--quick]

Table 1: ``background_mesh(scene, step=...)`` on a curved benchmark scene: triangles, build
time, and the largest distance between the strips' lane edges and the lane edge of the file's
polylines sampled every 0.25 m (strips keep every centre-line vertex, so ``step`` only adds
stations: the error stays at rounding level while triangles and time change). Table 2: ``generate_scene`` time, actors and gzipped size
per density (layout cycled). Writes ``bench/results/scenes.json`` (``scenes.quick.json`` with
--quick) with machine info and the command. Reports, never asserts, times.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adv3d_runner.machine import machine_info as _machine_info  # noqa: E402
from adv3d_runner.scene import lanes as lg  # noqa: E402
from adv3d_runner.scene.background import background_mesh  # noqa: E402
from adv3d_runner.scene.generate import DENSITIES, LAYOUTS, generate_scene  # noqa: E402
from adv3d_runner.scene.schema import load_scene, save_scene  # noqa: E402


def machine_info() -> dict:
    return _machine_info("numpy")


def edge_error(scene, step: float) -> float:
    """Largest distance (m) between a lane's exact left edge (centre line + half width, sampled
    every 0.25 m) and the edge polyline ``background_mesh`` builds at ``step`` (same
    construction as ``background._lane_edges``), over all lanes."""
    from adv3d_runner.scene.background import _lane_edges

    worst = 0.0
    for lane in scene.lanes:
        pts = lg.clean_polyline(lane.centerline)
        if lg.length(pts) < 1.0:
            continue
        s = np.arange(0.0, lg.length(pts), 0.25)
        w = lg.width_at(lane.centerline, lane.width, s)
        fine = lg.pose_at(pts, s, 0.5 * w)[:, :2]
        _, _, coarse, _ = _lane_edges(lane.centerline, lane.width, step)
        _, d, _ = lg.project(coarse, fine)
        worst = max(worst, float(np.abs(d).max()))
    return worst


def bench_background(scene, steps: list[float], repeats: int) -> list[dict]:
    rows = []
    for step in steps:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            v, f, k = background_mesh(scene, step=step)
            times.append(time.perf_counter() - t0)
        rows.append({"step_m": step, "triangles": int(len(f)), "build_ms": 1000 * float(np.median(times)),
                     "max_edge_error_m": edge_error(scene, step)})
    return rows


def bench_generator(seeds_per_density: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for di, density in enumerate(DENSITIES):
            times, sizes, actors = [], [], []
            for j in range(seeds_per_density):
                seed = 5000 + 10 * di + j
                layout = LAYOUTS[j % len(LAYOUTS)]
                t0 = time.perf_counter()
                scene = generate_scene(seed, layout=layout, density=density)
                times.append(time.perf_counter() - t0)
                path = Path(tmp) / f"{seed}.json.gz"
                save_scene(scene, path)
                sizes.append(path.stat().st_size)
                actors.append(len(scene.actors))
            rows.append({"density": density, "scenes": seeds_per_density, "gen_s_mean": float(np.mean(times)),
                         "actors_mean": float(np.mean(actors)), "kB_mean": float(np.mean(sizes)) / 1000,
                         "kB_max": float(np.max(sizes)) / 1000})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps, repeats and scenes")
    args = parser.parse_args()
    scene = load_scene(REPO / "scenes" / "highway" / "highway-benchmark-000001.json.gz")  # curved
    steps = [2.0, 5.0, 10.0, 20.0] if not args.quick else [5.0, 20.0]
    bg = bench_background(scene, steps, repeats=1 if args.quick else 3)
    print(f"background_mesh on {scene.id} (curved, {len(scene.lanes)} lanes)")
    print(f"{'step m':>7} {'triangles':>10} {'build ms':>9} {'max edge error m':>17}")
    for r in bg:
        print(f"{r['step_m']:>7.1f} {r['triangles']:>10d} {r['build_ms']:>9.1f} {r['max_edge_error_m']:>17.4f}")
    gen = bench_generator(1 if args.quick else 4)
    print("\ngenerate_scene (20 s at 10 Hz) per density")
    print(f"{'density':>10} {'scenes':>6} {'gen s':>6} {'actors':>7} {'kB mean':>8} {'kB max':>7}")
    for r in gen:
        print(f"{r['density']:>10} {r['scenes']:>6d} {r['gen_s_mean']:>6.2f} {r['actors_mean']:>7.1f} "
              f"{r['kB_mean']:>8.1f} {r['kB_max']:>7.1f}")
    out = REPO / "bench" / "results" / ("scenes.quick.json" if args.quick else "scenes.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"command": " ".join([".venv/bin/python"] + sys.argv), "machine": machine_info(),
                               "background": bg, "generator": gen}, indent=1) + "\n")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
