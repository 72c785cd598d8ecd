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
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import FileFormatError
from ..fileio import check_header, read_json, write_json
from ..geometry.angles import wrap_angle

FORMAT = "adv3d-scene"
VERSION = 1
SUPPORTED_VERSIONS = (1,)

SOURCE_KINDS = ("generated", "commonroad", "blender")
# Usual vehicle classes (shared with the vehicle library); any lower-case identifier is
# accepted (``CLASS_RE``), e.g. the library's "ambulance"; "other" for anything unknown.
ACTOR_CLASSES = ("sedan", "hatchback", "sports", "suv", "van", "pickup", "truck", "bus", "motorcycle", "other")
CLASS_RE = re.compile(r"^[a-z][a-z0-9_]*$")
BARRIER_KINDS = ("concrete", "guardrail")
SURFACE_KINDS_FOR_MESHES = ("asphalt", "concrete", "metal", "ground", "vegetation")

# Decimals kept in files: 1 cm, 1 mrad, 1 cm/s; dimensions 1 mm. 1 cm is far below vehicle
# sizes and LiDAR range noise (~2 cm) and keeps busy 20 s scenes around 20-90 kB gzipped.
POS_DECIMALS = 2
ANGLE_DECIMALS = 3
SPEED_DECIMALS = 2
DIM_DECIMALS = 3

NO_ACTOR = -1  # label used by consumers for "background" (never a valid actor id)


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


class _V:
    """Validation helpers that raise FileFormatError(path, json_path, expected, got)."""

    def __init__(self, path: str | Path | None):
        self.path = path

    def fail(self, where: str, expected: str, got: object = None) -> None:
        raise FileFormatError(self.path, where, expected, got)

    def obj(self, parent: dict, key: str, where: str) -> dict:
        value = self.key(parent, key, where)
        if not isinstance(value, dict):
            self.fail(f"{where}.{key}", "an object", type(value).__name__)
        return value

    def key(self, parent: dict, key: str, where: str) -> Any:
        if key not in parent:
            self.fail(f"{where}.{key}", "a value (field is missing)")
        return parent[key]

    def number(self, value: Any, where: str, *, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(where, "a number", value)
        v = float(value)
        if not math.isfinite(v):
            self.fail(where, "a finite number", value)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(where, f"a number {'>' if lo_open else '>='} {lo}", value)
        if hi is not None and v > hi:
            self.fail(where, f"a number <= {hi}", value)
        return v

    def integer(self, value: Any, where: str, *, lo: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(where, "an integer", value)
        if lo is not None and value < lo:
            self.fail(where, f"an integer >= {lo}", value)
        return int(value)

    def string(self, value: Any, where: str, *, choices: tuple[str, ...] | None = None, nullable: bool = False) -> str | None:
        if value is None and nullable:
            return None
        if not isinstance(value, str) or not value:
            self.fail(where, "a non-empty string" + (" or null" if nullable else ""), value)
        if choices is not None and value not in choices:
            self.fail(where, f"one of {list(choices)}", value)
        return value

    def array(self, value: Any, where: str, *, length: int | None = None, min_length: int = 0,
              lo: float | None = None) -> np.ndarray:
        """A JSON list of finite numbers -> (n,) float64."""
        if not isinstance(value, list):
            self.fail(where, "a list of numbers", type(value).__name__)
        if length is not None and len(value) != length:
            self.fail(where, f"a list of {length} numbers", f"{len(value)} items")
        if len(value) < min_length:
            self.fail(where, f"a list of at least {min_length} numbers", f"{len(value)} items")
        for i, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, (int, float)):
                self.fail(f"{where}[{i}]", "a number", item)
            if not math.isfinite(item):
                self.fail(f"{where}[{i}]", "a finite number", item)
            if lo is not None and item < lo:
                self.fail(f"{where}[{i}]", f"a number >= {lo}", item)
        return np.asarray(value, dtype=np.float64).reshape(-1)

    def flags(self, value: Any, where: str, length: int) -> np.ndarray:
        if not isinstance(value, list) or len(value) != length:
            self.fail(where, f"a list of {length} flags (0 or 1)", value if not isinstance(value, list) else f"{len(value)} items")
        for i, item in enumerate(value):
            if item not in (0, 1) or isinstance(item, float):
                self.fail(f"{where}[{i}]", "0 or 1", item)
        return np.asarray(value, dtype=bool)

    def objects(self, value: Any, where: str, expected: str, *, non_empty: bool = False) -> Iterator[tuple[str, dict]]:
        """A JSON list of objects -> yields (json path of the item, item)."""
        if not isinstance(value, list) or (non_empty and not value):
            self.fail(where, expected, value if not isinstance(value, list) else "an empty list")
        for i, item in enumerate(value):
            w = f"{where}[{i}]"
            if not isinstance(item, dict):
                self.fail(w, "an object", type(item).__name__)
            yield w, item

    def unique(self, value: Any, where: str, seen: set, what: str) -> Any:
        """Records ``value`` in ``seen``; a repeat is an error naming ``what`` (e.g. "lane id")."""
        if value in seen:
            self.fail(where, f"a unique {what}", value)
        seen.add(value)
        return value

    def points(self, value: Any, where: str, *, min_points: int = 2) -> np.ndarray:
        """A JSON list of [x, y] -> (P, 2) float64."""
        if not isinstance(value, list) or len(value) < min_points:
            got = f"{len(value)} points" if isinstance(value, list) else type(value).__name__
            self.fail(where, f"a list of at least {min_points} [x, y] points", got)
        for i, item in enumerate(value):
            self.array(item, f"{where}[{i}]", length=2)
        return np.asarray(value, dtype=np.float64).reshape(-1, 2)


def _load_track(v: _V, doc: Any, where: str, frames: int, *, full: bool) -> Track:
    if not isinstance(doc, dict):
        v.fail(where, "an object", type(doc).__name__)
    start = v.integer(v.key(doc, "start", where), f"{where}.start", lo=0)
    x = v.array(v.key(doc, "x", where), f"{where}.x", min_length=1)
    n = len(x)
    if start + n > frames:
        v.fail(f"{where}.x", f"at most {frames - start} values (start {start} + length <= frames {frames})", f"{n} items")
    if full and (start != 0 or n != frames):
        v.fail(f"{where}.x", f"{frames} values starting at frame 0 (the ego track covers every frame)", f"start {start}, {n} items")
    y = v.array(v.key(doc, "y", where), f"{where}.y", length=n)
    yaw = v.array(v.key(doc, "yaw", where), f"{where}.yaw", length=n)
    bad = np.flatnonzero((yaw < -math.pi - 1e-3) | (yaw > math.pi + 1e-3))
    if len(bad):
        v.fail(f"{where}.yaw[{bad[0]}]", "an angle in [-pi, pi] rad", float(yaw[bad[0]]))
    speed = None
    if "speed" in doc:
        speed = v.array(doc["speed"], f"{where}.speed", length=n, lo=0.0)
    elif full:
        v.fail(f"{where}.speed", "a value (field is missing; the ego track needs speeds)")
    valid = v.flags(doc["valid"], f"{where}.valid", n) if "valid" in doc else None
    synthetic = v.flags(doc["synthetic"], f"{where}.synthetic", n) if "synthetic" in doc else None
    if full and valid is not None and not valid.all():
        v.fail(f"{where}.valid", "all 1 (the ego is valid in every frame)")
    if valid is not None and not valid.any():
        v.fail(f"{where}.valid", "at least one valid frame")
    unknown = set(doc) - {"start", "x", "y", "yaw", "speed", "valid", "synthetic"}
    if unknown:
        v.fail(f"{where}.{sorted(unknown)[0]}", "no such field (known: start, x, y, yaw, speed, valid, synthetic)")
    return Track(x=x, y=y, yaw=yaw, speed=speed, start=start, valid=valid, synthetic=synthetic)


def _load_dims(v: _V, value: Any, where: str) -> np.ndarray:
    dims = v.array(value, where, length=3)
    bad = np.flatnonzero(dims <= 0)
    if len(bad):
        v.fail(f"{where}[{bad[0]}]", "a positive size in m", float(dims[bad[0]]))
    return dims


def _load_class(v: _V, value: Any, where: str) -> str:
    name = v.string(value, where)
    if not CLASS_RE.match(name):
        v.fail(where, f"a lower-case class name such as {list(ACTOR_CLASSES[:4])}", name)
    return name


def _scene_from_dict(doc: Any, path: str | Path | None) -> Scene:
    v = _V(path)
    check_header(doc, path, FORMAT, SUPPORTED_VERSIONS)
    scene_id = v.string(v.key(doc, "id", "$"), "$.id")

    src = v.obj(doc, "source", "$")
    kind = v.string(v.key(src, "kind", "$.source"), "$.source.kind", choices=SOURCE_KINDS)
    details = src.get("details", {})
    if not isinstance(details, dict):
        v.fail("$.source.details", "an object", type(details).__name__)
    source = Source(
        kind=kind, details=details,
        licence=v.string(src.get("licence"), "$.source.licence", nullable=True),
        attribution=v.string(src.get("attribution"), "$.source.attribution", nullable=True),
    )

    dt = v.number(v.key(doc, "dt", "$"), "$.dt", lo=0.0, lo_open=True)
    frames = v.integer(v.key(doc, "frames", "$"), "$.frames", lo=1)

    # map
    mp = v.obj(doc, "map", "$")
    lanes: list[Lane] = []
    seen: set[int] = set()
    for w, ld in v.objects(v.key(mp, "lanes", "$.map"), "$.map.lanes", "a non-empty list of lanes", non_empty=True):
        lane_id = v.unique(v.integer(v.key(ld, "id", w), f"{w}.id", lo=0), f"{w}.id", seen, "lane id")
        centerline = v.points(v.key(ld, "centerline", w), f"{w}.centerline")
        wd = v.key(ld, "width", w)
        if isinstance(wd, list):
            width = v.array(wd, f"{w}.width", length=len(centerline), lo=0.0)
        else:
            width = np.array(v.number(wd, f"{w}.width", lo=0.0, lo_open=True))
        if np.ndim(width) and np.all(width == 0):
            v.fail(f"{w}.width", "widths > 0 somewhere along the lane")
        left = ld.get("left")
        right = ld.get("right")
        left = None if left is None else v.integer(left, f"{w}.left", lo=0)
        right = None if right is None else v.integer(right, f"{w}.right", lo=0)
        succ = ld.get("successors", [])
        if not isinstance(succ, list):
            v.fail(f"{w}.successors", "a list of lane ids", succ)
        successors = [v.integer(s, f"{w}.successors[{k}]", lo=0) for k, s in enumerate(succ)]
        limit = ld.get("speed_limit")
        limit = None if limit is None else v.number(limit, f"{w}.speed_limit", lo=0.0, lo_open=True)
        lanes.append(Lane(lane_id, centerline, width, left, right, successors, limit))
    for i, lane in enumerate(lanes):  # references must name existing lanes
        w = f"$.map.lanes[{i}]"
        for name in ("left", "right"):
            ref = getattr(lane, name)
            if ref is not None and (ref not in seen or ref == lane.id):
                v.fail(f"{w}.{name}", "the id of another lane in $.map.lanes, or null", ref)
        for k, ref in enumerate(lane.successors):
            if ref not in seen:
                v.fail(f"{w}.successors[{k}]", "the id of a lane in $.map.lanes", ref)

    # background
    bd = v.obj(doc, "background", "$")
    barriers = []
    for w, b in v.objects(bd.get("barriers", []), "$.background.barriers", "a list of barriers"):
        barriers.append(Barrier(
            kind=v.string(v.key(b, "kind", w), f"{w}.kind", choices=BARRIER_KINDS),
            polyline=v.points(v.key(b, "polyline", w), f"{w}.polyline"),
            height=v.number(b.get("height", 0.8), f"{w}.height", lo=0.0, lo_open=True),
        ))
    meshes = []
    for w, m in v.objects(bd.get("meshes", []), "$.background.meshes", "a list of static meshes"):
        meshes.append(StaticMesh(
            file=v.string(v.key(m, "file", w), f"{w}.file"),
            pose=v.array(m.get("pose", [0, 0, 0, 0]), f"{w}.pose", length=4),
            surface=v.string(m.get("surface", "concrete"), f"{w}.surface", choices=SURFACE_KINDS_FOR_MESHES),
        ))
    markings = bd.get("lane_markings", True)
    if not isinstance(markings, bool):
        v.fail("$.background.lane_markings", "true or false", markings)
    background = Background(
        shoulder_left=v.number(v.key(bd, "shoulder_left", "$.background"), "$.background.shoulder_left", lo=0.0),
        shoulder_right=v.number(v.key(bd, "shoulder_right", "$.background"), "$.background.shoulder_right", lo=0.0),
        ground_margin=v.number(bd.get("ground_margin", 30.0), "$.background.ground_margin", lo=0.0),
        lane_markings=markings, barriers=barriers, meshes=meshes,
    )

    # ego
    ed = v.obj(doc, "ego", "$")
    sensors = []
    names: set[str] = set()
    for w, s in v.objects(ed.get("sensors", []), "$.ego.sensors", "a list of LiDARs"):
        name = v.unique(v.string(v.key(s, "name", w), f"{w}.name"), f"{w}.name", names, "sensor name")
        sensors.append(Lidar(name=name, model=v.string(v.key(s, "model", w), f"{w}.model"),
                             mount=v.array(v.key(s, "mount", w), f"{w}.mount", length=6)))
    ego = Ego(
        dimensions=_load_dims(v, v.key(ed, "dimensions", "$.ego"), "$.ego.dimensions"),
        wheelbase=v.number(v.key(ed, "wheelbase", "$.ego"), "$.ego.wheelbase", lo=0.0, lo_open=True),
        track=_load_track(v, v.key(ed, "track", "$.ego"), "$.ego.track", frames, full=True),
        sensors=sensors,
    )

    # actors
    actors: list[Actor] = []
    ids: set[int] = set()
    for w, ad in v.objects(v.key(doc, "actors", "$"), "$.actors", "a list of actors"):
        actor_id = v.unique(v.integer(v.key(ad, "id", w), f"{w}.id", lo=0), f"{w}.id", ids, "actor id")
        actors.append(Actor(
            id=actor_id,
            cls=_load_class(v, v.key(ad, "class", w), f"{w}.class"),
            dimensions=_load_dims(v, v.key(ad, "dimensions", w), f"{w}.dimensions"),
            asset=v.string(ad.get("asset"), f"{w}.asset", nullable=True),
            track=_load_track(v, v.key(ad, "track", w), f"{w}.track", frames, full=False),
        ))
    return Scene(scene_id, source, dt, frames, lanes, background, ego, actors)


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file (``.json`` or ``.json.gz``).

    Raises:
        FileFormatError: naming the file and the JSON path of the first bad field.
    """
    return _scene_from_dict(read_json(path), path)


def save_scene(scene: Scene, path: str | Path, *, indent: int | None = None) -> None:
    """Validate and write ``scene`` atomically (gzip when ``path`` ends in ``.gz``; gzip mtime 0,
    so the same scene always gives the same bytes)."""
    doc = scene.to_dict()
    _scene_from_dict(doc, path)  # never write a file we could not read back
    write_json(path, doc, indent=indent)


def scene_equal(a: Scene, b: Scene) -> bool:
    """True when two scenes serialise to the same document (exact numbers)."""
    return a.to_dict() == b.to_dict()
