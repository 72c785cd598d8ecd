"""Reactive actors: the scene's vehicles driven by the IDM/MOBIL traffic model around the ego.

:class:`~adv3d_runner.dynamics.traffic.Traffic` works in road coordinates (arc length ``s`` along one
reference line, integer lane index 0 = rightmost). A scene has a lane *graph* instead (centre
lines with left/right neighbours and successors). :class:`RoadFrame` maps one onto the other:

* reference line: the ego's lane at the start, chained backwards through predecessors and
  forwards through first successors;
* each lane that heads the same way is projected onto it; its index is its lateral offset at
  its **end** divided by the lane width (an on-ramp's end is where it merges, so a ramp and the
  acceleration lane it feeds share an index), shifted so the rightmost index is 0;
* per index, the lateral offset ``d_k(s)`` of the lane centre as a function of ``s`` (from the
  lane vertices; ramps curve in), where the index exists (``lane_start/lane_end``) and where it
  has a neighbour, i.e. lane changes are possible (``lane_open``).

:class:`ReactiveTraffic` starts every actor valid at the first frame from its logged pose and
speed (desired speed = the larger of its speed now and its mean logged speed over the episode),
adds actors that enter the log later at their logged pose (delayed while they would overlap the
ego), and replays the log for actors that are more than 0.75 lane widths from every mapped lane.
The ego is a vehicle of the traffic whose state is overwritten from the episode every step and
that never starts a lane change itself, so actors follow it and respect it in their MOBIL gap
checks. A vehicle's pose keeps the lateral residual of its logged start pose (off the lane
centre) and lets it decay linearly over ``settle_s`` = 2 s, so the first frame is exactly the
log (nothing jumps onto the ego) and vehicles then settle to their lane centre.
"""
from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..geometry.angles import wrap_angle
from ..geometry.boxes import boxes_overlap
from ..scene import lanes as lanegeo
from ..dynamics.traffic import Traffic
from ..scene.lanemap import LaneMap

SETTLE_S = 2.0
MAX_OFFSET_LANES = 0.75


class RoadFrame:
    """Reference line + lane indices of a scene's lane graph (see module docstring).

    Attributes:
        ref: (P, 2) reference polyline. width: m (the ego lane's median width).
        stations: (S,) s samples (1 m). offsets: (K, S) lateral offset of index k at each
        station (NaN where the index does not exist). lane_start, lane_end, lane_open: (K,).
    """

    def __init__(self, lanes, ego_pose: np.ndarray):
        by_id = {int(lane.id): lane for lane in lanes}
        lane_id, _, _ = LaneMap(lanes).locate(ego_pose)
        if lane_id is None:
            raise ConfigError("--reactive: the ego is not on any lane of the scene")
        preds: dict[int, int] = {}
        for lane in lanes:
            for succ in lane.successors:
                preds.setdefault(int(succ), int(lane.id))
        chain = [lane_id]
        while chain[0] in preds and preds[chain[0]] not in chain:
            chain.insert(0, preds[chain[0]])
        while by_id[chain[-1]].successors and by_id[chain[-1]].successors[0] in by_id \
                and by_id[chain[-1]].successors[0] not in chain:
            chain.append(int(by_id[chain[-1]].successors[0]))
        ref = lanegeo.clean_polyline(np.concatenate([np.asarray(by_id[i].centerline, float) for i in chain]))
        self.ref = ref
        total = lanegeo.length(ref)
        self.width = float(np.median(np.atleast_1d(by_id[lane_id].width)))
        self.stations = np.arange(0.0, total + 1.0, 1.0)
        entries = []  # (index, s (P,), d (P,), has_neighbour)
        for lane in lanes:
            pts = lanegeo.clean_polyline(np.asarray(lane.centerline, float))
            if len(pts) < 2:
                continue
            s, d, h = lanegeo.project(ref, pts)
            own = lanegeo.heading_at(pts, np.clip(lanegeo.arc_length(pts), 0, lanegeo.length(pts) - 1e-6))
            if np.median(np.abs(wrap_angle(own - h))) > np.pi / 2:
                continue  # opposite direction
            if s.max() < 0 or s.min() > total:
                continue
            idx = int(np.round(d[-1] / self.width))
            entries.append((idx, s, d, lane.left is not None or lane.right is not None))
        if not entries:
            raise ConfigError("--reactive: no lane of the scene follows the ego's road")
        lo = min(e[0] for e in entries)
        K = max(e[0] for e in entries) - lo + 1
        self.offsets = np.full((K, len(self.stations)), np.nan)
        self.lane_start = np.full(K, np.inf)
        self.lane_end = np.full(K, -np.inf)
        self.lane_open = np.full(K, np.inf)
        for idx, s, d, has_nb in entries:
            k = idx - lo
            order = np.argsort(s)
            s, d = s[order], d[order]
            inside = (self.stations >= s[0]) & (self.stations <= s[-1])
            self.offsets[k, inside] = np.interp(self.stations[inside], s, d)
            self.lane_start[k] = min(self.lane_start[k], s[0])
            self.lane_end[k] = max(self.lane_end[k], s[-1])
            if has_nb:
                self.lane_open[k] = min(self.lane_open[k], s[0])
        # lanes reaching the ends of the reference line are through lanes
        self.lane_start[self.lane_start <= 1.0] = -np.inf
        self.lane_end[self.lane_end >= total - 1.0] = np.inf
        self.road_end = total

    @property
    def n_lanes(self) -> int:
        return len(self.offsets)

    def offset(self, k: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Lateral offset (m) of lane index ``k`` at ``s`` (NaN where it does not exist)."""
        k = np.asarray(k, int)
        j = np.clip(np.round(np.asarray(s, float)).astype(int), 0, len(self.stations) - 1)
        return self.offsets[np.clip(k, 0, self.n_lanes - 1), j]

    def slope(self, k: np.ndarray, s: np.ndarray) -> np.ndarray:
        """d offset / d s of lane index ``k`` at ``s`` (0 where undefined)."""
        k = np.clip(np.asarray(k, int), 0, self.n_lanes - 1)
        j = np.clip(np.round(np.asarray(s, float)).astype(int), 1, len(self.stations) - 2)
        g = 0.5 * (self.offsets[k, j + 1] - self.offsets[k, j - 1])
        return np.nan_to_num(g)

    def locate(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Road coordinates of points (N, 2): s, d, nearest lane index (-1 when farther than
        0.75 lane widths from every lane)."""
        s, d, _ = lanegeo.project(self.ref, np.asarray(xy, float).reshape(-1, 2))
        j = np.clip(np.round(s).astype(int), 0, len(self.stations) - 1)
        dist = np.abs(self.offsets[:, j] - d[None, :])  # (K, N)
        dist = np.where(np.isfinite(dist), dist, np.inf)
        k = np.argmin(dist, axis=0) if self.n_lanes else np.zeros(len(s), int)
        far = dist[k, np.arange(len(s))] > MAX_OFFSET_LANES * self.width
        return s, d, np.where(far, -1, k)

    def pose(self, s: np.ndarray, d: np.ndarray, d_rate: np.ndarray) -> np.ndarray:
        """Map poses (N, 3) at road coordinates; ``d_rate`` = dd/ds tilts the heading."""
        p = lanegeo.pose_at(self.ref, s, d)
        p[..., 2] = wrap_angle(p[..., 2] + np.arctan(d_rate))
        return p


def _smoothstep(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u), 6 * u * (1 - u)


class ReactiveTraffic:
    """IDM/MOBIL actors around the ego, started from the scene's log (see module docstring).

    Args:
        scene: the scene. log_poses: (N, F, 3) logged actor poses of the frames the episode
            may use (NaN where invalid), in ``scene.actors`` order; log_speeds: (N, F).
        lengths, widths: (N,) actor footprints (after shape substitution).
        ego_pose: (3,), ego_speed, ego_dims (L, W): the ego at the first frame.
        dt: s.
    """

    def __init__(self, scene, log_poses: np.ndarray, log_speeds: np.ndarray, lengths: np.ndarray,
                 widths: np.ndarray, ego_pose: np.ndarray, ego_speed: float, ego_dims, dt: float,
                 settle_s: float = SETTLE_S):
        self.road = RoadFrame(scene.lanes, ego_pose)
        r = self.road
        self.log = np.asarray(log_poses, float)
        self.log_speeds = np.asarray(log_speeds, float)
        self.lengths = np.asarray(lengths, float)
        self.widths = np.asarray(widths, float)
        self.ego_dims = (float(ego_dims[0]), float(ego_dims[1]))
        self.dt = float(dt)
        self.settle_s = float(settle_s)
        self.traffic = Traffic(r.lane_start, r.lane_end, road_end=r.road_end, lane_open=r.lane_open)
        n = len(self.log)
        self.slot = np.full(n, -1)            # actor -> traffic index
        self.replay = np.zeros(n, bool)       # unmapped actors replay their log
        self.residual = np.zeros(n)           # lateral offset from the lane centre at entry
        self.yaw_residual = np.zeros(n)       # logged yaw minus the model's yaw at entry
        self.age = np.zeros(n)                # s since entry
        self.frame = 0
        s, _, k = r.locate(np.asarray(ego_pose, float)[None, :2])
        self.ego_slot = self.traffic.add(s[0], max(int(k[0]), 0), ego_speed, self.ego_dims[0], v0=60.0)
        self._ego_pose = np.asarray(ego_pose, float)
        self._enter(0)

    def _enter(self, f: int) -> None:
        """Add actors valid in log frame ``f`` that are not in the traffic yet."""
        r = self.road
        for i in np.flatnonzero((self.slot < 0) & ~self.replay):
            if f >= self.log.shape[1] or not np.isfinite(self.log[i, f]).all():
                continue
            pose = self.log[i, f]
            box = np.array([[pose[0], pose[1], self.lengths[i], self.widths[i], pose[2]]])
            ego = np.array([[*self._ego_pose[:2], self.ego_dims[0] + 2.0, self.ego_dims[1] + 2.0, self._ego_pose[2]]])
            if boxes_overlap(box, ego)[0]:
                continue  # would appear on top of the ego: try again next frame
            s, d, k = r.locate(pose[None, :2])
            if k[0] < 0:
                self.replay[i] = True
                continue
            v = self.log_speeds[i, f] if np.isfinite(self.log_speeds[i, f]) else 0.0
            ahead = self.log_speeds[i, f:]
            v0 = max(float(v), float(np.nanmean(ahead)) if np.isfinite(ahead).any() else 0.0, 1.0)
            self.slot[i] = self.traffic.add(s[0], int(k[0]), v, self.lengths[i], v0=v0)
            self.residual[i] = d[0] - r.offset(k[:1], s[:1])[0]
            self.age[i] = 0.0
            self.yaw_residual[i] = 0.0
            model_yaw = self.poses()[i, 2]
            self.yaw_residual[i] = wrap_angle(pose[2] - model_yaw)

    def poses(self) -> np.ndarray:
        """(N, 3) current actor poses (NaN for absent actors)."""
        r, t = self.road, self.traffic
        out = np.full((len(self.log), 3), np.nan)
        live = np.flatnonzero(self.slot >= 0)
        if len(live):
            j = self.slot[live]
            ok = t.active[j]
            live, j = live[ok], j[ok]
            g, dg = _smoothstep(t.lc_progress[j])
            d_new, d_old = r.offset(t.lane[j], t.s[j]), r.offset(t.lane_prev[j], t.s[j])
            d_old = np.where(np.isfinite(d_old), d_old, d_new)
            fade = np.clip(1.0 - self.age[live] / self.settle_s, 0.0, 1.0)
            d = d_old + g * (d_new - d_old) + fade * self.residual[live]
            v = np.maximum(t.v[j], 0.5)
            rate = (r.slope(t.lane[j], t.s[j]) * g + r.slope(t.lane_prev[j], t.s[j]) * (1 - g)
                    + dg * (d_new - d_old) / (t.mobil.lc_duration * v)
                    - np.where(fade > 0, self.residual[live] / (self.settle_s * v), 0.0))
            good = np.isfinite(d)
            out[live[good]] = r.pose(t.s[j][good], d[good], np.nan_to_num(rate[good]))
            yaw = out[live[good], 2] + fade[good] * self.yaw_residual[live[good]]
            out[live[good], 2] = wrap_angle(yaw)
        rep = np.flatnonzero(self.replay)
        if len(rep) and self.frame < self.log.shape[1]:
            out[rep] = self.log[rep, self.frame]
        return out

    def speeds(self) -> np.ndarray:
        """(N,) current speeds (NaN for absent or replaying actors)."""
        out = np.full(len(self.log), np.nan)
        live = np.flatnonzero(self.slot >= 0)
        out[live] = np.where(self.traffic.active[self.slot[live]], self.traffic.v[self.slot[live]], np.nan)
        return out

    def step(self, ego_pose: np.ndarray, ego_speed: float) -> None:
        """Advance one ``dt`` with the ego at ``ego_pose`` / ``ego_speed`` (its state *now*,
        which the actors react to), then add actors whose log starts in the next frame."""
        t, r = self.traffic, self.road
        s, _, k = r.locate(np.asarray(ego_pose, float)[None, :2])
        e = self.ego_slot
        t.s[e], t.v[e] = s[0], max(float(ego_speed), 0.0)
        if k[0] >= 0:
            t.lane[e] = t.lane_prev[e] = int(k[0])
        t.lc_progress[e], t.lc_timer[e], t.active[e] = 1.0, 0.0, True  # never changes lanes itself
        t.step(self.dt)
        self.age[self.slot >= 0] += self.dt
        self.frame += 1
        self._ego_pose = np.asarray(ego_pose, float)
        self._enter(self.frame)
