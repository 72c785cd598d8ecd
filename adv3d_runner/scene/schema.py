"""The scene file contract (``"format": "adv3d-scene"``, version 1): data model, load, save.

A scene is one driving scenario: a lane map, a description of the static background, an ego
vehicle with a logged trajectory and its LiDAR rig, and the other actors with per-frame tracks.
Everything is in the scene's map frame (metres, radians, x/y on the ground plane, yaw CCW from
+x), sampled at ``dt`` (0.1 s) for ``frames`` frames. See ``docs/formats.md`` ("Scene").

Per-frame data are stored as column arrays rounded to fixed decimals (cm for positions, mrad
for angles, cm/s for speeds) so files stay small *and* a load -> save -> load round trip gives
bit-identical numbers: rounding is idempotent (``round(round(x)) == round(x)``), and the
shortest ``repr`` of a value with 3 decimals parses back to the same double.

Numpy accessors (``Scene.ego_poses``, ``Scene.actor_poses``, ``Scene.actor_valid``,
``Scene.lane_polylines``) give consumers (LiDAR, planner, Blender add-on) arrays directly.
This module needs only numpy, so the Blender add-on can import it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..fileio import MEMORY_BUDGET, atomic_write_text, dump_json, gib, read_json
from ..geometry.angles import wrap_angle
from ..validate import Node, check_header
from ..vehicle_classes import CLASS_PATTERN, class_examples

FORMAT = "adv3d-scene"
VERSION = 1
SUPPORTED_VERSIONS = (1,)

SOURCE_KINDS = ("generated", "commonroad", "blender")
# Sources whose ego track is a measurement (NGSIM: positions tracked in video, speeds
# differentiated from them) rather than a simulator's or an artist's exact states. A one-frame
# difference of such speeds is mostly noise (up to +-4 m/s^2 within 0.3 s where the positions
# show a steady speed), so their accelerations are estimated by a local fit instead.
MEASURED_SOURCE_KINDS = ("commonroad",)
# Width of that fit (s): the smoothing width Thiemann, Kesting & Treiber (2008, "Estimating
# acceleration and lane-changing dynamics from NGSIM trajectory data") use for accelerations.
MEASURED_ACCEL_WINDOW_S = 1.0
# Actor classes: any lower-case identifier (``CLASS_PATTERN``); the known ones are the one list
# ``adv3d_runner.vehicle_classes.VEHICLE_CLASSES`` (shared with the vehicle library and the add-on).
BARRIER_KINDS = ("concrete", "guardrail")
SURFACE_KINDS_FOR_MESHES = ("asphalt", "concrete", "metal", "ground", "vegetation")

# Decimals kept in files: 1 cm, 1 mrad, 1 cm/s; dimensions 1 mm. 1 cm is far below vehicle
# sizes and LiDAR range noise (~2 cm) and keeps busy 20 s scenes around 20-90 kB gzipped.
POS_DECIMALS = 2
ANGLE_DECIMALS = 3
SPEED_DECIMALS = 2
DIM_DECIMALS = 3

NO_ACTOR = -1  # label used by consumers for "background" (never a valid actor id)

# Bounds of the contract (docs/formats.md): far outside any real scene, close enough that a
# mistyped or hostile number (1e308 m, a 1e9-frame scene) is refused when the file is read
# instead of overflowing a rounding or allocating gigabytes downstream.
MAX_COORD = 1e7     # m, |x|, |y| of every position (a local map frame; UTM northings fit)
MAX_SIZE = 100.0    # m, vehicle dimensions, lane widths, barrier heights, wheelbase
MAX_MARGIN = 10_000.0  # m, shoulders and ground margin
MAX_SPEED = 150.0   # m/s, recorded speeds and speed limits
MAX_FRAMES = 100_000  # frames (2.8 h at 10 Hz)
MAX_DT = 10.0       # s
#: s: scenes are sampled at 10 Hz, recordings at 10-100 Hz; an episode of --seconds S takes
#: S / dt frames (1e-9 s would make a 5 s episode 5e9 frames)
MIN_DT = 1e-3
#: actors of one scene: the benchmark's busiest has 80; checked before any actor is read, so a
#: file listing a million is refused at once instead of validated for minutes
MAX_ACTORS = 10_000
#: bytes per actor and scene frame of the arrays sized by both (``Scene.actor_poses``: x, y, yaw
#: float64, the valid flag, and as much again for the episode's working copies); actors x frames
#: x this stays within ``fileio.MEMORY_BUDGET``
ACTOR_FRAME_BYTES = 64
#: Largest scene (JSON bytes, after gzip): the benchmark's biggest is 0.4 MB; 64 MiB holds about
#: two million actor-frames and keeps reading and checking any scene to seconds. A scene is
#: refused when written too (save_scene), so nothing writes a scene it could not read back.
MAX_SCENE_BYTES = 64 * 2**20


def _round(values: np.ndarray | float, decimals: int) -> np.ndarray:
    """Round to ``decimals`` the way files store numbers (idempotent, exact on reload)."""
    out = np.round(np.asarray(values, dtype=np.float64), decimals)
    return out + 0.0  # adding +0.0 turns "-0.0" into "0.0" (files never hold -0.0)



# --------------------------------------------------------------------------------------------
# data classes
# --------------------------------------------------------------------------------------------


@dataclass
class Source:
    """Where a scene came from: ``kind`` (generated | commonroad | blender), free-form
    ``details`` (generator seed/layout/density, original file and benchmark id, ...),
    and the ``licence`` / ``attribution`` texts to keep with the data."""

    kind: str
    details: dict = field(default_factory=dict)
    licence: str | None = None
    attribution: str | None = None


@dataclass
class Lane:
    """One lane as a centre line.

    Attributes:
        id: lane id (int >= 0, unique in the map).
        centerline: (P, 2) float64 m, P >= 2, in driving direction.
        width: (P,) float64 m, lane width at each centre-line point (constant lanes repeat it).
        left, right: id of the adjacent lane with the same driving direction, or None.
        successors: ids of the lanes that continue this one.
        speed_limit: m/s, or None when unknown.
    """

    id: int
    centerline: np.ndarray
    width: np.ndarray
    left: int | None = None
    right: int | None = None
    successors: list[int] = field(default_factory=list)
    speed_limit: float | None = None

    def __post_init__(self) -> None:
        self.centerline = _round(np.asarray(self.centerline, dtype=np.float64).reshape(-1, 2), POS_DECIMALS)
        width = np.asarray(self.width, dtype=np.float64)
        if width.ndim == 0:
            width = np.full(len(self.centerline), float(width))
        self.width = _round(width, DIM_DECIMALS)
        if self.speed_limit is not None:
            self.speed_limit = float(_round(self.speed_limit, SPEED_DECIMALS))


@dataclass
class Barrier:
    """A roadside barrier along ``polyline`` ((P, 2) m): ``kind`` concrete | guardrail,
    ``height`` m above the road."""

    kind: str
    polyline: np.ndarray
    height: float = 0.8

    def __post_init__(self) -> None:
        self.polyline = _round(np.asarray(self.polyline, dtype=np.float64).reshape(-1, 2), POS_DECIMALS)
        self.height = float(_round(self.height, DIM_DECIMALS))


@dataclass
class StaticMesh:
    """An extra static mesh (signs, bridges, ...): ``file`` relative to the scene file,
    ``pose`` (x, y, z, yaw) in the map frame, ``surface`` kind for its reflectivity."""

    file: str
    pose: np.ndarray = field(default_factory=lambda: np.zeros(4))
    surface: str = "concrete"

    def __post_init__(self) -> None:
        pose = np.asarray(self.pose, dtype=np.float64).reshape(4)
        self.pose = np.concatenate([_round(pose[:3], POS_DECIMALS), _round(pose[3:], ANGLE_DECIMALS)])


@dataclass
class Background:
    """Static surroundings beyond the lanes.

    The road surface is the union of the lane strips; ``shoulder_left`` / ``shoulder_right``
    (m) extend it beyond the outermost lanes' edges; ground (grass/soil) continues for
    ``ground_margin`` m beyond the shoulders. ``lane_markings`` draws painted lines between
    lanes and at the road edge.
    """

    shoulder_left: float = 1.0
    shoulder_right: float = 2.5
    ground_margin: float = 30.0
    lane_markings: bool = True
    barriers: list[Barrier] = field(default_factory=list)
    meshes: list[StaticMesh] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.shoulder_left = float(_round(self.shoulder_left, DIM_DECIMALS))
        self.shoulder_right = float(_round(self.shoulder_right, DIM_DECIMALS))
        self.ground_margin = float(_round(self.ground_margin, DIM_DECIMALS))


@dataclass
class Track:
    """Per-frame poses of one vehicle over a contiguous frame span.

    The arrays cover frames ``start .. start + n - 1`` of the scene. ``valid[i]`` False marks a
    gap (its pose values are placeholders, never to be used). ``synthetic[i]`` True marks a pose
    that was not recorded but extrapolated (e.g. ``import-commonroad --extend``).

    Attributes:
        start: first frame (int >= 0).
        x, y: (n,) float64 m, footprint centre in the map frame.
        yaw: (n,) float64 rad in [-pi, pi).
        speed: (n,) float64 m/s (>= 0), or None when not recorded.
        valid: (n,) bool.
        synthetic: (n,) bool.
    """

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray | None = None
    start: int = 0
    valid: np.ndarray | None = None
    synthetic: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.x = _round(self.x, POS_DECIMALS).reshape(-1)
        self.y = _round(self.y, POS_DECIMALS).reshape(-1)
        yaw = np.asarray(self.yaw, dtype=np.float64).reshape(-1).copy()
        # Wrap only angles clearly outside [-pi, pi]: re-wrapping an already rounded +-3.142
        # would move it and break the exact round trip.
        outside = np.abs(yaw) > math.pi + 0.5 * 10.0 ** -ANGLE_DECIMALS
        yaw[outside] = wrap_angle(yaw[outside])
        self.yaw = _round(yaw, ANGLE_DECIMALS)
        if self.speed is not None:
            self.speed = _round(self.speed, SPEED_DECIMALS).reshape(-1)
        n = len(self.x)
        self.valid = np.ones(n, bool) if self.valid is None else np.asarray(self.valid, bool).reshape(-1)
        self.synthetic = np.zeros(n, bool) if self.synthetic is None else np.asarray(self.synthetic, bool).reshape(-1)
        self.start = int(self.start)

    def __len__(self) -> int:
        return len(self.x)


@dataclass
class Lidar:
    """One LiDAR of the ego's sensor rig: ``model`` name (a key of the sensor model table in
    ``adv3d_runner.sensors``), ``mount`` (x, y, z, roll, pitch, yaw) in the ego frame (m, rad;
    ego origin at the footprint centre on the ground)."""

    name: str
    model: str
    mount: np.ndarray

    def __post_init__(self) -> None:
        mount = np.asarray(self.mount, dtype=np.float64).reshape(6)
        self.mount = np.concatenate([_round(mount[:3], POS_DECIMALS), _round(mount[3:], ANGLE_DECIMALS)])


@dataclass
class Ego:
    """The ego vehicle: ``dimensions`` (L, W, H) m, ``wheelbase`` m, logged ``track`` over
    every frame (start 0, all valid, speed required), and its LiDAR ``sensors``."""

    dimensions: np.ndarray
    wheelbase: float
    track: Track
    sensors: list[Lidar] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.dimensions = _round(np.asarray(self.dimensions, dtype=np.float64).reshape(3), DIM_DECIMALS)
        self.wheelbase = float(_round(self.wheelbase, DIM_DECIMALS))


@dataclass
class Actor:
    """Another road user: ``id`` (int >= 0, unique), ``cls`` (vehicle class, stored as
    ``"class"``), ``dimensions`` (L, W, H) m, ``asset`` (vehicle library asset id, or None until
    assigned), ``track``."""

    id: int
    cls: str
    dimensions: np.ndarray
    track: Track
    asset: str | None = None

    def __post_init__(self) -> None:
        self.dimensions = _round(np.asarray(self.dimensions, dtype=np.float64).reshape(3), DIM_DECIMALS)


def default_sensors() -> list[Lidar]:
    """The default rig: one Velodyne HDL-64E on the roof (KITTI-like height)."""
    return [Lidar(name="top", model="hdl64", mount=np.array([0.0, 0.0, 1.73, 0.0, 0.0, 0.0]))]


@dataclass
class Scene:
    """A driving scene (see module docstring). ``frames`` = T, ``dt`` in s."""

    id: str
    source: Source
    dt: float
    frames: int
    lanes: list[Lane]
    background: Background
    ego: Ego
    actors: list[Actor]

    # ---------------------------------------------------------------- accessors
    @property
    def times(self) -> np.ndarray:
        """(T,) float64 s, time of each frame."""
        return np.arange(self.frames) * self.dt

    def lane(self, lane_id: int) -> Lane:
        """The lane with this id (KeyError if absent)."""
        for lane in self.lanes:
            if lane.id == lane_id:
                return lane
        raise KeyError(lane_id)

    def lane_polylines(self) -> dict[int, np.ndarray]:
        """{lane id: (P, 2) float64 centre line in m}."""
        return {lane.id: lane.centerline.copy() for lane in self.lanes}

    def actor(self, actor_id: int) -> Actor:
        """The actor with this id (KeyError if absent)."""
        for actor in self.actors:
            if actor.id == actor_id:
                return actor
        raise KeyError(actor_id)

    @property
    def actor_ids(self) -> list[int]:
        return [a.id for a in self.actors]

    def ego_poses(self) -> np.ndarray:
        """(T, 3) float64: x, y (m), yaw (rad) of the ego per frame."""
        return _track_array(self.ego.track, self.frames, ("x", "y", "yaw"))

    def ego_speeds(self) -> np.ndarray:
        """(T,) float64 m/s."""
        return _track_array(self.ego.track, self.frames, ("speed",))[:, 0]

    def ego_accelerations(self) -> np.ndarray:
        """(T,) float64 m/s^2: the logged ego's longitudinal acceleration per frame.

        Exact tracks (generated, authored): the forward difference of the speeds (the last
        frame the backward one). Measured tracks (``MEASURED_SOURCE_KINDS``): the slope of a
        least-squares line through the speeds of ``MEASURED_ACCEL_WINDOW_S`` around the frame
        (shifted inside the track at its ends).
        """
        v = self.ego_speeds()
        if self.source.kind in MEASURED_SOURCE_KINDS:
            return local_slope(v, self.dt, MEASURED_ACCEL_WINDOW_S)
        if len(v) < 2:
            return np.zeros(len(v))
        a = np.empty(len(v))
        a[:-1] = np.diff(v) / self.dt
        a[-1] = a[-2]
        return a

    def actor_poses(self, actor_id: int) -> np.ndarray:
        """(T, 3) float64: x, y (m), yaw (rad) per frame; NaN rows where the actor is not valid."""
        return _track_array(self.actor(actor_id).track, self.frames, ("x", "y", "yaw"))

    def actor_speeds(self, actor_id: int) -> np.ndarray:
        """(T,) float64 m/s; NaN where invalid. Tracks without recorded speeds get the speed
        of their positions (central differences, one-sided at the ends and next to gaps)."""
        track = self.actor(actor_id).track
        if track.speed is not None:
            return _track_array(track, self.frames, ("speed",))[:, 0]
        xy = _track_array(track, self.frames, ("x", "y"))
        step = np.hypot(*np.diff(xy, axis=0).T) / self.dt  # (T-1,), NaN across gaps
        fwd = np.append(step, np.nan)
        bwd = np.insert(step, 0, np.nan)
        with np.errstate(invalid="ignore"):
            both = 0.5 * (fwd + bwd)
        out = np.where(np.isfinite(both), both, np.where(np.isfinite(fwd), fwd, bwd))
        out[np.isnan(xy[:, 0])] = np.nan
        return out

    def actor_valid(self, actor_id: int) -> np.ndarray:
        """(T,) bool: True where the actor exists (recorded or synthetic)."""
        return _track_mask(self.actor(actor_id).track, self.frames, "valid")

    def actor_synthetic(self, actor_id: int) -> np.ndarray:
        """(T,) bool: True where the actor's pose was extrapolated, not recorded."""
        return _track_mask(self.actor(actor_id).track, self.frames, "synthetic")

    def all_actor_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """All actors at once: poses (N, T, 3) float64 (NaN where invalid), valid (N, T) bool,
        in ``self.actors`` order."""
        n = len(self.actors)
        poses = np.full((n, self.frames, 3), np.nan)
        valid = np.zeros((n, self.frames), bool)
        for i, actor in enumerate(self.actors):
            poses[i] = _track_array(actor.track, self.frames, ("x", "y", "yaw"))
            valid[i] = _track_mask(actor.track, self.frames, "valid")
        return poses, valid

    def actor_dimensions(self) -> np.ndarray:
        """(N, 3) float64 L, W, H in m, in ``self.actors`` order."""
        return np.array([a.dimensions for a in self.actors], dtype=np.float64).reshape(-1, 3)

    # ---------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict:
        """The JSON document (plain Python types, fixed field order)."""
        return _scene_to_dict(self)

    @classmethod
    def from_dict(cls, doc: Any, path: str | Path | None = None) -> "Scene":
        """Validate ``doc`` and build a Scene; errors name ``path`` and the JSON path."""
        return _scene_from_dict(doc, path)

    def validate(self) -> None:
        """Check the in-memory scene against the contract (same checks as loading)."""
        _scene_from_dict(_scene_to_dict(self), f"<scene {self.id}>")


def local_slope(values: np.ndarray, dt: float, window_s: float) -> np.ndarray:
    """(T,) slope per second of a least-squares line through ``values`` ((T,), one per ``dt``
    s) over the ``round(window_s / dt) + 1`` samples centred on each one, the window shifted
    inside the series at its ends (all of it when it is shorter)."""
    values = np.asarray(values, np.float64)
    T = len(values)
    n = min(T, int(round(window_s / dt)) + 1)
    if n < 2:
        return np.zeros(T)
    starts = np.clip(np.arange(T) - (n - 1) // 2, 0, T - n)
    t = (np.arange(n) - (n - 1) / 2.0) * dt               # centred times of a window
    windows = values[starts[:, None] + np.arange(n)]       # (T, n)
    return windows @ t / float(t @ t)


def _track_array(track: Track, frames: int, names: tuple[str, ...]) -> np.ndarray:
    out = np.full((frames, len(names)), np.nan)
    n = len(track)
    stop = min(frames, track.start + n)
    if stop > track.start:
        cols = []
        for name in names:
            value = getattr(track, name)
            cols.append(np.full(n, np.nan) if value is None else value)
        block = np.stack(cols, axis=1)[: stop - track.start]
        block[~track.valid[: stop - track.start]] = np.nan
        out[track.start:stop] = block
    return out


def _track_mask(track: Track, frames: int, name: str) -> np.ndarray:
    out = np.zeros(frames, bool)
    stop = min(frames, track.start + len(track))
    if stop > track.start:
        out[track.start:stop] = getattr(track, name)[: stop - track.start]
    return out


# --------------------------------------------------------------------------------------------
# to JSON
# --------------------------------------------------------------------------------------------


def _floats(values: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]


def _points(values: np.ndarray) -> list[list[float]]:
    return [[float(a), float(b)] for a, b in np.asarray(values, dtype=np.float64).reshape(-1, 2)]


def _track_to_dict(track: Track) -> dict:
    out: dict[str, Any] = {"start": track.start, "x": _floats(track.x), "y": _floats(track.y), "yaw": _floats(track.yaw)}
    if track.speed is not None:
        out["speed"] = _floats(track.speed)
    if not track.valid.all():  # omitted when all valid: most tracks, smaller files
        out["valid"] = [int(v) for v in track.valid]
    if track.synthetic.any():
        out["synthetic"] = [int(v) for v in track.synthetic]
    return out


def _width_to_json(width: np.ndarray) -> float | list[float]:
    return float(width[0]) if np.all(width == width[0]) else _floats(width)


def _scene_to_dict(scene: Scene) -> dict:
    bg = scene.background
    return {
        "format": FORMAT,
        "version": VERSION,
        "id": scene.id,
        "source": {
            "kind": scene.source.kind,
            "details": scene.source.details,
            "licence": scene.source.licence,
            "attribution": scene.source.attribution,
        },
        "dt": float(scene.dt),
        "frames": int(scene.frames),
        "map": {
            "lanes": [
                {
                    "id": lane.id,
                    "centerline": _points(lane.centerline),
                    "width": _width_to_json(lane.width),
                    "left": lane.left,
                    "right": lane.right,
                    "successors": list(lane.successors),
                    "speed_limit": lane.speed_limit,
                }
                for lane in scene.lanes
            ]
        },
        "background": {
            "shoulder_left": bg.shoulder_left,
            "shoulder_right": bg.shoulder_right,
            "ground_margin": bg.ground_margin,
            "lane_markings": bg.lane_markings,
            "barriers": [{"kind": b.kind, "height": b.height, "polyline": _points(b.polyline)} for b in bg.barriers],
            "meshes": [{"file": m.file, "pose": _floats(m.pose), "surface": m.surface} for m in bg.meshes],
        },
        "ego": {
            "dimensions": _floats(scene.ego.dimensions),
            "wheelbase": scene.ego.wheelbase,
            "sensors": [{"name": s.name, "model": s.model, "mount": _floats(s.mount)} for s in scene.ego.sensors],
            "track": _track_to_dict(scene.ego.track),
        },
        "actors": [
            {
                "id": a.id,
                "class": a.cls,
                "dimensions": _floats(a.dimensions),
                "asset": a.asset,
                "track": _track_to_dict(a.track),
            }
            for a in scene.actors
        ],
    }


# --------------------------------------------------------------------------------------------
# from JSON, with validation
# --------------------------------------------------------------------------------------------


def _load_track(t: Node, frames: int, *, full: bool) -> Track:
    t.object()
    t.check_keys(_TRACK_KEYS)
    start = t["start"].integer(lo=0)
    x = t["x"].numbers(min_length=1, lo=-MAX_COORD, hi=MAX_COORD)
    n = len(x)
    if start + n > frames:
        t["x"].fail(f"at most {frames - start} values (start {start} + length <= frames {frames})", f"{n} items")
    if full and (start != 0 or n != frames):
        t["x"].fail(f"{frames} values starting at frame 0 (the ego track covers every frame)",
                    f"start {start}, {n} items")
    y = t["y"].numbers(length=n, lo=-MAX_COORD, hi=MAX_COORD)
    yaw = t["yaw"].numbers(length=n)
    bad = np.flatnonzero((yaw < -math.pi - 1e-3) | (yaw > math.pi + 1e-3))
    if len(bad):
        t["yaw"].fail("an angle in [-pi, pi] rad", float(yaw[bad[0]]), at=f"[{bad[0]}]")
    speed = None
    if "speed" in t:
        speed = t["speed"].numbers(length=n, lo=0.0, hi=MAX_SPEED)
    elif full:
        t.child("speed").fail("a value (field is missing; the ego track needs speeds)")
    valid = t["valid"].flags(n) if "valid" in t else None
    synthetic = t["synthetic"].flags(n) if "synthetic" in t else None
    if full and valid is not None and not valid.all():
        t["valid"].fail("all 1 (the ego is valid in every frame)")
    if valid is not None and not valid.any():
        t["valid"].fail("at least one valid frame")
    return Track(x=x, y=y, yaw=yaw, speed=speed, start=start, valid=valid, synthetic=synthetic)


_TRACK_KEYS = ("start", "x", "y", "yaw", "speed", "valid", "synthetic")


def _load_dims(node: Node) -> np.ndarray:
    return node.numbers(length=3, lo=0.0, lo_open=True, hi=MAX_SIZE, expected=f"a positive size in m (at most {MAX_SIZE:g})")


def _load_class(node: Node) -> str:
    return node.string(pattern=CLASS_PATTERN, expected=f"a lower-case class name such as {class_examples(4)}")


_LANE_KEYS = ("id", "centerline", "width", "left", "right", "successors", "speed_limit")


def _load_lane(ld: Node) -> Lane:
    ld.check_keys(_LANE_KEYS)
    centerline = ld["centerline"].points(limit=MAX_COORD)
    wd = ld["width"]
    if isinstance(wd.value, list):
        width = wd.numbers(length=len(centerline), lo=0.0, hi=MAX_SIZE)
        if np.all(width == 0):
            wd.fail("widths > 0 somewhere along the lane")
    else:
        width = np.array(wd.number(lo=0.0, lo_open=True, hi=MAX_SIZE))
    left = ld.get("left")
    right = ld.get("right")
    succ = ld.get("successors", [])
    limit = ld.get("speed_limit")
    lane = Lane(
        ld["id"].integer(lo=0), centerline, width,
        None if left.value is None else left.integer(lo=0),
        None if right.value is None else right.integer(lo=0),
        [s.integer(lo=0) for s in succ.items("a list of lane ids")],
        None if limit.value is None else limit.number(lo=0.0, lo_open=True, hi=MAX_SPEED),
    )
    if not np.any(lane.centerline[1:] != lane.centerline[:-1]):  # one point repeated: no direction, no length
        ld["centerline"].fail("at least two distinct points (a centre line of positive length)",
                              f"{len(lane.centerline)} copies of {ld['centerline'].value[0]}")
    return lane


def _load_map(doc: Node) -> list[Lane]:
    doc["map"].object()
    doc["map"].check_keys(("lanes",))
    nodes = doc["map"]["lanes"].objects("a non-empty list of lanes", non_empty=True)
    lanes: list[Lane] = []
    seen: set[int] = set()
    for ld in nodes:
        lane = _load_lane(ld)
        ld["id"].unique(lane.id, seen, "lane id")
        lanes.append(lane)
    for ld, lane in zip(nodes, lanes):  # references must name existing lanes
        for name in ("left", "right"):
            ref = getattr(lane, name)
            if ref is not None and (ref not in seen or ref == lane.id):
                ld[name].fail("the id of another lane in $.map.lanes, or null", ref)
        for k, ref in enumerate(lane.successors):
            if ref not in seen:
                ld["successors"][k].fail("the id of a lane in $.map.lanes", ref)
    return lanes


_BACKGROUND_KEYS = ("shoulder_left", "shoulder_right", "ground_margin", "lane_markings", "barriers", "meshes")


def _load_barrier(b: Node) -> Barrier:
    b.check_keys(("kind", "height", "polyline"))
    return Barrier(kind=b["kind"].string(choices=BARRIER_KINDS), polyline=b["polyline"].points(limit=MAX_COORD),
                   height=b.get("height", 0.8).number(lo=0.0, lo_open=True, hi=MAX_SIZE))


def _load_static_mesh(m: Node) -> StaticMesh:
    m.check_keys(("file", "pose", "surface"))
    pose = m.get("pose", [0, 0, 0, 0]).numbers(length=4, lo=-MAX_COORD, hi=MAX_COORD)
    return StaticMesh(file=m["file"].rel_path(inside="the scene's folder"), pose=pose,
                      surface=m.get("surface", "concrete").string(choices=SURFACE_KINDS_FOR_MESHES))


def _load_background(bd: Node) -> Background:
    bd.object()
    bd.check_keys(_BACKGROUND_KEYS)
    barriers = [_load_barrier(b) for b in bd.get("barriers", []).objects("a list of barriers")]
    meshes = [_load_static_mesh(m) for m in bd.get("meshes", []).objects("a list of static meshes")]
    return Background(
        shoulder_left=bd["shoulder_left"].number(lo=0.0, hi=MAX_MARGIN),
        shoulder_right=bd["shoulder_right"].number(lo=0.0, hi=MAX_MARGIN),
        ground_margin=bd.get("ground_margin", 30.0).number(lo=0.0, hi=MAX_MARGIN),
        lane_markings=bd.get("lane_markings", True).boolean(), barriers=barriers, meshes=meshes,
    )


def _load_ego(ed: Node, frames: int) -> Ego:
    ed.check_keys(("dimensions", "wheelbase", "sensors", "track"))
    sensors = []
    names: set[str] = set()
    for s in ed.get("sensors", []).objects("a list of LiDARs"):
        s.check_keys(("name", "model", "mount"))
        name = s["name"].unique(s["name"].string(), names, "sensor name")
        sensors.append(Lidar(name=name, model=s["model"].string(),
                             mount=s["mount"].numbers(length=6, lo=-MAX_SIZE, hi=MAX_SIZE)))
    return Ego(
        dimensions=_load_dims(ed["dimensions"]),
        wheelbase=ed["wheelbase"].number(lo=0.0, lo_open=True, hi=MAX_SIZE),
        track=_load_track(ed["track"], frames, full=True),
        sensors=sensors,
    )


def _load_actors(nodes: Node, frames: int) -> list[Actor]:
    actors: list[Actor] = []
    ids: set[int] = set()
    for ad in nodes.objects("a list of actors"):
        ad.check_keys(("id", "class", "dimensions", "asset", "track"))
        actors.append(Actor(
            id=ad["id"].unique(ad["id"].integer(lo=0), ids, "actor id"),
            cls=_load_class(ad["class"]),
            dimensions=_load_dims(ad["dimensions"]),
            asset=_load_asset_id(ad.get("asset")),
            track=_load_track(ad["track"], frames, full=False),
        ))
    return actors


def _load_asset_id(node: Node) -> str | None:
    """A vehicle library asset id or null (checked against a library by ``scene.actors.check_assets``)."""
    return None if node.value is None else node.name()


_SCENE_KEYS = ("format", "version", "id", "source", "dt", "frames", "map", "background", "ego", "actors")


def _check_actor_count(nodes: Node, frames: int) -> None:
    """At most :data:`MAX_ACTORS` actors, and actors x frames within the memory budget, checked
    on the list's length before any actor is read (validation stays linear and short)."""
    n = len(nodes.list("a list of actors"))
    if n > MAX_ACTORS:
        nodes.fail(f"at most {MAX_ACTORS} actors", f"{n} actors")
    if n * frames * ACTOR_FRAME_BYTES > MEMORY_BUDGET:
        most = MEMORY_BUDGET // (frames * ACTOR_FRAME_BYTES)
        nodes.fail(f"at most {most} actors for {frames} frames (their poses over the scene's frames would take "
                   f"{gib(n * frames * ACTOR_FRAME_BYTES)}, more than the {gib(MEMORY_BUDGET)} memory budget)",
                   f"{n} actors")


def _scene_from_dict(raw: Any, path: str | Path | None) -> Scene:
    doc = Node(raw, "$", path)
    check_header(doc, FORMAT, SUPPORTED_VERSIONS)
    doc.check_keys(_SCENE_KEYS, required=_SCENE_KEYS)
    scene_id = doc["id"].name()  # becomes a folder name (attack run bundles)
    src = doc["source"]
    src.object()
    src.check_keys(("kind", "details", "licence", "attribution"))
    source = Source(
        kind=src["kind"].string(choices=SOURCE_KINDS),
        details=src.get("details", {}).object(),
        licence=src.get("licence").string(nullable=True),
        attribution=src.get("attribution").string(nullable=True),
    )
    dt = doc["dt"].number(lo=MIN_DT, hi=MAX_DT)
    frames = doc["frames"].integer(lo=1, hi=MAX_FRAMES)
    _check_actor_count(doc["actors"], frames)
    lanes = _load_map(doc)
    background = _load_background(doc["background"])
    ed = doc["ego"]
    ed.object()
    ego = _load_ego(ed, frames)
    actors = _load_actors(doc["actors"], frames)
    return Scene(scene_id, source, dt, frames, lanes, background, ego, actors)


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file (``.json`` or ``.json.gz``).

    Raises:
        FileFormatError: naming the file and the JSON path of the first bad field.
    """
    return _scene_from_dict(read_json(path, limit=MAX_SCENE_BYTES), path)


def save_scene(scene: Scene, path: str | Path, *, indent: int | None = None) -> None:
    """Validate and write ``scene`` atomically (gzip when ``path`` ends in ``.gz``; gzip mtime 0,
    so the same scene always gives the same bytes)."""
    doc = scene.to_dict()
    _scene_from_dict(doc, path)  # never write a file we could not read back
    text = dump_json(doc, indent=indent)
    if len(text.encode("utf-8")) > MAX_SCENE_BYTES:
        Node(doc, "$", path).fail(f"a scene of at most {MAX_SCENE_BYTES >> 20} MiB of JSON (cut a long recording "
                                   "into shorter scenes, e.g. import-commonroad --seconds)",
                                   f"{len(text.encode('utf-8')) / 2**20:.0f} MiB")
    atomic_write_text(path, text)


def scene_equal(a: Scene, b: Scene) -> bool:
    """True when two scenes serialise to the same document (exact numbers)."""
    return a.to_dict() == b.to_dict()
