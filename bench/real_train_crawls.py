"""Standstill starts from the *train* recordings, played backwards (docs/benchmark.md).

No car of the train recordings (1, 2, 3, 5, 8) starts from standstill and moves off: in recording
5 three cars brake into a queue and stand until its end, and no car there ever rolls off again.
Played backwards, such a stop is a move-off: the queue's cars stand, the one at its head rolls
first, each follower rolls when the gap ahead has opened. Time-reversing a scene and driving it
the other way along mirrored lanes turns every car's recorded braking into an acceleration with
the same speeds, gaps and timing in reverse. This is a recorded *braking* profile, not a recorded
move-off (drivers may move off differently from how they stop), so these scenes are for finding
mechanisms only, next to ``scenes/real-train-egos``; never a result.

    .venv/bin/python bench/real_train_crawls.py [--out scenes/real-train-crawls]

Source: every scene of the train part of ``scenes/real/`` and of ``scenes/real-train-egos/``
(kept in the repository; no CommonRoad file is opened) whose frames are all recorded (no
``--extend`` frames, which would come first when reversed). Reversed (``reverse_scene``), a scene
is kept when its ego, at the first frame, drives at most ``MAX_START_SPEED`` m/s with a car ahead
in its lane (centre to centre at most ``MAX_LEADER_GAP`` m, laterally within ``LANE_HALF`` m), and
moves at least ``MIN_LOGGED_PROGRESS`` m in its first ``WINDOW_S`` s (it moves off). The rule is
applied to the reversed scene starting at each of ``START_FRAMES`` (the frames before cut off,
``cut_scene``), so one queue gives starts with the leader about to roll, rolling, or standing
longer. Writes ``<out>/<source stem>.reversed.from<F>.json.gz`` and ``<out>/index.csv``.

    .venv/bin/python bench/real_train_crawls.py --rolling [--out scenes/real-train-crawls-rolling]

makes *rolling-in* starts from the kept crawls (``rolling_start``): the ego moving at 0.5, 1 or
1.5 m/s at frame 0 where the logged driver stands, so that it must stop behind the queue's car
and then move off; ``<crawl>.rolling<speed>.json.gz`` and ``index.csv``.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.geometry.angles import wrap_angle  # noqa: E402
from adv3d_runner.scene import Scene, load_scene, save_scene  # noqa: E402
from adv3d_runner.scene.real import load_real_split  # noqa: E402

#: selection rule of the reversed scenes (fixed from the logged tracks only, before any stack ran)
MAX_START_SPEED = 1.5  # m/s, the ego's logged speed at the first frame
MAX_LEADER_GAP = 12.0  # m, centre to centre, to the nearest car ahead in the ego's lane
LANE_HALF = 1.8  # m, |lateral offset| in the ego's frame that counts as its lane
MIN_LOGGED_PROGRESS = 1.0  # m, logged ego travel within WINDOW_S: it moves off
WINDOW_S = 5.0  # s, the closed-loop length of bench/sanity.py
START_FRAMES = (0, 10, 20, 30)  # first frames of the reversed scene tried (every 1 s; >= 7 s stay)

DEFAULT_SOURCES = (ROOT / "scenes" / "real-train-egos",)

#: rolling-in starts (``--rolling``): each kept crawl whose logged ego stands at least
#: ROLLING_MIN_STANDING s of its first WINDOW_S s, started at each of these speeds instead
ROLLING_SPEEDS = (0.5, 1.0, 1.5)  # m/s
ROLLING_MIN_STANDING = 1.0  # s


def _reverse_track(track: dict, frames: int) -> dict:
    """A track dict (``start``, ``x``, ``y``, ``yaw``[, ``speed``, ``valid``, ``synthetic``]) of a
    scene of ``frames`` frames, played backwards: frame k becomes frames - 1 - k; yaw turned by pi."""
    n = len(track["x"])
    out = {"start": frames - (int(track["start"]) + n),
           "x": list(reversed(track["x"])), "y": list(reversed(track["y"])),
           "yaw": [round(float(v), 3) for v in wrap_angle(np.asarray(track["yaw"][::-1], float) + math.pi)]}
    for key in ("speed", "valid", "synthetic"):
        if key in track:
            out[key] = list(reversed(track[key]))
    return out


def _reverse_lanes(lanes: list[dict]) -> list[dict]:
    """Lanes driven the other way: centre line and widths reversed, left and right neighbours
    swapped, successors become predecessors."""
    out = []
    for lane in lanes:
        width = lane["width"]
        new = dict(lane, centerline=list(reversed(lane["centerline"])),
                   width=list(reversed(width)) if isinstance(width, list) else width,
                   left=lane["right"], right=lane["left"],
                   successors=sorted(m["id"] for m in lanes if lane["id"] in m["successors"]))
        out.append(new)
    return out


def reverse_scene(scene: Scene, scene_id: str) -> Scene:
    """``scene`` played backwards in time along mirrored lanes, with id ``scene_id``.

    Every vehicle drives forward again (yaw + pi) through the same positions in reverse order
    with the same speeds; a recorded stop becomes a move-off. The shoulders swap sides with the
    driving direction; barriers and meshes stay where they are. ``source.details`` records
    ``time_reversed_from`` (the source scene's id).

    Raises:
        ValueError: the scene has extrapolated (``--extend``) frames, which would come first.
    """
    d = scene.to_dict()
    details = dict(d["source"]["details"])
    if int(details.get("extended_frames", 0)):
        raise ValueError(f"{scene.id}: {details['extended_frames']} extrapolated frames; only fully recorded "
                         "scenes can be reversed")
    frames = int(d["frames"])
    details["time_reversed_from"] = scene.id
    details["ego_rule"] = (details.get("ego_rule", "") + "; the scene played backwards along mirrored lanes "
                           "(bench/real_train_crawls.py)")
    bg = dict(d["background"], shoulder_left=d["background"]["shoulder_right"],
              shoulder_right=d["background"]["shoulder_left"])
    ego = dict(d["ego"], track=_reverse_track(d["ego"]["track"], frames))
    actors = [dict(a, track=_reverse_track(a["track"], frames)) for a in d["actors"]]
    new = dict(d, id=scene_id, source=dict(d["source"], details=details), background=bg,
               map=dict(d["map"], lanes=_reverse_lanes(d["map"]["lanes"])), ego=ego, actors=actors)
    return Scene.from_dict(new, None)


def cut_scene(scene: Scene, first: int, scene_id: str) -> Scene:
    """``scene`` from frame ``first`` on (frame ``first`` becomes frame 0), with id ``scene_id``;
    vehicles gone before ``first`` are dropped, ``source.details`` records ``first_frame`` and the
    remaining ``recorded_frames``.

    Raises:
        ValueError: ``first`` outside the scene or the ego's track.
    """
    if not 0 <= first < scene.frames or scene.ego.track.start > first:
        raise ValueError(f"{scene.id}: first frame {first} outside its {scene.frames} frames or before its ego")
    d = scene.to_dict()

    def cut(track: dict) -> dict | None:
        skip = first - int(track["start"])
        if skip >= len(track["x"]):
            return None
        if skip <= 0:
            return dict(track, start=-skip)
        return {k: (v[skip:] if isinstance(v, list) else 0) for k, v in track.items()}

    details = dict(d["source"]["details"], first_frame=first,
                   recorded_frames=int(d["source"]["details"]["recorded_frames"]) - first)
    actors = [dict(a, track=t) for a in d["actors"] if (t := cut(a["track"])) is not None]
    new = dict(d, id=scene_id, frames=int(d["frames"]) - first, source=dict(d["source"], details=details),
               ego=dict(d["ego"], track=cut(d["ego"]["track"])), actors=actors)
    return Scene.from_dict(new, None)


def standstill_start(scene: Scene) -> dict | None:
    """The selection rule (module docstring) on a scene's logged ego: a dict with ``speed0``
    (m/s), ``leader`` (actor id), ``leader_gap`` (m, centre to centre), ``logged_progress`` (m in
    ``WINDOW_S``), ``standing_s`` (s at < 0.1 m/s in the window) when it holds, else None."""
    e = scene.ego.track
    v = np.asarray(e.speed, float)
    if e.start != 0 or v[0] > MAX_START_SPEED:
        return None
    x0, y0, yaw0 = float(e.x[0]), float(e.y[0]), float(e.yaw[0])
    best = None
    for actor in scene.actors:
        t = actor.track
        if t.start != 0 or not t.valid[0]:
            continue
        dx, dy = float(t.x[0]) - x0, float(t.y[0]) - y0
        lon = dx * math.cos(yaw0) + dy * math.sin(yaw0)
        lat = -dx * math.sin(yaw0) + dy * math.cos(yaw0)
        if 0.0 < lon <= MAX_LEADER_GAP and abs(lat) <= LANE_HALF and (best is None or lon < best[0]):
            best = (lon, actor.id)
    if best is None:
        return None
    k = int(round(WINDOW_S / scene.dt))
    xy = np.stack([e.x[: k + 1], e.y[: k + 1]], axis=1)
    travel = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    if travel < MIN_LOGGED_PROGRESS:
        return None
    return {"speed0": round(float(v[0]), 2), "leader": int(best[1]), "leader_gap": round(best[0], 2),
            "logged_progress": round(travel, 2), "standing_s": round(float((v[:k] < 0.1).sum()) * scene.dt, 1)}


def rolling_start(scene: Scene, speed: float, scene_id: str) -> Scene:
    """``scene`` with its ego moving at ``speed`` (m/s) at frame 0 instead of its logged speed,
    with id ``scene_id``; nothing else changes (the logged positions, hence the logged progress,
    stay). Closed loop, the ego starts where the logged driver stands, rolling towards the queue's
    car ahead, so it must stop behind it and then move off when it pulls away: a standing start
    reached from a crawl. ``source.details`` records ``rolling_start_mps``.

    Raises:
        ValueError: ``speed`` negative or the ego not tracked at frame 0.
    """
    if speed < 0.0 or scene.ego.track.start != 0:
        raise ValueError(f"{scene.id}: a rolling start needs speed >= 0 m/s (got {speed}) and the ego at frame 0")
    d = scene.to_dict()
    track = dict(d["ego"]["track"])
    track["speed"] = [round(float(speed), 3)] + list(track["speed"][1:])
    details = dict(d["source"]["details"], rolling_start_mps=round(float(speed), 3))
    details["ego_rule"] = details.get("ego_rule", "") + f"; started at {speed:g} m/s (bench/real_train_crawls.py --rolling)"
    new = dict(d, id=scene_id, source=dict(d["source"], details=details), ego=dict(d["ego"], track=track))
    return Scene.from_dict(new, None)


def build_rolling(out: Path, crawls: Path = ROOT / "scenes" / "real-train-crawls") -> list[dict]:
    """Write the rolling-in starts (:func:`rolling_start`) of the kept crawls of ``crawls`` whose
    ``index.csv`` row stands >= ``ROLLING_MIN_STANDING`` s, at each of ``ROLLING_SPEEDS``, and
    their ``index.csv`` into ``out``; returns the index rows."""
    out.mkdir(parents=True, exist_ok=True)
    lines = (crawls / "index.csv").read_text().splitlines()
    cols = lines[0].split(",")
    rows = []
    for line in lines[1:]:
        row = dict(zip(cols, line.split(",")))
        if float(row["standing_s"]) < ROLLING_MIN_STANDING:
            continue
        scene = load_scene(crawls / f"{row['scene']}.json.gz")
        for speed in ROLLING_SPEEDS:
            name = f"{row['scene']}.rolling{speed:g}"
            save_scene(rolling_start(scene, speed, f"commonroad-{name}"), out / f"{name}.json.gz")
            rows.append({"scene": name, "crawl": row["scene"], "start_speed": f"{speed:g}", "leader": row["leader"],
                         "leader_gap": row["leader_gap"], "logged_progress": row["logged_progress"],
                         "logged_standing_s": row["standing_s"]})
            print(name)
    keys = ["scene", "crawl", "start_speed", "leader", "leader_gap", "logged_progress", "logged_standing_s"]
    (out / "index.csv").write_text("\n".join([",".join(keys)] + [",".join(r[k] for k in keys) for r in rows]) + "\n")
    return rows


def source_paths(sources: tuple[Path, ...] = DEFAULT_SOURCES) -> list[Path]:
    """The train scenes the rule is applied to: the train part of ``scenes/real/`` and every scene
    file of ``sources``, sorted by name."""
    paths = list(load_real_split().paths("train"))
    for folder in sources:
        paths += sorted(folder.glob("*.json.gz"))
    return sorted(paths, key=lambda p: p.name)


def build(out: Path, sources: tuple[Path, ...] = DEFAULT_SOURCES) -> list[dict]:
    """Write the reversed standstill starts and ``index.csv`` into ``out``; returns the index rows."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in source_paths(sources):
        scene = load_scene(path)
        if int(scene.source.details.get("extended_frames", 0)):
            continue
        stem = path.name[: -len(".json.gz")]
        rev = reverse_scene(scene, f"commonroad-{stem}.reversed")
        for first in START_FRAMES:
            name = f"{stem}.reversed.from{first}"
            cut = cut_scene(rev, first, f"commonroad-{name}")
            info = standstill_start(cut)
            if info is None:
                continue
            save_scene(cut, out / f"{name}.json.gz")
            rows.append({"scene": name, "source": path.relative_to(ROOT).as_posix(), "first_frame": first, **info})
            print(f"{name}: {info}")
    cols = ["scene", "source", "first_frame", "speed0", "leader", "leader_gap", "logged_progress", "standing_s"]
    # a CSV, not JSON: `adv3d scenes validate <folder>` reads every .json in a folder as a scene
    lines = [",".join(cols)] + [",".join(str(r[c]) for c in cols) for r in rows]
    (out / "index.csv").write_text("\n".join(lines) + "\n")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="default scenes/real-train-crawls (with --rolling: "
                    "scenes/real-train-crawls-rolling)")
    ap.add_argument("--rolling", action="store_true", help="the rolling-in starts of the kept crawls "
                    "(rolling_start), not the crawls")
    args = ap.parse_args()
    if args.rolling:
        out = Path(args.out or ROOT / "scenes" / "real-train-crawls-rolling")
        rows = build_rolling(out)
    else:
        out = Path(args.out or ROOT / "scenes" / "real-train-crawls")
        rows = build(out)
    args.out = out
    print(f"{len(rows)} scenes in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
