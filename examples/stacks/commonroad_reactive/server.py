"""Autonomy-C: oracle perception + constant-velocity prediction + CommonRoad's reactive planner,
served over adv3d's stack wire protocol (docs/stack_protocol.md) from this folder's own venv.

    .venv/bin/python server.py          # reads messages on stdin, answers on stdout

adv3d starts it through the plugin (plugin/, entry point ``C`` of ``adv3d.stacks``), or by hand:
``--autonomy "exec:examples/stacks/commonroad_reactive/.venv/bin/python examples/stacks/commonroad_reactive/server.py"``.

It imports nothing of ``adv3d_runner``: the protocol's one self-contained file,
``adv3d_runner/autonomy/wire.py`` (standard library, numpy, msgpack), is loaded by file path from
the adv3d checkout this folder lives in (or from ``$ADV3D_ROOT``).

Per frame (10 Hz):

* **perception (oracle)**: the stack asks for ground truth; ``frame.ground_truth`` holds every
  actor's box (x, y, length, width, yaw) in the ego frame, NaN rows for absent actors. A row is
  seen when it is finite, within ``max_range`` of the ego and hit by at least ``min_points``
  LiDAR returns (``ground_truth_points``): the rule of adv3d's own ``oracle`` stack, so a shape
  that reflects few rays is missed here too. Boxes go to the map frame with the ego's pose.
* **tracking**: a track is a ground-truth row (ids are row indices). Its velocity is the
  difference of its map-frame centre over the last ``velocity_window`` frames it was seen
  in a row; an actor seen for the first time gets the ego's speed along its own heading (a
  traffic-flow prior, replaced at the next frame, which is forced to replan).
* **prediction**: constant velocity over the planner's horizon (CommonRoad ``TrajectoryPrediction``
  of each obstacle, built by ``CRPlanner``).
* **planning**: :class:`adv3d_crp.CRPlanner` (CommonRoad reactive planner, its default cost
  function) with the :class:`Settings`. First attempt: the obstacles lengthened by a following
  margin (the package keeps no distance of its own), sampling level 1. If it finds no feasible
  collision-free trajectory: the true boxes, with velocity samples reaching further down,
  levels 1-2. If that fails too: the fallback, IDM car following along the lane (counted,
  flagged ``fallback`` in the log). Between replans (every ``replan_every`` frames) the last
  plan is followed, shifted in time, unless the shifted plan would come within
  ``reuse_margin`` of an obstacle's constant-velocity prediction or an actor was seen for the
  first time: then it replans at once.

Answers: the plan (trajectory (T, 3) x, y, yaw in the map frame starting at the ego's pose, speed
(T,), dt 0.1 s) and timings (tracker: ground truth to tracks; planner: the rest); ``provides`` is empty (plan only), so
adv3d reports detection and prediction metrics as not available.
``hello`` says name ``C``, the plugin's version and a fingerprint: sha256 (first 16 hex digits) of
``requirements.lock.txt`` and the settings.

Settings can be overridden for experiments with ``ADV3D_CRP_SETTINGS='{"time_gap": 1.0}'``
(the fingerprint changes with them). ``ADV3D_CRP_LOG=path.jsonl`` appends one line per frame
(why it replanned, which attempt succeeded, fallback, times) and one per episode (written at
the next reset or at a clean close; a process killed with its runner loses its last one).
``ADV3D_CRP_DUMP=DIR`` pickles the inputs of every frame that ended on the fallback (debugging).
"""
from __future__ import annotations

import os
import sys

# The message stream is this process's original stdout; anything else that prints (the
# planner's packages, a C extension writing to fd 1) must land on stderr instead.
_MSG_FD = os.dup(1)
os.dup2(2, 1)
sys.stdout = sys.stderr

import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from collections import deque  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from adv3d_crp import CRPlanner, EgoInput, LaneInput, ObstacleInput, PlannerOptions  # noqa: E402

NAME = "C"
DT = 0.1


def _load_wire():
    """adv3d's ``wire.py`` by file path (``$ADV3D_ROOT`` or the checkout three levels up)."""
    root = Path(os.environ.get("ADV3D_ROOT") or HERE.parents[2])
    path = root / "adv3d_runner" / "autonomy" / "wire.py"
    if not path.is_file():
        raise SystemExit(f"Autonomy-C server: {path} not found (set ADV3D_ROOT to the adv3d checkout)")
    spec = importlib.util.spec_from_file_location("adv3d_stack_wire", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


wire = _load_wire()


@dataclass(frozen=True)
class Settings:
    """Autonomy-C's settings (README: "Settings and why").

    horizon_steps: the planner's horizon in steps of 0.1 s (package default 60).
    replan_every: run the planner every k-th frame at most; in between the last plan is
        followed (the package's run_planner.py replans every 3rd step).
    margin_ahead, time_gap: an obstacle ahead of the ego is lengthened backwards (towards the
        ego) by ``margin_ahead + time_gap * ego speed`` m before the planner sees it: the
        planner keeps that distance behind it (the package itself keeps none).
    margin_behind: an obstacle behind the ego is lengthened forwards by this many m.
    margin_lat: m added to each side of every obstacle.
        (A margin that would already cover the ego is shrunk until it does not: the planner
        then keeps at least the current distance.)
    brake_decel_ratio: the second attempt's ``sampling.max_deceleration_ratio`` (package
        default 0.125: its lowest velocity sample is v - 0.125 * horizon * a_max, 4.3 m/s below
        the current speed at a 3 s horizon, too little to follow a braking leader).
    attempts: the planner runs tried in order until one finds a trajectory: ``margins`` (the
        margins above, package velocity sampling, ``margins_levels``), ``brake`` (margins,
        velocity sampling down by ``brake_decel_ratio``), ``bare`` (the true boxes, velocity
        sampling ``bare_decel_ratio``); then the fallback.
    margins_levels: sampling levels of the ``margins`` attempt (2: level 1 only, 180 samples).
    attempt_budget_s: no further attempt starts after this many seconds in a frame.
    sampling_levels: the package's ``num_sampling_levels`` (default 4, i.e. levels 1-3 are
        tried; level 3 alone has ~4300 samples and takes ~4 s here when nothing is feasible).
    fallback: when no attempt finds a trajectory: ``idm`` (IDM car following along the lane
        behind the true boxes: idm_* settings) or ``brake`` (emergency_decel along the lane).
    idm_accel, idm_decel, idm_gap, idm_headway: the IDM fallback's a_max, b, s0, T.
    reuse_margin, reuse_margin_lat: m, a reused plan that comes this close (along, across an
        obstacle) to a constant-velocity prediction is dropped and the planner runs at once.
    min_points, max_range: oracle perception (as adv3d's own oracle stack).
    velocity_window: frames over which a track's velocity is differenced.
    emergency_decel: m/s^2, the hardest braking of either fallback.
    """

    horizon_steps: int = 30
    replan_every: int = 3
    margin_ahead: float = 2.0
    time_gap: float = 0.5
    margin_behind: float = 1.0
    margin_lat: float = 0.25
    brake_decel_ratio: float = 0.5
    bare_decel_ratio: float = 0.5
    attempts: tuple = ("margins", "bare")
    margins_levels: int = 2
    attempt_budget_s: float = 6.0
    sampling_levels: int = 3
    fallback: str = "idm"
    idm_accel: float = 1.5
    idm_decel: float = 2.0
    idm_gap: float = 2.0
    idm_headway: float = 1.0
    reuse_margin: float = 1.0
    reuse_margin_lat: float = 0.3
    min_points: int = 5
    max_range: float = 100.0
    velocity_window: int = 3
    emergency_decel: float = 8.0


def _settings() -> Settings:
    text = os.environ.get("ADV3D_CRP_SETTINGS", "").strip()
    if not text:
        return Settings()
    over = json.loads(Path(text).read_text() if text.endswith(".json") else text)
    if "attempts" in over:
        over["attempts"] = tuple(over["attempts"])
    return dataclasses.replace(Settings(), **over)


def plugin_version() -> str:
    with open(HERE / "plugin" / "pyproject.toml", "rb") as f:
        return str(tomllib.load(f)["project"]["version"])


def fingerprint(settings: Settings) -> str:
    h = hashlib.sha256()
    h.update((HERE / "requirements.lock.txt").read_bytes())
    h.update(json.dumps(dataclasses.asdict(settings), sort_keys=True).encode())
    return h.hexdigest()[:16]


def _array(a: np.ndarray) -> dict:
    """A wire array; empty arrays are written here (wire.pack_array cannot cast a zero-size
    memoryview)."""
    a = np.ascontiguousarray(a)
    if a.size == 0:
        return {"dtype": a.dtype.str, "shape": list(a.shape), "data": b""}
    return wire.pack_array(a)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _corners(x, y, L, W, yaw, grow: float = 0.0, grow_lat: float | None = None) -> np.ndarray:
    """(..., 4, 2) corners of boxes (broadcast), front and back grown by ``grow``, the sides by
    ``grow_lat`` (default ``grow``)."""
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = np.asarray(L) / 2 + grow, np.asarray(W) / 2 + (grow if grow_lat is None else grow_lat)
    out = []
    for sl, sw in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        dx, dy = sl * hl, sw * hw
        out.append(np.stack([x + c * dx - s * dy, y + s * dx + c * dy], axis=-1))
    return np.stack(out, axis=-2)


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Separating-axis test of convex quads a (..., 4, 2) and b (..., 4, 2) -> (...) bool."""
    hit = np.ones(a.shape[:-2], bool)
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=-2) - poly
        axes = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)  # (..., 4, 2)
        for k in range(4):
            ax = axes[..., k, :][..., None, :]
            pa, pb = (a * ax).sum(-1), (b * ax).sum(-1)
            hit &= ~((pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1)))
    return hit


class _Budgeted(list):
    """The attempts, cut short once ``budget_s`` has passed since iteration began."""

    def __init__(self, items, budget_s: float):
        super().__init__(items)
        self.budget_s = budget_s

    def __iter__(self):
        t0 = time.perf_counter()
        for i, item in enumerate(list.__iter__(self)):
            if i and time.perf_counter() - t0 > self.budget_s:
                return
            yield item


class AutonomyC:
    """The stack behind the messages (see the module docstring)."""

    def __init__(self, settings: Settings):
        self.s = settings
        unknown = set(settings.attempts) - {"margins", "brake", "bare"}
        if unknown or not settings.attempts:
            raise ValueError(f"attempts: unknown {sorted(unknown)} (known: margins, brake, bare)")
        if settings.fallback not in ("idm", "brake"):
            raise ValueError(f"fallback: {settings.fallback!r} (known: idm, brake)")
        self.opt = PlannerOptions(horizon_steps=settings.horizon_steps, replan_every=1, safety_margin=0.0,
                                  emergency_decel=settings.emergency_decel, sampling_levels=settings.sampling_levels,
                                  fallback=settings.fallback, standstill_is_failure=settings.fallback == "idm",
                                  idm_accel=settings.idm_accel, idm_decel=settings.idm_decel,
                                  idm_gap=settings.idm_gap, idm_headway=settings.idm_headway)
        self.log = open(os.environ["ADV3D_CRP_LOG"], "a") if os.environ.get("ADV3D_CRP_LOG") else None

    def hello(self) -> dict:
        return {"type": "hello", "protocol": wire.PROTOCOL_VERSION,
                "info": {"name": NAME, "version": plugin_version(), "provides": [],
                         "fingerprint": fingerprint(self.s)},
                "sensors": {"lidar": True, "ground_truth": True}}

    # ---- per episode
    def reset(self, episode: dict) -> dict:
        self.episode_end()
        self.scene_id = str(episode.get("scene_id", ""))
        self.lanes = [LaneInput(id=int(ln["id"]), centerline=np.array(ln["centerline"], np.float64),
                                width=np.array(ln["width"], np.float64), left=ln.get("left"), right=ln.get("right"),
                                successors=[int(x) for x in ln.get("successors") or []],
                                speed_limit=ln.get("speed_limit")) for ln in episode["lanes"]]
        if not self.lanes:
            raise ValueError("Autonomy-C needs the episode's lanes (it got none)")
        self.planner = None  # built at the first frame: CRPlanner.reset needs the ego's state
        self.hist: dict[int, deque] = {}
        self.last_plan = None        # the PlanResult sent last (for the ego's acceleration/curvature)
        self.last_planned = None     # the last result of the planner itself
        self.last_planned_index = -1
        self.replan_next = False
        self.stats = {"frames": 0, "replans": 0, "forced": 0, "fallback": 0, "plan_s": [], "used": {}}
        return {"type": "ok"}

    def episode_end(self) -> None:
        if self.log is not None and getattr(self, "stats", None) and self.stats["frames"]:
            st = self.stats
            ps = np.array(st["plan_s"]) * 1e3
            self.log.write(json.dumps({"episode": self.scene_id, "frames": st["frames"], "replans": st["replans"],
                                       "forced_replans": st["forced"], "fallback": st["fallback"],
                                       "attempts_used": st["used"],
                                       "planner_ms_mean_per_frame": float(ps.sum() / st["frames"]),
                                       "planner_ms_per_replan": float(ps.mean()) if len(ps) else 0.0,
                                       "reasons": sorted(set(self.planner.emergency_reasons)) if self.planner else []})
                           + "\n")
            self.log.flush()

    # ---- per frame
    def _ego(self, e: dict) -> EgoInput:
        x, y, yaw = (float(v) for v in e["pose"])
        acc, kap = float(e.get("acceleration", 0.0)), float(e.get("curvature", 0.0))
        lp = self.last_plan
        if lp is not None and len(lp.trajectory) > 1 and math.hypot(lp.trajectory[1, 0] - x,
                                                                     lp.trajectory[1, 1] - y) < 0.05:
            # the ego is where our last plan put it (adv3d's perfect control): its acceleration
            # and curvature are the plan's there (the wire's plan carries poses and speeds only,
            # so adv3d reports 0 for both)
            acc, kap = float(lp.acceleration[1]), float(lp.curvature[1])
        return EgoInput(x=x, y=y, yaw=yaw, speed=float(e["speed"]), acceleration=acc, length=float(e["length"]),
                        width=float(e["width"]), wheelbase=float(e["wheelbase"]), curvature=kap)

    def _perceive(self, frame: dict, ego: EgoInput):
        """(ids, boxes (M, 5) map frame, velocities (M, 2), any first sighting)."""
        gt = frame.get("ground_truth")
        if gt is None:
            raise ValueError("no ground truth in the frame (Autonomy-C asks for it: oracle perception)")
        gt = np.asarray(gt, np.float64).reshape(-1, 5)
        npts = np.asarray(frame.get("ground_truth_points", np.full(len(gt), 10 ** 6)), np.int64).reshape(-1)
        ok = np.isfinite(gt).all(axis=1)
        ok &= np.hypot(np.nan_to_num(gt[:, 0], nan=1e9), np.nan_to_num(gt[:, 1], nan=1e9)) <= self.s.max_range
        ok &= npts >= self.s.min_points
        ids = np.flatnonzero(ok)
        b = gt[ids]
        c, s = math.cos(ego.yaw), math.sin(ego.yaw)
        boxes = np.column_stack([ego.x + c * b[:, 0] - s * b[:, 1], ego.y + s * b[:, 0] + c * b[:, 1],
                                 b[:, 2], b[:, 3], _wrap(b[:, 4] + ego.yaw)])
        t, index = float(frame["time"]), int(frame["index"])
        vel = np.zeros((len(ids), 2))
        first = False
        for k, i in enumerate(ids):
            h = self.hist.get(int(i))
            if h and h[-1][0] != index - 1:
                h.clear()  # not seen in the previous frame: start over
            if h is None:
                h = self.hist[int(i)] = deque(maxlen=self.s.velocity_window + 1)
            h.append((index, t, boxes[k, 0], boxes[k, 1]))
            if len(h) >= 2 and h[-1][1] > h[0][1]:
                vel[k] = (h[-1][2] - h[0][2], h[-1][3] - h[0][3])
                vel[k] /= h[-1][1] - h[0][1]
            else:
                vel[k] = ego.speed * np.array([math.cos(boxes[k, 4]), math.sin(boxes[k, 4])])
                first = True
        return ids.astype(np.int64), boxes, vel, first

    def _with_margins(self, boxes: np.ndarray, ego: EgoInput) -> np.ndarray:
        """The boxes the planner sees in the ``margins`` and ``brake`` attempts: each lengthened
        on the side that faces the ego (by margin_ahead + time_gap * v for an obstacle ahead,
        margin_behind for one behind) and widened by margin_lat a side; a margin that would
        cover the ego's footprint now is shrunk (bisection on its scale) until it does not."""
        out = boxes.copy()
        if not len(boxes):
            return out
        ego_box = _corners(ego.x, ego.y, ego.length, ego.width, ego.yaw, grow=0.1)
        for k, (x, y, L, W, yaw) in enumerate(boxes):
            h = np.array([math.cos(yaw), math.sin(yaw)])
            side = 1.0 if float(np.dot([ego.x - x, ego.y - y], h)) > 0 else -1.0  # +1: the ego is in front of it
            m_lon = self.s.margin_behind if side > 0 else self.s.margin_ahead + self.s.time_gap * max(ego.speed, 0.0)

            def grown(scale: float) -> np.ndarray:
                m = scale * m_lon
                c = np.array([x, y]) + side * 0.5 * m * h
                return np.array([c[0], c[1], L + m, W + 2 * scale * self.s.margin_lat, yaw])

            def hits(b: np.ndarray) -> bool:
                return bool(_overlap(ego_box, _corners(*b)))

            scale = 1.0
            if hits(grown(1.0)):
                lo, hi = 0.0, 1.0
                for _ in range(10):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (lo, mid) if hits(grown(mid)) else (mid, hi)
                scale = lo
            out[k] = grown(scale)
        return out

    def _reuse_unsafe(self, plan, boxes: np.ndarray, vel: np.ndarray, ego: EgoInput) -> bool:
        if not len(boxes):
            return False
        T = min(len(plan.trajectory), self.s.horizon_steps + 1)
        tr = plan.trajectory[:T]
        t = DT * np.arange(T)
        ex = _corners(tr[:, 0], tr[:, 1], ego.length, ego.width, tr[:, 2])                  # (T, 4, 2)
        ox = boxes[:, 0][:, None] + vel[:, 0][:, None] * t[None]                           # (M, T)
        oy = boxes[:, 1][:, None] + vel[:, 1][:, None] * t[None]
        ob = _corners(ox, oy, boxes[:, 2][:, None], boxes[:, 3][:, None], boxes[:, 4][:, None],
                      grow=self.s.reuse_margin, grow_lat=self.s.reuse_margin_lat)          # (M, T, 4, 2)
        return bool(_overlap(np.broadcast_to(ex, ob.shape), ob).any())

    def step(self, frame: dict) -> dict:
        t0 = time.perf_counter()
        index = int(frame["index"])
        ego = self._ego(frame["ego"])
        ids, boxes, vel, first = self._perceive(frame, ego)
        t2 = t1 = time.perf_counter()  # prediction (constant velocity) is built inside the planner

        if self.planner is None:
            self.planner = CRPlanner(self.opt)
            self.planner.reset(self.lanes, ego)
        reason = ""
        j = index - self.last_planned_index
        lp = self.last_planned
        if lp is None or (lp.emergency and self.s.fallback == "brake"):
            reason = "first" if lp is None else "after emergency"
        elif j >= self.s.replan_every:
            reason = "scheduled"
        elif self.replan_next:
            reason = "first sighting"
        elif j >= len(lp.trajectory) - 1:
            reason = "plan ran out"
        else:
            shifted = self.planner._shifted(lp, j)
            if self._reuse_unsafe(shifted, boxes, vel, ego):
                reason = "reused plan too close"
        if reason:
            bare = [ObstacleInput(box=boxes[k], velocity=vel[k]) for k in range(len(ids))]
            grown = self._with_margins(boxes, ego)
            margins = [ObstacleInput(box=grown[k], velocity=vel[k]) for k in range(len(ids))]
            kinds = {"margins": {"obstacles": margins, "label": "margins", "sampling_levels": self.s.margins_levels},
                     "brake": {"obstacles": margins, "max_deceleration_ratio": self.s.brake_decel_ratio,
                               "label": "brake"},
                     "bare": {"obstacles": bare, "max_deceleration_ratio": self.s.bare_decel_ratio,
                              "label": "bare"}}
            res = self.planner.plan(ego, attempts=_Budgeted([kinds[a] for a in self.s.attempts],
                                                            self.s.attempt_budget_s), fallback_obstacles=bare)
            self.last_planned, self.last_planned_index = res, index
            self.stats["replans"] += 1
            self.stats["forced"] += reason not in ("first", "scheduled")
            self.stats["fallback"] += bool(res.emergency)
            if res.emergency and os.environ.get("ADV3D_CRP_DUMP"):  # debugging: the failed inputs
                import pickle
                with open(Path(os.environ["ADV3D_CRP_DUMP"]) / f"{self.scene_id}-{index:03d}.pkl", "wb") as f:
                    pickle.dump({"lanes": self.lanes, "ego": ego, "boxes": boxes, "grown": grown, "vel": vel,
                                 "settings": dataclasses.asdict(self.s)}, f)
            used = res.stats.get("attempt", "fallback")
            self.stats["used"][used] = self.stats["used"].get(used, 0) + 1
        else:
            res = shifted
        self.replan_next = first
        t3 = time.perf_counter()
        self.last_plan = res
        self.stats["frames"] += 1
        if reason:
            self.stats["plan_s"].append(t3 - t2)

        trajectory = np.array(res.trajectory, np.float64)
        trajectory[0] = (ego.x, ego.y, ego.yaw)
        speed = np.maximum(np.array(res.speed, np.float64), 0.0)
        if self.log is not None:
            self.log.write(json.dumps({"scene": self.scene_id, "i": index, "replan": reason, "fallback": res.emergency,
                                       "why": res.reason[:200], "v": ego.speed, "a": ego.acceleration,
                                       "lane": res.stats.get("lane"), "n": len(ids),
                                       "stats": {k: v for k, v in res.stats.items() if k != "chain"},
                                       "plan_ms": (t3 - t2) * 1e3}) + "\n")
            self.log.flush()
        # plan only: tracks and predictions are not sent (README, "Known problems": adv3d's
        # remote.output_from_wire cannot read non-empty tracks), so they are reported as not available
        out = {"plan": {"trajectory": _array(trajectory), "speed": _array(speed), "dt": DT},
               "timings": {"tracker": t1 - t0, "planner": t3 - t2}}
        return {"type": "step", "output": out}


def main() -> int:
    stack = AutonomyC(_settings())

    def handle(msg: dict):
        kind = msg["type"]
        if kind == "hello":
            return stack.hello()
        if kind == "reset":
            return stack.reset(msg["episode"])
        if kind == "step":
            return stack.step(msg["frame"])
        return {"type": "error", "message": f"unknown message type {kind!r}"}

    out = os.fdopen(_MSG_FD, "wb", buffering=0)
    try:
        wire.serve_messages(handle, sys.stdin.buffer, out)
    finally:
        stack.episode_end()
    return 0


if __name__ == "__main__":
    sys.exit(main())
