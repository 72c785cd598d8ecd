"""Criticality of an episode in the terms safety engineers use: time to collision, time and
distance headway, required deceleration, ..., computed by CommonRoad's CriMe (Y. Lin and M. Althoff,
"CommonRoad-CriMe: A Toolbox for Criticality Measures of Autonomous Vehicles", IEEE IV 2023;
``commonroad-crime`` on PyPI) on the episode's driven trajectories (docs/attack.md,
"Criticality (CriMe)").

How:

1. The episode becomes a CommonRoad scenario (commonroad-io, :func:`write_episode_scenario`):
   each lane a lanelet (bounds at +-width/2), the ego and every actor present a dynamic obstacle
   (a rectangle of its length and width, the attacked actors with their found shape's
   dimensions) whose trajectory is the episode's poses, one state per frame at the episode's dt
   (speed: the ego's, the actors' from their poses' finite differences along the heading).
2. CriMe runs **out of process**, in its own virtual environment
   (:mod:`adv3d_runner.sim.crime_server`; ``bash examples/crime/install.sh`` builds it):
   installing ``commonroad-crime`` into adv3d's environment would replace numpy 1.26 by numpy 2
   (bpy pins numpy < 2) and commonroad-io 2026.1 by 2024.3. One server process per adv3d
   process, started on first use (its import takes several seconds) and kept.
3. Per frame k and actor i, CriMe's ``compute(vehicle_id, time_step)`` of TTC, THW, HW,
   ALongReq and BTN, on the trajectories going on after the episode (the ego on its last plan,
   the actors on the poses the episode keeps after its end), so that THW, which follows the
   ego's future positions, is defined up to the last frame; DCE once per actor, and TTC* and
   TTB at the first frame, on the episode alone (:data:`MEASURES`). :meth:`Criticality.summary`
   keeps per episode the most critical value of each, with the actor and the frame.

Cost (5 s episode, 20 actors, highway-benchmark-000007): about 1.6 s of the server's processor
time (7-9 s wall on a 2-core machine under load 10), plus 8-10 s to start the server once per
process; so it is computed for the best shapes and the originals only, never per query.

The scenario is moved rigidly (rotated so the ego's first heading is :data:`HEADING_OFFSET` rad
off the +x axis, the ego's first position at the origin): every measure is invariant under a
rigid motion, but CriMe 0.4.5 projects speeds on the lane with the cosine of the lane's
*absolute* orientation (right only for lanes along +x) and takes an orientation of exactly 0 as
"no lane" (ALongReq and BTN then read 0). Lanes that stop at the edge of the mapped area (no
successor, and no neighbour going on past their end) are extended straight by
:data:`EXTEND_ENDS` m, so the map's edge is not a wall for TTC* and TTB.

When the CriMe environment is missing, :func:`criticality_block` says so
(:data:`NOT_AVAILABLE`) instead of failing the run.
"""
from __future__ import annotations

import json
import math
import os
import selectors
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import Adv3dError

#: how to get CriMe (the message of an evaluation made without it)
INSTALL_HINT = "bash examples/crime/install.sh"
NOT_AVAILABLE = f"not available ({INSTALL_HINT})"
#: interpreter of CriMe's environment: this variable, else ``examples/crime/.venv`` of the checkout
PYTHON_ENV = "ADV3D_CRIME_PYTHON"
DEFAULT_PYTHON = Path(__file__).resolve().parents[2] / "examples" / "crime" / ".venv" / "bin" / "python"
SERVER = Path(__file__).resolve().with_name("crime_server.py")
#: seconds the server may take to start (import CriMe) and to answer one episode
START_TIMEOUT_S = 300.0
REQUEST_TIMEOUT_S = 300.0
HEADING_OFFSET = 1e-3  # rad; see the module docstring
EXTEND_ENDS = 200.0  # m
#: CriMe measures, per (actor, frame) unless noted: key -> (CriMe class, unit, meaning)
MEASURES = {
    "ttc": ("TTC", "s", "time to collision: bumper gap / closing speed along the lane, constant accelerations "
                        "(Jansson 2005, (5.24)); only a vehicle ahead in the ego's lane"),
    "thw": ("THW", "s", "time headway: time until the ego's front reaches where the leader's rear is now "
                        "(along the driven trajectory, then the last plan; a multiple of dt, rounded up)"),
    "dhw": ("HW", "m", "distance headway: bumper-to-bumper gap to the vehicle ahead in the ego's lane"),
    "a_long_req": ("ALongReq", "m/s^2", "required longitudinal acceleration: the constant acceleration that brings "
                                        "the closing speed to 0 at the leader's bumper (<= 0; Jansson 2005)"),
    "btn": ("BTN", "1", "brake threat number: a_long_req / the ego's maximum deceleration (11.5 m/s^2 in "
                        "CriMe); >= 1: braking alone cannot avoid the collision"),
    "dce": ("DCE", "m", "distance of closest encounter: smallest footprint distance along the driven "
                        "trajectories (once per actor)"),
    "ttc_star": ("TTCStar", "s", "TTC*: time from the first frame until the driven ego trajectory first touches "
                                 "a vehicle or the road boundary (ego, first frame only)"),
    "ttb": ("TTB", "s", "time to brake: the latest time after the first frame at which full braking still "
                        "avoids the TTC* collision (ego, first frame only; -inf: it cannot)"),
}
PAIR = ("ttc", "thw", "dhw", "a_long_req", "btn")
#: summary: per measure, whether its most critical value is its minimum (else its maximum)
CRITICAL_LOW = {"ttc": True, "thw": True, "dhw": True, "a_long_req": True, "btn": False, "dce": True}
OBSTACLE_TYPES = {"truck": "truck", "bus": "bus", "motorcycle": "motorcycle", "garbage_truck": "truck",
                  "fire_truck": "truck", "taxi": "taxi"}


class CriticalityUnavailable(Adv3dError):
    """CriMe's environment is missing, does not start, or does not answer."""


# ------------------------------------------------------------------------------ the scenario

def _extend_open_ends(lanes: Sequence) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Lane id -> (centre line (P, 2), widths (P,)), lanes that stop at the map's edge extended
    straight by :data:`EXTEND_ENDS` m (5 m vertices). A lane with successors, or whose end has
    another lane's centre line going on past it within a lane width sideways (a lane drop or
    merge), is kept as it is."""
    ids = {int(lane.id) for lane in lanes}
    out = {}
    for lane in lanes:
        c = np.asarray(lane.centerline, dtype=np.float64)
        w = np.broadcast_to(np.asarray(lane.width, dtype=np.float64), (len(c),)).copy()
        out[int(lane.id)] = (c, w)
        if any(int(s) in ids for s in lane.successors) or len(c) < 2:
            continue
        end, t = c[-1], c[-1] - c[-2]
        t = t / max(np.linalg.norm(t), 1e-12)
        n = np.array([-t[1], t[0]])
        drop = False
        for other in lanes:
            if other is lane:
                continue
            d = np.asarray(other.centerline, dtype=np.float64) - end
            ahead, side = d @ t, np.abs(d @ n)
            if np.any((ahead > 1.0) & (ahead < 50.0) & (side < 1.5 * float(w[-1]))):
                drop = True
                break
        if drop:
            continue
        add = end + np.arange(1, int(EXTEND_ENDS / 5.0) + 1)[:, None] * 5.0 * t
        out[int(lane.id)] = (np.concatenate([c, add]), np.concatenate([w, np.full(len(add), w[-1])]))
    return out


def _bounds(c: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) bounds: the centre line offset by +-w/2 along its vertex normals."""
    from ..scene.lanes import lane_bounds

    return lane_bounds(c, w)


def _speeds_from_poses(poses: np.ndarray, dt: float) -> np.ndarray:
    """(F,) signed speed along the heading from (F, 3) poses (central differences inside a run
    of present frames, one-sided at its ends; 0 for a frame alone; NaN where absent)."""
    ok = np.isfinite(poses).all(axis=1)
    v = np.full(len(poses), np.nan)
    k = 0
    while k < len(poses):
        if not ok[k]:
            k += 1
            continue
        e = k
        while e + 1 < len(poses) and ok[e + 1]:
            e += 1
        p = poses[k:e + 1]
        if e > k:
            vel = np.gradient(p[:, :2], dt, axis=0)
            v[k:e + 1] = vel[:, 0] * np.cos(p[:, 2]) + vel[:, 1] * np.sin(p[:, 2])
        else:
            v[k] = 0.0
        k = e + 1
    return v


@dataclass(frozen=True)
class ScenarioIds:
    """The obstacle ids of a written scenario: the ego's, and per actor index (into the
    episode's ``actor_ids``) its obstacle id (absent actors have none)."""

    ego: int
    actors: dict[int, int]


def _ego_ahead(result, T: int) -> tuple[np.ndarray, np.ndarray]:
    """The ego's poses (T + P - 1, 3) and speeds: the episode's, then its last plan (index 0 is
    the last frame's pose), when the plan has the episode's dt; else the episode's alone."""
    poses = np.asarray(result.ego_poses, dtype=np.float64)[:T]
    speeds = np.asarray(result.ego_speeds, dtype=np.float64)[:T]
    plan = getattr(result.outputs[-1], "plan", None) if len(result.outputs) >= T else None
    if plan is None or abs(float(plan.dt) - float(result.dt)) > 1e-9 or len(plan.trajectory) < 2:
        return poses, speeds
    traj = np.asarray(plan.trajectory, dtype=np.float64)[1:]
    v = np.asarray(plan.speed, dtype=np.float64).reshape(-1)[1:len(traj) + 1]
    n = min(len(traj), len(v))
    return np.concatenate([poses, traj[:n]]), np.concatenate([speeds, v[:n]])


def write_episode_scenario(result, lanes: Sequence, path: str | Path, ahead: bool = False) -> ScenarioIds:
    """Write ``result`` (an :class:`~adv3d_runner.sim.episode.EpisodeResult`) on ``lanes`` (the
    scene's :class:`~adv3d_runner.scene.schema.Lane` s) as a CommonRoad XML scenario at
    ``path``, moved rigidly as the module docstring says (positions m, orientations rad,
    speeds m/s, time steps = frames 0..T-1 at ``result.dt`` s).

    ``ahead``: the trajectories go on after the episode (time steps T, T + 1, ...): the ego on
    its last plan (perfect tracking, as in the closed loop), the actors on the poses the episode
    keeps after its end (their log, or the traffic model), as far as the ego's plan reaches.

    Ids: the ego is obstacle 1, actor index i (present in some frame) is ``2 + i``, lanelets
    follow (CriMe reads an id of 0 as "none").
    """
    from commonroad.common.common_scenario import ScenarioID
    from commonroad.common.file_writer import CommonRoadFileWriter, OverwriteExistingFile
    from commonroad.common.util import FileFormat
    from commonroad.planning.planning_problem import PlanningProblemSet
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.lanelet import Lanelet, LaneletNetwork
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
    from commonroad.scenario.scenario import Scenario
    from commonroad.scenario.state import CustomState, InitialState
    from commonroad.scenario.trajectory import Trajectory
    try:  # commonroad-io >= 2025
        from commonroad.geometry.obstacle_shapes.rect_obstacle_shape import RectObstacleShape

        def rectangle(length: float, width: float):
            return RectObstacleShape(width=width, length=length)
    except ImportError:  # pragma: no cover - commonroad-io 2024
        from commonroad.geometry.shape import Rectangle

        def rectangle(length: float, width: float):
            return Rectangle(length, width)

    dt = float(result.dt)
    T = int(result.frames)
    if ahead:
        ego_poses, ego_speeds = _ego_ahead(result, T)
    else:
        ego_poses = np.asarray(result.ego_poses, dtype=np.float64)[:T]
        ego_speeds = np.asarray(result.ego_speeds, dtype=np.float64)[:T]
    F = len(ego_poses)  # frames written
    origin, yaw0 = ego_poses[0, :2].copy(), float(ego_poses[0, 2])
    phi = HEADING_OFFSET - yaw0
    rot = np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])

    def xy(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, dtype=np.float64) - origin) @ rot.T

    def wrap(a: float) -> float:
        return float((a + phi + math.pi) % (2 * math.pi) - math.pi)

    n_actors = len(result.actor_ids)
    actor_obstacle = {}
    next_id = 2 + n_actors
    scenario = Scenario(dt=dt, scenario_id=ScenarioID(country_id="ZAM", map_name="adv3d", map_id=1))
    lane_geo = _extend_open_ends(lanes)
    ll_id = {int(lane.id): next_id + i for i, lane in enumerate(lanes)}
    preds: dict[int, list[int]] = {}
    for lane in lanes:
        for s in lane.successors:
            if int(s) in ll_id:
                preds.setdefault(int(s), []).append(int(lane.id))
    network = LaneletNetwork()
    for lane in lanes:
        c, w = lane_geo[int(lane.id)]
        left, right = _bounds(c, w)
        left_id = None if lane.left is None or int(lane.left) not in ll_id else ll_id[int(lane.left)]
        right_id = None if lane.right is None or int(lane.right) not in ll_id else ll_id[int(lane.right)]
        network.add_lanelet(Lanelet(
            xy(left), xy(c), xy(right), ll_id[int(lane.id)],
            predecessor=[ll_id[p] for p in preds.get(int(lane.id), [])],
            successor=[ll_id[int(s)] for s in lane.successors if int(s) in ll_id],
            adjacent_left=left_id, adjacent_left_same_direction=None if left_id is None else True,
            adjacent_right=right_id, adjacent_right_same_direction=None if right_id is None else True))
    scenario.add_objects(network)

    def obstacle(oid: int, kind: str, dims: np.ndarray, poses: np.ndarray, speeds: np.ndarray):
        """poses (T, 3), speeds (T,), NaN where absent; the span from the first to the last
        present frame (gaps inside interpolated)."""
        ok = np.isfinite(poses).all(axis=1) & np.isfinite(speeds)
        idx = np.flatnonzero(ok)
        a, b = int(idx[0]), int(idx[-1]) + 1
        f = np.arange(a, b)
        p = np.empty((b - a, 3))
        yaw = np.unwrap(poses[idx, 2])
        for j, col in enumerate((poses[idx, 0], poses[idx, 1], yaw)):
            p[:, j] = np.interp(f, idx, col)
        v = np.interp(f, idx, speeds[idx])
        acc = np.gradient(v, dt) if len(v) > 1 else np.zeros(1)
        pos = xy(p[:, :2])
        shape = rectangle(float(dims[0]), float(dims[1]))
        init = InitialState(time_step=a, position=pos[0].copy(), orientation=wrap(p[0, 2]), velocity=float(v[0]),
                            acceleration=float(acc[0]), yaw_rate=0.0, slip_angle=0.0)
        prediction = None
        if b - a > 1:
            states = [CustomState(time_step=a + k, position=pos[k].copy(), orientation=wrap(p[k, 2]),
                                  velocity=float(v[k]), acceleration=float(acc[k])) for k in range(1, b - a)]
            prediction = TrajectoryPrediction(Trajectory(a + 1, states), shape)
        return DynamicObstacle(oid, ObstacleType(OBSTACLE_TYPES.get(kind, "car")), shape, init, prediction)

    scenario.add_objects(obstacle(1, "car", np.asarray(result.ego_dimensions), ego_poses, ego_speeds))
    all_poses = np.asarray(result.actor_poses, dtype=np.float64)
    for i in range(n_actors):
        poses = all_poses[:, i]
        if not np.isfinite(poses[:T]).all(axis=1).any():
            continue  # only actors present during the episode
        speeds = _speeds_from_poses(poses, dt)[:F]  # the frames after the episode help the last one
        poses = poses[:F]
        if len(poses) < F:
            poses = np.concatenate([poses, np.full((F - len(poses), 3), np.nan)])
            speeds = np.concatenate([speeds, np.full(F - len(speeds), np.nan)])
        oid = 2 + i
        scenario.add_objects(obstacle(oid, str(result.actor_classes[i]), np.asarray(result.actor_dimensions[i]),
                                      poses, speeds))
        actor_obstacle[i] = oid
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "lanelet has no type" per lanelet
        writer = CommonRoadFileWriter(scenario, PlanningProblemSet(), author="adv3d", affiliation="",
                                      source="adv3d episode", tags=set(), decimal_precision=6,
                                      file_format=FileFormat.XML)
        writer.write_to_file(str(path), OverwriteExistingFile.ALWAYS)
    return ScenarioIds(ego=1, actors=actor_obstacle)


# ------------------------------------------------------------------------------ the CriMe server

def switched_off() -> bool:
    """``$ADV3D_CRIME_PYTHON`` is ``none``: no criticality figures even where CriMe is installed."""
    return os.environ.get(PYTHON_ENV, "").strip().lower() == "none"


def crime_python() -> Path | None:
    """The interpreter of CriMe's environment (``$ADV3D_CRIME_PYTHON``, else
    :data:`DEFAULT_PYTHON`), or None when there is none (or it is switched off)."""
    env = os.environ.get(PYTHON_ENV)
    if switched_off():
        return None
    path = Path(env).expanduser() if env else DEFAULT_PYTHON
    return path if path.is_file() and os.access(path, os.X_OK) else None


class CrimeServer:
    """A running :mod:`~adv3d_runner.sim.crime_server` (JSON lines over a pipe).

    Raises:
        CriticalityUnavailable: no environment, or the server does not start.
    """

    def __init__(self, python: str | Path | None = None, start_timeout: float = START_TIMEOUT_S):
        python = Path(python) if python else crime_python()
        if python is None:
            raise CriticalityUnavailable(NOT_AVAILABLE)
        t0 = time.perf_counter()
        self.proc = subprocess.Popen([str(python), "-P", str(SERVER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True, bufsize=1)
        self._buf = ""
        self.owner = os.getpid()  # a forked child must not talk over its parent's pipe
        try:
            hello = self._read(start_timeout)
        except CriticalityUnavailable:
            self.close()
            raise
        if not hello.get("ready"):
            self.close()
            raise CriticalityUnavailable(f"CriMe does not start: {hello.get('error')} ({INSTALL_HINT})")
        self.versions: dict[str, str] = dict(hello.get("versions") or {})
        self.start_s = time.perf_counter() - t0

    def _read(self, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        try:
            while "\n" not in self._buf:
                left = deadline - time.monotonic()
                if left <= 0 or not sel.select(left):
                    self.close()
                    raise CriticalityUnavailable(f"CriMe server gave no answer in {timeout:g} s")
                chunk = os.read(self.proc.stdout.fileno(), 1 << 20).decode()
                if not chunk:
                    self.close()
                    raise CriticalityUnavailable("CriMe server ended")
                self._buf += chunk
        finally:
            sel.close()
        line, self._buf = self._buf.split("\n", 1)
        return json.loads(line)

    def request(self, payload: dict, timeout: float = REQUEST_TIMEOUT_S) -> dict:
        """Send one request, return its answer (``ok`` true), else raise
        :class:`CriticalityUnavailable` (an ``ok`` false answer raises with CriMe's error)."""
        if not self.alive():
            raise CriticalityUnavailable("CriMe server ended (or belongs to another process)")
        try:
            self.proc.stdin.write(json.dumps(payload) + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            self.close()
            raise CriticalityUnavailable(f"CriMe server: {exc}") from None
        answer = self._read(timeout)
        if not answer.get("ok"):
            raise CriticalityUnavailable(f"CriMe failed: {answer.get('error')}")
        return answer

    def alive(self) -> bool:
        return self.owner == os.getpid() and self.proc.poll() is None

    def close(self) -> None:
        if self.owner == os.getpid() and self.proc.poll() is None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


_SERVER: CrimeServer | None = None


def server() -> CrimeServer:
    """This process's CriMe server (started on first use, restarted if it ended)."""
    global _SERVER
    if _SERVER is None or not _SERVER.alive():
        _SERVER = CrimeServer()
        import atexit

        atexit.register(_SERVER.close)
    return _SERVER


def available() -> bool:
    """Whether CriMe's environment is there (does not start it)."""
    return crime_python() is not None


# ------------------------------------------------------------------------------ the measures

@dataclass
class Criticality:
    """CriMe's measures of one episode.

    Attributes:
        dt: s per frame. actor_ids: (N,) the episode's actor ids.
        pairs: key of :data:`PAIR` -> (T, N) float64, CriMe's value per frame and actor (units
            in :data:`MEASURES`); NaN: no value (actor absent), inf: "never" (not in the ego's
            lane, nobody ahead, not closing).
        dce: (N, 2) distance of closest encounter (m) and the frame it happens (NaN: never met).
        ttc_star, ttb: s, at the first frame (inf: no collision; TTB -inf: braking cannot avoid it).
        versions: CriMe's packages. seconds: wall time per measure (the server's), ``cpu`` (the
            server's processor time for the episode), ``total`` (wall, this side: writing the
            scenarios and the round trips), ``start`` (starting the server, 0 when it was running).
    """

    dt: float
    actor_ids: np.ndarray
    pairs: dict[str, np.ndarray]
    dce: np.ndarray
    ttc_star: float
    ttb: float
    versions: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def extreme(self, key: str) -> tuple[float, int | None, int | None]:
        """(most critical finite value, actor id, frame) of a per-actor measure: its minimum,
        or its maximum where :data:`CRITICAL_LOW` is False; (NaN, None, None) when it has no
        finite value."""
        low = CRITICAL_LOW[key]
        if key == "dce":
            vals = self.dce[:, 0]
            ok = np.isfinite(vals)
            if not ok.any():
                return math.nan, None, None
            i = int(np.flatnonzero(ok)[np.argmin(vals[ok]) if low else np.argmax(vals[ok])])
            f = self.dce[i, 1]
            return float(vals[i]), int(self.actor_ids[i]), (None if not np.isfinite(f) else int(f))
        a = self.pairs[key]
        ok = np.isfinite(a)
        if not ok.any():
            return math.nan, None, None
        masked = np.where(ok, a, np.inf if low else -np.inf)
        k, i = np.unravel_index(np.argmin(masked) if low else np.argmax(masked), a.shape)
        return float(a[k, i]), int(self.actor_ids[i]), int(k)

    def summary(self) -> dict[str, Any]:
        """JSON-safe per-episode figures: per measure ``{"value", "unit", "actor", "frame"}``
        (value null: never finite, e.g. no vehicle ever ahead in the ego's lane). TTC, THW,
        DHW, DCE: the minimum; ``required_deceleration``: the largest -ALongReq (m/s^2 >= 0);
        BTN: the maximum; TTC* and TTB at frame 0 (``ttb`` null with ``unavoidable`` true:
        braking at once does not avoid the collision)."""
        out: dict[str, Any] = {}
        for key, name in (("ttc", "ttc"), ("thw", "thw"), ("dhw", "dhw"), ("a_long_req", "required_deceleration"),
                          ("btn", "btn"), ("dce", "dce")):
            v, actor, frame = self.extreme(key)
            unit = MEASURES[key][1]
            if key == "a_long_req" and np.isfinite(v):
                v = -v if v < 0 else 0.0
            out[name] = {"value": _r(v), "unit": unit, "actor": actor, "frame": frame}
        out["ttc_star"] = {"value": _r(self.ttc_star), "unit": "s", "frame": 0}
        ttb = {"value": _r(self.ttb), "unit": "s", "frame": 0}
        if self.ttb == -math.inf:
            ttb["unavoidable"] = True
        out["ttb"] = ttb
        return out


def _r(x: float) -> float | None:
    return round(float(x), 4) if x is not None and np.isfinite(x) else None


def episode_criticality(result, lanes: Sequence, crime: CrimeServer | None = None,
                        plain: bool = False) -> Criticality:
    """CriMe's measures of one episode (see the module docstring).

    Args:
        result: an :class:`~adv3d_runner.sim.episode.EpisodeResult`.
        lanes: the scene's lanes.
        crime: a running server (default: this process's, :func:`server`).
        plain: CriMe without the server's shortcuts (same results, slower; for tests).

    Raises:
        CriticalityUnavailable: no CriMe environment, or it failed on this episode.
    """
    t0 = time.perf_counter()
    started = _SERVER is None or not _SERVER.alive()
    crime = crime or server()
    start_s = crime.start_s if started and crime is _SERVER else 0.0
    T, N = int(result.frames), len(result.actor_ids)
    with tempfile.TemporaryDirectory(prefix="adv3d-crime-") as tmp:
        # per frame, with the trajectories going on after the episode (THW looks ahead) ...
        ahead = Path(tmp) / "ahead.xml"
        ids = write_episode_scenario(result, lanes, ahead, ahead=True)
        vehicles = sorted(ids.actors.values())
        answer = crime.request({"xml": str(ahead), "ego_id": ids.ego, "plain": plain, "vehicles": vehicles,
                                "measures": [MEASURES[k][0] for k in PAIR], "time_steps": list(range(T))})
        # ... and on the episode alone: the closest encounter, TTC* and TTB at its first frame
        episode = Path(tmp) / "episode.xml"
        write_episode_scenario(result, lanes, episode)
        within = crime.request({"xml": str(episode), "ego_id": ids.ego, "plain": plain, "vehicles": vehicles,
                                "measures": ["DCE", "TTCStar", "TTB"], "time_steps": list(range(T)),
                                "ego_time_steps": [0]})
    steps = list(answer["time_steps"])
    pairs = {}
    for key in PAIR:
        a = np.full((T, N), np.nan)
        for i, oid in ids.actors.items():
            vals = answer["pairs"].get(MEASURES[key][0], {}).get(str(oid))
            if vals is not None:
                for k, v in zip(steps, vals):
                    if 0 <= k < T:
                        a[k, i] = float(v)
        pairs[key] = a
    dce = np.full((N, 2), np.nan)
    for i, oid in ids.actors.items():
        got = within["dce"].get(str(oid))
        if got is not None:
            dce[i] = [float(got[0]), np.nan if got[1] is None else float(got[1])]
    ego = within.get("ego", {})

    def first(name: str) -> float:
        vals = ego.get(name) or []
        return float(vals[0]) if vals else math.nan

    seconds = {k: float(v) for k, v in {**answer.get("seconds", {}), **within.get("seconds", {})}.items()}
    seconds["cpu"] = round(float(answer["seconds"].get("cpu", 0.0)) + float(within["seconds"].get("cpu", 0.0)), 4)
    seconds["start"] = round(start_s, 3)
    seconds["total"] = round(time.perf_counter() - t0 - start_s, 3)
    return Criticality(dt=float(result.dt), actor_ids=np.asarray(result.actor_ids, dtype=np.int64), pairs=pairs,
                       dce=dce, ttc_star=first("TTCStar"), ttb=first("TTB"), versions=dict(crime.versions),
                       seconds=seconds)


def criticality_block(result, lanes: Sequence) -> dict[str, Any]:
    """The ``criticality`` block of an evaluation (summary.json): ``{"tool", "frames", "dt",
    **summary}`` (:meth:`Criticality.summary`; no wall time: timing is not a result), or
    ``{"note": NOT_AVAILABLE}`` without CriMe's environment, or
    ``{"note": "failed: ..."}`` (``{"note": "off (...)"}`` when :func:`switched_off`). Never
    raises for a missing or failing CriMe."""
    if switched_off():
        return {"note": f"off ({PYTHON_ENV}=none)"}
    if not available():
        return {"note": NOT_AVAILABLE}
    try:
        c = episode_criticality(result, lanes)
    except CriticalityUnavailable as exc:
        msg = str(exc)
        return {"note": msg if msg == NOT_AVAILABLE else f"failed: {msg}"}
    tool = ", ".join(f"{k} {v}" for k, v in c.versions.items() if k in ("commonroad-crime", "commonroad-io"))
    return {"tool": f"CriMe ({tool})", "frames": int(result.frames), "dt": float(result.dt), **c.summary()}
