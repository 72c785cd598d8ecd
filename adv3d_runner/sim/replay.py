"""The replay file: one episode, frame by frame, for review (Blender add-on) and for reports.

Contract "adv3d-replay", version 1 or 2 (documented in ``docs/formats.md``, section "Replay"):

* ``NAME.json`` or ``NAME.json.gz``: header, how the episode was run, ego and actors (poses per
  frame, ``null`` where an actor is absent), and per frame the detections with scores, the
  confirmed tracks, the predicted trajectories (modes + probabilities) and the chosen plan;
  version 2 adds, for a stack with occupancy output (Autonomy-B), per frame an
  ``occupancy`` heat map: the predicted occupancy on a small grid around the attacked actors
  (or ahead of the ego) at a few future times (:class:`OccupancyMap`). A file without maps is
  written as version 1, exactly as before;
* optionally ``points``: the name of a sibling ``.npz`` (``np.load(..., allow_pickle=False)``)
  with every frame's LiDAR points in the **ego frame**, concatenated: ``xyz_cm`` (P, 3) int16
  centimetres, ``intensity`` (P,) uint8 (intensity x 255), ``label`` (P,) int16 (index into the
  file's ``actors``, -1 background), ``offsets`` (T + 1,) int64 (frame k's points are rows
  ``offsets[k]:offsets[k+1]``), plus ``format``/``version`` scalars.

Everything numeric is quantised when a :class:`Replay` is built (positions 1 mm, angles 1e-4 rad,
speeds 1 mm/s, scores and probabilities 1e-4, LiDAR 1 cm and 1/255), so writing and reading give
back exactly the same arrays. Loading validates every field and raises
:class:`~adv3d_runner.errors.FileFormatError` naming the file and the JSON path.

numpy only (the Blender add-on imports this module in-process).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError
from ..fileio import atomic_path, check_header, read_json, write_json

FORMAT = "adv3d-replay"
VERSION = 1             # a replay without occupancy maps (and the points file)
VERSION_OCCUPANCY = 2   # a replay with occupancy maps
POINTS_FORMAT = "adv3d-replay-points"
#: occupancy maps: times (s after the frame), cell size (m), extent along / across the ego's
#: heading (m), and how far ahead of the ego the map is centred when no actor is attacked
MAP_TIMES = (0.0, 1.0, 2.0, 3.0)
MAP_CELL = 0.5
MAP_SIZE = (40.0, 16.0)
MAP_AHEAD = 20.0
POS, ANG, SPD, SCORE = 3, 4, 3, 4  # decimals


def _q(a, decimals: int) -> np.ndarray:
    return np.round(np.asarray(a, dtype=np.float64), decimals) + 0.0  # + 0.0: no negative zeros


def _qpose(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    out = _q(a, POS)
    out[..., 2] = _q(a[..., 2], ANG)
    return out


def _qbox(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(-1, 5)
    out = _q(a, POS)
    out[:, 4] = _q(a[:, 4], ANG)
    return out


@dataclass
class ReplayActor:
    """One actor: ``id``, ``cls`` (class), ``dimensions`` (3,) L, W, H m, ``poses`` (T, 3) x, y,
    yaw (NaN rows where absent), ``adversarial`` (its shape was substituted), ``mesh`` (optional
    path, relative to the replay file, of its substituted shape)."""

    id: int
    cls: str
    dimensions: np.ndarray
    poses: np.ndarray
    adversarial: bool = False
    mesh: str | None = None

    def __post_init__(self) -> None:
        self.id = int(self.id)
        self.dimensions = _q(np.asarray(self.dimensions, float).reshape(3), POS)
        self.poses = _qpose(np.asarray(self.poses, float).reshape(-1, 3))
        self.poses[~np.isfinite(self.poses).all(axis=1)] = np.nan
        self.adversarial = bool(self.adversarial)


@dataclass(eq=False)
class OccupancyMap:
    """Predicted occupancy of one frame on small grids, one per time (map frame).

    Grid k is centred at ``poses[k]`` (x, y) with its x axis along ``poses[k]`` yaw (the ego's
    heading); cell (i, j) has its centre at local ((i + 0.5) cell - nx cell / 2,
    (j + 0.5) cell - ny cell / 2).

    Attributes:
        times: (K,) s after the frame. poses: (K, 3) x, y, yaw. cell: m.
        values: (K, nx, ny) uint8, occupancy probability x 255 (rounded).
    """

    times: np.ndarray
    poses: np.ndarray
    cell: float
    values: np.ndarray

    def __post_init__(self) -> None:
        self.times = _q(np.asarray(self.times, float).reshape(-1), SCORE)
        self.poses = _qpose(np.asarray(self.poses, float).reshape(-1, 3))
        self.cell = float(_q(self.cell, POS))
        v = np.asarray(self.values)
        if v.ndim != 3 or len(v) != len(self.times) or len(self.poses) != len(self.times):
            raise ValueError(f"occupancy values must be (K, nx, ny) for {len(self.times)} times, got {v.shape}")
        if v.dtype != np.uint8:
            v = np.clip(np.rint(np.asarray(v, dtype=np.float64)), 0, 255).astype(np.uint8)
        self.values = v

    @property
    def probabilities(self) -> np.ndarray:
        """(K, nx, ny) float64 in [0, 1]."""
        return self.values / 255.0

    def cell_centres(self, k: int) -> np.ndarray:
        """(nx, ny, 2) map-frame centres of grid k's cells."""
        nx, ny = self.values.shape[1:]
        lx = (np.arange(nx) + 0.5) * self.cell - 0.5 * nx * self.cell
        ly = (np.arange(ny) + 0.5) * self.cell - 0.5 * ny * self.cell
        gx, gy = np.meshgrid(lx, ly, indexing="ij")
        x, y, yaw = self.poses[k]
        c, s = np.cos(yaw), np.sin(yaw)
        return np.stack([x + c * gx - s * gy, y + s * gx + c * gy], axis=-1)

    def equals(self, other: "OccupancyMap") -> bool:
        return (np.array_equal(self.times, other.times) and np.array_equal(self.poses, other.poses)
                and self.cell == other.cell and np.array_equal(self.values, other.values))


def occupancy_map(field, centre: np.ndarray, yaw: float, speed: float, times=MAP_TIMES, cell: float = MAP_CELL,
                  size: tuple[float, float] = MAP_SIZE) -> OccupancyMap:
    """Query ``field`` (an ``OccupancyField``) on the map grids of one frame: grid k centred at
    ``centre`` (2,) carried ``speed`` x t m along ``yaw`` (the traffic around moves with the
    ego), aligned with ``yaw``."""
    nx, ny = int(round(size[0] / cell)), int(round(size[1] / cell))
    d = np.array([np.cos(yaw), np.sin(yaw)])
    times = np.asarray(times, dtype=np.float64)
    poses = np.array([[*(np.asarray(centre, float) + speed * t * d), yaw] for t in times]).reshape(-1, 3)
    m = OccupancyMap(times, poses, cell, np.zeros((len(times), nx, ny), np.uint8))
    pts = np.concatenate([m.cell_centres(k).reshape(-1, 2) for k in range(len(times))])
    occ, _ = field.query(pts, np.repeat(m.times, nx * ny))
    m.values = np.clip(np.rint(occ * 255.0), 0, 255).astype(np.uint8).reshape(len(times), nx, ny)
    return m


@dataclass
class ReplayFrame:
    """The stack's outputs in one frame (map frame).

    Attributes:
        det_boxes: (D, 5) x, y, length, width, yaw; det_scores: (D,).
        track_ids: (M,) int64; track_boxes: (M, 5); track_velocities: (M, 2) m/s.
        pred_track_ids: (P,) int64; pred_trajectories: (P, K, H, 2); pred_probabilities: (P, K).
        plan: (S, 3) x, y, yaw of the chosen plan (index 0 = now); plan_speed: (S,);
        plan_label: str; plan_cost: float.
        occupancy: the frame's :class:`OccupancyMap` (stacks with occupancy output), or None.
    """

    det_boxes: np.ndarray
    det_scores: np.ndarray
    track_ids: np.ndarray
    track_boxes: np.ndarray
    track_velocities: np.ndarray
    pred_track_ids: np.ndarray
    pred_trajectories: np.ndarray
    pred_probabilities: np.ndarray
    plan: np.ndarray
    plan_speed: np.ndarray
    plan_label: str = ""
    plan_cost: float = 0.0
    occupancy: OccupancyMap | None = None

    def __post_init__(self) -> None:
        self.det_boxes = _qbox(self.det_boxes)
        self.det_scores = _q(np.asarray(self.det_scores, float).reshape(-1), SCORE)
        self.track_ids = np.asarray(self.track_ids, np.int64).reshape(-1)
        self.track_boxes = _qbox(self.track_boxes)
        self.track_velocities = _q(np.asarray(self.track_velocities, float).reshape(-1, 2), SPD)
        self.pred_track_ids = np.asarray(self.pred_track_ids, np.int64).reshape(-1)
        traj = np.asarray(self.pred_trajectories, float)
        if len(self.pred_track_ids) == 0:  # one canonical empty shape (JSON cannot keep K, H)
            traj = np.zeros((0, 0, 0, 2))
        if traj.ndim != 4 or traj.shape[-1] != 2 or len(traj) != len(self.pred_track_ids):
            raise ValueError(f"pred_trajectories must be (P, K, H, 2) for {len(self.pred_track_ids)} tracks, got {traj.shape}")
        self.pred_trajectories = _q(traj, POS)
        self.pred_probabilities = _q(np.asarray(self.pred_probabilities, float).reshape(traj.shape[:2]), SCORE)
        self.plan = _qpose(np.asarray(self.plan, float).reshape(-1, 3))
        self.plan_speed = _q(np.asarray(self.plan_speed, float).reshape(-1), SPD)
        self.plan_label = str(self.plan_label)
        self.plan_cost = float(_q(self.plan_cost, SCORE))


@dataclass
class Replay:
    """An episode for review (see module docstring).

    Attributes:
        scene_id, scene_file (optional path as given), dt, start_frame, closed_loop, reactive,
        seed, autonomy (e.g. "A", "oracle").
        ego_dimensions: (3,); ego_poses: (T, 3); ego_speeds: (T,).
        actors: list of :class:`ReplayActor` (poses over the same T frames).
        frames: T :class:`ReplayFrame`.
        points: None or T float32 arrays (P, 5) x, y, z (ego frame, m), intensity, label.
        metadata: free JSON object (e.g. the attack's query and cost).
    """

    scene_id: str
    dt: float
    ego_dimensions: np.ndarray
    ego_poses: np.ndarray
    ego_speeds: np.ndarray
    actors: list[ReplayActor]
    frames: list[ReplayFrame]
    start_frame: int = 0
    closed_loop: bool = True
    reactive: bool = False
    seed: int = 0
    autonomy: str = ""
    scene_file: str | None = None
    points: list[np.ndarray] | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.dt = float(self.dt)
        self.ego_dimensions = _q(np.asarray(self.ego_dimensions, float).reshape(3), POS)
        self.ego_poses = _qpose(np.asarray(self.ego_poses, float).reshape(-1, 3))
        self.ego_speeds = _q(np.asarray(self.ego_speeds, float).reshape(-1), SPD)
        if self.points is not None:
            self.points = [_quantise_points(p) for p in self.points]

    @property
    def n_frames(self) -> int:
        return len(self.ego_poses)

    def points_in_map(self, k: int) -> np.ndarray:
        """(P, 3) float64 frame k's points in the map frame (for drawing), or (0, 3)."""
        if self.points is None:
            return np.zeros((0, 3))
        p = self.points[k].astype(np.float64)
        x, y, yaw = self.ego_poses[k]
        c, s = np.cos(yaw), np.sin(yaw)
        return np.c_[x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1], p[:, 2]]


def _quantise_points(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=np.float32).reshape(-1, 5)
    out = np.empty_like(p)
    out[:, :3] = (np.round(np.clip(p[:, :3], -327.67, 327.67) * 100.0) / np.float32(100.0)).astype(np.float32)
    out[:, 3] = (np.round(np.clip(p[:, 3], 0.0, 1.0) * 255.0) / np.float32(255.0)).astype(np.float32)
    out[:, 4] = np.round(p[:, 4])
    return out


# ------------------------------------------------------------------ from an episode

def map_centre(result, k: int) -> np.ndarray:
    """Where frame k's occupancy map is centred: the mean position of the attacked actors
    present in frame k, else ``MAP_AHEAD`` m ahead of the ego. (2,) map frame."""
    pos = result.actor_poses[k][np.asarray(result.adversarial, bool)]
    pos = pos[np.isfinite(pos).all(axis=1)]
    if len(pos):
        return pos[:, :2].mean(axis=0)
    x, y, yaw = result.ego_poses[k]
    return np.array([x + MAP_AHEAD * np.cos(yaw), y + MAP_AHEAD * np.sin(yaw)])


def replay_from_episode(result, *, autonomy: str = "", scene_file: str | None = None,
                        metadata: dict | None = None, meshes: dict[int, str] | None = None) -> Replay:
    """Build a :class:`Replay` from an :class:`~adv3d_runner.sim.episode.EpisodeResult`.

    ``meshes``: {actor id: path of its substituted mesh file, relative to the replay file}.
    Frames whose outputs carry an occupancy field get an :class:`OccupancyMap` (around
    :func:`map_centre`, at ``MAP_TIMES``).
    """
    T = result.frames
    actors = [ReplayActor(int(a), c, result.actor_dimensions[i], result.actor_poses[:T, i],
                          bool(result.adversarial[i]), (meshes or {}).get(int(a)))
              for i, (a, c) in enumerate(zip(result.actor_ids, result.actor_classes))]
    frames = []
    for k, o in enumerate(result.outputs):
        p = o.predictions
        occ = None
        if o.occupancy is not None:
            times = [t for t in MAP_TIMES if t <= o.occupancy.horizon + 1e-9]
            occ = occupancy_map(o.occupancy, map_centre(result, k), float(result.ego_poses[k][2]),
                                float(result.ego_speeds[k]), times)
        frames.append(ReplayFrame(o.detections.boxes, o.detections.scores, o.tracks.ids, o.tracks.boxes,
                                  o.tracks.velocities, p.track_ids, p.trajectories, p.probabilities,
                                  o.plan.trajectory, o.plan.speed, o.plan.label, o.plan.cost, occ))
    return Replay(result.scene_id, result.dt, result.ego_dimensions, result.ego_poses, result.ego_speeds, actors,
                  frames, result.start_frame, result.closed_loop, result.reactive, result.seed, autonomy, scene_file,
                  result.points, dict(metadata or {}))


# ------------------------------------------------------------------ JSON

def _num(a: np.ndarray) -> Any:
    """Nested lists of floats; NaN -> None."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 0:
        return None if not np.isfinite(a) else float(a)
    return [_num(x) for x in a] if a.ndim > 1 else [float(x) if np.isfinite(x) else None for x in a]


def _poses_json(poses: np.ndarray) -> list:
    return [None if not np.isfinite(p).all() else [float(v) for v in p] for p in poses]


def points_path(path: str | Path) -> Path:
    """The points file that goes with a replay file: ``NAME.points.npz``."""
    p = Path(path)
    name = p.name
    for suffix in (".json.gz", ".json"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return p.with_name(name + ".points.npz")


def _occupancy_json(m: OccupancyMap) -> dict:
    return {"times": _num(m.times), "poses": _num(m.poses), "cell": m.cell, "shape": list(m.values.shape[1:]),
            "values": m.values.tolist()}


def replay_to_dict(replay: Replay, points_file: str | None = None) -> dict:
    """The JSON document (plain types, fixed field order); version 2 when a frame has an
    occupancy map, else version 1."""
    has_maps = any(f.occupancy is not None for f in replay.frames)
    doc = {
        "format": FORMAT, "version": VERSION_OCCUPANCY if has_maps else VERSION,
        "scene": {"id": replay.scene_id, "file": replay.scene_file},
        "dt": replay.dt, "start_frame": int(replay.start_frame), "frames": replay.n_frames,
        "closed_loop": bool(replay.closed_loop), "reactive": bool(replay.reactive), "seed": int(replay.seed),
        "autonomy": replay.autonomy,
        "ego": {"dimensions": _num(replay.ego_dimensions), "poses": _poses_json(replay.ego_poses),
                "speed": _num(replay.ego_speeds)},
        "actors": [{"id": a.id, "class": a.cls, "dimensions": _num(a.dimensions), "adversarial": a.adversarial,
                    "mesh": a.mesh, "poses": _poses_json(a.poses)} for a in replay.actors],
        "outputs": [{
            "detections": {"boxes": _num(f.det_boxes), "scores": _num(f.det_scores)},
            "tracks": {"ids": [int(i) for i in f.track_ids], "boxes": _num(f.track_boxes),
                       "velocities": _num(f.track_velocities)},
            "predictions": {"track_ids": [int(i) for i in f.pred_track_ids],
                            "probabilities": _num(f.pred_probabilities),
                            "trajectories": _num(f.pred_trajectories)},
            "plan": {"trajectory": _num(f.plan), "speed": _num(f.plan_speed), "label": f.plan_label,
                     "cost": f.plan_cost},
        } for f in replay.frames],
        "points": points_file,
        "metadata": replay.metadata,
    }
    if has_maps:
        for out, f in zip(doc["outputs"], replay.frames):
            out["occupancy"] = None if f.occupancy is None else _occupancy_json(f.occupancy)
    return doc


def save_replay(replay: Replay, path: str | Path, *, indent: int | None = None) -> Path:
    """Write ``path`` (``.json`` or ``.json.gz``) and, when the replay has points, the sibling
    ``NAME.points.npz``; both atomically. Returns the JSON path."""
    path = Path(path)
    points_file = None
    if replay.points is not None:
        pp = points_path(path)
        points_file = pp.name
        pts = np.concatenate(replay.points) if replay.points else np.zeros((0, 5), np.float32)
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in replay.points])]).astype(np.int64)
        with atomic_path(pp, suffix=".npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, format=np.array(POINTS_FORMAT), version=np.array(VERSION, np.int64),
                                    xyz_cm=np.round(pts[:, :3].astype(np.float64) * 100.0).astype(np.int16),
                                    intensity=np.round(pts[:, 3].astype(np.float64) * 255.0).astype(np.uint8),
                                    label=pts[:, 4].astype(np.int16), offsets=offsets)
    write_json(path, replay_to_dict(replay, points_file), indent=indent)
    return path


class _Check:
    """Validation helpers that name the file and the JSON path."""

    def __init__(self, path):
        self.path = path

    def fail(self, where: str, expected: str, got: Any = None):
        raise FileFormatError(self.path, where, expected, got)

    def obj(self, doc: Any, key: str, where: str) -> Any:
        if not isinstance(doc, dict) or key not in doc:
            self.fail(f"{where}.{key}", "a field (missing)")
        return doc[key]

    def number(self, v: Any, where: str, lo: float | None = None) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or (lo is not None and v < lo):
            self.fail(where, "a finite number" + (f" >= {lo}" if lo is not None else ""), v)
        return float(v)

    def integer(self, v: Any, where: str, lo: int | None = None) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or (lo is not None and v < lo):
            self.fail(where, "an integer" + (f" >= {lo}" if lo is not None else ""), v)
        return int(v)

    def boolean(self, v: Any, where: str) -> bool:
        if not isinstance(v, bool):
            self.fail(where, "true or false", v)
        return v

    def string(self, v: Any, where: str, nullable: bool = False) -> str | None:
        if v is None and nullable:
            return None
        if not isinstance(v, str):
            self.fail(where, "a string" + (" or null" if nullable else ""), v)
        return v

    def array(self, v: Any, where: str, shape: tuple, nullable: bool = False) -> np.ndarray:
        """Nested list of numbers with ``shape`` (None = any length), all finite (or null
        where ``nullable``)."""
        if not isinstance(v, list):
            self.fail(where, f"an array of shape {_shape_text(shape)}", type(v).__name__)
        try:
            a = np.array([np.nan if x is None else x for x in v] if len(shape) == 1 else v, dtype=np.float64)
        except (ValueError, TypeError):
            a = None
        if a is None or a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)) \
                or (a.size == 0 and len(v) and a.ndim != len(shape)):
            if isinstance(v, list) and len(v) == 0:
                return np.zeros(tuple(0 if s is None else s for s in shape))
            self.fail(where, f"an array of shape {_shape_text(shape)} of numbers", _brief(v))
        if not nullable and not np.isfinite(a).all():
            bad = np.argwhere(~np.isfinite(a))[0]
            self.fail(where + "".join(f"[{int(i)}]" for i in bad), "a finite number", None)
        return a

    def poses(self, v: Any, where: str, T: int, nullable: bool) -> np.ndarray:
        if not isinstance(v, list) or len(v) != T:
            self.fail(where, f"a list of {T} poses", _brief(v))
        out = np.full((T, 3), np.nan)
        for k, p in enumerate(v):
            if p is None and nullable:
                continue
            out[k] = self.array(p, f"{where}[{k}]", (3,))
        return out


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"


def _brief(v: Any) -> Any:
    return v if not isinstance(v, list) else f"list of {len(v)}"


def _occupancy_from_json(c: "_Check", doc: Any, where: str) -> OccupancyMap | None:
    if doc is None:
        return None
    times = c.array(c.obj(doc, "times", where), f"{where}.times", (None,))
    poses = c.array(c.obj(doc, "poses", where), f"{where}.poses", (len(times), 3))
    cell = c.number(c.obj(doc, "cell", where), f"{where}.cell", lo=1e-6)
    shape = c.obj(doc, "shape", where)
    if not (isinstance(shape, list) and len(shape) == 2 and all(isinstance(n, int) and not isinstance(n, bool)
                                                                 and n >= 1 for n in shape)):
        c.fail(f"{where}.shape", "[nx, ny], two integers >= 1", shape)
    values = c.array(c.obj(doc, "values", where), f"{where}.values", (len(times), shape[0], shape[1]))
    if np.any(values != np.round(values)) or np.any(values < 0) or np.any(values > 255):
        c.fail(f"{where}.values", "integers in [0, 255] (occupancy probability x 255)", _brief(doc["values"]))
    if np.any(times < 0):
        c.fail(f"{where}.times", "times >= 0 s", _brief(doc["times"]))
    return OccupancyMap(times, poses, cell, values.astype(np.uint8))


def replay_from_dict(doc: Any, path: str | Path | None = None, points: list[np.ndarray] | None = None) -> Replay:
    """Validate a replay document and build the :class:`Replay` (points loaded separately)."""
    version = check_header(doc, path, FORMAT, (VERSION, VERSION_OCCUPANCY))
    c = _Check(path)
    scene = c.obj(doc, "scene", "$")
    scene_id = c.string(c.obj(scene, "id", "$.scene"), "$.scene.id")
    scene_file = c.string(scene.get("file") if isinstance(scene, dict) else None, "$.scene.file", nullable=True)
    dt = c.number(c.obj(doc, "dt", "$"), "$.dt", lo=1e-6)
    T = c.integer(c.obj(doc, "frames", "$"), "$.frames", lo=0)
    ego = c.obj(doc, "ego", "$")
    ego_dims = c.array(c.obj(ego, "dimensions", "$.ego"), "$.ego.dimensions", (3,))
    ego_poses = c.poses(c.obj(ego, "poses", "$.ego"), "$.ego.poses", T, nullable=False)
    ego_speed = c.array(c.obj(ego, "speed", "$.ego"), "$.ego.speed", (T,))
    actors_doc = c.obj(doc, "actors", "$")
    if not isinstance(actors_doc, list):
        c.fail("$.actors", "a list", type(actors_doc).__name__)
    actors, seen = [], set()
    for i, a in enumerate(actors_doc):
        w = f"$.actors[{i}]"
        aid = c.integer(c.obj(a, "id", w), f"{w}.id", lo=0)
        if aid in seen:
            c.fail(f"{w}.id", "a unique actor id", aid)
        seen.add(aid)
        actors.append(ReplayActor(aid, c.string(c.obj(a, "class", w), f"{w}.class"),
                                  c.array(c.obj(a, "dimensions", w), f"{w}.dimensions", (3,)),
                                  c.poses(c.obj(a, "poses", w), f"{w}.poses", T, nullable=True),
                                  c.boolean(a.get("adversarial", False), f"{w}.adversarial"),
                                  c.string(a.get("mesh"), f"{w}.mesh", nullable=True)))
    outs = c.obj(doc, "outputs", "$")
    if not isinstance(outs, list) or len(outs) != T:
        c.fail("$.outputs", f"a list of {T} frames", _brief(outs))
    frames = []
    for k, o in enumerate(outs):
        w = f"$.outputs[{k}]"
        det = c.obj(o, "detections", w)
        boxes = c.array(c.obj(det, "boxes", f"{w}.detections"), f"{w}.detections.boxes", (None, 5))
        scores = c.array(c.obj(det, "scores", f"{w}.detections"), f"{w}.detections.scores", (len(boxes),))
        tr = c.obj(o, "tracks", w)
        tids = c.array(c.obj(tr, "ids", f"{w}.tracks"), f"{w}.tracks.ids", (None,))
        if np.any(tids != np.round(tids)):
            c.fail(f"{w}.tracks.ids", "integers", _brief(tr["ids"]))
        tboxes = c.array(c.obj(tr, "boxes", f"{w}.tracks"), f"{w}.tracks.boxes", (len(tids), 5))
        tvel = c.array(c.obj(tr, "velocities", f"{w}.tracks"), f"{w}.tracks.velocities", (len(tids), 2))
        pr = c.obj(o, "predictions", w)
        pids = c.array(c.obj(pr, "track_ids", f"{w}.predictions"), f"{w}.predictions.track_ids", (None,))
        if np.any(pids != np.round(pids)):
            c.fail(f"{w}.predictions.track_ids", "integers", _brief(pr["track_ids"]))
        probs = c.array(c.obj(pr, "probabilities", f"{w}.predictions"), f"{w}.predictions.probabilities",
                        (len(pids), None))
        traj = c.array(c.obj(pr, "trajectories", f"{w}.predictions"), f"{w}.predictions.trajectories",
                       (len(pids), probs.shape[1] if probs.ndim == 2 else None, None, 2))
        pl = c.obj(o, "plan", w)
        plan = c.array(c.obj(pl, "trajectory", f"{w}.plan"), f"{w}.plan.trajectory", (None, 3))
        speed = c.array(c.obj(pl, "speed", f"{w}.plan"), f"{w}.plan.speed", (len(plan),))
        label = c.string(pl.get("label", ""), f"{w}.plan.label")
        cost = c.number(pl.get("cost", 0.0), f"{w}.plan.cost")
        occ = None
        if isinstance(o, dict) and "occupancy" in o:
            if version < VERSION_OCCUPANCY:
                c.fail(f"{w}.occupancy", f"no occupancy map in a version {version} file (maps need version "
                                         f"{VERSION_OCCUPANCY})", "a map")
            occ = _occupancy_from_json(c, o["occupancy"], f"{w}.occupancy")
        frames.append(ReplayFrame(boxes, scores, tids.astype(np.int64), tboxes, tvel, pids.astype(np.int64), traj,
                                  probs, plan, speed, label, cost, occ))
    meta = doc.get("metadata", {})
    if not isinstance(meta, dict):
        c.fail("$.metadata", "a JSON object", type(meta).__name__)
    return Replay(scene_id, dt, ego_dims, ego_poses, ego_speed, actors, frames,
                  c.integer(doc.get("start_frame", 0), "$.start_frame", lo=0),
                  c.boolean(doc.get("closed_loop", True), "$.closed_loop"),
                  c.boolean(doc.get("reactive", False), "$.reactive"),
                  c.integer(doc.get("seed", 0), "$.seed"),
                  c.string(doc.get("autonomy", ""), "$.autonomy"), scene_file, points, meta)


def load_points(path: str | Path, frames: int, n_actors: int) -> list[np.ndarray]:
    """Read a replay's points file -> T float32 (P, 5) arrays (validated)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise FileFormatError(path, "$", "an existing points file", "file not found") from None
    except (OSError, ValueError) as exc:
        raise FileFormatError(path, "$", "a numpy .npz file without pickled objects", str(exc)) from None
    for key in ("format", "version", "xyz_cm", "intensity", "label", "offsets"):
        if key not in data:
            raise FileFormatError(path, f"$.{key}", "an array (missing)")
    if str(data["format"]) != POINTS_FORMAT:
        raise FileFormatError(path, "$.format", f'"{POINTS_FORMAT}"', str(data["format"]))
    if int(data["version"]) != VERSION:
        raise FileFormatError(path, "$.version", f"[{VERSION}]", int(data["version"]))
    xyz, inten, lab, off = data["xyz_cm"], data["intensity"], data["label"], data["offsets"]
    P = len(xyz)
    if xyz.dtype != np.int16 or xyz.ndim != 2 or xyz.shape[1] != 3:
        raise FileFormatError(path, "$.xyz_cm", "int16 array (P, 3)", f"{xyz.dtype} {xyz.shape}")
    if inten.dtype != np.uint8 or inten.shape != (P,):
        raise FileFormatError(path, "$.intensity", f"uint8 array ({P},)", f"{inten.dtype} {inten.shape}")
    if lab.dtype != np.int16 or lab.shape != (P,) or (P and (lab.min() < -1 or lab.max() >= n_actors)):
        raise FileFormatError(path, "$.label", f"int16 array ({P},) in [-1, {n_actors - 1}]", f"{lab.dtype} {lab.shape}")
    if off.shape != (frames + 1,) or off[0] != 0 or off[-1] != P or np.any(np.diff(off) < 0):
        raise FileFormatError(path, "$.offsets", f"non-decreasing int array ({frames + 1},) from 0 to {P}",
                              f"{off.shape}")
    # filled in place (no temporaries): this is most of the load time of a long replay
    pts = np.empty((P, 5), np.float32)
    np.divide(xyz, np.float32(100.0), out=pts[:, :3], dtype=np.float32)
    np.divide(inten, np.float32(255.0), out=pts[:, 3], dtype=np.float32)
    pts[:, 4] = lab
    return [pts[off[k]:off[k + 1]] for k in range(frames)]


def load_replay(path: str | Path, *, points: bool = True) -> Replay:
    """Load and validate a replay file (and its points file when it names one and ``points``)."""
    path = Path(path)
    doc = read_json(path)
    replay = replay_from_dict(doc, path)
    pf = doc.get("points")
    if pf is not None and not isinstance(pf, str):
        raise FileFormatError(path, "$.points", "a file name or null", pf)
    if pf and points:
        replay.points = load_points(path.parent / pf, replay.n_frames, len(replay.actors))
    return replay


def replay_equal(a: Replay, b: Replay) -> bool:
    """Exact equality (NaN == NaN) of two replays, points included."""
    def eq(x, y) -> bool:
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            x, y = np.asarray(x), np.asarray(y)
            return x.shape == y.shape and bool(np.array_equal(x, y, equal_nan=x.dtype.kind == "f"))
        return x == y

    scalars = ("scene_id", "dt", "start_frame", "closed_loop", "reactive", "seed", "autonomy", "scene_file", "metadata")
    if any(not eq(getattr(a, s), getattr(b, s)) for s in scalars):
        return False
    if not all(eq(getattr(a, s), getattr(b, s)) for s in ("ego_dimensions", "ego_poses", "ego_speeds")):
        return False
    if len(a.actors) != len(b.actors) or len(a.frames) != len(b.frames):
        return False
    for x, y in zip(a.actors, b.actors):
        if not all(eq(getattr(x, f), getattr(y, f)) for f in ("id", "cls", "dimensions", "poses", "adversarial", "mesh")):
            return False
    for x, y in zip(a.frames, b.frames):
        if not all(eq(getattr(x, f), getattr(y, f)) for f in ReplayFrame.__dataclass_fields__ if f != "occupancy"):
            return False
        if (x.occupancy is None) != (y.occupancy is None) or (x.occupancy is not None and not x.occupancy.equals(y.occupancy)):
            return False
    if (a.points is None) != (b.points is None):
        return False
    return a.points is None or (len(a.points) == len(b.points) and all(eq(x, y) for x, y in zip(a.points, b.points)))
