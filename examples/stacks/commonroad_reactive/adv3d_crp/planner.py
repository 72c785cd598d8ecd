"""adv3d lane map + ego + obstacles -> CommonRoad's reactive planner -> a planned trajectory.

Runs in this folder's own virtual environment (commonroad-reactive-planner pulls numpy 2, which
adv3d's own environment cannot take because of Blender's bpy); imports nothing of adv3d_runner.

Per episode (:meth:`CRPlanner.reset`): the lanes become a CommonRoad ``LaneletNetwork`` in a
``Scenario`` (dt 0.1 s); the road boundary collision object is computed once from it; a
``ReactivePlannerConfiguration`` is made (package defaults, the ego's dimensions, multiprocessing
off) and one ``ReactivePlanner`` is built.

Per step (:meth:`CRPlanner.plan`): the ego's lane is located; the reference path is that lane
chained through its successors (one ``CoordinateSystem`` per chain, kept for the episode); every
obstacle becomes a ``DynamicObstacle`` with a ``TrajectoryPrediction`` (one obstacle per
prediction mode above ``min_mode_probability``, or constant velocity when no prediction is
given), and a fresh ``pycrcc.CollisionChecker`` holds them and the road boundary; a
``PlanningProblem`` (goal: a box far ahead on the ego's lane, at the desired speed) is set; the
planner is reset to the ego's state (``ReactivePlanner.reset``), given the lateral sampling range
(up to the neighbouring lanes' centres) and the desired speed (``set_desired_velocity``), and
``plan()`` runs its sampling levels. If it finds no feasible, collision-free trajectory (or
raises), an emergency-braking trajectory along the current lane is returned instead and counted.

Frames and units: map frame, m, s, rad, m/s. The ego pose and obstacle boxes are footprint
centres (adv3d's convention); the reactive planner works on the rear axle, which is put at
``wheelbase / 2`` behind the centre, so the box it checks is the ego's footprint.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np

from commonroad.common.util import Interval
from commonroad.geometry.shape import Rectangle
from commonroad.planning.goal import GoalRegion
from commonroad.planning.planning_problem import PlanningProblem
from commonroad.prediction.prediction import TrajectoryPrediction
from commonroad.scenario.lanelet import Lanelet, LaneletNetwork
from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
from commonroad.scenario.scenario import Scenario
from commonroad.scenario.state import CustomState, InitialState
from commonroad.scenario.trajectory import Trajectory

import commonroad_dc.pycrcc as pycrcc
from commonroad_dc.boundary.boundary import create_road_boundary_obstacle
from commonroad_dc.collision.collision_detection.pycrcc_collision_dispatch import create_collision_object

from commonroad_rp.reactive_planner import ReactivePlanner
from commonroad_rp.state import ReactivePlannerState
from commonroad_rp.utility.config import ReactivePlannerConfiguration, VehicleConfiguration
from commonroad_rp.utility.utils_coordinate_system import create_coordinate_system

DT = 0.1
LANELET_ID_OFFSET = 1           # CommonRoad ids > 0; lane id k -> lanelet id k + 1
OBSTACLE_ID_BASE = 1_000_000    # obstacle ids, clear of lanelet ids


# ----------------------------------------------------------------------------------------------
# inputs / outputs


@dataclass
class LaneInput:
    """One lane (adv3d's ``scene.schema.Lane`` attributes): ``centerline`` (P, 2) m in driving
    direction, ``width`` scalar or (P,) m, ``left`` / ``right`` same-direction neighbour ids or
    None, ``successors`` ids, ``speed_limit`` m/s or None."""

    id: int
    centerline: np.ndarray
    width: Any = 3.7
    left: Optional[int] = None
    right: Optional[int] = None
    successors: list[int] = field(default_factory=list)
    speed_limit: Optional[float] = None

    @classmethod
    def coerce(cls, lane: Any) -> "LaneInput":
        """From a LaneInput, a dict with these keys, or any object with these attributes."""
        if isinstance(lane, LaneInput):
            return dataclasses.replace(lane, centerline=np.asarray(lane.centerline, np.float64).reshape(-1, 2),
                                       successors=list(lane.successors))
        get = (lambda k, d=None: lane.get(k, d)) if isinstance(lane, dict) else \
            (lambda k, d=None: getattr(lane, k, d))
        return cls(id=int(get("id")), centerline=np.asarray(get("centerline"), np.float64).reshape(-1, 2),
                   width=get("width", 3.7), left=get("left"), right=get("right"),
                   successors=[int(s) for s in (get("successors") or [])], speed_limit=get("speed_limit"))


@dataclass
class EgoInput:
    """The ego at the current instant (map frame, footprint centre). ``curvature`` (1/m) sets the
    initial steering angle; when None it is estimated from the previous call's yaw."""

    x: float
    y: float
    yaw: float
    speed: float
    acceleration: float = 0.0
    length: float = 4.8
    width: float = 2.0
    wheelbase: float = 2.9
    curvature: Optional[float] = None


@dataclass
class ObstacleInput:
    """One other road user: ``box`` (x, y, length, width, yaw) footprint, ``velocity`` (vx, vy)
    m/s, optional ``predictions`` (K, T, 2) positions at t + dt .. t + T dt and
    ``probabilities`` (K,)."""

    box: Sequence[float]
    velocity: Sequence[float] = (0.0, 0.0)
    predictions: Optional[np.ndarray] = None
    probabilities: Optional[np.ndarray] = None


@dataclass
class PlanResult:
    """``trajectory`` (T+1, 3) x, y, yaw (footprint centre) at t, t + dt, ...; index 0 is the
    current pose as the planner saw it. ``speed``, ``acceleration``, ``curvature`` (T+1,).
    ``emergency``: the planner found nothing and this is the braking fallback (``reason``).
    ``time_s``: wall time of the whole step (conversion + planning)."""

    trajectory: np.ndarray
    speed: np.ndarray
    acceleration: np.ndarray
    curvature: np.ndarray
    emergency: bool
    reason: str
    time_s: float
    stats: dict = field(default_factory=dict)


@dataclass
class PlannerOptions:
    """Settings of this adapter; the reactive planner's own cost weights stay the package's.

    horizon_steps: planning horizon in steps of dt (package default 60 = 6 s).
    desired_speed: m/s; None = the ego lane's speed limit, else the ego's speed at reset.
    lateral_range: None = up to the neighbouring lanes' centres (so lane changes can be sampled);
        a number = +- that many metres (the package default is +-3 m).
    min_mode_probability: prediction modes below this are not added as obstacles.
    multiproc: the package's multiprocessing kinematic check (default True there; off here:
        a fork per step costs more than it saves on 2 cores).
    emergency_decel: m/s^2 of the braking fallback.
    extend_ends: a lane without successors that ends at the edge of the mapped area (no
        neighbouring lane goes on past its end: not a lane drop) is extended straight by this
        many metres, in the lanelet network too; otherwise the road boundary closes the map's
        end and the planner brakes for it from a horizon's distance away.
    safety_margin: the package's ``planning.safety_margin_dynamic_obstacles`` (default 0): obstacles
        are grown by a circle of this radius (Minkowski sum, as the package does) before checking.
    replan_every: run the planner every k-th step only (the package's run_planner.py uses 3);
        in between, the last plan shifted by the steps elapsed is returned (stats["reused"]).
    logging_level: of the package's "RP_LOGGER".
    """

    horizon_steps: int = 60
    desired_speed: Optional[float] = None
    lateral_range: Optional[float] = None
    min_mode_probability: float = 0.05
    multiproc: bool = False
    emergency_decel: float = 8.0
    logging_level: str = "ERROR"
    safety_margin: float = 0.0     # the package's planning.safety_margin_dynamic_obstacles (m)
    replan_every: int = 1          # 1 = replan every step; k = the package's replanning_frequency
    #                                (between replans the last plan is followed, shifted in time)
    extend_ends: float = 300.0     # m added straight to lanes that stop at the map's edge (0 = off)
    ahead_margin: float = 80.0     # m of reference path beyond the horizon's reach
    extrapolate: float = 40.0      # m of straight extension past a chain's ends (projection domain)
    max_deceleration_ratio: Optional[float] = None  # the package's sampling.max_deceleration_ratio
    #                                (None = its default 0.125); per attempt in plan(attempts=...)
    sampling_levels: Optional[int] = None  # the package's sampling.num_sampling_levels (None = 4:
    #                                levels 1..3 are tried; the last one alone has ~4300 samples)
    fallback: str = "brake"        # when the planner finds nothing: "brake" (emergency_decel along
    #                                the lane) or "idm" (IDM car following along the lane)
    standstill_is_failure: bool = False  # from standstill, a standstill chosen because no sample
    #                                was feasible counts as a failure (-> fallback)
    idm_accel: float = 1.5         # m/s^2, IDM maximum acceleration
    idm_decel: float = 2.0         # m/s^2, IDM comfortable deceleration (hard limit: emergency_decel)
    idm_gap: float = 2.0           # m, IDM standstill gap
    idm_headway: float = 1.0       # s, IDM time headway


# ----------------------------------------------------------------------------------------------
# polyline helpers (numpy only)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class _Polyline:
    """A cleaned polyline with arc length, projection and point-at-s (linear beyond the ends)."""

    def __init__(self, pts: np.ndarray, width: Optional[np.ndarray] = None):
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        keep = np.ones(len(pts), bool)
        keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6
        self.p = pts[keep]
        if len(self.p) < 2:
            raise ValueError("a lane centre line needs two distinct points")
        w = np.full(len(pts), 3.7) if width is None else np.broadcast_to(np.asarray(width, np.float64), (len(pts),))
        self.w = np.asarray(w)[keep]
        seg = np.diff(self.p, axis=0)
        self.seg_len = np.linalg.norm(seg, axis=1)
        self.t = seg / self.seg_len[:, None]
        self.s = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.s[-1])

    def project(self, q) -> tuple[float, float, int]:
        """(s, d left +, segment index) of the nearest point (ends extended)."""
        q = np.asarray(q, np.float64)
        rel = q[None, :] - self.p[:-1]
        u = np.einsum("ij,ij->i", rel, self.t)
        uc = np.clip(u, 0.0, self.seg_len)
        dist = np.linalg.norm(rel - uc[:, None] * self.t, axis=1)
        i = int(np.argmin(dist))
        u_i = u[i]
        if 0 < i < len(self.t) - 1:
            u_i = uc[i]
        elif i == 0:
            u_i = min(u_i, self.seg_len[0])
        else:
            u_i = max(u_i, 0.0)
        d = float(self.t[i, 0] * rel[i, 1] - self.t[i, 1] * rel[i, 0])
        return float(self.s[i] + u_i), d, i

    def at(self, s) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 2) and headings (n,) at arc lengths s (linear extrapolation past the ends)."""
        s = np.atleast_1d(np.asarray(s, np.float64))
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.t) - 1)
        u = s - self.s[i]
        pts = self.p[i] + u[:, None] * self.t[i]
        return pts, np.arctan2(self.t[i, 1], self.t[i, 0])

    def width_at(self, s: float) -> float:
        return float(np.interp(s, self.s, self.w))


def _offset(pts: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Offset a polyline to the left by ``off`` (per point), using averaged vertex normals."""
    tan = np.gradient(pts, axis=0)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    return pts + nrm * np.asarray(off)[:, None]


# ----------------------------------------------------------------------------------------------
# the planner


class CRPlanner:
    """CommonRoad reactive planner behind adv3d's inputs (see the module docstring).

    Usage: ``p = CRPlanner(); p.reset(lanes, ego); res = p.plan(ego, obstacles)`` every 0.1 s.
    ``p.step_times`` (s per call) and ``p.emergency_count`` accumulate over the episode.
    """

    def __init__(self, options: Optional[PlannerOptions] = None):
        self.opt = options or PlannerOptions()
        logging.getLogger("RP_LOGGER").setLevel(self.opt.logging_level)
        self.planner: Optional[ReactivePlanner] = None
        self.step_times: list[float] = []
        self.emergency_count = 0
        self.emergency_reasons: list[str] = []
        self.reset_time_s = 0.0

    # ---- per episode -------------------------------------------------------------------------

    def reset(self, lanes: Sequence[Any], ego: EgoInput) -> None:
        """Build the lanelet network, scenario, road boundary and planner for a new episode."""
        t0 = time.perf_counter()
        self.lanes = {ln.id: ln for ln in (LaneInput.coerce(x) for x in lanes)}
        if not self.lanes:
            raise ValueError("no lanes")
        self.extended = self._extend_border_ends() if self.opt.extend_ends > 0 else []
        self.lines = {i: _Polyline(ln.centerline, ln.width) for i, ln in self.lanes.items()}
        self.pred = {i: [] for i in self.lanes}
        for i, ln in self.lanes.items():
            for s in ln.successors:
                if s in self.pred:
                    self.pred[s].append(i)

        self.scenario = Scenario(dt=DT)
        self.scenario.add_objects(self._lanelet_network())
        _, self.road_boundary = create_road_boundary_obstacle(self.scenario)

        self.initial_speed = float(ego.speed)
        self.vehicle = self._vehicle_config(ego)
        self.config = self._make_config(ego)
        self.planner = ReactivePlanner(self.config)
        self._coords: dict[tuple[int, ...], tuple[Any, _Polyline]] = {}
        self._prev_yaw: Optional[float] = None
        self.step_times, self.emergency_count, self.emergency_reasons = [], 0, []
        self._step, self._last, self._last_step = -1, None, -1
        self.reset_time_s = time.perf_counter() - t0

    def _extend_border_ends(self) -> list[int]:
        """Extend lanes that stop at the map's edge (see PlannerOptions.extend_ends)."""
        raw = {i: _Polyline(ln.centerline, ln.width) for i, ln in self.lanes.items()}
        ext = []
        for i, ln in self.lanes.items():
            if any(s in self.lanes for s in ln.successors):
                continue
            end = raw[i].p[-1]
            w_end = raw[i].w[-1]
            drop = False
            for j, other in raw.items():
                if j == i:
                    continue
                s, d, _ = other.project(end)
                if abs(d) < (w_end + other.width_at(s)) / 2 + 0.5 and \
                        (s < other.length - 1.0 or any(x in self.lanes for x in self.lanes[j].successors)):
                    drop = True  # a neighbour goes on past this end: a lane drop / merge
                    break
            if drop:
                continue
            c = raw[i].p
            t = (c[-1] - c[-2]) / np.linalg.norm(c[-1] - c[-2])
            add = c[-1] + np.arange(1, int(self.opt.extend_ends / 5.0) + 1)[:, None] * 5.0 * t
            w = np.concatenate([raw[i].w, np.full(len(add), raw[i].w[-1])])
            ln.centerline = np.concatenate([c, add])
            ln.width = w
            ext.append(i)
        return ext

    def _lanelet_network(self) -> LaneletNetwork:
        net = LaneletNetwork()
        for i, ln in self.lanes.items():
            c = np.asarray(ln.centerline, np.float64).reshape(-1, 2)
            w = np.broadcast_to(np.asarray(ln.width, np.float64), (len(c),))
            lid = i + LANELET_ID_OFFSET
            ok = lambda j: j is not None and int(j) in self.lanes  # noqa: E731
            net.add_lanelet(Lanelet(
                left_vertices=_offset(c, w / 2), center_vertices=c, right_vertices=_offset(c, -w / 2),
                lanelet_id=lid,
                predecessor=[p + LANELET_ID_OFFSET for p in self.pred[i]],
                successor=[s + LANELET_ID_OFFSET for s in ln.successors if s in self.lanes],
                adjacent_left=int(ln.left) + LANELET_ID_OFFSET if ok(ln.left) else None,
                adjacent_left_same_direction=True if ok(ln.left) else None,
                adjacent_right=int(ln.right) + LANELET_ID_OFFSET if ok(ln.right) else None,
                adjacent_right_same_direction=True if ok(ln.right) else None))
        return net

    def _vehicle_config(self, ego: EgoInput) -> VehicleConfiguration:
        # package defaults (BMW 320i, id_type_vehicle 2) for the limits; the ego's dimensions,
        # with the rear axle wheelbase/2 behind the footprint centre.
        return VehicleConfiguration(length=float(ego.length), width=float(ego.width),
                                    wb_front_axle=float(ego.wheelbase) / 2, wb_rear_axle=float(ego.wheelbase) / 2)

    def _make_config(self, ego: EgoInput) -> ReactivePlannerConfiguration:
        cfg = ReactivePlannerConfiguration()
        cfg.vehicle = self.vehicle
        cfg.planning.dt = DT
        cfg.planning.time_steps_computation = int(self.opt.horizon_steps)
        cfg.planning.planning_horizon = DT * int(self.opt.horizon_steps)
        cfg.debug.multiproc = bool(self.opt.multiproc)
        cfg.planning.safety_margin_dynamic_obstacles = float(self.opt.safety_margin)
        if self.opt.max_deceleration_ratio is not None:
            cfg.sampling.max_deceleration_ratio = float(self.opt.max_deceleration_ratio)
        if self.opt.sampling_levels is not None:
            cfg.sampling.num_sampling_levels = int(self.opt.sampling_levels)
        cfg.debug.logging_level = self.opt.logging_level
        cfg.debug.show_plots = cfg.debug.save_plots = False
        lane_id = self._locate(ego)
        cfg.update(scenario=self.scenario, planning_problem=self._planning_problem(ego, lane_id))
        return cfg

    # ---- geometry -----------------------------------------------------------------------------

    def _locate(self, ego: EgoInput) -> int:
        """The lane whose strip holds the ego centre with the smallest |d| (heading within 90
        deg); else the nearest such lane."""
        best, best_key = None, None
        for i, pl in self.lines.items():
            s, d, seg = pl.project((ego.x, ego.y))
            head = math.atan2(pl.t[seg, 1], pl.t[seg, 0])
            if abs(_wrap(ego.yaw - head)) > np.pi / 2:
                continue
            past = max(0.0, -s, s - pl.length)
            inside = abs(d) <= pl.width_at(s) / 2 + 1e-6 and past == 0.0
            key = (0 if inside else 1, abs(d) + past)
            if best_key is None or key < best_key:
                best, best_key = i, key
        if best is None:
            raise ValueError("no lane with a compatible heading")
        return best

    def _chain(self, lane_id: int, s_on_lane: float, ahead: float) -> tuple[int, ...]:
        ids = []
        p = self.pred[lane_id]
        if p and s_on_lane < 20.0:
            ids.append(p[0])
        ids.append(lane_id)
        reach = self.lines[lane_id].length - s_on_lane
        seen = {lane_id}
        cur = lane_id
        while reach < ahead:
            succ = [s for s in self.lanes[cur].successors if s in self.lanes and s not in seen]
            if not succ:
                break
            cur = succ[0]
            seen.add(cur)
            ids.append(cur)
            reach += self.lines[cur].length
        return tuple(ids)

    def _reference(self, chain: tuple[int, ...]):
        """(CoordinateSystem, raw chained polyline) for a lane chain, kept for the episode."""
        if chain not in self._coords:
            pts = []
            for k, i in enumerate(chain):
                c = self.lines[i].p
                pts.append(c if k == 0 else c[1:] if np.linalg.norm(c[0] - pts[-1][-1]) < 1e-3 else c)
            pts = np.concatenate(pts)
            e = self.opt.extrapolate
            t0 = pts[1] - pts[0]
            t1 = pts[-1] - pts[-2]
            t0 /= np.linalg.norm(t0)
            t1 /= np.linalg.norm(t1)
            ext = np.concatenate([[pts[0] - e * t0], pts, [pts[-1] + e * t1]])
            # dense, evenly spaced input for the CLCS preprocessing (spline smoothing, resampling)
            raw = _Polyline(ext)
            dense, _ = raw.at(np.linspace(0.0, raw.length, max(3, int(raw.length / 1.0)) + 1))
            with np.errstate(divide="ignore"):  # clcs divides by a zero curvature on straight paths
                co = create_coordinate_system(dense)
            self._coords[chain] = (co, _Polyline(pts))
        return self._coords[chain]

    def _lateral_range(self, lane_id: int, s: float, ego: EgoInput) -> float:
        if self.opt.lateral_range is not None:
            return float(self.opt.lateral_range)
        ln, w = self.lanes[lane_id], self.lines[lane_id].width_at(s)
        offs = []
        for nb in (ln.left, ln.right):
            if nb is not None and int(nb) in self.lanes:
                nl = self.lines[int(nb)]
                sn, _, _ = nl.project(self.lines[lane_id].at(s)[0][0])
                offs.append((w + nl.width_at(sn)) / 2)
        return max(offs) if offs else max(0.5, (w - ego.width) / 2)

    def _desired_speed(self, lane_id: int) -> float:
        if self.opt.desired_speed is not None:
            return float(self.opt.desired_speed)
        lim = self.lanes[lane_id].speed_limit
        return float(lim) if lim is not None else self.initial_speed

    def _planning_problem(self, ego: EgoInput, lane_id: int) -> PlanningProblem:
        pl = self.lines[lane_id]
        s, _, _ = pl.project((ego.x, ego.y))
        goal_s = s + max(ego.speed, 10.0) * DT * self.opt.horizon_steps + 100.0
        gp, gh = pl.at(goal_s)
        v_des = self._desired_speed(lane_id)
        init = InitialState(time_step=0, position=np.array([ego.x, ego.y]), orientation=float(ego.yaw),
                            velocity=float(ego.speed), acceleration=float(ego.acceleration), yaw_rate=0.0,
                            slip_angle=0.0)
        goal = GoalRegion([CustomState(
            time_step=Interval(0, 100_000),
            position=Rectangle(20.0, 10.0, center=gp[0], orientation=float(gh[0])),
            velocity=Interval(max(0.0, v_des - 2.0), v_des + 2.0))])
        return PlanningProblem(1, init, goal)

    # ---- obstacles ----------------------------------------------------------------------------

    def _obstacles(self, obstacles: Sequence[ObstacleInput]) -> list[DynamicObstacle]:
        N = self.opt.horizon_steps
        out: list[DynamicObstacle] = []
        for k, ob in enumerate(obstacles):
            x, y, L, W, yaw = (float(v) for v in ob.box)
            vx, vy = (float(v) for v in ob.velocity)
            shape = Rectangle(max(L, 0.1), max(W, 0.1))
            init = InitialState(time_step=0, position=np.array([x, y]), orientation=yaw,
                                velocity=math.hypot(vx, vy), acceleration=0.0, yaw_rate=0.0, slip_angle=0.0)
            if ob.predictions is not None and len(ob.predictions):
                P = np.asarray(ob.predictions, np.float64)
                P = P.reshape((1,) + P.shape) if P.ndim == 2 else P
                prob = np.full(len(P), 1.0 / len(P)) if ob.probabilities is None \
                    else np.asarray(ob.probabilities, np.float64).reshape(-1)
                modes = [P[m] for m in range(len(P)) if prob[m] >= self.opt.min_mode_probability] or \
                        [P[int(np.argmax(prob))]]
            else:
                t = DT * np.arange(1, N + 1)[:, None]
                modes = [np.array([x, y]) + t * np.array([vx, vy])]
            for m, path in enumerate(modes):
                path = self._extend(np.array([x, y]), path, np.array([vx, vy]), N)
                yaws = self._headings(np.array([x, y]), path, yaw)
                states = [CustomState(time_step=i + 1, position=path[i], orientation=float(yaws[i]))
                          for i in range(N)]
                pred = TrajectoryPrediction(Trajectory(1, states), shape)
                out.append(DynamicObstacle(OBSTACLE_ID_BASE + 100 * k + m, ObstacleType.CAR, shape, init, pred))
        return out

    @staticmethod
    def _extend(p0: np.ndarray, path: np.ndarray, v: np.ndarray, N: int) -> np.ndarray:
        """A prediction cut or extended (constant velocity from its last step) to N steps."""
        path = np.asarray(path, np.float64).reshape(-1, 2)
        if len(path) >= N:
            return path[:N]
        last_v = (path[-1] - (path[-2] if len(path) > 1 else p0)) / DT if len(path) else v
        start = path[-1] if len(path) else p0
        extra = start + DT * np.arange(1, N - len(path) + 1)[:, None] * last_v
        return np.concatenate([path, extra])

    @staticmethod
    def _headings(p0: np.ndarray, path: np.ndarray, yaw0: float) -> np.ndarray:
        d = np.diff(np.concatenate([p0[None], path]), axis=0)
        out = np.empty(len(path))
        prev = yaw0
        for i, (dx, dy) in enumerate(d):
            if dx * dx + dy * dy > 0.05 ** 2:
                prev = math.atan2(dy, dx)
            out[i] = prev
        return out

    def _collision_checker(self, obstacles: Sequence[DynamicObstacle]) -> pycrcc.CollisionChecker:
        cc = pycrcc.CollisionChecker()
        cc.add_collision_object(self.road_boundary)
        params = None
        if self.opt.safety_margin > 0.0:  # as ReactivePlanner.set_collision_checker does
            params = {"minkowski_sum_circle": True, "minkowski_sum_circle_radius": float(self.opt.safety_margin),
                      "resolution": 4, "triangulation_method": "gpc"}
        for o in obstacles:
            cc.add_collision_object(create_collision_object(o, params=params))
        return cc

    # ---- per step -----------------------------------------------------------------------------

    def plan(self, ego: EgoInput, obstacles: Sequence[ObstacleInput] = (),
             attempts: Optional[Sequence[dict]] = None,
             fallback_obstacles: Optional[Sequence[ObstacleInput]] = None) -> PlanResult:
        """One replanning step (see the module docstring).

        ``attempts``: planner runs tried in order until one finds a trajectory, each a dict
        with ``obstacles`` (a sequence of :class:`ObstacleInput`), optional
        ``max_deceleration_ratio`` (the package's ``sampling.max_deceleration_ratio``: the
        lowest velocity sample is ``v - ratio * horizon * a_max``; None = the option's),
        optional ``sampling_levels`` (at most the option's: levels 1 .. n-1 are tried) and
        ``label``. None = one attempt with ``obstacles``. When every attempt fails (no feasible
        collision-free sample, or the package raises), the fallback (``PlannerOptions.fallback``)
        is returned, flagged ``emergency``; ``fallback_obstacles`` are the obstacles the IDM
        fallback follows (default: the last attempt's). ``stats["attempt"]`` is the label of the
        attempt that succeeded."""
        assert self.planner is not None, "call reset() first"
        t0 = time.perf_counter()
        self._step += 1
        k = max(1, int(self.opt.replan_every))
        if k > 1 and self._last is not None and not self._last.emergency and self._step % k != 0:
            res = self._shifted(self._last, self._step - self._last_step)
            self._prev_yaw = float(ego.yaw)
            res.time_s = time.perf_counter() - t0
            self.step_times.append(res.time_s)
            return res
        if attempts is None:
            attempts = [{"obstacles": obstacles, "label": "single"}]
        stats: dict = {"attempts": []}
        lane_id = self._locate(ego)
        pl = self.lines[lane_id]
        s_lane, _, _ = pl.project((ego.x, ego.y))
        ahead = max(ego.speed, self._desired_speed(lane_id)) * DT * self.opt.horizon_steps + self.opt.ahead_margin
        chain = self._chain(lane_id, s_lane, ahead)
        stats.update(lane=lane_id, chain=list(chain))
        res, reason = None, "no attempt"
        try:
            co, raw = self._reference(chain)
        except Exception as exc:  # noqa: BLE001 - the reference path's construction failed
            co, raw, reason = None, _Polyline(pl.p), f"planner raised {type(exc).__name__}: {exc}"
        if co is not None:
            kappa = ego.curvature
            if kappa is None:
                kappa = 0.0 if self._prev_yaw is None or ego.speed < 0.5 else \
                    float(_wrap(ego.yaw - self._prev_yaw)) / (ego.speed * DT)
            L = self.vehicle.wheelbase
            delta = float(np.clip(math.atan(L * kappa), self.vehicle.delta_min, self.vehicle.delta_max))
            rear = np.array([ego.x, ego.y]) - self.vehicle.wb_rear_axle * np.array([math.cos(ego.yaw),
                                                                                   math.sin(ego.yaw)])
            self.config.planning_problem = self._planning_problem(ego, lane_id)
            D = self._lateral_range(lane_id, s_lane, ego)
            v_des = self._desired_speed(lane_id)
            stats.update(v_des=v_des, d_range=D)
            default_ratio = self.config.sampling.max_deceleration_ratio
            for attempt in attempts:
                ta = time.perf_counter()
                label = str(attempt.get("label", len(stats["attempts"])))
                entry = {"label": label}
                try:
                    dyn = self._obstacles(attempt.get("obstacles", ()))
                    cc = self._collision_checker(dyn)
                    x0 = ReactivePlannerState(time_step=0, position=rear.copy(), orientation=float(ego.yaw),
                                              velocity=float(ego.speed), acceleration=float(ego.acceleration),
                                              steering_angle=delta, yaw_rate=float(ego.speed * math.tan(delta) / L))
                    rp = self.planner
                    # keep the low-velocity flag consistent for the curvilinear conversion in reset()
                    rp._low_vel_mode = ego.speed < self.config.planning.low_vel_mode_threshold
                    rp.reset(initial_state_cart=x0, collision_checker=cc, coordinate_system=co)
                    rp.set_d_sampling_parameters(-D, D)
                    ratio = attempt.get("max_deceleration_ratio")
                    self.config.sampling.max_deceleration_ratio = default_ratio if ratio is None else float(ratio)
                    try:
                        rp.set_desired_velocity(desired_velocity=v_des, current_speed=float(ego.speed))
                    finally:
                        self.config.sampling.max_deceleration_ratio = default_ratio
                    levels = attempt.get("sampling_levels")
                    rp.sampling_level = self.config.sampling.num_sampling_levels if levels is None else \
                        min(int(levels), self.config.sampling.num_sampling_levels)
                    t1 = time.perf_counter()
                    result = rp.plan()
                    entry.update(t_plan=time.perf_counter() - t1, samples=rp.total_count_samples,
                                 infeasible_kin=rp.infeasible_count_kinematics,
                                 infeasible_coll=rp.infeasible_count_collision, n_obstacles=len(dyn))
                    none_feasible = rp.infeasible_count_kinematics + rp.infeasible_count_collision \
                        >= rp.total_count_samples
                    if result is None:
                        reason = "no feasible collision-free sample"
                    elif self.opt.standstill_is_failure and ego.speed <= 0.05 and none_feasible:
                        reason = "standstill: no feasible sample to move off"
                    else:
                        res = self._from_states(result[0].state_list)
                except Exception as exc:  # noqa: BLE001 - projection out of domain, the package's own bugs, ...
                    reason = f"planner raised {type(exc).__name__}: {exc}"
                    entry["error"] = reason[:200]
                entry["t"] = time.perf_counter() - ta
                stats["attempts"].append(entry)
                if res is not None:
                    stats["attempt"] = label
                    break
        if res is None:
            if self.opt.fallback == "idm":
                follow = fallback_obstacles if fallback_obstacles is not None else \
                    (attempts[-1].get("obstacles", ()) if attempts else obstacles)
                res = self._idm(ego, raw, reason, follow, self._desired_speed(lane_id))
            else:
                res = self._emergency(ego, raw, reason)
        self._prev_yaw = float(ego.yaw)
        res.time_s = time.perf_counter() - t0
        res.stats = stats
        self.step_times.append(res.time_s)
        self._last, self._last_step = res, self._step
        return res

    def _shifted(self, last: PlanResult, j: int) -> PlanResult:
        """The last plan j steps on, its tail extended at its final speed and heading."""
        tr, v = last.trajectory[j:], last.speed[j:]
        a, kap = last.acceleration[j:], last.curvature[j:]
        n = j
        step = DT * v[-1] * np.arange(1, n + 1)
        ext = tr[-1, :2] + step[:, None] * np.array([math.cos(tr[-1, 2]), math.sin(tr[-1, 2])])
        tr = np.concatenate([tr, np.column_stack([ext, np.full(n, tr[-1, 2])])])
        return PlanResult(tr, np.concatenate([v, np.full(n, v[-1])]), np.concatenate([a, np.zeros(n)]),
                          np.concatenate([kap, np.zeros(n)]), False, "", 0.0, {"reused": j})

    def _from_states(self, states) -> PlanResult:
        N = self.opt.horizon_steps
        wb_r, L = self.vehicle.wb_rear_axle, self.vehicle.wheelbase
        th = np.array([float(s.orientation) for s in states])
        pos = np.array([np.asarray(s.position, np.float64) for s in states])
        ctr = pos + wb_r * np.stack([np.cos(th), np.sin(th)], axis=1)
        v = np.array([float(s.velocity) for s in states])
        a = np.array([float(getattr(s, "acceleration", 0.0) or 0.0) for s in states])
        kap = np.array([math.tan(float(getattr(s, "steering_angle", 0.0) or 0.0)) / L for s in states])
        traj = np.column_stack([ctr, _wrap(th)])
        if len(traj) < N + 1:  # the package's standstill trajectory has N states
            pad = N + 1 - len(traj)
            traj = np.concatenate([traj, np.repeat(traj[-1:], pad, 0)])
            v = np.concatenate([v, np.zeros(pad)])
            a, kap = np.concatenate([a, np.zeros(pad)]), np.concatenate([kap, np.repeat(kap[-1:], pad)])
        return PlanResult(traj[:N + 1], v[:N + 1], a[:N + 1], kap[:N + 1], False, "", 0.0)

    def _emergency(self, ego: EgoInput, line: _Polyline, reason: str) -> PlanResult:
        """Brake at ``emergency_decel`` along the lane, keeping the current lateral offset."""
        self.emergency_count += 1
        self.emergency_reasons.append(reason)
        N, dec = self.opt.horizon_steps, self.opt.emergency_decel
        t = DT * np.arange(N + 1)
        t_stop = ego.speed / dec
        tt = np.minimum(t, t_stop)
        ds = ego.speed * tt - 0.5 * dec * tt ** 2
        s0, d0, _ = line.project((ego.x, ego.y))
        pts, head = line.at(s0 + ds)
        nrm = np.stack([-np.sin(head), np.cos(head)], axis=1)
        xy = pts + d0 * nrm
        xy[0] = (ego.x, ego.y)
        yaw = head.copy()
        yaw[0] = ego.yaw
        v = np.maximum(ego.speed - dec * t, 0.0)
        a = np.where(t < t_stop, -dec, 0.0)
        return PlanResult(np.column_stack([xy, _wrap(yaw)]), v, a, np.zeros(N + 1), True, reason, 0.0)

    def _idm(self, ego: EgoInput, line: _Polyline, reason: str, obstacles: Sequence[ObstacleInput],
             v_des: float) -> PlanResult:
        """Fallback: IDM car following along the reference line (keeping the current lateral
        offset) behind the obstacles that overlap the ego's corridor ahead, each moving at
        constant velocity; braking capped at ``emergency_decel``."""
        self.emergency_count += 1
        self.emergency_reasons.append(reason)
        o = self.opt
        N = o.horizon_steps
        s0, d0, _ = line.project((ego.x, ego.y))
        lead_s, lead_v, lead_half = [], [], []
        for ob in obstacles:
            x, y, L, W, yaw = (float(v) for v in ob.box)
            so, do, seg = line.project((x, y))
            if so <= s0 or abs(do - d0) >= (W + ego.width) / 2 + 0.2:
                continue
            t = line.t[seg]
            lead_s.append(so)
            lead_v.append(float(np.dot(np.asarray(ob.velocity, np.float64), t)))
            lead_half.append(L / 2)
        lead_s, lead_v, lead_half = np.array(lead_s), np.array(lead_v), np.array(lead_half)
        v, s = float(ego.speed), s0
        vs, ss, acc = [v], [s], []
        v0 = max(float(v_des), 1.0)
        root = math.sqrt(o.idm_accel * o.idm_decel)
        for k in range(N):
            a = o.idm_accel * (1.0 - (v / v0) ** 4)
            if len(lead_s):
                ls = lead_s + lead_v * k * DT
                gap = ls - lead_half - s - ego.length / 2
                i = int(np.argmin(gap))
                dv = v - lead_v[i]
                s_star = o.idm_gap + max(0.0, v * o.idm_headway + v * dv / (2 * root))
                a = -o.emergency_decel if gap[i] <= 0.1 else a - o.idm_accel * (s_star / gap[i]) ** 2
            a = float(np.clip(a, -o.emergency_decel, o.idm_accel))
            if v + a * DT < 0.0:
                a = -v / DT
            s += v * DT + 0.5 * a * DT ** 2
            v += a * DT
            vs.append(v)
            ss.append(s)
            acc.append(a)
        pts, head = line.at(np.array(ss))
        nrm = np.stack([-np.sin(head), np.cos(head)], axis=1)
        xy = pts + d0 * nrm
        xy[0] = (ego.x, ego.y)
        yaw = head.copy()
        yaw[0] = ego.yaw
        a_arr = np.array(acc + [acc[-1] if acc else 0.0])
        return PlanResult(np.column_stack([xy, _wrap(yaw)]), np.array(vs), a_arr, np.zeros(N + 1), True,
                          "fallback (IDM): " + reason, 0.0)
