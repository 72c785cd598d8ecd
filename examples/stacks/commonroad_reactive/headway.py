"""How closely a stack follows: time headway to the leader in its lane, on the sanity scenes.

Runs in adv3d's own venv (it drives episodes like bench/sanity.py does):

    .venv/bin/python examples/stacks/commonroad_reactive/headway.py --autonomy C B

Per stack and scene (5 s closed loop, seed 0): the leader of a frame is the nearest actor ahead
of the ego (ego frame x > 0) whose footprint overlaps the ego's laterally
(|y| < (W_actor + W_ego) / 2); its bumper gap is x - (L_actor + L_ego) / 2 and the time headway
gap / ego speed. Printed: per scene the smallest gap and headway, the frames with a headway
under 1 s; per stack the totals. ``--json PATH`` writes the rows.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))


def scenes() -> list[Path]:
    """The scenes of ``bench/sanity.py --quick``: every 10th generated benchmark scene and the
    real benchmark part."""
    gen = sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json*"))[::10]
    split = json.loads((ROOT / "scenes" / "real" / "split.json").read_text())
    real = [ROOT / "scenes" / "real" / f"{name}.json.gz" for name in split["scenes"]["benchmark"]]
    return gen + real


def headways(result) -> dict:
    from adv3d_runner.geometry.frames import boxes_to_frame

    L_e, W_e = result.ego_dimensions[:2]
    gaps, hws = [], []
    for k in range(result.frames):
        b = boxes_to_frame(result.gt_boxes(k), result.ego_poses[k])
        ok = np.isfinite(b).all(axis=1) & (b[:, 0] > 0) & (np.abs(b[:, 1]) < (b[:, 3] + W_e) / 2)
        if not ok.any():
            continue
        gap = float(np.min(b[ok, 0] - (b[ok, 2] + L_e) / 2))
        v = float(result.ego_speeds[k])
        gaps.append(gap)
        hws.append(gap / v if v > 0.5 else np.inf)
    hws = np.array(hws)
    return {"frames_with_leader": len(gaps), "min_gap_m": min(gaps) if gaps else None,
            "min_headway_s": float(hws.min()) if len(hws) else None,
            "frames_headway_under_1s": int(np.sum(hws < 1.0)), "frames_headway_under_0_5s": int(np.sum(hws < 0.5))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--autonomy", nargs="+", default=["C"])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import world_from_scene
    from adv3d_runner.sim.episode import default_library, run_episode

    lib = default_library()
    rows = []
    for name in args.autonomy:
        stack = make_stack(name)
        for path in scenes():
            scene = load_scene(path)
            result = run_episode(scene, stack, seconds=args.seconds, world=world_from_scene(scene, lib), seed=0)
            row = {"autonomy": name, "scene": scene.id, **headways(result)}
            rows.append(row)
            print(json.dumps(row), flush=True)
        close = getattr(stack, "close", None)
        if close is not None:
            close()
    print("\n| stack | frames with a leader | min gap (m) | min headway (s) | frames < 1 s | frames < 0.5 s |")
    print("|---|---|---|---|---|---|")
    for name in args.autonomy:
        mine = [r for r in rows if r["autonomy"] == name and r["frames_with_leader"]]
        print(f"| {name} | {sum(r['frames_with_leader'] for r in mine)} | {min(r['min_gap_m'] for r in mine):.2f} | "
              f"{min(r['min_headway_s'] for r in mine):.2f} | {sum(r['frames_headway_under_1s'] for r in mine)} | "
              f"{sum(r['frames_headway_under_0_5s'] for r in mine)} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
