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

from ..fileio import atomic_path, read_json_steps, write_json
from ..progress import Steps, run_steps
from ..validate import Node, check_header, describe, read_npz_steps

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
#: Largest |value| of any number in a replay (m, m/s, rad): far beyond any scene (whose
#: positions are bounded by 1e7 m), so a hostile 1e308 cannot overflow the quantisation.
MAX_ABS = 1e7
#: Largest vehicle dimension (m): the scene contract's bound (``scene.schema.MAX_SIZE``).
MAX_SIZE = 100.0
_DIMS_EXPECTED = f"a positive size in m (at most {MAX_SIZE:g})"
MAX_FRAMES = 100_000
_KEYS = ("format", "version", "scene", "dt", "start_frame", "frames", "closed_loop", "reactive", "seed", "autonomy",
         "ego", "actors", "outputs", "points", "metadata")


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


def _poses(node: Node, T: int, *, nullable: bool) -> np.ndarray:
    """(T, 3) x, y, yaw per frame; ``null`` frames (actor absent) are NaN when ``nullable``."""
    out = np.full((T, 3), np.nan)
    for k, p in enumerate(node.items(f"a list of {T} poses", length=T)):
        if p.value is None and nullable:
            continue
        out[k] = p.array((3,), limit=MAX_ABS)
    return out


def _ids(node: Node, n: int | None = None) -> np.ndarray:
    """A list of integer ids -> (n,) int64 (JSON numbers that are whole)."""
    ids = node.array((n,), limit=2**62)
    if np.any(ids != np.round(ids)):
        node.fail("integers", describe(node.value))
    return ids.astype(np.int64)


def _frame(o: Node, version: int = VERSION) -> ReplayFrame:
    o.check_keys(("detections", "tracks", "predictions", "plan", "occupancy"))
    det = o["detections"]
    det.check_keys(("boxes", "scores"))
    boxes = det["boxes"].array((None, 5), limit=MAX_ABS)
    scores = det["scores"].array((len(boxes),), limit=MAX_ABS)
    tr = o["tracks"]
    tr.check_keys(("ids", "boxes", "velocities"))
    tids = _ids(tr["ids"])
    tboxes = tr["boxes"].array((len(tids), 5), limit=MAX_ABS)
    tvel = tr["velocities"].array((len(tids), 2), limit=MAX_ABS)
    pr = o["predictions"]
    pr.check_keys(("track_ids", "probabilities", "trajectories"))
    pids = _ids(pr["track_ids"])
    probs = pr["probabilities"].array((len(pids), None), limit=MAX_ABS)
    traj = pr["trajectories"].array((len(pids), probs.shape[1] if probs.ndim == 2 else None, None, 2), limit=MAX_ABS)
    pl = o["plan"]
    pl.check_keys(("trajectory", "speed", "label", "cost"))
    plan = pl["trajectory"].array((None, 3), limit=MAX_ABS)
    speed = pl["speed"].array((len(plan),), limit=MAX_ABS)
    occ = None
    if "occupancy" in o:
        if version < VERSION_OCCUPANCY:
            o["occupancy"].fail(f"no occupancy map in a version {version} file (maps need version "
                                f"{VERSION_OCCUPANCY})", "a map")
        occ = _occupancy(o["occupancy"])
    return ReplayFrame(boxes, scores, tids, tboxes, tvel, pids, traj, probs, plan, speed,
                       pl.get("label", "").string(empty=True), pl.get("cost", 0.0).number(lo=-MAX_ABS, hi=MAX_ABS),
                       occ)


def _occupancy(o: Node) -> OccupancyMap | None:
    """A frame's ``occupancy`` heat map (version 2), or None for ``null``."""
    if o.value is None:
        return None
    o.check_keys(("times", "poses", "cell", "shape", "values"))
    times = o["times"].array((None,), limit=MAX_ABS)
    if np.any(times < 0):
        o["times"].fail("times >= 0 s", describe(o["times"].value))
    poses = o["poses"].array((len(times), 3), limit=MAX_ABS)
    cell = o["cell"].number(lo=1e-6, hi=MAX_ABS)
    shape = o["shape"]
    nxy = [n.integer(lo=1, hi=100_000) for n in shape.items("[nx, ny], two integers >= 1", length=2)]
    values = o["values"].array((len(times), nxy[0], nxy[1]), limit=MAX_ABS)
    if np.any(values != np.round(values)) or np.any(values < 0) or np.any(values > 255):
        o["values"].fail("integers in [0, 255] (occupancy probability x 255)", describe(o["values"].value))
    return OccupancyMap(times, poses, cell, values.astype(np.uint8))


#: Frames validated per step of :func:`load_replay_steps`; points rows converted per step.
STEP_FRAMES = 25
STEP_ROWS = 1 << 19


def replay_from_dict(raw: Any, path: str | Path | None = None, points: list[np.ndarray] | None = None) -> Replay:
    """Validate a replay document and build the :class:`Replay` (points loaded separately)."""
    return run_steps(replay_from_dict_steps(raw, path, points))


def replay_from_dict_steps(raw: Any, path: str | Path | None = None,
                           points: list[np.ndarray] | None = None) -> Steps[Replay]:
    """:func:`replay_from_dict` as a steps generator (``STEP_FRAMES`` frames per step)."""
    doc = Node(raw, "$", path)
    version = check_header(doc, FORMAT, (VERSION, VERSION_OCCUPANCY))
    doc.check_keys(_KEYS)
    scene = doc["scene"]
    scene.object()
    scene.check_keys(("id", "file"))
    scene_id = scene["id"].string(empty=True)
    scene_file = scene.get("file").string(nullable=True, empty=True)
    dt = doc["dt"].number(lo=1e-6, hi=10.0)
    T = doc["frames"].integer(lo=0, hi=MAX_FRAMES)
    ego = doc["ego"]
    ego.object()
    ego.check_keys(("dimensions", "poses", "speed"))
    ego_dims = ego["dimensions"].numbers(length=3, lo=0.0, lo_open=True, hi=MAX_SIZE, expected=_DIMS_EXPECTED)
    ego_poses = _poses(ego["poses"], T, nullable=False)
    ego_speed = ego["speed"].array((T,), limit=MAX_ABS)
    actors, seen = [], set()
    for a in doc["actors"].objects("a list of actors"):
        a.check_keys(("id", "class", "dimensions", "adversarial", "mesh", "poses"))
        aid = a["id"].unique(a["id"].integer(lo=0), seen, "actor id")
        mesh = a.get("mesh")
        actors.append(ReplayActor(aid, a["class"].string(empty=True),
                                  a["dimensions"].numbers(length=3, lo=0.0, lo_open=True, hi=MAX_SIZE,
                                                          expected=_DIMS_EXPECTED),
                                  _poses(a["poses"], T, nullable=True),
                                  a.get("adversarial", False).boolean(),
                                  None if mesh.value is None else mesh.rel_path(inside="the replay's folder")))
    frames = []
    for o in doc["outputs"].items(f"a list of {T} frames", length=T):
        frames.append(_frame(o, version))
        if len(frames) % STEP_FRAMES == 0:
            yield
    meta = doc.get("metadata", {}).object("a JSON object")
    return Replay(scene_id, dt, ego_dims, ego_poses, ego_speed, actors, frames,
                  doc.get("start_frame", 0).integer(lo=0),
                  doc.get("closed_loop", True).boolean(),
                  doc.get("reactive", False).boolean(),
                  doc.get("seed", 0).integer(),
                  doc.get("autonomy", "").string(empty=True), scene_file, points, meta)


def load_points(path: str | Path, frames: int, n_actors: int) -> list[np.ndarray]:
    """Read a replay's points file -> T float32 (P, 5) arrays (validated)."""
    return run_steps(load_points_steps(path, frames, n_actors))


def load_points_steps(path: str | Path, frames: int, n_actors: int) -> Steps[list[np.ndarray]]:
    """:func:`load_points` as a steps generator: the file inflated and converted in pieces,
    yielding ``(fraction,)``."""
    from ..progress import span

    z = yield from span(read_npz_steps(path, "points file"), 0.0, 0.8, "")
    z.require(("format", "version", "xyz_cm", "intensity", "label", "offsets"))
    z.header(POINTS_FORMAT, VERSION)
    xyz = z.array("xyz_cm", dtype=np.int16, shape=("P", 3))
    P = len(xyz)
    inten = z.array("intensity", dtype=np.uint8, shape=(P,))
    lab = z.array("label", dtype=np.int16, shape=(P,))
    if P and (lab.min() < -1 or lab.max() >= n_actors):
        z.fail("label", f"int16 array ({P},) in [-1, {n_actors - 1}]", f"values in [{lab.min()}, {lab.max()}]")
    off = z.array("offsets", kind="i", shape=(frames + 1,))
    if off.shape != (frames + 1,) or off[0] != 0 or off[-1] != P or np.any(np.diff(off) < 0):
        z.fail("offsets", f"non-decreasing int array ({frames + 1},) from 0 to {P}", f"{off.shape}")
    # filled in place (no temporaries): this is most of the load time of a long replay
    pts = np.empty((P, 5), np.float32)
    for s in range(0, P, STEP_ROWS):  # row blocks: elementwise, so the same bytes as one call
        e = min(s + STEP_ROWS, P)
        np.divide(xyz[s:e], np.float32(100.0), out=pts[s:e, :3], dtype=np.float32)
        np.divide(inten[s:e], np.float32(255.0), out=pts[s:e, 3], dtype=np.float32)
        pts[s:e, 4] = lab[s:e]
        yield 0.8 + 0.2 * e / P,
    return [pts[off[k]:off[k + 1]] for k in range(frames)]


def load_replay(path: str | Path, *, points: bool = True) -> Replay:
    """Load and validate a replay file (and its points file when it names one and ``points``)."""
    return run_steps(load_replay_steps(path, points=points))


def load_replay_steps(path: str | Path, *, points: bool = True) -> Steps[Replay]:
    """:func:`load_replay` as a steps generator (``progress.run_steps``): reading, parsing,
    validating and the points file in pieces of a few tens of milliseconds, yielding
    ``(fraction, message)`` between them (the Blender add-on's Load review stays responsive)."""
    from ..progress import relay, span

    name = Path(path).name
    doc = Node((yield from relay(read_json_steps(path), (0.05, f"reading {name}"))), "$", path)
    replay = yield from relay(replay_from_dict_steps(doc.value, path), (0.2, f"checking {name}"))
    pf = doc.get("points")
    if pf.value is not None:
        pf.string(empty=True, expected="a file name or null")
    if pf.value and points:
        pfile = pf.file_in(Path(path).parent, inside="the replay's folder")
        replay.points = yield from span(load_points_steps(pfile, replay.n_frames, len(replay.actors)),
                                        0.3, 1.0, f"reading {pf.value}")
    return replay


def actor_mesh_path(replay_path: str | Path, replay: Replay, index: int) -> Path | None:
    """The file of actor ``index``'s substituted mesh, checked to stay inside the replay's
    folder (symlinks included), or None when the actor has no mesh."""
    from ..fileio import resolve_inside

    rel = replay.actors[index].mesh
    if not rel:
        return None
    return resolve_inside(Path(replay_path).parent, rel, file=replay_path, field=f"$.actors[{index}].mesh",
                          inside="the replay's folder")


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
