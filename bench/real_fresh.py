"""The fresh real benchmark part: recordings 10-18 of NGSIM US-101, several egos per recording.

The benchmark part of ``scenes/real/`` (recordings 4, 6, 9; 7 scenes) is the benchmark that was
tuned on: the planner's changes were looked at on it many times. Recordings 10-18 came later and
no model, planner setting or generator profile has seen them. This script cuts them into
``scenes/real-fresh/``, evaluation only (docs/scenes.md, "Real recorded scenes").

Rule (fixed before any stack ran on these recordings):

* one CommonRoad file per recording: the largest (its variants share the traffic and differ in
  the planning problem only; ties by name);
* the ego candidates are the cars the importer accepts as an ego (sedan, hatchback, SUV whose
  track covers the whole recording) that *move*: a mean logged speed of at least
  ``--min-speed`` (1.0 m/s) over the first 5 s, since a car standing in a queue has no progress
  to compare a driven ego with;
* of these, sorted by that mean speed (then by obstacle id), ``--per-recording`` (5) at evenly
  spaced ranks ``round(i * (n - 1) / (k - 1))``: the slowest (the crawls of recordings 10, 15
  and 18) and the fastest of every recording, and the middle between them.

Every scene is ``adv3d scenes import-commonroad FILE --seconds 10 --extend --ego ID`` with its
id set to ``commonroad-<file>.ego<ID>`` and its actors' meshes recorded (``adv3d scenes
assign-assets``), as ``bench/real_train_egos.py`` makes the train recordings' extra egos.

    .venv/bin/python bench/real_fresh.py [--out scenes/real-fresh] [--source DIR] [--recordings 10,11]

Writes ``<out>/<file stem>.ego<obstacle id>.json.gz`` and the manifest ``<out>/index.csv``
(scene, recording, CommonRoad file and its SHA-256, ego, the logged speed range of the first 5 s),
which ``adv3d_runner.scene.real.load_fresh_part`` reads and checks against ``split.json``.
"""
from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.scene import Scene, save_scene  # noqa: E402
from adv3d_runner.scene.actors import assign_assets  # noqa: E402
from adv3d_runner.scene.commonroad import import_commonroad  # noqa: E402
from adv3d_runner.scene.real import FRESH_INDEX_HEADER, FRESH_RECORDINGS, longest_file_per_recording  # noqa: E402
from adv3d_runner.shapes.library import load_library  # noqa: E402

SHARED = ROOT.parent / "shared" / "scenarios" / "commonroad-us101"


def moving_cars(path: Path, min_speed: float, window_s: float = 5.0) -> list[tuple[float, int]]:
    """(mean logged speed over the first ``window_s`` s in m/s, obstacle id) of the cars the
    importer accepts as an ego (whole-recording track, sedan/hatchback/SUV) whose mean speed is
    at least ``min_speed``, sorted by speed then id."""
    from commonroad.common.file_reader import CommonRoadFileReader

    from adv3d_runner.scene import commonroad as cr

    scenario, _ = CommonRoadFileReader(str(path)).open()
    sdt = float(scenario.dt)
    states = {o.obstacle_id: (cr._states(o, sdt), o) for o in scenario.dynamic_obstacles}
    t_end = max(t[-1] for (t, _), _o in states.values())
    out = []
    for oid, ((t, vals), o) in states.items():
        if t[0] > 1e-6 or t[-1] < t_end - 1e-6 or cr._obstacle_class(o) not in cr.EGO_CLASSES:
            continue
        v = float(np.mean(vals[t <= window_s + 1e-6, 3]))
        if v >= min_speed:
            out.append((v, int(oid)))
    return sorted(out)


def spread(n: int, k: int) -> list[int]:
    """``k`` evenly spaced ranks of ``n`` sorted items (all of them when n <= k)."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(i * (n - 1) / (k - 1))) for i in range(k)})


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "scenes" / "real-fresh"))
    ap.add_argument("--source", default=str(SHARED), help="folder of the CommonRoad US-101 files")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--per-recording", type=int, default=5)
    ap.add_argument("--min-speed", type=float, default=1.0)
    ap.add_argument("--recordings", default=None,
                    help="comma-separated subset of the fresh recordings (a partial build, e.g. for a test)")
    args = ap.parse_args(argv)
    wanted = set(FRESH_RECORDINGS)
    if args.recordings:
        wanted = {int(x) for x in args.recordings.split(",")}
        if not wanted <= set(FRESH_RECORDINGS):
            ap.error(f"--recordings: only the fresh recordings {list(FRESH_RECORDINGS)}")
    files = longest_file_per_recording(args.source, wanted)
    missing = wanted - set(files)
    if missing:
        ap.error(f"{args.source}: no CommonRoad file of recording(s) {sorted(missing)}")
    library = load_library()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [",".join(FRESH_INDEX_HEADER)]
    for r, f in sorted(files.items()):
        cars = moving_cars(f, args.min_speed)
        digest = sha256(f)
        for i in spread(len(cars), args.per_recording):
            oid = cars[i][1]
            scene = import_commonroad(f, seconds=args.seconds, extend=True, ego_id=oid)
            name = f"{f.stem}.ego{oid}"
            scene = Scene.from_dict(dict(scene.to_dict(), id=f"commonroad-{name}"), f)
            scene = assign_assets(scene, library)
            save_scene(scene, out / f"{name}.json.gz")
            v = scene.ego_speeds()[: int(round(5.0 / scene.dt))]
            lines.append(f"{name},{r},{f.name},{digest},{oid},{v.min():.2f},{v.max():.2f}")
            print(f"{name}: recording {r}, speed {v.min():.1f}-{v.max():.1f} m/s in the first 5 s", flush=True)
    # a CSV, not JSON: `adv3d scenes validate <folder>` reads every .json in a folder as a scene
    (out / "index.csv").write_text("\n".join(lines) + "\n")
    print(f"{len(lines) - 1} scenes in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
