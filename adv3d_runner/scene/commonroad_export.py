"""Write an episode as a CommonRoad scenario (commonroad-io), and read back what CommonRoad
cannot hold (``adv3d scenes import-commonroad --manifest``). Used by ``adv3d export``
(``attack/export.py``); the reverse of :mod:`.commonroad`, whose reader it is tested against.

* Lanes -> lanelets: left/right bounds at +-width/2 along the centre line's vertex normals (so the
  reader's centre, the bounds' mean, is the centre line, and their distance the width), same-
  direction neighbours, successors and predecessors, a ``MAX_SPEED`` traffic sign per speed limit
  (value in m/s, the reader's unit). Lanelet ids are the lane ids, or, where a lane id is also a
  vehicle id (CommonRoad ids are unique across a file), the lane id plus the smallest power of 10
  above every vehicle id (order kept).
* Vehicles -> dynamic obstacles: a rectangle of the vehicle's length and width, the initial state
  at its first frame and a trajectory of one state per frame (position, orientation, velocity,
  acceleration: the forward difference of the speeds; the ego's initial one as the stack was
  given it) at the episode's dt. CommonRoad trajectories have no gaps: an actor absent for some
  frames between two present ones is interpolated across them (reported in ``gaps_filled``).
* The ego -> a dynamic obstacle like the others (its driven, closed-loop trajectory) and the
  planning problem (its initial state; the goal: a 10 m x lane-width rectangle around where the
  ego was at the last frame, any time up to then).

What CommonRoad has no field for (vehicle heights and classes, the library asset of each actor's
mesh, the ego's wheelbase and LiDARs, the static background) travels in the export manifest's
``scene`` object (docs/export.md); :func:`apply_manifest` puts it back into an imported scene.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .schema import Lane, Scene

#: CommonRoad obstacle type of each vehicle class (anything else: ``unknown``); the reader
#: (:func:`.commonroad._obstacle_class`) turns car types back into hatchback / sedan / suv by
#: footprint, which the manifest corrects.
OBSTACLE_TYPES = {"sedan": "car", "hatchback": "car", "sports": "car", "suv": "car", "van": "car", "pickup": "car",
                  "taxi": "taxi", "police": "priorityVehicle", "ambulance": "priorityVehicle",
                  "fire_truck": "priorityVehicle", "truck": "truck", "garbage_truck": "truck", "bus": "bus",
                  "motorcycle": "motorcycle"}
GOAL_LENGTH = 10.0  # m, along the ego's last heading
DECIMALS = 4  # commonroad-io's decimal precision: 0.1 mm, 1e-4 rad, 1e-4 m/s


@dataclass(frozen=True)
class Vehicle:
    """One vehicle's episode: ``poses`` (T, 3) x, y, yaw with NaN rows where absent, ``speeds``
    (T,) m/s, ``dimensions`` L, W, H m, its adv3d class and its CommonRoad obstacle id;
    ``initial_acceleration`` (m/s^2) when known (the ego's, as the stack was given it), else the
    speeds' first forward difference."""

    obstacle_id: int
    cls: str
    dimensions: tuple[float, float, float]
    poses: np.ndarray
    speeds: np.ndarray
    initial_acceleration: float | None = None


@dataclass(frozen=True)
class CommonRoadIds:
    """Ids the written file uses: lanelet id per lane id, the planning problem's id, actors whose
    gaps were interpolated."""

    lanelets: dict[int, int]
    planning_problem: int
    gaps_filled: list[int]


def _bounds(lane: Lane) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, centre, right) vertices of a lane (:func:`~adv3d_runner.scene.lanes.lane_bounds`)."""
    from .lanes import lane_bounds

    c = np.asarray(lane.centerline, dtype=np.float64)
    left, right = lane_bounds(c, lane.width)
    return left, c, right


def lanelet_ids(lanes: list[Lane], vehicle_ids: list[int]) -> dict[int, int]:
    """Lane id -> lanelet id (see the module docstring)."""
    taken = set(int(v) for v in vehicle_ids)
    if not taken & {lane.id for lane in lanes}:
        return {lane.id: lane.id for lane in lanes}
    offset = 10 ** len(str(max(taken) + 1))
    return {lane.id: lane.id + offset for lane in lanes}


def _fill_gaps(poses: np.ndarray, speeds: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray, bool]:
    """(first, last + 1 frame present, poses, speeds over that span with gaps interpolated, had gaps)."""
    ok = np.isfinite(poses[:, 0])
    idx = np.flatnonzero(ok)
    a, b = int(idx[0]), int(idx[-1]) + 1
    p, v, okk = poses[a:b].copy(), np.asarray(speeds[a:b], dtype=np.float64).copy(), ok[a:b]
    if okk.all():
        return a, b, p, v, False
    f = np.arange(b - a)
    yaw = np.unwrap(p[okk, 2])
    for k, col in enumerate((p[okk, 0], p[okk, 1], yaw)):
        p[:, k] = np.interp(f, f[okk], col)
    p[:, 2] = (p[:, 2] + np.pi) % (2 * np.pi) - np.pi
    v = np.interp(f, f[okk], v[okk])
    return a, b, p, v, True


def _shapes():
    """(rectangle(length, width) for an obstacle, region(length, width, centre, orientation) for a
    goal) in the installed commonroad-io's classes (``Rectangle`` before 2026, the obstacle-shape
    and occupancy classes since)."""
    try:
        from commonroad.geometry.obstacle_shapes.rect_obstacle_shape import RectObstacleShape
        from commonroad.geometry.occupancy.rect_occupancy import RectOccupancy
    except ImportError:  # commonroad-io < 2026
        from commonroad.geometry.shape import Rectangle

        return (lambda length, width: Rectangle(length, width),
                lambda length, width, centre, yaw: Rectangle(length, width, centre, yaw))
    import shapely

    return (lambda length, width: RectObstacleShape(width=width, length=length),
            lambda length, width, centre, yaw: RectOccupancy(rect_center=shapely.Point(centre), width=width,
                                                             length=length, orientation=yaw))


def write_commonroad(path: str | Path, lanes: list[Lane], ego: Vehicle, actors: list[Vehicle], dt: float, *,
                     name: str, author: str, affiliation: str, source: str) -> CommonRoadIds:
    """Write the episode (``ego`` and ``actors`` over T frames of ``dt`` s) as a CommonRoad XML
    file at ``path`` (overwritten). ``name`` becomes the scenario id's map name
    (``ZAM_<name>-1_1_T-1``; letters and digits kept).

    Raises:
        ConfigError: an ego pose is missing, ids clash, or no lane.
    """
    from commonroad.common.common_lanelet import LaneletType
    from commonroad.common.common_scenario import ScenarioID
    from commonroad.common.file_writer import CommonRoadFileWriter, OverwriteExistingFile
    from commonroad.common.util import FileFormat, Interval
    from commonroad.planning.goal import GoalRegion
    from commonroad.planning.planning_problem import PlanningProblem, PlanningProblemSet
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.lanelet import Lanelet, LaneletNetwork
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
    from commonroad.scenario.scenario import Scenario, Tag
    from commonroad.scenario.state import CustomState, InitialState
    from commonroad.scenario.trajectory import Trajectory
    from commonroad.scenario.traffic_sign import TrafficSign, TrafficSignElement, TrafficSignIDZamunda

    rectangle, region = _shapes()
    if not lanes:
        raise ConfigError("a CommonRoad export needs at least one lane")
    T = len(ego.poses)
    if T < 1 or not np.isfinite(ego.poses).all():
        raise ConfigError("the ego's trajectory must cover every frame")
    vehicle_ids = [ego.obstacle_id] + [a.obstacle_id for a in actors]
    if len(set(vehicle_ids)) != len(vehicle_ids):
        raise ConfigError(f"vehicle ids clash: {sorted(vehicle_ids)}")
    ll_id = lanelet_ids(lanes, vehicle_ids)
    next_id = max([*vehicle_ids, *ll_id.values()]) + 1
    map_name = "".join(ch for ch in name if ch.isalnum()) or "adv3d"
    scenario = Scenario(dt=float(dt), scenario_id=ScenarioID(country_id="ZAM", map_name=map_name, map_id=1,
                                                            configuration_id=1, obstacle_behavior="T",
                                                            prediction_id=1))
    # lanelets, predecessors from successors
    preds: dict[int, list[int]] = {}
    for lane in lanes:
        for s in lane.successors:
            preds.setdefault(int(s), []).append(lane.id)
    limits = sorted({float(lane.speed_limit) for lane in lanes if lane.speed_limit is not None})
    sign_id = {v: next_id + i for i, v in enumerate(limits)}
    next_id += len(limits)
    network = LaneletNetwork()
    for lane in lanes:
        left, centre, right = _bounds(lane)
        signs = {sign_id[float(lane.speed_limit)]} if lane.speed_limit is not None else None
        network.add_lanelet(Lanelet(
            left, centre, right, ll_id[lane.id],
            predecessor=[ll_id[p] for p in preds.get(lane.id, [])], successor=[ll_id[s] for s in lane.successors],
            adjacent_left=None if lane.left is None else ll_id[lane.left],
            adjacent_left_same_direction=None if lane.left is None else True,
            adjacent_right=None if lane.right is None else ll_id[lane.right],
            adjacent_right_same_direction=None if lane.right is None else True,
            traffic_signs=signs, lanelet_type={LaneletType.UNKNOWN}))
    for v, sid in sign_id.items():
        first = {ll_id[lane.id] for lane in lanes if lane.speed_limit is not None and float(lane.speed_limit) == v}
        at = next(lane for lane in lanes if ll_id[lane.id] == min(first))
        network.add_traffic_sign(TrafficSign(sid, [TrafficSignElement(TrafficSignIDZamunda.MAX_SPEED, [f"{v:g}"])],
                                             first, np.asarray(at.centerline[0], dtype=np.float64)), set())
    scenario.add_objects(network)

    def obstacle(vehicle: Vehicle, gaps: list[int]):
        a, b, p, v, filled = _fill_gaps(np.asarray(vehicle.poses, dtype=np.float64), vehicle.speeds)
        if filled:
            gaps.append(vehicle.obstacle_id)
        acc = np.zeros(len(v))
        if len(v) > 1:
            acc[:-1] = np.diff(v) / dt
            acc[-1] = acc[-2]
        if vehicle.initial_acceleration is not None and a == 0:
            acc[0] = float(vehicle.initial_acceleration)
        init = InitialState(time_step=a, position=p[0, :2].copy(), orientation=float(p[0, 2]), velocity=float(v[0]),
                            acceleration=float(acc[0]), yaw_rate=0.0, slip_angle=0.0)
        shape = rectangle(float(vehicle.dimensions[0]), float(vehicle.dimensions[1]))
        prediction = None
        if b - a > 1:
            states = [CustomState(time_step=a + k, position=p[k, :2].copy(), orientation=float(p[k, 2]),
                                  velocity=float(v[k]), acceleration=float(acc[k])) for k in range(1, b - a)]
            prediction = TrajectoryPrediction(Trajectory(a + 1, states), shape)
        kind = ObstacleType(OBSTACLE_TYPES.get(vehicle.cls, "unknown"))
        return DynamicObstacle(int(vehicle.obstacle_id), kind, shape, init, prediction), init

    gaps: list[int] = []
    ego_obstacle, ego_init = obstacle(ego, gaps)
    scenario.add_objects(ego_obstacle)
    for actor in actors:
        if np.isfinite(np.asarray(actor.poses)[:, 0]).any():
            scenario.add_objects(obstacle(actor, gaps)[0])
    # planning problem: the ego's initial state; goal around its last pose
    last = np.asarray(ego.poses[-1], dtype=np.float64)
    width = max(float(np.mean(np.atleast_1d(lane.width))) for lane in lanes)
    goal = GoalRegion([CustomState(time_step=Interval(0, T - 1),
                                   position=region(GOAL_LENGTH, width, last[:2].copy(), float(last[2])))])
    pp_id = next_id
    problem = PlanningProblem(pp_id, ego_init, goal)
    writer = CommonRoadFileWriter(scenario, PlanningProblemSet([problem]), author=author, affiliation=affiliation,
                                  source=source, tags={Tag.CRITICAL}, decimal_precision=DECIMALS,
                                  file_format=FileFormat.XML)
    writer.write_to_file(str(path), OverwriteExistingFile.ALWAYS)
    return CommonRoadIds(lanelets=ll_id, planning_problem=pp_id, gaps_filled=gaps)


# ----------------------------------------------------------------------------- the manifest

MANIFEST_FORMAT = "adv3d-export"
MANIFEST_VERSION = 1
#: top-level fields of the export manifest (docs/export.md); the importer reads ``scene`` only
MANIFEST_KEYS = ("format", "version", "source", "stack", "failure", "files", "ids", "reproduce", "licence",
                 "notes", "scene")
_SCENE_HINT_KEYS = ("ego", "actors", "background")


@dataclass(frozen=True)
class ImportHints:
    """What the manifest's ``scene`` object restores: the ego's obstacle id, dimensions (L, W, H),
    wheelbase and LiDARs; per actor obstacle id its class, dimensions and library asset; the
    static background; and the export's ``source`` (run, scene, mode, query)."""

    ego_id: int
    ego_dimensions: np.ndarray
    ego_wheelbase: float
    ego_sensors: list
    actors: dict[int, tuple[str, np.ndarray, str | None]]
    background: object
    source: dict


def read_manifest(path: str | Path) -> ImportHints:
    """Read and check an export manifest's header and ``scene`` object.

    Raises:
        FileFormatError: naming the manifest and the JSON path of the first bad field.
    """
    from ..validate import Node, check_header
    from .schema import MAX_SIZE, Lidar, _load_asset_id, _load_background, _load_class, _load_dims

    path = Path(path)
    doc = Node.load(path)
    check_header(doc, MANIFEST_FORMAT, (MANIFEST_VERSION,))
    doc.check_keys(MANIFEST_KEYS, required=("scene",))
    hints = doc["scene"]
    hints.object()
    hints.check_keys(_SCENE_HINT_KEYS, required=_SCENE_HINT_KEYS)
    ego = hints["ego"]
    ego.object()
    ego.check_keys(("obstacle_id", "dimensions", "wheelbase", "sensors"), required=("obstacle_id", "dimensions"))
    sensors, names = [], set()
    for s in ego.get("sensors", []).objects("a list of LiDARs"):
        s.check_keys(("name", "model", "mount"))
        sensors.append(Lidar(name=s["name"].unique(s["name"].string(), names, "sensor name"), model=s["model"].string(),
                             mount=s["mount"].numbers(length=6, lo=-MAX_SIZE, hi=MAX_SIZE)))
    actors: dict[int, tuple[str, np.ndarray, str | None]] = {}
    seen: set[int] = set()
    for a in hints["actors"].objects("a list of actors"):
        a.check_keys(("obstacle_id", "class", "dimensions", "asset", "adversarial"),
                     required=("obstacle_id", "class", "dimensions"))
        oid = a["obstacle_id"].unique(a["obstacle_id"].integer(lo=0), seen, "obstacle id")
        a.get("adversarial", False).boolean()
        actors[oid] = (_load_class(a["class"]), _load_dims(a["dimensions"]), _load_asset_id(a.get("asset")))
    source = doc.get("source", {})
    source.object()
    return ImportHints(ego_id=ego["obstacle_id"].integer(lo=0), ego_dimensions=_load_dims(ego["dimensions"]),
                       ego_wheelbase=ego.get("wheelbase", 0.0).number(lo=0.0, hi=MAX_SIZE),
                       ego_sensors=sensors, actors=actors, background=_load_background(hints["background"]),
                       source=dict(source.value))


def apply_manifest(scene: Scene, hints: ImportHints, path: str | Path) -> Scene:
    """``scene`` (imported from the export's CommonRoad file with the manifest's ego) with what
    CommonRoad has no field for put back from ``hints``: the ego's dimensions, wheelbase and
    LiDARs, each listed actor's class, dimensions (the height) and asset, and the background.
    Actors of the scene the manifest does not list keep what the importer gave them.

    Raises:
        UsageError: the scene's ego is not the manifest's (imported with another ``--ego``).
    """
    from ..errors import UsageError

    if scene.source.details.get("ego_obstacle_id") != hints.ego_id:
        raise UsageError(f"--ego {scene.source.details.get('ego_obstacle_id')}: the manifest {Path(path).name} "
                         f"names obstacle {hints.ego_id} as the ego")
    doc = scene.to_dict()
    ego = doc["ego"]
    ego["dimensions"] = [float(v) for v in hints.ego_dimensions]
    if hints.ego_wheelbase > 0:
        ego["wheelbase"] = float(hints.ego_wheelbase)
    if hints.ego_sensors:
        ego["sensors"] = [{"name": s.name, "model": s.model, "mount": [float(v) for v in s.mount]}
                          for s in hints.ego_sensors]
    for actor in doc["actors"]:
        if actor["id"] in hints.actors:
            cls, dims, asset = hints.actors[actor["id"]]
            actor.update({"class": cls, "dimensions": [float(v) for v in dims], "asset": asset})
    bg = hints.background
    doc["background"] = {"shoulder_left": bg.shoulder_left, "shoulder_right": bg.shoulder_right,
                         "ground_margin": bg.ground_margin, "lane_markings": bg.lane_markings,
                         "barriers": [{"kind": b.kind, "height": b.height, "polyline": np.asarray(b.polyline).tolist()}
                                      for b in bg.barriers], "meshes": []}
    doc["source"]["details"] = {**doc["source"]["details"], "manifest": Path(path).name,
                                "export": hints.source}
    return Scene.from_dict(doc, path)
