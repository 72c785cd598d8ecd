"""One lane map per scene: every lane structure the autonomy stack reads, built once.

:class:`LaneMap` is made from a scene's lanes (``LaneMap.from_scene(scene)``) when an episode
starts and handed to the stack through ``AutonomyStack.reset(SceneContext)``; the planner, the
learned predictor and the lane-following baseline all read the same object, and none of them
keeps lane geometry of its own. It holds:

* ``lanes`` (in scene order) and ``by_id``; ``lane_length(id)`` (m, raw centre line);
* ``geometry``: every lane's cleaned centre line prepared for projection
  (:class:`~.corridor.LaneGeometry`), built in the constructor; ``locate`` / ``locate_many``
  (which lane a pose is on) use it;
* ``corridor(...)``: a lane chained through its successors around a point and resampled
  (:func:`~.corridor.build_corridor`; the planner builds its current / left / right corridors
  around the ego every frame);
* derived structures that depend on the reader's resolution, each computed on first use and then
  kept by the map for its lifetime (the map is static within a scene, and every reader of one
  map shares them): ``lane_corridor(id, ahead)`` (a whole lane plus its successors as a
  one-corridor :class:`~.corridor.CorridorSet`, the lane-following baseline) and
  ``index(chain_step, chain_ahead)`` (:class:`LaneIndex`, padded segment and chain arrays for
  the learned predictor's batched queries); ``border_ends()`` (the lanes that stop at the edge
  of the mapped area rather than in a lane drop).

The map is read-only: the lane objects must not be edited while a map of them is in use (build
a new map instead). Lane input is the scene's :class:`~.schema.Lane` or anything with the same
attributes (see :mod:`.corridor`). Units: m, rad, m/s; Frenet ``s`` along the lane, ``d`` left +.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..geometry.angles import wrap_angle
from ..jit import kernel
from . import lanes as lanegeo
from .corridor import DEFAULT_SPEED_LIMIT, Corridor, CorridorSet, LaneGeometry, build_corridor, lane_geometry


class LaneMap:
    """The lanes of one scene with the geometry every reader needs (see the module docstring).

    Args:
        lanes: the scene's lanes (ids unique).
    """

    def __init__(self, lanes: Sequence[Any] = ()):
        self.lanes: tuple[Any, ...] = tuple(lanes)
        self.by_id: dict[int, Any] = {int(lane.id): lane for lane in self.lanes}
        self.ids = np.array([int(lane.id) for lane in self.lanes], np.int64)
        self.geometry: tuple[LaneGeometry, ...] = tuple(lane_geometry(lane) for lane in self.lanes)
        self._length = {int(lane.id): lanegeo.length(np.asarray(lane.centerline, dtype=np.float64))
                        for lane in self.lanes}
        self._lane_corridors: dict[tuple[int, float], CorridorSet] = {}
        self._indexes: dict[tuple[float, float, float], LaneIndex] = {}
        self._border: dict[tuple[float, float], frozenset[int]] = {}
        self._flat: tuple[np.ndarray, ...] | None = None  # every lane's geometry in flat arrays, on first use

    @classmethod
    def from_scene(cls, scene: Any) -> "LaneMap":
        """The map of a :class:`~.schema.Scene` (its ``lanes``)."""
        return cls(scene.lanes)

    def __len__(self) -> int:
        return len(self.lanes)

    def lane_length(self, lane_id: int) -> float:
        """Length (m) of a lane's centre line as given (``scene.lanes.length``)."""
        return self._length[int(lane_id)]

    def locate(self, pose: np.ndarray, max_heading_error: float = np.pi / 2) -> tuple[int | None, float, float]:
        """The lane the pose (3,) x, y, yaw is on: the lane whose strip contains the point with the
        smallest |d|, among lanes heading within ``max_heading_error`` of the pose; if no strip
        contains it, the nearest such lane by |d| (plus the distance past the lane's ends).
        Returns (lane id, or None if no lane has a compatible heading, s, d)."""
        ids, s, d = self.locate_many(np.asarray(pose, dtype=np.float64).reshape(1, 3), max_heading_error)
        if ids[0] < 0:
            return None, 0.0, 0.0
        return int(ids[0]), float(s[0]), float(d[0])

    def locate_many(self, poses: np.ndarray, max_heading_error: float = np.pi / 2,
                    max_gap: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`locate` for many poses (N, 3) at once.

        Lanes whose bounding box is more than ``max_gap`` m further from a pose than the nearest
        lane's box are not considered for it (they cannot be the lane it is on).
        Returns:
            lane ids (N,) int64 (-1: none), s (N,), d (N,).

        One compiled pass over the poses and lanes (:func:`_locate_kernel`): the planner
        locates the ego every frame, and the numpy version (:meth:`locate_many_numpy`, the
        tests' reference) paid ~10 array calls per lane of the map for one pose. Poses with a
        NaN or an infinity take the numpy version (its NaN rules are numpy's).
        """
        P = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 3))
        if len(P) == 0 or not len(self.lanes) or not np.isfinite(P).all():
            return self.locate_many_numpy(P, max_heading_error, max_gap)
        if self._flat is None:
            self._flat = _flatten(self.geometry)
        return _locate_kernel(P, float(max_heading_error), float(max_gap), self.ids, *self._flat)

    def locate_many_numpy(self, poses: np.ndarray, max_heading_error: float = np.pi / 2,
                          max_gap: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`locate_many` in numpy, one projection call per lane (the definition the
        compiled version is tested against)."""
        P = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        n = len(P)
        best_key = np.full((n, 2), np.inf)
        out_id = np.full(n, -1, np.int64)
        out_s = np.zeros(n)
        out_d = np.zeros(n)
        if n == 0 or not len(self.lanes):
            return out_id, out_s, out_d
        geos = self.geometry
        gaps = np.stack([np.hypot(np.maximum(np.maximum(g.lo[0] - P[:, 0], P[:, 0] - g.hi[0]), 0.0),
                                  np.maximum(np.maximum(g.lo[1] - P[:, 1], P[:, 1] - g.hi[1]), 0.0)) for g in geos])
        nearest = gaps.min(axis=0)
        for lane, geo, gap in zip(self.lanes, geos, gaps):
            use = np.flatnonzero(gap <= nearest + max_gap)
            if len(use) == 0:
                continue
            s, d, h = geo.project(P[use, :2])
            herr = np.abs(wrap_angle(P[use, 2] - h))
            half = 0.5 * geo.width_at(s)
            beyond = np.maximum(np.maximum(-s, s - geo.length), 0.0)  # distance past the lane's ends
            inside = (np.abs(d) <= half) & (beyond == 0.0)
            key = np.stack([np.where(inside, 0.0, 1.0), np.abs(d) + beyond], axis=1)
            key[herr > max_heading_error] = np.inf
            better = (key[:, 0] < best_key[use, 0]) | ((key[:, 0] == best_key[use, 0]) & (key[:, 1] < best_key[use, 1]))
            rows = use[better]
            best_key[rows] = key[better]
            out_id[rows] = int(lane.id)
            out_s[rows] = s[better]
            out_d[rows] = d[better]
        return out_id, out_s, out_d

    def corridor(self, lane_id: int, xy: np.ndarray, behind: float = 20.0, ahead: float = 200.0,
                 spacing: float = 2.0, default_speed_limit: float = DEFAULT_SPEED_LIMIT) -> Corridor:
        """The corridor along ``lane_id`` and its successors around the point ``xy`` (2,): from
        ``behind`` m behind its projection to ``ahead`` m in front (see
        :func:`~.corridor.build_corridor`). Built on every call (it depends on the point)."""
        return build_corridor(self.by_id, lane_id, xy, behind, ahead, spacing, default_speed_limit)

    def border_ends(self, tolerance: float = 5.0, reach: float = 10.0) -> frozenset[int]:
        """Ids of the lanes without successor that end at the edge of the mapped area: no point of
        any other lane's centre line (driven the same way, i.e. on a segment within 90 degrees of
        the lane's final direction) lies more than ``tolerance`` m beyond the lane's end along
        that direction and within ``reach`` m of its end across it. A lane that stops while a
        lane beside it goes on (a lane drop, a merge lane) is not in the set. Computed on the
        first call and kept.

        Why: real recordings (``scenes/real/``) are cut out of a longer road, and every lane of
        the road stops at the same cross-section; for the planner that is not a dead end."""
        key = (float(tolerance), float(reach))
        out = self._border.get(key)
        if out is not None:
            return out
        lines = {int(lane.id): np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2) for lane in self.lanes}
        border = []
        for lane in self.lanes:
            lid = int(lane.id)
            c = lines[lid]
            if [q for q in (getattr(lane, "successors", None) or []) if int(q) in self.by_id] or len(c) < 2:
                continue
            t = c[-1] - c[-2]
            norm = float(np.hypot(*t))
            if norm <= 0.0:
                continue
            t = t / norm
            beyond = False
            for oid, o in lines.items():
                if oid == lid or len(o) < 2:
                    continue
                seg = np.diff(o, axis=0)
                same_way = seg @ t > 0.0
                rel = o[1:] - c[-1]  # each segment's end point
                lon = rel @ t
                lat = np.abs(rel[:, 0] * t[1] - rel[:, 1] * t[0])
                if np.any(same_way & (lon > tolerance) & (lat < reach)):
                    beyond = True
                    break
            if not beyond:
                border.append(lid)
        out = frozenset(border)
        self._border[key] = out
        return out

    def lane_corridor(self, lane_id: int, ahead: float) -> CorridorSet:
        """The lane from its first point, ``ahead`` m along it and its successors (``behind`` 0,
        2 m spacing), as a one-corridor :class:`~.corridor.CorridorSet`; built on the first call
        for a (lane, ahead) pair and kept by the map."""
        key = (int(lane_id), float(ahead))
        cs = self._lane_corridors.get(key)
        if cs is None:
            start = np.asarray(self.by_id[key[0]].centerline, dtype=np.float64)[0]
            cs = CorridorSet([self.corridor(key[0], start, behind=0.0, ahead=ahead)])
            self._lane_corridors[key] = cs
        return cs

    def index(self, chain_step: float, chain_ahead: float,
              default_speed_limit: float = DEFAULT_SPEED_LIMIT) -> "LaneIndex":
        """The :class:`LaneIndex` of this map at a chain resolution; built on the first call for
        those parameters and kept by the map."""
        key = (float(chain_step), float(chain_ahead), float(default_speed_limit))
        idx = self._indexes.get(key)
        if idx is None:
            idx = LaneIndex(self.lanes, *key)
            self._indexes[key] = idx
        return idx


class LaneIndex:
    """Lane geometry prepared once per lane map for vectorised queries.

    * Every lane's cleaned centre line, padded into ``(L, Smax)`` segment arrays, for one
      batched projection of many positions onto every lane (``project_all``).
    * Every lane chained through its first successors from its start to ``chain_ahead`` m past
      its end, resampled every ``chain_step`` m and padded into ``(L, Cmax, 2)`` (``sample``);
      ``chain_len`` and ``dead_end`` say where a chain really stops.

    Built by :meth:`LaneMap.index` (once per map and chain resolution); the learned predictor's
    lane features read it.

    Args:
        lanes: objects with ``id``, ``centerline`` (P, 2), ``width`` (P,) or scalar, ``left``,
            ``right``, ``successors``, ``speed_limit`` (the scene's ``Lane``).
        chain_step: m between resampled chain points.
        chain_ahead: m chained past each lane's end.
        default_speed_limit: m/s for lanes without one.
    """

    def __init__(self, lanes: Sequence[Any], chain_step: float, chain_ahead: float,
                 default_speed_limit: float = DEFAULT_SPEED_LIMIT):
        self.chain_step = float(chain_step)
        self.chain_ahead = float(chain_ahead)
        self.ids = np.array([int(lane.id) for lane in lanes], np.int64)
        L = len(self.ids)
        self.row = {int(i): r for r, i in enumerate(self.ids)}
        by_id = {int(lane.id): lane for lane in lanes}
        cls = [lanegeo.clean_polyline(np.asarray(lane.centerline, np.float64).reshape(-1, 2)) for lane in lanes]
        widths = [_lane_widths(lane) for lane in lanes]
        smax = max([max(len(c) - 1, 1) for c in cls], default=1)
        self.seg_a = np.zeros((L, smax, 2))
        self.seg_u = np.zeros((L, smax, 2))
        self.seg_u[..., 0] = 1.0
        self.seg_len = np.zeros((L, smax))
        self.seg_s = np.zeros((L, smax))
        self.seg_w0 = np.zeros((L, smax))
        self.seg_w1 = np.zeros((L, smax))
        self.seg_ok = np.zeros((L, smax), bool)
        self.n_seg = np.ones(L, np.int64)
        self.length = np.zeros(L)
        for r, (c, w) in enumerate(zip(cls, widths)):
            if len(c) < 2:
                self.seg_a[r, 0] = c[0]
                self.seg_ok[r, 0] = True
                self.seg_w0[r, 0] = self.seg_w1[r, 0] = w[0]
                continue
            d = np.diff(c, axis=0)
            ln = np.hypot(d[:, 0], d[:, 1])
            n = len(ln)
            self.n_seg[r] = n
            self.seg_a[r, :n] = c[:-1]
            self.seg_u[r, :n] = d / ln[:, None]
            self.seg_len[r, :n] = ln
            self.seg_s[r, :n] = np.concatenate([[0.0], np.cumsum(ln)[:-1]])
            self.seg_w0[r, :n] = w[:-1]
            self.seg_w1[r, :n] = w[1:]
            self.seg_ok[r, :n] = True
            self.length[r] = float(ln.sum())
        self.left = np.array([self.row.get(_opt_int(lane.left), -1) for lane in lanes], np.int64)
        self.right = np.array([self.row.get(_opt_int(lane.right), -1) for lane in lanes], np.int64)
        self.limit = np.array([float(lane.speed_limit) if getattr(lane, "speed_limit", None) is not None
                               else default_speed_limit for lane in lanes])
        # projection bounds: interior segments clamp to [0, len]; the end segments extend
        self._lo = np.zeros_like(self.seg_len)
        self._hi = self.seg_len.copy()
        if L:
            self._lo[:, 0] = -np.inf
            self._hi[np.arange(L), self.n_seg - 1] = np.inf
        chains = [self._chain(by_id, int(lane.id)) for lane in lanes]
        cmax = max([len(p) for p, _ in chains], default=2)
        self.chain = np.zeros((L, cmax, 2))
        self.chain_len = np.zeros(L)
        self.dead_end = np.zeros(L, bool)
        for r, (pts, dead) in enumerate(chains):
            self.chain[r, :len(pts)] = pts
            self.chain[r, len(pts):] = pts[-1]
            self.chain_len[r] = self.chain_step * (len(pts) - 1)
            self.dead_end[r] = dead
        # per-frame queries read these instead of recomputing them for every point: each
        # segment's heading (arctan2 stays numpy's), and each chain's last real point and the unit
        # direction of its last segment, along which ``sample`` extrapolates past the chain's end
        self.seg_head = np.arctan2(self.seg_u[..., 1], self.seg_u[..., 0])
        last = np.maximum(np.round(self.chain_len / self.chain_step).astype(np.int64), 1)
        ext = self.chain[np.arange(L), last] - self.chain[np.arange(L), last - 1]
        self.ext_from = self.chain[np.arange(L), last]
        self.ext_dir = ext / np.maximum(np.linalg.norm(ext, axis=-1, keepdims=True), 1e-9)

    def __len__(self) -> int:
        return len(self.ids)

    def _chain(self, by_id: dict[int, Any], start: int) -> tuple[np.ndarray, bool]:
        """Uniformly resampled chain from ``start``'s first point through first successors,
        ``chain_ahead`` m past the start lane's end (or to a dead end). Returns points (C, 2)
        with C >= 2 (exactly ``chain_step`` apart except at a too-short end) and whether the
        chain stops at a dead end before that."""
        first = lanegeo.clean_polyline(np.asarray(by_id[start].centerline, np.float64).reshape(-1, 2))
        need = lanegeo.length(first) + self.chain_ahead
        parts, seen, total, dead = [first], {start}, lanegeo.length(first), False
        cur = start
        while total < need:
            succ = [int(s) for s in (getattr(by_id[cur], "successors", None) or []) if int(s) in by_id and int(s) not in seen]
            if not succ:
                dead = True
                break
            cur = succ[0]
            seen.add(cur)
            nxt = lanegeo.clean_polyline(np.asarray(by_id[cur].centerline, np.float64).reshape(-1, 2))
            parts.append(nxt)
            total += lanegeo.length(nxt)
        raw = lanegeo.clean_polyline(np.concatenate(parts))
        total = lanegeo.length(raw)
        end = min(total, need)
        n = max(1, int(np.floor(end / self.chain_step + 1e-9)))
        s = np.arange(n + 1) * self.chain_step
        pts = lanegeo.point_at(raw, s)
        return pts, dead

    def project_all(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Project (N, 2) positions onto every lane.

        Returns (each (N, L)): s along the lane (extrapolated before its start / past its end),
        d lateral offset (left +), heading of the closest segment, width there, and the distance
        past the lane's ends (0 inside its length).
        """
        q = np.asarray(xy, np.float64).reshape(-1, 2)
        rows = np.arange(len(self.ids))
        # squared distance to the foot on each segment without building (N, L, S, 2) feet:
        # |r - tc u|^2 = |r|^2 - 2 tc t + tc^2 for unit u, with t = r.u and tc = clip(t)
        rx = q[:, 0, None, None] - self.seg_a[None, ..., 0]                  # (N, L, S)
        ry = q[:, 1, None, None] - self.seg_a[None, ..., 1]
        t = rx * self.seg_u[None, ..., 0] + ry * self.seg_u[None, ..., 1]
        tc = np.clip(t, self._lo[None], self._hi[None])
        dist2 = rx * rx + ry * ry + tc * (tc - 2.0 * t)
        dist2[:, ~self.seg_ok] = np.inf
        best = np.argmin(dist2, axis=2)                                       # (N, L)
        take = lambda a: np.take_along_axis(a, best[..., None], axis=2)[..., 0]  # noqa: E731
        tb = take(tc)
        u = self.seg_u[rows[None, :], best]                                   # (N, L, 2)
        r = np.stack([take(rx), take(ry)], axis=-1)                           # (N, L, 2)
        s = self.seg_s[rows[None, :], best] + tb
        d = u[..., 0] * r[..., 1] - u[..., 1] * r[..., 0]
        head = self.seg_head[rows[None, :], best]
        seg_len = self.seg_len[rows[None, :], best]
        frac = np.clip(tb / np.maximum(seg_len, 1e-9), 0.0, 1.0)
        width = self.seg_w0[rows[None, :], best] * (1 - frac) + self.seg_w1[rows[None, :], best] * frac
        beyond = np.maximum(np.maximum(-s, s - self.length[None]), 0.0)
        return s, d, head, width, beyond

    def locate(self, poses: np.ndarray, max_heading_error: float = np.pi / 2):
        """The lane each pose (N, 3) is on (same rule as :meth:`LaneMap.locate_many`: the
        lane strip containing it with the smallest |d| among lanes heading within 90 degrees;
        else the nearest such lane).

        Returns:
            row (N,) int64 index into the lanes (-1: none), and the full ``project_all`` arrays.
        """
        P = np.asarray(poses, np.float64).reshape(-1, 3)
        n = len(P)
        if n == 0 or len(self.ids) == 0:
            z = np.zeros((n, len(self.ids)))
            return np.full(n, -1, np.int64), (z, z, z, z, z)
        proj = self.project_all(P[:, :2])
        s, d, head, width, beyond = proj
        herr = np.abs(wrap_angle(P[:, 2:3] - head))
        inside = (np.abs(d) <= 0.5 * width) & (beyond == 0.0)
        key = np.where(inside, 0.0, 1e6) + np.abs(d) + beyond
        key = np.where(herr <= max_heading_error, key, np.inf)
        row = np.argmin(key, axis=1)
        row = np.where(np.isfinite(key[np.arange(n), row]), row, -1)
        return row.astype(np.int64), proj

    def sample(self, rows: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chain points of lane ``rows`` (N,) at arc lengths ``s`` (N, M) from the lane's start.

        Returns points (N, M, 2) (extrapolated before the start along the first segment) and
        validity (N, M): False past a dead end (and for ``rows`` = -1).
        """
        rows = np.asarray(rows, np.int64)
        ok_row = rows >= 0
        r = np.where(ok_row, rows, 0)
        if len(self.ids) == 0:
            return np.zeros(s.shape + (2,)), np.zeros(s.shape, bool)
        cmax = self.chain.shape[1]
        u = s / self.chain_step
        i = np.clip(np.floor(u).astype(np.int64), 0, cmax - 2)
        f = u - i                                                            # extrapolates at the ends
        a = self.chain[r[:, None], i]
        b = self.chain[r[:, None], i + 1]
        pts = a + f[..., None] * (b - a)
        # past the chain's last real point: extrapolate along its last segment (chains that were
        # cut at chain_ahead are never queried that far; dead ends are flagged invalid)
        clen = self.chain_len[r][:, None]
        past = s > clen
        if np.any(past):
            ext = self.ext_from[r][:, None] + (s - clen)[..., None] * self.ext_dir[r][:, None]
            pts = np.where(past[..., None], np.broadcast_to(ext, pts.shape), pts)
        valid = ok_row[:, None] & ~(past & self.dead_end[r][:, None])
        return pts, valid


def _opt_int(v: Any) -> int:
    return -10 ** 12 if v is None else int(v)


def _lane_widths(lane: Any) -> np.ndarray:
    """Per cleaned-point widths of a lane (scalar widths broadcast)."""
    raw = np.asarray(lane.centerline, np.float64).reshape(-1, 2)
    w = np.asarray(lane.width, np.float64).reshape(-1)
    keep = lanegeo._kept_indices(raw)
    if w.size == 1:
        return np.full(len(keep), float(w[0]))
    return w[keep]


# ----------------------------------------------------------------------------- compiled locate


def _flatten(geometry: Sequence[LaneGeometry]) -> tuple[np.ndarray, ...]:
    """Every lane's :class:`LaneGeometry` in flat arrays for :func:`_locate_kernel`: lo, hi
    (L, 2) m, length (L,) m, point and segment offsets (L + 1,) int64, points (P, 2), cum (P,),
    width (P,) m, unit (S, 2), seg_len (S,) m, heading (S,) rad (numpy's arctan2, as
    :meth:`LaneGeometry.project` takes it)."""
    def cat(arrays, cols=0):
        if not arrays:
            return np.zeros((0, cols) if cols else 0)
        return np.ascontiguousarray(np.concatenate(arrays), dtype=np.float64)

    g = list(geometry)
    lo = np.array([x.lo for x in g], np.float64).reshape(-1, 2)
    hi = np.array([x.hi for x in g], np.float64).reshape(-1, 2)
    length = np.array([x.length for x in g], np.float64)
    p_off = np.r_[0, np.cumsum([len(x.points) for x in g])].astype(np.int64)
    s_off = np.r_[0, np.cumsum([len(x.seg_len) for x in g])].astype(np.int64)
    unit = cat([x.unit for x in g], 2)
    heading = np.arctan2(unit[:, 1], unit[:, 0])
    return (lo, hi, length, p_off, s_off, cat([x.points for x in g], 2), cat([x.cum for x in g]),
            cat([x.width for x in g]), unit, cat([x.seg_len for x in g]), heading)


@kernel
def _interp_one(x, xp, fp, a, b):
    """``np.interp(x, xp[a:b], fp[a:b])`` for one x in [xp[a], xp[b - 1]] (b - a >= 2), with
    numpy's rules: the exact value at a knot and at the right end, else slope x (x - x_j) + f_j."""
    if x >= xp[b - 1]:
        return fp[b - 1]
    lo, hi = a, b - 1  # the last j with xp[j] <= x: xp[lo] <= x < xp[hi]
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    if xp[lo] == x:
        return fp[lo]
    slope = (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo])
    return slope * (x - xp[lo]) + fp[lo]


@kernel
def _locate_kernel(P, max_herr, max_gap, ids, lo, hi, length, p_off, s_off, points, cum, width, unit, seg_len,
                   heading):
    """:meth:`LaneMap.locate_many_numpy` for finite poses, one pose and one lane at a time, the
    same float64 operations in the same order (the projection is ``corridor._project_polyline``'s
    loop). P: (N, 3) poses; the lanes: :func:`_flatten`. Returns ids (N,) int64, s, d (N,) m."""
    n, L = P.shape[0], ids.shape[0]
    out_id = np.full(n, -1, np.int64)
    out_s = np.zeros(n)
    out_d = np.zeros(n)
    gaps = np.empty(L)
    two_pi = 2 * np.pi
    for k in range(n):
        x, y, yaw = P[k, 0], P[k, 1], P[k, 2]
        nearest = np.inf
        for l in range(L):
            gx = max(max(lo[l, 0] - x, x - hi[l, 0]), 0.0)
            gy = max(max(lo[l, 1] - y, y - hi[l, 1]), 0.0)
            gaps[l] = np.hypot(gx, gy)
            nearest = min(nearest, gaps[l])
        best0, best1 = np.inf, np.inf
        for l in range(L):
            if not gaps[l] <= nearest + max_gap:
                continue
            # global projection on the lane's polyline (first / last segment extended)
            a, S = s_off[l], s_off[l + 1] - s_off[l]
            pa = p_off[l]
            best, bi, s, d = np.inf, 0, 0.0, 0.0
            for i in range(S):
                ux, uy = unit[a + i, 0], unit[a + i, 1]
                rx, ry = x - points[pa + i, 0], y - points[pa + i, 1]
                t = rx * ux + ry * uy
                tlo = -np.inf if i == 0 else 0.0
                thi = np.inf if i == S - 1 else seg_len[a + i]
                tc = min(max(t, tlo), thi)
                ex, ey = rx - tc * ux, ry - tc * uy
                e2 = ex * ex + ey * ey
                if e2 < best or i == 0:
                    best, bi = e2, i
                    s = cum[pa + i] + tc
                    d = ux * ry - uy * rx
            herr = abs((yaw - heading[a + bi] + np.pi) % two_pi - np.pi)
            half = 0.5 * _interp_one(min(max(s, 0.0), length[l]), cum, width, pa, p_off[l + 1])
            beyond = max(max(-s, s - length[l]), 0.0)
            k0 = 0.0 if (abs(d) <= half and beyond == 0.0) else 1.0
            k1 = abs(d) + beyond
            if herr > max_herr:
                k0, k1 = np.inf, np.inf
            if k0 < best0 or (k0 == best0 and k1 < best1):
                best0, best1 = k0, k1
                out_id[k], out_s[k], out_d[k] = ids[l], s, d
    return out_id, out_s, out_d
