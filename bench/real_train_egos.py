"""More tuning scenes from the *train* recordings: every other car of them as the ego (docs/scenes.md).

The train part of ``scenes/real/`` has 14 scenes, one ego each; its recordings hold more cars
whose tracks cover the whole recording, among them crawls at 0-4 m/s (recording 5) that none of
the 14 egos drives. This script imports each such car as the ego of its own scene, from the
longest CommonRoad version of each train recording, skipping the cars that already are an ego
in ``scenes/real/``. The benchmark recordings are never opened.

    .venv/bin/python bench/real_train_egos.py [--out scenes/real-train-egos] [--seconds 10]

Writes ``<out>/<benchmark id>.ego<obstacle id>.json.gz`` (``adv3d scenes import-commonroad
FILE --seconds 10 --extend --ego ID``) and ``<out>/index.csv`` (scene, recording, ego, the
logged speed range of its first 5 s). Run them with ``bench/sanity.py --sets real --real-dir
<out> --name NAME``: tuning only, never a result.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.scene import Scene, load_scene, save_scene  # noqa: E402
from adv3d_runner.scene.commonroad import import_commonroad  # noqa: E402
from adv3d_runner.scene.actors import assign_assets  # noqa: E402
from adv3d_runner.scene.real import load_real_split, longest_file_per_recording, recording_of  # noqa: E402
from adv3d_runner.shapes.library import load_library  # noqa: E402

SHARED = ROOT.parent / "shared" / "scenarios" / "commonroad-us101"


def _full_cover_cars(path: Path) -> list[int]:
    """Obstacle ids of the cars (sedan, hatchback, suv) whose track covers the whole recording:
    the cars the importer accepts as an ego."""
    from commonroad.common.file_reader import CommonRoadFileReader

    from adv3d_runner.scene import commonroad as cr

    scenario, _ = CommonRoadFileReader(str(path)).open()
    sdt = float(scenario.dt)
    states = {o.obstacle_id: (cr._states(o, sdt)[0], o) for o in scenario.dynamic_obstacles}
    t_end = max(t[-1] for t, _ in states.values())
    return sorted(oid for oid, (t, o) in states.items()
                  if t[0] <= 1e-6 and t[-1] >= t_end - 1e-6
                  and cr._obstacle_class(o) in cr.EGO_CLASSES)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "scenes" / "real-train-egos"))
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--source", default=str(SHARED), help="folder of the CommonRoad US-101 files")
    args = ap.parse_args()
    split = load_real_split()
    train = set(split.recordings["train"])
    used: dict[int, set[int]] = {}
    for p in split.paths("train") + split.paths("benchmark"):
        s = load_scene(p)
        used.setdefault(recording_of(p.name.split(".")[0]), set()).add(int(s.source.details["ego_obstacle_id"]))
    # one file per train recording: the one that records longest (its variants share the traffic)
    files = longest_file_per_recording(args.source, train)
    library = load_library()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    index = []
    for r, f in sorted(files.items()):
        for oid in _full_cover_cars(f):
            if oid in used.get(r, set()):
                continue
            scene = import_commonroad(f, seconds=args.seconds, extend=True, ego_id=oid)
            name = f"{f.stem}.ego{oid}"
            # one id per scene (the variants' id names the recording only); rows are keyed by it
            scene = Scene.from_dict(dict(scene.to_dict(), id=f"commonroad-{name}"), f)
            # record the meshes (the library's draw by scene and actor id, what loading the
            # scene would draw anyway), so the library's growth does not change these scenes
            scene = assign_assets(scene, library)
            save_scene(scene, out / f"{name}.json.gz")
            v = scene.ego_speeds()[: int(round(5.0 / scene.dt))]
            index.append({"scene": name, "recording": r, "file": f.name, "ego_obstacle_id": oid,
                          "speed_first_5s": [round(float(v.min()), 2), round(float(v.max()), 2)]})
            print(f"{name}: recording {r}, speed {v.min():.1f}-{v.max():.1f} m/s in the first 5 s")
    # a CSV, not JSON: `adv3d scenes validate <folder>` reads every .json in a folder as a scene
    lines = ["scene,recording,commonroad_file,ego_obstacle_id,speed_min_first_5s,speed_max_first_5s"]
    lines += [f"{r['scene']},{r['recording']},{r['file']},{r['ego_obstacle_id']},{r['speed_first_5s'][0]},"
              f"{r['speed_first_5s'][1]}" for r in index]
    (out / "index.csv").write_text("\n".join(lines) + "\n")
    print(f"{len(index)} scenes in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
