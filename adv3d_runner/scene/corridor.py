"""Lane corridors: a lane chained through its successors and resampled uniformly, and several
corridors stacked into padded arrays so candidate paths on different lanes are handled in one
vectorised pass. The planner builds the ego's current / left / right corridors every frame; the
lane-following baseline reads one whole-lane corridor per lane (kept by
:class:`~adv3d_runner.scene.lanemap.LaneMap`, which owns every lane structure of a scene).

Lane input is the scene's lane type (:class:`adv3d_runner.scene.schema.Lane`) or anything with
the same attributes: ``id``, ``centerline`` (P, 2) m in driving direction, ``width`` (P,) or
scalar m, ``left`` / ``right`` neighbour ids (same direction) or None, ``successors`` (ids),
``speed_limit`` m/s or None. Polyline cleaning, arc length and global projection reuse
:mod:`adv3d_runner.scene.lanes`; the per-step queries here (local projection, point at s) use
the uniform spacing of the resampled corridor to index segments in O(1), which a planner making
~25 candidates x 50 steps per frame needs.

Frenet conventions as in ``scene.lanes``: ``s`` arc length along the corridor (m, from its first
point), ``d`` lateral offset, left positive (m).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..jit import kernel

from . import lanes as lanegeo

DEFAULT_SPEED_LIMIT = 29.0  # m/s (~65 mph, US highway) when a lane has none


@dataclass
class LaneGeometry:
    """Cleaned centre line of one lane, prepared once for fast repeated projection.

    Attributes: points (P, 2) (``scene.lanes.clean_polyline``), cum (P,) arc length, unit
    (S, 2) and seg_len (S,) of its segments, width (P,) m, lo / hi (2,) bounding box, length m.
    """

    points: np.ndarray
    cum: np.ndarray
    unit: np.ndarray
    seg_len: np.ndarray
    width: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    length: float
    _heading: np.ndarray | None = field(default=None, repr=False, compare=False)

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points (N, 2) -> s, d, heading (N,), as ``scene.lanes.project`` (ends extrapolated)."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self._heading is None:  # the segments' headings, once (arctan2 stays numpy's)
            self._heading = np.arctan2(self.unit[:, 1], self.unit[:, 0])
        s, d, best = _project_polyline(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), self.points,
                                       self.unit, self.seg_len, self.cum)
        return s, d, self._heading[best]

    def width_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(np.clip(s, 0.0, self.length), self.cum, self.width)


def lane_geometry(lane: Any) -> LaneGeometry:
    """The :class:`LaneGeometry` of a lane object (a :class:`~.lanemap.LaneMap` prepares every
    lane of a scene once)."""
    raw = np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2)
    pts = lanegeo.clean_polyline(raw)
    width = _lane_width(lane)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(raw, axis=0), axis=1) > lanegeo.EPS])
    width = width[keep] if len(width) == len(raw) and keep.sum() == len(pts) else np.full(len(pts), float(width[0]))
    if len(pts) == 1:  # degenerate lane: a point with one zero-length segment along +x
        pts2, unit, seg = np.vstack([pts, pts]), np.array([[1.0, 0.0]]), np.zeros(1)
        geo = LaneGeometry(pts2, np.zeros(2), unit, seg, np.repeat(width[:1], 2), pts[0], pts[0], 0.0)
    else:
        d = np.diff(pts, axis=0)
        seg = np.hypot(d[:, 0], d[:, 1])
        cum = lanegeo.arc_length(pts)
        geo = LaneGeometry(pts, cum, d / seg[:, None], seg, width, pts.min(axis=0), pts.max(axis=0), float(cum[-1]))
    return geo


@dataclass
class Corridor:
    """One lane chain, resampled at uniform spacing.

    Attributes:
        lane_ids: ids of the chained lanes (first = the lane the corridor starts on).
        points: (P, 2) m, uniformly spaced by ``spacing`` (P >= 2).
        width: (P,) lane width, m. speed_limit: (P,) m/s.
        lane_of_point: (P,) id of the lane each point came from.
        s_offset: arc length of ``points[0]`` along the raw chain (m), for reference.
        ends: True if the chain really ends at the last point (no successor); False if it was
            cut at the planning window (continues beyond).
    """

    lane_ids: tuple[int, ...]
    points: np.ndarray
    width: np.ndarray
    speed_limit: np.ndarray
    lane_of_point: np.ndarray
    spacing: float
    s_offset: float = 0.0
    ends: bool = True

    @property
    def length(self) -> float:
        return float(self.spacing * (len(self.points) - 1))

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Global projection of (N, 2) points -> s, d, heading (N,) (see ``scene.lanes.project``)."""
        return lanegeo.project(self.points, np.asarray(xy, dtype=np.float64).reshape(-1, 2))


def lanes_by_id(lanes: Sequence[Any]) -> dict[int, Any]:
    return {int(lane.id): lane for lane in lanes}


def _lane_width(lane: Any) -> np.ndarray:
    w = np.asarray(lane.width, dtype=np.float64).reshape(-1)
    n = len(np.asarray(lane.centerline).reshape(-1, 2))
    return np.full(n, float(w[0])) if w.size == 1 else w


def _chain(by_id: dict[int, Any], start: int, need: float, cache: "ChainCache | None" = None) -> tuple[list[int], bool]:
    """Lane ids from ``start`` following the first successor until ``need`` m are covered."""
    lane_length = cache.lane_length if cache is not None else _lane_length
    ids = [start]
    total = lane_length(by_id, start)
    while total < need:
        succ = [int(s) for s in getattr(by_id[ids[-1]], "successors", []) or [] if int(s) in by_id]
        succ = [s for s in succ if s not in ids]  # no loops
        if not succ:
            return ids, True
        ids.append(succ[0])
        total += lane_length(by_id, succ[0])
    return ids, False


def _lane_length(by_id: dict[int, Any], lane_id: int) -> float:
    return lanegeo.length(np.asarray(by_id[lane_id].centerline, dtype=np.float64))


def _lane_segments(by_id: dict[int, Any], lane_id: int) -> tuple:
    return lanegeo.polyline_segments(np.asarray(by_id[lane_id].centerline, dtype=np.float64).reshape(-1, 2))


def _chain_arrays(by_id: dict[int, Any], ids: tuple[int, ...], default_speed_limit: float) -> tuple:
    """A lane chain's centre line with its repeated points dropped, their widths, speed limits
    and owner lanes, and the line's ``polyline_segments``."""
    pts, widths, limits, owner = [], [], [], []
    for lid in ids:
        lane = by_id[lid]
        c = np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2)
        pts.append(c)
        widths.append(_lane_width(lane))
        lim = lane.speed_limit if getattr(lane, "speed_limit", None) is not None else default_speed_limit
        limits.append(np.full(len(c), float(lim)))
        owner.append(np.full(len(c), lid))
    raw = np.concatenate(pts)
    # drop repeated points (lane joins repeat the shared end point) with their attributes
    keep = np.concatenate([[True], np.linalg.norm(np.diff(raw, axis=0), axis=1) > lanegeo.EPS])
    raw = raw[keep]
    return (raw, np.concatenate(widths)[keep], np.concatenate(limits)[keep], np.concatenate(owner)[keep],
            lanegeo.arc_length(raw), lanegeo.polyline_segments(raw))


class ChainCache:
    """What :func:`build_corridor` derives from a lane map's geometry alone (lane lengths, the
    first lane's segments, a chain's joined centre line), kept per lane id and per chain: the
    planner builds its corridors on every frame from a handful of chains.

    One cache serves one lane map, whose lanes do not change (the planner makes a new one on
    :meth:`~adv3d_runner.autonomy.planner.planner.SamplingPlanner.reset`). The corridors are
    the same numbers as without it.
    """

    def __init__(self):
        self._length: dict[int, float] = {}
        self._segments: dict[int, tuple] = {}
        self._chains: dict[tuple, tuple] = {}

    def lane_length(self, by_id: dict[int, Any], lane_id: int) -> float:
        if lane_id not in self._length:
            self._length[lane_id] = _lane_length(by_id, lane_id)
        return self._length[lane_id]

    def lane_segments(self, by_id: dict[int, Any], lane_id: int) -> tuple:
        if lane_id not in self._segments:
            self._segments[lane_id] = _lane_segments(by_id, lane_id)
        return self._segments[lane_id]

    def chain(self, by_id: dict[int, Any], ids: tuple[int, ...], default_speed_limit: float) -> tuple:
        key = (ids, float(default_speed_limit))
        if key not in self._chains:
            self._chains[key] = _chain_arrays(by_id, ids, default_speed_limit)
        return self._chains[key]


def build_corridor(lanes: Sequence[Any] | dict[int, Any], lane_id: int, xy: np.ndarray, behind: float = 20.0,
                   ahead: float = 200.0, spacing: float = 2.0,
                   default_speed_limit: float = DEFAULT_SPEED_LIMIT, cache: ChainCache | None = None) -> Corridor:
    """The corridor along ``lane_id`` and its successors around the point ``xy``: from ``behind``
    m behind its projection to ``ahead`` m in front (or the chain's end).

    Before the first lane's start the centre line is extrapolated (the ego may sit on a lane's
    first metres); beyond the chain's end nothing is added (``ends`` says whether it is a real
    dead end). ``cache``: a :class:`ChainCache` of this lane map (the same corridor, cheaper).
    """
    by_id = lanes if isinstance(lanes, dict) else lanes_by_id(lanes)
    xy = np.asarray(xy, dtype=np.float64).reshape(2)
    first = cache.lane_segments(by_id, lane_id) if cache is not None else _lane_segments(by_id, lane_id)
    s_first, _, _ = lanegeo.project_on_segments(first, xy)
    ids, dead_end = _chain(by_id, lane_id, s_first + ahead, cache)
    ids = tuple(ids)
    chain = (cache.chain(by_id, ids, default_speed_limit) if cache is not None
             else _chain_arrays(by_id, ids, default_speed_limit))
    raw, w_raw, lim_raw, own_raw, cum, segments = chain
    total = float(cum[-1])
    # s along the chain equals s along its first lane near the ego
    lo = s_first - behind
    hi = min(total, s_first + ahead)
    if hi - lo < spacing:
        hi = lo + spacing
    n = max(1, int(np.ceil((hi - lo) / spacing - 1e-9)))
    step = (hi - lo) / n  # exactly uniform, so a segment index is floor(s / step)
    s = lo + step * np.arange(n + 1)
    points = lanegeo.point_on_segments(segments, s)
    sc = np.clip(s, 0.0, total)
    width = np.interp(sc, cum, w_raw)
    limit = np.interp(sc, cum, lim_raw)
    owner_pts = own_raw[np.clip(np.searchsorted(cum, sc, side="right") - 1, 0, len(cum) - 1)]
    ends = bool(dead_end and hi >= total - 1e-6)
    return Corridor(ids, points, width, limit, owner_pts, float(step), float(lo), ends)


class CorridorSet:
    """Several corridors stacked into padded arrays (C, Pmax, ...) for vectorised queries.

    ``c`` arguments are corridor indices (int arrays broadcasting with the query).
    """

    def __init__(self, corridors: Sequence[Corridor]):
        if not corridors:
            raise ValueError("need at least one corridor")
        self.corridors = list(corridors)
        C = len(corridors)
        P = max(len(c.points) for c in corridors)
        self.n_points = np.array([len(c.points) for c in corridors])
        self.points = np.zeros((C, P, 2))
        self.width = np.zeros((C, P))
        self.limit = np.zeros((C, P))
        for i, c in enumerate(corridors):
            k = len(c.points)
            self.points[i, :k] = c.points
            self.points[i, k:] = c.points[-1]
            self.width[i, :k] = c.width
            self.width[i, k:] = c.width[-1]
            self.limit[i, :k] = c.speed_limit
            self.limit[i, k:] = c.speed_limit[-1]
        self.spacing = np.array([c.spacing for c in corridors])
        self.length = np.array([c.length for c in corridors])
        self.ends = np.array([c.ends for c in corridors])
        seg = np.diff(self.points, axis=1)  # (C, P-1, 2)
        seg_len = np.linalg.norm(seg, axis=-1)
        self.unit = np.where(seg_len[..., None] > 0, seg / np.maximum(seg_len, 1e-12)[..., None], 0.0)
        # padded (zero-length) segments inherit the last real direction
        for i, k in enumerate(self.n_points):
            self.unit[i, k - 1:] = self.unit[i, k - 2]
        self.heading = np.arctan2(self.unit[..., 1], self.unit[..., 0])
        # flat copies: gathering with one flat index is much cheaper than 2-D fancy indexing,
        # and the planner gathers every step for every candidate
        self._P = P
        self._px, self._py = self.points[..., 0].ravel(), self.points[..., 1].ravel()
        self._ux, self._uy = self.unit[..., 0].ravel(), self.unit[..., 1].ravel()
        self._hd = self.heading.ravel()
        self._sampled: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.corridors)

    def _seg_index(self, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        return np.clip(np.floor(s / self.spacing[c]).astype(np.int64), 0, self.n_points[c] - 2)

    def pose_at(self, c: np.ndarray, s: np.ndarray, d: np.ndarray | float = 0.0) -> np.ndarray:
        """(..., 3) x, y, heading at arc length s (extrapolated beyond the ends) and offset d."""
        c, s = np.asarray(c), np.asarray(s, dtype=np.float64)
        if c.shape != s.shape:
            c, s = np.broadcast_arrays(c, s)
        i = self._seg_index(c, s)
        ku = c * (self._P - 1) + i
        ux, uy = self._ux[ku], self._uy[ku]
        t = s - i * self.spacing[c]
        d = np.asarray(d, dtype=np.float64)
        out = np.empty(s.shape + (3,))
        kp = c * self._P + i
        out[..., 0] = self._px[kp] + t * ux - d * uy
        out[..., 1] = self._py[kp] + t * uy + d * ux
        out[..., 2] = self._hd[ku]
        return out

    def width_at(self, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        c, s = np.broadcast_arrays(np.asarray(c), np.asarray(s, dtype=np.float64))
        i = self._seg_index(c, s)
        f = np.clip(s / self.spacing[c] - i, 0.0, 1.0)
        return (1 - f) * self.width[c, i] + f * self.width[c, i + 1]

    def limit_at(self, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        c, s = np.broadcast_arrays(np.asarray(c), np.asarray(s, dtype=np.float64))
        i = self._seg_index(c, s)
        return np.minimum(self.limit[c, i], self.limit[c, i + 1])

    def project_local(self, c: np.ndarray, xy: np.ndarray, s_guess: np.ndarray, window: int = 3) -> tuple[np.ndarray, np.ndarray]:
        """Project points near a known arc length: searches ``window`` segments either side of
        ``s_guess`` (the first / last segment extend to infinity). c (...), xy (..., 2),
        s_guess (...) -> s, d (...)."""
        xy = np.asarray(xy, dtype=np.float64)
        c, s_guess = np.broadcast_arrays(np.asarray(c), np.asarray(s_guess, dtype=np.float64))
        shape = s_guess.shape
        c = np.ascontiguousarray(c.reshape(-1), dtype=np.int64)
        q = xy.reshape(-1, 2)
        s, d = _project_local_many(c, np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]),
                                   np.ascontiguousarray(s_guess.reshape(-1)), int(window), self._px, self._py,
                                   self._ux, self._uy, int(self._P), self.spacing.astype(np.float64),
                                   self.n_points.astype(np.int64))
        return s.reshape(shape), d.reshape(shape)

    def project(self, c: int, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global projection onto corridor ``c`` of points (..., 2) -> s, d (...)."""
        xy = np.asarray(xy, dtype=np.float64)
        q = xy.reshape(-1, 2)
        k = int(self.n_points[c])
        sp = float(self.spacing[c])
        s, d, _ = _project_polyline(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), self.points[c, :k],
                                    self.unit[c, :k - 1], np.full(k - 1, sp), np.arange(k - 1) * sp)
        return s.reshape(xy.shape[:-1]), d.reshape(xy.shape[:-1])

    def project_near(self, c: int, xy: np.ndarray, stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` through the nearest of every ``stride``-th corridor point and a local
        search of ``stride + 1`` segments either side of it: the same result wherever the
        closest segment lies within that window of the closest sampled point (always for
        points not much further from the corridor than its curve radius), at a fraction of the
        cost for many points. c: corridor index; xy (..., 2) -> s, d (...)."""
        xy = np.asarray(xy, dtype=np.float64)
        q = xy.reshape(-1, 2)
        idx, sub = self._sampled_points(c, stride)
        # one compiled pass (nearest sampled point, then the local search): the numpy version
        # (project_near_numpy, the tests' reference) built (n, n_sampled) temporaries per call
        s, d = _project_near_many(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), idx,
                                  np.ascontiguousarray(sub[:, 0]), np.ascontiguousarray(sub[:, 1]), int(c),
                                  stride + 1, self._px, self._py, self._ux, self._uy, int(self._P),
                                  float(self.spacing[c]), int(self.n_points[c]))
        return s.reshape(xy.shape[:-1]), d.reshape(xy.shape[:-1])

    def project_near_numpy(self, c: int, xy: np.ndarray, stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project_near` in numpy (the definition the compiled pass is tested against)."""
        xy = np.asarray(xy, dtype=np.float64)
        q = xy.reshape(-1, 2)
        idx, sub = self._sampled_points(c, stride)
        dx = q[:, None, 0] - sub[None, :, 0]
        dy = q[:, None, 1] - sub[None, :, 1]
        i = idx[np.argmin(dx * dx + dy * dy, axis=1)]
        s, d = self.project_local(np.full(len(q), c), q, i * self.spacing[c] + 1e-9, window=stride + 1)
        return s.reshape(xy.shape[:-1]), d.reshape(xy.shape[:-1])

    def _sampled_points(self, c: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
        """Every ``stride``-th point index of corridor ``c`` and its last, with the points
        (kept: :meth:`project_near` runs several times a plan)."""
        key = (int(c), int(stride))
        if key not in self._sampled:
            k = int(self.n_points[c])
            idx = np.unique(np.r_[np.arange(0, k, stride), k - 1])
            self._sampled[key] = (idx, self.points[c, idx])
        return self._sampled[key]

    def heading_on(self, c: int, s: np.ndarray) -> np.ndarray:
        """:meth:`pose_at` heading on the single corridor ``c`` (an int): (...) -> (...)."""
        s = np.asarray(s, dtype=np.float64)
        i = np.clip(np.floor(s / self.spacing[c]).astype(np.int64), 0, int(self.n_points[c]) - 2)
        return self.heading[c][i]

    def road_excess_on(self, c: int, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """:meth:`road_excess` on the single corridor ``c`` (an int), same arithmetic with the
        corridor's rows gathered once."""
        s = np.asarray(s, dtype=np.float64)
        sp = self.spacing[c]
        i = np.clip(np.floor(s / sp).astype(np.int64), 0, int(self.n_points[c]) - 2)
        f = np.clip(s / sp - i, 0.0, 1.0)
        w = self.width[c]
        half = 0.5 * ((1 - f) * w[i] + f * w[i + 1])
        lat = np.maximum(np.abs(d) - half, 0.0)
        if not self.ends[c]:
            return lat  # = hypot(lat, 0)
        return np.hypot(lat, np.maximum(s - self.length[c], 0.0))

    def road_excess(self, c: np.ndarray, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """How far (m) a point with Frenet coordinates (s, d) on corridor ``c`` lies outside that
        corridor's lane strip (0 inside). Past a dead end the longitudinal overshoot counts;
        before the start the strip is extrapolated."""
        half = 0.5 * self.width_at(c, s)
        lat = np.maximum(np.abs(d) - half, 0.0)
        over = np.where(self.ends[c], np.maximum(s - self.length[c], 0.0), 0.0)
        return np.hypot(lat, over)


@kernel
def project_on_segments(x: float, y: float, i0: int, window: int, px: np.ndarray, py: np.ndarray,
                        ux: np.ndarray, uy: np.ndarray, base_p: int, base_u: int, spacing: float,
                        last_i: int) -> tuple[float, float]:
    """Frenet (s, d) of the point (x, y) (m) on one corridor of a :class:`CorridorSet`, searched
    over the segments ``i0 - window .. i0 + window`` (clamped; the first / last segment extend
    to infinity); the first of equally near segments wins.

    Compiled (:mod:`adv3d_runner.jit`): the planner projects one point per candidate per step,
    and as numpy calls on (n, 2 window + 1) arrays their overhead was most of the cost.

    Args:
        px, py, ux, uy: the set's flattened points and segment unit vectors;
        base_p, base_u: the corridor's first flat point and segment index; spacing: m;
        last_i: the corridor's last segment index.
    """
    i0 = min(max(i0, 0), last_i)
    best, s_best, d_best = np.inf, 0.0, 0.0
    for off in range(-window, window + 1):
        i = min(max(i0 + off, 0), last_i)
        kp, ku = base_p + i, base_u + i
        rx, ry = x - px[kp], y - py[kp]
        t = rx * ux[ku] + ry * uy[ku]
        lo = -np.inf if i == 0 else 0.0
        hi = np.inf if i == last_i else spacing
        tc = min(max(t, lo), hi)
        ex, ey = rx - tc * ux[ku], ry - tc * uy[ku]
        e2 = ex * ex + ey * ey
        if e2 < best or off == -window:
            best, s_best, d_best = e2, i * spacing + tc, ux[ku] * ry - uy[ku] * rx
    return s_best, d_best


@kernel
def _project_local_many(c, qx, qy, s_guess, window, px, py, ux, uy, P, spacing, n_points):
    """:meth:`CorridorSet.project_local` of n points: c, qx, qy, s_guess (n,) -> s, d (n,)."""
    n = len(c)
    s = np.empty(n)
    d = np.empty(n)
    for k in range(n):
        ci = c[k]
        last_i = n_points[ci] - 2
        i0 = min(max(np.int64(np.floor(s_guess[k] / spacing[ci])), 0), last_i)
        s[k], d[k] = project_on_segments(qx[k], qy[k], i0, window, px, py, ux, uy, ci * P, ci * (P - 1),
                                         spacing[ci], last_i)
    return s, d


@kernel
def _project_polyline(qx, qy, points, unit, seg_len, cum):
    """Global projection of points onto one polyline (:meth:`LaneGeometry.project`): the
    nearest segment (the first of equally near ones; the first / last segment extend to
    infinity), compiled because numpy needed (N, S) temporaries for a few points per call.

    Args:
        qx, qy: (N,) m; points (S + 1, 2), unit (S, 2), seg_len (S,), cum (S + 1,) of the polyline.
    Returns:
        s, d (N,) m and the nearest segment's index (N,).
    """
    n, S = len(qx), len(seg_len)
    s = np.empty(n)
    d = np.empty(n)
    best_i = np.zeros(n, np.int64)
    for k in range(n):
        best = np.inf
        for i in range(S):
            rx, ry = qx[k] - points[i, 0], qy[k] - points[i, 1]
            t = rx * unit[i, 0] + ry * unit[i, 1]
            lo = -np.inf if i == 0 else 0.0
            hi = np.inf if i == S - 1 else seg_len[i]
            tc = min(max(t, lo), hi)
            ex, ey = rx - tc * unit[i, 0], ry - tc * unit[i, 1]
            e2 = ex * ex + ey * ey
            if e2 < best or i == 0:
                best = e2
                best_i[k] = i
                s[k] = cum[i] + tc
                d[k] = unit[i, 0] * ry - unit[i, 1] * rx
    return s, d, best_i


@kernel
def _project_near_many(qx, qy, idx, sub_x, sub_y, c, window, px, py, ux, uy, P, spacing, n_points):
    """:meth:`CorridorSet.project_near_numpy` of n points (qx, qy (n,) m) on corridor ``c``:
    the first nearest of the sampled points (indices ``idx``, coordinates sub_x, sub_y (K,)),
    then :func:`project_on_segments` within ``window`` segments of it, with the guess
    ``idx * spacing + 1e-9`` as numpy computed it. Returns s, d (n,) m."""
    n, K = qx.shape[0], sub_x.shape[0]
    s = np.empty(n)
    d = np.empty(n)
    last_i = n_points - 2
    for k in range(n):
        best, j = np.inf, 0
        for m in range(K):
            dx, dy = qx[k] - sub_x[m], qy[k] - sub_y[m]
            e2 = dx * dx + dy * dy
            if e2 < best:  # the first minimum, as np.argmin (a NaN point stays at 0, as there)
                best, j = e2, m
        guess = idx[j] * spacing + 1e-9
        i0 = min(max(np.int64(np.floor(guess / spacing)), 0), last_i)
        s[k], d[k] = project_on_segments(qx[k], qy[k], i0, window, px, py, ux, uy, c * P, c * (P - 1), spacing,
                                         last_i)
    return s, d


@kernel
def nearest_segment(qx, qy, pts, cum, unit, seg_len):
    """``lanes.project_on_segments_numpy`` of finite points qx, qy (n,) m, one point at a time
    with the same float64 operations (foot point = vertex + clamped t x unit, the squared
    distance to it; the first of equally near segments). Returns s, d (n,) m and the nearest
    segment (n,) int64."""
    n, S = qx.shape[0], unit.shape[0]
    out_s = np.empty(n)
    out_d = np.empty(n)
    out_i = np.zeros(n, np.int64)
    for k in range(n):
        best = np.inf
        for i in range(S):
            rx, ry = qx[k] - pts[i, 0], qy[k] - pts[i, 1]
            t = rx * unit[i, 0] + ry * unit[i, 1]
            lo = -np.inf if i == 0 else 0.0
            hi = np.inf if i == S - 1 else seg_len[i]
            tc = min(max(t, lo), hi)
            ex = qx[k] - (pts[i, 0] + tc * unit[i, 0])
            ey = qy[k] - (pts[i, 1] + tc * unit[i, 1])
            e2 = ex * ex + ey * ey
            if e2 < best or i == 0:
                best = e2
                out_i[k] = i
                out_s[k] = cum[i] + tc
                out_d[k] = unit[i, 0] * ry - unit[i, 1] * rx
    return out_s, out_d, out_i
