"""Learned multi-modal trajectory predictor (Autonomy-A's prediction stage).

``LearnedPredictor.predict(tracks, lanes) -> Predictions``: for every confirmed track, K modes
of its future centre positions over 6 s at 10 Hz (60 steps) with mode probabilities, in the
map frame. The paper's stack predicts "per-timestep endpoints" from the lane graph and the
detections (appendix "LiDAR-Based Autonomy Details"); this is a small agent-centric version
of that idea (features in the spirit of MultiPath / LaneGCN, with an MLP instead of a graph
network because highway lane graphs are tiny):

* **Agent frame**: origin at the track's current centre, x along its (smoothed) box heading.
* **Features** (``agent_features``, all in the agent frame, scaled to O(1)):
  history of the last ``HISTORY`` = 10 filtered states (1 s; x, y, cos/sin of the relative
  yaw, validity), Kalman velocity, speed, box size, misses, history length; the centre lines of
  the agent's lane and of its left / right neighbours, each sampled at ``LANE_OFFSETS`` (every
  10 m from 10 m behind to 200 m ahead along the lane and its successors; a point past a dead
  end is zero with validity 0, which is how lane drops and merges are seen), lane width, the
  agent's lateral offset, the speed limit; the ``NEIGHBOURS`` = 6 nearest other tracks
  (relative position and velocity).
* **Prior**: the lane-following extrapolation (speed along the heading, lateral offset kept,
  along the lane chain; straight for tracks off the lanes), in the agent frame.
* **Network** (:class:`PredictorNet`): MLP 3 x 256 (LayerNorm, ReLU) -> K x 60 x 2 residuals
  on top of the prior, plus K mode logits.
* **Training** (``adv3d train predictor``, :mod:`.predictor_cli`): winner-takes-all on the
  average displacement of the best mode + cross-entropy of the mode logits towards it.

Inference batches every track in one forward pass; lane geometry is indexed once per lane map
(:class:`LaneIndex`, cached by a fingerprint of the map), so a frame with 20 tracks costs
about 2-3 ms on one core (features ~1.3 ms, network ~0.3 ms). Tracks with short or invalid history, non-finite states,
and frames with no lanes are handled (their features are zero with validity flags 0).

Weights are a plain ``state_dict`` (``torch.load(weights_only=True)``) next to a
``config.json``; nothing is pickled.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import FileFormatError
from ..fileio import REPO_ROOT
from ..scene import lanes as lanegeo
from ..validate import Node, check_header
from .interface import DT, PREDICTION_STEPS, Predictions, Tracks

DEFAULT_MODEL_DIR = REPO_ROOT / "assets" / "models" / "predictor"
WEIGHTS_NAME = "weights.pt"
CONFIG_NAME = "config.json"
MODEL_FORMAT = "adv3d-predictor"
MODEL_VERSION = 1

HISTORY = 10                                          # past states used (1 s at 10 Hz)
LANE_OFFSETS = np.arange(-10.0, 200.1, 10.0)          # m along the lane from the agent (22)
NEIGHBOURS = 6                                        # nearest other tracks
NEIGHBOUR_RANGE = 80.0                                # m
CHAIN_STEP = 2.0                                      # m, resampling of the lane chains
CHAIN_AHEAD = float(LANE_OFFSETS[-1]) + 20.0          # m chained past a lane's end
DEFAULT_SPEED_LIMIT = 29.0                            # m/s when a lane has none
OFF_LANE = 1.0                                        # m outside a lane strip still lane-bound (prior)

# feature block sizes (kept in one place so the layout is documented and checked)
_HIST_F = HISTORY * 5
_AGENT_F = 8
_LANE_F = 1 + 3 * len(LANE_OFFSETS) + 3               # exists, (x, y, valid) per point, width, d, limit
_NEIGH_F = NEIGHBOURS * 5
NUM_FEATURES = _HIST_F + _AGENT_F + 3 * _LANE_F + _NEIGH_F


# --------------------------------------------------------------------------- lane index
class LaneIndex:
    """Lane geometry prepared once per lane map for vectorised queries.

    * Every lane's cleaned centre line, padded into ``(L, Smax)`` segment arrays, for one
      batched projection of many positions onto every lane (``project_all``).
    * Every lane chained through its first successors from its start to ``CHAIN_AHEAD`` m past
      its end, resampled every ``CHAIN_STEP`` m and padded into ``(L, Cmax, 2)`` (``sample``);
      ``chain_len`` and ``dead_end`` say where a chain really stops.

    Args:
        lanes: objects with ``id``, ``centerline`` (P, 2), ``width`` (P,) or scalar, ``left``,
            ``right``, ``successors``, ``speed_limit`` (the scene's ``Lane``).
    """

    def __init__(self, lanes: Sequence[Any]):
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
                               else DEFAULT_SPEED_LIMIT for lane in lanes])
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
            self.chain_len[r] = CHAIN_STEP * (len(pts) - 1)
            self.dead_end[r] = dead

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def _chain(by_id: dict[int, Any], start: int) -> tuple[np.ndarray, bool]:
        """Uniformly resampled chain from ``start``'s first point through first successors,
        ``CHAIN_AHEAD`` m past the start lane's end (or to a dead end). Returns points (C, 2)
        with C >= 2 (exactly ``CHAIN_STEP`` apart except at a too-short end) and whether the
        chain stops at a dead end before that."""
        first = lanegeo.clean_polyline(np.asarray(by_id[start].centerline, np.float64).reshape(-1, 2))
        need = lanegeo.length(first) + CHAIN_AHEAD
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
        n = max(1, int(np.floor(end / CHAIN_STEP + 1e-9)))
        s = np.arange(n + 1) * CHAIN_STEP
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
        head = np.arctan2(u[..., 1], u[..., 0])
        seg_len = self.seg_len[rows[None, :], best]
        frac = np.clip(tb / np.maximum(seg_len, 1e-9), 0.0, 1.0)
        width = self.seg_w0[rows[None, :], best] * (1 - frac) + self.seg_w1[rows[None, :], best] * frac
        beyond = np.maximum(np.maximum(-s, s - self.length[None]), 0.0)
        return s, d, head, width, beyond

    def locate(self, poses: np.ndarray, max_heading_error: float = np.pi / 2):
        """The lane each pose (N, 3) is on (same rule as the planner's ``corridor.locate``: the
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
        herr = np.abs((P[:, 2:3] - head + np.pi) % (2 * np.pi) - np.pi)
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
        u = s / CHAIN_STEP
        i = np.clip(np.floor(u).astype(np.int64), 0, cmax - 2)
        f = u - i                                                            # extrapolates at the ends
        a = self.chain[r[:, None], i]
        b = self.chain[r[:, None], i + 1]
        pts = a + f[..., None] * (b - a)
        # past the chain's last real point: extrapolate along its last segment (chains that were
        # cut at CHAIN_AHEAD are never queried that far; dead ends are flagged invalid)
        clen = self.chain_len[r][:, None]
        last = np.maximum(np.round(clen / CHAIN_STEP).astype(np.int64), 1)
        past = s > clen
        if np.any(past):
            pa = self.chain[r[:, None], last - 1]
            pb = self.chain[r[:, None], last]
            seg = pb - pa
            seg_n = seg / np.maximum(np.linalg.norm(seg, axis=-1, keepdims=True), 1e-9)
            ext = pb + (s - clen)[..., None] * seg_n
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


def lane_fingerprint(lanes: Sequence[Any]) -> str:
    """Cheap identity of a lane map (ids, point counts, end points, widths, links)."""
    h = hashlib.sha1()
    for lane in lanes:
        c = np.asarray(lane.centerline, np.float64).reshape(-1, 2)
        w = np.asarray(lane.width, np.float64).reshape(-1)
        h.update(np.array([lane.id, len(c), *c[0], *c[-1], float(c.sum()), float(w.sum()),
                           _opt_int(lane.left), _opt_int(lane.right)], np.float64).tobytes())
        h.update(np.asarray(list(getattr(lane, "successors", []) or []), np.int64).tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------- features
def _rot(xy: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Rotate (N, ..., 2) vectors by -yaw given c = cos(yaw), s = sin(yaw) of shape (N,)."""
    shape = (-1,) + (1,) * (xy.ndim - 2)
    c = c.reshape(shape)
    s = s.reshape(shape)
    return np.stack([c * xy[..., 0] + s * xy[..., 1], -s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def sanitize_tracks(tracks: Tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Finite copies of the track state a predictor needs.

    Returns boxes (N, 5), velocities (N, 2), history (N, H, 3) and history validity (N, H)
    aligned to ``HISTORY`` entries (the newest last; shorter histories are padded in front
    as invalid), and ``ok`` (N,): the current box is finite. Non-finite history entries are
    marked invalid; a non-finite velocity is zero.
    """
    n = len(tracks)
    boxes = np.asarray(tracks.boxes, np.float64).reshape(n, 5).copy()
    ok = np.all(np.isfinite(boxes), axis=1)
    boxes[~ok] = 0.0
    vel = np.nan_to_num(np.asarray(tracks.velocities, np.float64).reshape(n, 2), nan=0.0, posinf=0.0, neginf=0.0)
    hist_in = np.asarray(tracks.history, np.float64)
    hv_in = np.asarray(tracks.history_valid, bool)
    if hist_in.ndim != 3 or hist_in.shape[0] != n:
        hist_in = np.zeros((n, 0, 3))
        hv_in = np.zeros((n, 0), bool)
    H = hist_in.shape[1]
    hist = np.zeros((n, HISTORY, 3))
    hv = np.zeros((n, HISTORY), bool)
    k = min(H, HISTORY)
    if k:
        hist[:, HISTORY - k:] = hist_in[:, H - k:]
        hv[:, HISTORY - k:] = hv_in[:, H - k:]
    hv &= np.all(np.isfinite(hist), axis=-1)
    hist = np.where(hv[..., None], hist, 0.0)
    return boxes, vel, hist, hv, ok


def agent_features(tracks: Tracks, lanes: Sequence[Any], index: LaneIndex | None = None) -> np.ndarray:
    """Agent-centric features of every track (see the module docstring for the layout).

    Args:
        tracks: N tracks (map frame).
        lanes: the lane map (may be empty); ``index`` a prebuilt :class:`LaneIndex` of it.
    Returns:
        (N, NUM_FEATURES) float32, finite.
    """
    return encode(tracks, lanes, index)[0]


def encode(tracks: Tracks, lanes: Sequence[Any], index: LaneIndex | None = None,
           steps: int = PREDICTION_STEPS, dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """Features (N, NUM_FEATURES) float32 and the lane-following prior (N, steps, 2) float32
    (agent frame, m) that the network refines.

    The prior is what :class:`~.baselines.LaneFollowingPredictor`'s first mode does: keep the
    speed along the heading (>= 0) and the lateral offset in the lane, following the lane chain;
    a track more than ``OFF_LANE`` m outside its lane strip (or with no lane) goes straight.
    """
    n = len(tracks)
    if n == 0:
        return np.zeros((0, NUM_FEATURES), np.float32), np.zeros((0, steps, 2), np.float32)
    boxes, vel, hist, hv, ok = sanitize_tracks(tracks)
    x0, y0, yaw = boxes[:, 0], boxes[:, 1], boxes[:, 4]
    c, s = np.cos(yaw), np.sin(yaw)
    origin = boxes[:, None, :2]
    speed_h = np.maximum(vel[:, 0] * c + vel[:, 1] * s, 0.0)
    t = np.arange(1, steps + 1) * dt
    prior = np.zeros((n, steps, 2))
    prior[..., 0] = speed_h[:, None] * t[None]

    # history (N, H, 5): x, y, cos, sin of relative yaw, valid
    hxy = _rot(hist[..., :2] - origin, c, s)
    dyaw = hist[..., 2] - yaw[:, None]
    hist_f = np.concatenate([hxy / 10.0, np.cos(dyaw)[..., None], np.sin(dyaw)[..., None], hv[..., None]], axis=-1)
    hist_f = np.where(hv[..., None], hist_f, 0.0).reshape(n, -1)

    v_loc = _rot(vel[:, None, :], c, s)[:, 0]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    misses = np.asarray(tracks.misses, np.float64).reshape(n)
    agent_f = np.stack([v_loc[:, 0] / 10.0, v_loc[:, 1] / 10.0, speed / 10.0, boxes[:, 2] / 10.0,
                        boxes[:, 3] / 2.0, np.clip(misses, 0, 10) / 3.0, hv.sum(1) / HISTORY,
                        ok.astype(np.float64)], axis=1)

    lane_f = np.zeros((n, 3, _LANE_F))
    if len(lanes):
        index = index if index is not None else LaneIndex(lanes)
        poses = np.stack([x0, y0, yaw], axis=1)
        row, (ps, pd, _, pw, _) = index.locate(poses)
        row = np.where(ok, row, -1)
        ii = np.arange(n)
        rows = np.stack([row, np.where(row >= 0, index.left[np.maximum(row, 0)], -1),
                         np.where(row >= 0, index.right[np.maximum(row, 0)], -1)], axis=1)  # (N, 3)
        for j in range(3):
            rj = rows[:, j]
            has = rj >= 0
            rs = np.maximum(rj, 0)
            s_on = ps[ii, rs]
            pts, valid = index.sample(rj, s_on[:, None] + LANE_OFFSETS[None])
            loc = _rot(pts - origin, c, s)
            loc = np.where(valid[..., None], loc, 0.0)
            blk = np.concatenate([loc[..., 0:1] / 50.0, loc[..., 1:2] / 10.0, valid[..., None]], axis=-1)
            lane_f[:, j, 0] = has
            lane_f[:, j, 1:1 + 3 * len(LANE_OFFSETS)] = blk.reshape(n, -1)
            lane_f[:, j, -3] = np.where(has, pw[ii, rs] / 4.0, 0.0)
            lane_f[:, j, -2] = np.where(has, np.clip(pd[ii, rs], -20, 20) / 4.0, 0.0)
            lane_f[:, j, -1] = np.where(has, index.limit[rs] / 30.0, 0.0)
        # lane-following prior for tracks on (or within OFF_LANE m of) their lane strip
        rs = np.maximum(row, 0)
        d0 = pd[ii, rs]
        bound = (row >= 0) & (np.abs(d0) - 0.5 * pw[ii, rs] <= OFF_LANE)
        if np.any(bound):
            b = np.flatnonzero(bound)
            st = ps[b, rs[b]][:, None] + speed_h[b, None] * t[None]
            p0, _ = index.sample(row[b], st)
            p1, _ = index.sample(row[b], st + 1.0)
            tan = p1 - p0
            tan /= np.maximum(np.linalg.norm(tan, axis=-1, keepdims=True), 1e-9)
            path = p0 + d0[b, None, None] * np.stack([-tan[..., 1], tan[..., 0]], axis=-1)
            prior[b] = _rot(path - origin[b], c[b], s[b])
    lane_f = lane_f.reshape(n, -1)

    # nearest other tracks (relative position / velocity in the agent frame)
    neigh_f = np.zeros((n, NEIGHBOURS, 5))
    if n > 1:
        rel = boxes[None, :, :2] - boxes[:, None, :2]                       # (N, N, 2) j relative to i
        dist = np.hypot(rel[..., 0], rel[..., 1])
        bad = ~(ok[:, None] & ok[None, :]) | np.eye(n, dtype=bool) | (dist > NEIGHBOUR_RANGE)
        dist = np.where(bad, np.inf, dist)
        k = min(NEIGHBOURS, n - 1)
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        dsel = np.take_along_axis(dist, order, axis=1)
        valid = np.isfinite(dsel)
        rp = _rot(np.take_along_axis(rel, order[..., None], axis=1), c, s)
        rv = _rot(vel[order] - vel[:, None, :], c, s)
        blk = np.concatenate([rp[..., 0:1] / 50.0, rp[..., 1:2] / 10.0, rv / 10.0, valid[..., None]], axis=-1)
        neigh_f[:, :k] = np.where(valid[..., None], blk, 0.0)
    neigh_f = neigh_f.reshape(n, -1)
    out = np.concatenate([hist_f, agent_f, lane_f, neigh_f], axis=1)
    prior = np.where(ok[:, None, None], prior, 0.0)
    return (np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32),
            np.nan_to_num(prior).astype(np.float32))


def to_map_frame(local: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Agent-frame positions (N, K, T, 2) -> map frame with the boxes' (N, 5) pose."""
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    c = c[:, None, None]
    s = s[:, None, None]
    x = c * local[..., 0] - s * local[..., 1] + boxes[:, 0, None, None]
    y = s * local[..., 0] + c * local[..., 1] + boxes[:, 1, None, None]
    return np.stack([x, y], axis=-1)


# --------------------------------------------------------------------------- model
@dataclass(frozen=True)
class PredictorConfig:
    """Architecture of :class:`PredictorNet` (stored in ``config.json``)."""

    num_features: int = NUM_FEATURES
    num_modes: int = 6
    steps: int = PREDICTION_STEPS
    hidden: int = 256
    layers: int = 3
    residual_scale: float = 10.0   # m: network outputs are residuals / this
    dt: float = DT


def build_net(config: PredictorConfig):
    """The torch module for ``config`` (imports torch lazily)."""
    import torch
    from torch import nn

    class PredictorNet(nn.Module):
        """features (B, F) + prior (B, T, 2) -> trajectories (B, K, T, 2) m in the agent frame
        (prior + residuals), mode logits (B, K)."""

        def __init__(self, cfg: PredictorConfig):
            super().__init__()
            self.cfg = cfg
            dims = [cfg.num_features] + [cfg.hidden] * cfg.layers
            body = []
            for a, b in zip(dims[:-1], dims[1:]):
                body += [nn.Linear(a, b), nn.LayerNorm(b), nn.ReLU()]
            self.body = nn.Sequential(*body)
            self.traj = nn.Linear(cfg.hidden, cfg.num_modes * cfg.steps * 2)
            self.logits = nn.Linear(cfg.hidden, cfg.num_modes)

        def forward(self, feats, prior):
            h = self.body(feats)
            B = feats.shape[0]
            res = self.traj(h).view(B, self.cfg.num_modes, self.cfg.steps, 2) * self.cfg.residual_scale
            return prior[:, None] + res, self.logits(h)

    return PredictorNet(config)


class LearnedPredictor:
    """Tracks + lanes -> multi-modal predictions with a trained :class:`PredictorNet`.

    Args:
        net: the torch module; config: its :class:`PredictorConfig`.
        threads: torch intra-op threads for inference (1: the episode loop is single-core).
    """

    def __init__(self, net, config: PredictorConfig, threads: int | None = 1):
        import torch

        self.net = net.eval()
        self.config = config
        self.threads = threads
        self._index: LaneIndex | None = None
        self._index_key: tuple[int, str] | None = None
        self._torch = torch

    @property
    def num_modes(self) -> int:
        return self.config.num_modes

    def lane_index(self, lanes: Sequence[Any]) -> LaneIndex:
        """The cached :class:`LaneIndex` of ``lanes`` (rebuilt when the map changes)."""
        key = (len(lanes), lane_fingerprint(lanes))
        if self._index is None or self._index_key != key:
            self._index = LaneIndex(lanes)
            self._index_key = key
        return self._index

    def predict_local(self, feats: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network on precomputed features (N, F) and priors (N, T, 2) -> agent-frame
        trajectories (N, K, T, 2) float64 and probabilities (N, K)."""
        torch = self._torch
        if self.threads:
            torch.set_num_threads(self.threads)
        with torch.inference_mode():
            traj, logits = self.net(torch.from_numpy(np.ascontiguousarray(feats, np.float32)),
                                    torch.from_numpy(np.ascontiguousarray(prior, np.float32)))
            probs = torch.softmax(logits, dim=-1)
        return traj.numpy().astype(np.float64), probs.numpy().astype(np.float64)

    def predict(self, tracks: Tracks, lanes: Sequence[Any] = ()) -> Predictions:
        """(N,) tracks -> Predictions (N, K, 60, 2) in the map frame, rows of probabilities
        summing to 1. All tracks go through the network in one batch."""
        n = len(tracks)
        K, T = self.config.num_modes, self.config.steps
        if n == 0:
            return Predictions(np.zeros(0, np.int64), np.zeros((0, K, T, 2)), np.zeros((0, K)), self.config.dt)
        lanes = list(lanes) if lanes is not None else []
        index = self.lane_index(lanes) if lanes else None
        feats, prior = encode(tracks, lanes, index, T, self.config.dt)
        local, probs = self.predict_local(feats, prior)
        boxes = np.asarray(tracks.boxes, np.float64).reshape(n, 5)
        traj = to_map_frame(local, np.nan_to_num(boxes))
        bad = ~np.all(np.isfinite(boxes), axis=1)
        if np.any(bad):  # no pose: nothing sensible to predict; keep the rows but make them NaN
            traj[bad] = np.nan
        probs = probs / probs.sum(axis=1, keepdims=True)
        return Predictions(np.asarray(tracks.ids, np.int64).copy(), traj, probs, self.config.dt)


# --------------------------------------------------------------------------- files
def save_predictor(net, config: PredictorConfig, out_dir: str | Path, extra: dict | None = None) -> Path:
    """Write ``weights.pt`` (a plain state_dict of tensors) and ``config.json`` atomically."""
    import io

    import torch

    from ..fileio import atomic_write_bytes, write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}, buf)
    atomic_write_bytes(out / WEIGHTS_NAME, buf.getvalue())
    doc = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "config": asdict(config),
           "features": {"history": HISTORY, "lane_offsets_m": LANE_OFFSETS.tolist(), "neighbours": NEIGHBOURS,
                        "neighbour_range_m": NEIGHBOUR_RANGE, "chain_step_m": CHAIN_STEP},
           "weights": WEIGHTS_NAME}
    if extra:
        doc.update(extra)
    write_json(out / CONFIG_NAME, doc)
    return out


def load_predictor(path: str | Path = DEFAULT_MODEL_DIR, threads: int | None = 1) -> LearnedPredictor:
    """Load a trained predictor from its folder (``config.json`` + ``weights.pt``).

    Weights are read with ``torch.load(weights_only=True)``; a missing or malformed file raises
    :class:`~adv3d_runner.errors.FileFormatError` naming the file and field.
    """
    import torch

    path = Path(path)
    cfg_path = path / CONFIG_NAME
    if not cfg_path.is_file():
        raise FileFormatError(str(cfg_path), "$", "a predictor config.json (train one with `adv3d train predictor`)", "no file")
    doc = Node.load(cfg_path)
    check_header(doc, MODEL_FORMAT, (MODEL_VERSION,))
    raw = doc["config"]
    try:
        config = PredictorConfig(**raw.object())
    except TypeError as exc:
        raw.fail("PredictorConfig fields", str(exc))
    if config.num_features != NUM_FEATURES:
        raw.child("num_features").fail(str(NUM_FEATURES), config.num_features)
    feats = doc.get("features", {})
    layout = feats.object()
    if (list(layout.get("lane_offsets_m", LANE_OFFSETS.tolist())) != LANE_OFFSETS.tolist()
            or layout.get("history", HISTORY) != HISTORY):
        feats.fail("the feature layout of this code version", layout)
    w_path = path / doc.get("weights", WEIGHTS_NAME).string()
    if not w_path.is_file():
        raise FileFormatError(str(w_path), "$", "predictor weights", "no file")
    try:
        state = torch.load(w_path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt / pickled files
        raise FileFormatError(str(w_path), "$", "a weights-only torch state_dict", str(exc)) from exc
    net = build_net(config)
    try:
        net.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as exc:
        raise FileFormatError(str(w_path), "$", f"weights matching {config}", str(exc)) from exc
    return LearnedPredictor(net, config, threads=threads)
