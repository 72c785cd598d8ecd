"""Learned multi-modal trajectory predictor (Autonomy-A's prediction stage).

``LearnedPredictor.reset(lane_map)`` once per episode, then ``predict(tracks) -> Predictions``:
for every confirmed track, K modes
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
* **Training** (``adv3d train predictor``, :mod:`adv3d_runner.training.predictor_train`):
  winner-takes-all on the average displacement of the best mode + cross-entropy of the mode
  logits towards it.

Inference batches every track in one forward pass; lane geometry is indexed once per lane map
(:class:`~adv3d_runner.scene.lanemap.LaneIndex`, kept by the scene's
:class:`~adv3d_runner.scene.lanemap.LaneMap`), and the features, the prior and the map-frame
output are compiled loops (:mod:`adv3d_runner.jit`; bit for bit the numpy formulation they
replaced, which ``tests/test_predictor.py`` keeps as the reference), so a frame costs about
0.2 ms on one core with 5 tracks and 0.45 ms with 18 (features 0.04 / 0.11 ms, network
0.11 / 0.23 ms). Tracks with short or invalid history, non-finite states,
and frames with no lanes are handled (their features are zero with validity flags 0).

Weights are a plain ``state_dict`` (``torch.load(weights_only=True)``) next to a
``config.json``; nothing is pickled.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import FileFormatError
from ..jit import kernel
from ..scene.lanemap import LaneIndex, LaneMap
from ..validate import Node, check_header
from .interface import DT, PREDICTION_STEPS, Predictions, Tracks
from .names import MODEL_DIRS

DEFAULT_MODEL_DIR = MODEL_DIRS["predictor"]
WEIGHTS_NAME = "weights.pt"
CONFIG_NAME = "config.json"
MODEL_FORMAT = "adv3d-predictor"
MODEL_VERSION = 1                                     # prior-based models (the residuals refine one prior)
ANCHORED_VERSION = 2                                  # anchored models (one lane-following anchor per mode)

HISTORY = 10                                          # past states used (1 s at 10 Hz)
LANE_OFFSETS = np.arange(-10.0, 200.1, 10.0)          # m along the lane from the agent (22)
NEIGHBOURS = 6                                        # nearest other tracks
NEIGHBOUR_RANGE = 80.0                                # m
CHAIN_STEP = 2.0                                      # m, resampling of the lane chains
CHAIN_AHEAD = float(LANE_OFFSETS[-1]) + 20.0          # m chained past a lane's end
DEFAULT_SPEED_LIMIT = 29.0                            # m/s when a lane has none (feature "limit")
OFF_LANE = 1.0                                        # m outside a lane strip still lane-bound (prior)
PATH_STEP = 2.0                                       # m between the points of a track's lane path
PATH_S = np.arange(0.0, 250.0 + 0.5 * PATH_STEP, PATH_STEP)  # (126,) arc lengths of the lane path, m

# feature block sizes (kept in one place so the layout is documented and checked)
_HIST_F = HISTORY * 5
_AGENT_F = 8
_LANE_F = 1 + 3 * len(LANE_OFFSETS) + 3               # exists, (x, y, valid) per point, width, d, limit
_NEIGH_F = NEIGHBOURS * 5
NUM_FEATURES = _HIST_F + _AGENT_F + 3 * _LANE_F + _NEIGH_F


# --------------------------------------------------------------------------- features
def sanitize_tracks(tracks: Tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Finite copies of the track state a predictor needs.

    Returns boxes (N, 5), velocities (N, 2), history (N, H, 3) and history validity (N, H)
    aligned to ``HISTORY`` entries (the newest last; shorter histories are padded in front
    as invalid), and ``ok`` (N,): the current box is finite. Non-finite history entries are
    marked invalid; a non-finite velocity is zero. (:func:`encode` does the same in its compiled
    ``_sanitize_kernel``.)
    """
    n = len(tracks)
    boxes = np.asarray(tracks.boxes, np.float64).reshape(n, 5).copy()
    ok = np.all(np.isfinite(boxes), axis=1)
    boxes[~ok] = 0.0
    vel = np.nan_to_num(np.asarray(tracks.velocities, np.float64).reshape(n, 2), nan=0.0, posinf=0.0, neginf=0.0)
    hist_in, hv_in = _history(tracks, n)
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


def lane_index(lane_map: LaneMap) -> LaneIndex:
    """The map's :class:`LaneIndex` at this predictor's chain resolution (``CHAIN_STEP``,
    ``CHAIN_AHEAD``); the map builds it once and keeps it."""
    return lane_map.index(CHAIN_STEP, CHAIN_AHEAD, DEFAULT_SPEED_LIMIT)


def agent_features(tracks: Tracks, lane_map: LaneMap) -> np.ndarray:
    """Agent-centric features of every track (see the module docstring for the layout).

    Args:
        tracks: N tracks (map frame).
        lane_map: the scene's lane map (may be empty).
    Returns:
        (N, NUM_FEATURES) float32, finite.
    """
    return encode(tracks, lane_map)[0]


def encode(tracks: Tracks, lane_map: LaneMap, steps: int = PREDICTION_STEPS,
           dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """Features (N, NUM_FEATURES) float32 and the lane-following prior (N, steps, 2) float32
    (agent frame, m) that the network refines.

    The prior is what :class:`~.baselines.LaneFollowingPredictor`'s first mode does: keep the
    speed along the heading (>= 0) and the lateral offset in the lane, following the lane chain;
    a track more than ``OFF_LANE`` m outside its lane strip (or with no lane) goes straight.

    Two compiled passes (:mod:`adv3d_runner.jit`) around the few numpy calls kept for their
    exact results (cos, sin, hypot): about ten calls per frame instead of some two hundred small
    numpy calls on (N, ...) arrays, with the same bits (``tests/test_predictor.py`` checks them
    against the numpy formulation, kept there).
    """
    n = len(tracks)
    if n == 0:
        return np.zeros((0, NUM_FEATURES), np.float32), np.zeros((0, steps, 2), np.float32)
    return _encode(tracks, lane_map, steps, dt)[:2]


def _encode(tracks: Tracks, lane_map: LaneMap, steps: int, dt: float, with_path: bool = False):
    """:func:`encode` of n > 0 tracks -> features, prior, and for :meth:`LearnedPredictor.predict`
    the sanitized boxes (n, 5), ``ok`` (n,) (the box is finite) and cos, sin of their yaw (n,);
    with ``with_path`` also the lane path (n, len(PATH_S), 2) of :func:`lane_paths`."""
    n = len(tracks)
    boxes, vel, hist, hv, misses = _track_arrays(tracks, n)
    boxes, vel, hist, hv, ok, dyaw, rel = _sanitize_kernel(boxes, vel, hist, hv)
    yaw = boxes[:, 4]
    c, s = np.cos(yaw), np.sin(yaw)
    cd, sd = np.cos(dyaw), np.sin(dyaw)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    dist = np.hypot(rel[..., 0], rel[..., 1])
    lanes = _lane_arrays(lane_index(lane_map)) if len(lane_map) else _NO_LANES
    feats, prior = _features_kernel(boxes, vel, hist, hv, ok, c, s, cd, sd, speed, dist, rel, misses,
                                    _times(steps, dt), LANE_OFFSETS, *lanes, _CAST)
    if not with_path:
        return feats, prior, boxes, ok, c, s
    # the lane path: the prior's rule at 1 m/s along the heading, sampled at the arc lengths PATH_S
    # (the same kernel; its features of this call are not used)
    unit = np.ascontiguousarray(np.c_[c, s])
    _, path = _features_kernel(boxes, unit, hist, hv, ok, c, s, cd, sd, np.ones(n), dist, rel, misses,
                               PATH_S, LANE_OFFSETS, *lanes, _CAST)
    return feats, prior, boxes, ok, c, s, path


def lane_paths(tracks: Tracks, lane_map: LaneMap) -> np.ndarray:
    """Each track's lane path in its agent frame: (N, len(PATH_S), 2) float32, the points at arc
    lengths ``PATH_S`` (0, 2, .., 250 m) along its lane chain keeping its lateral offset, or
    straight ahead for a track more than ``OFF_LANE`` m outside its lane strip (the prior's rule,
    :func:`encode`). The anchors of an anchored model move along it (:func:`anchor_trajectories`)."""
    n = len(tracks)
    if n == 0:
        return np.zeros((0, len(PATH_S), 2), np.float32)
    return _encode(tracks, lane_map, PREDICTION_STEPS, DT, with_path=True)[6]


def anchor_speed(feats: np.ndarray) -> np.ndarray:
    """(N,) m/s the anchors start from: the Kalman velocity along the heading, >= 0, as the
    features hold it (feature ``_HIST_F`` is that velocity / 10; the prior uses the same speed)."""
    return np.maximum(np.asarray(feats, np.float64)[:, _HIST_F] * 10.0, 0.0)


def anchor_trajectories(path: np.ndarray, speed: np.ndarray, scales, accels, steps: int = PREDICTION_STEPS,
                        dt: float = DT) -> np.ndarray:
    """Lane-following anchors: (N, K, steps, 2) agent-frame positions at t = dt .. steps dt.

    Mode k moves along the track's lane path (``path`` (N, G, 2) at arc lengths ``PATH_S``) at the
    speed ``max(scales[k] * speed + accels[k] * t, 0)`` m/s (``speed`` (N,) m/s): a scale of 1
    and no acceleration is the lane-following baseline's first mode, a negative acceleration
    brakes to a stop and stays there. Past the path's end the last segment is extended."""
    path = np.asarray(path, np.float64)
    v0 = np.asarray(speed, np.float64)[:, None, None] * np.asarray(scales, np.float64)[None, :, None]
    a = np.broadcast_to(np.asarray(accels, np.float64)[None, :, None], v0.shape)
    t = (np.arange(1, steps + 1) * dt)[None, None, :]
    s_go = v0 * t + 0.5 * a * t * t
    with np.errstate(divide="ignore", invalid="ignore"):
        t_stop = np.where(a < 0, v0 / np.where(a < 0, -a, 1.0), np.inf)
        s_stop = np.where(a < 0, v0 * v0 / np.where(a < 0, -2.0 * a, 1.0), np.inf)
    s_arc = np.where(t < t_stop, s_go, s_stop)                         # (N, K, T)
    G = path.shape[1]
    # a NaN or absurd speed (degenerate tracks) stays finite and indexable: past the path's end
    # the last segment is extended anyway
    u = np.clip(np.nan_to_num(s_arc / PATH_STEP, nan=0.0, posinf=1e12, neginf=0.0), 0.0, 1e12)
    i = np.minimum(np.floor(u).astype(np.int64), G - 2)
    f = (u - i)[..., None]
    rows = np.arange(len(path))[:, None, None]
    p0 = path[rows, i]
    p1 = path[rows, i + 1]
    return p0 + f * (p1 - p0)


def _history(tracks: Tracks, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The tracks' history (n, H, 3) float64 and its validity (n, H) bool as given, or empty
    ((n, 0, 3), (n, 0)) when the history does not have one row per track."""
    hist = np.asarray(tracks.history, np.float64)
    hv = np.asarray(tracks.history_valid, bool)
    if hist.ndim != 3 or hist.shape[0] != n:
        return np.zeros((n, 0, 3)), np.zeros((n, 0), bool)
    return hist, hv


def _track_arrays(tracks: Tracks, n: int):
    """The track arrays as the kernels take them: boxes (n, 5), velocities (n, 2), history
    (n, H, 3) float64 and its validity (n, H) bool, C-contiguous, and misses (n,) float64."""
    boxes = np.ascontiguousarray(np.asarray(tracks.boxes, np.float64).reshape(n, 5))
    vel = np.ascontiguousarray(np.asarray(tracks.velocities, np.float64).reshape(n, 2))
    hist, hv = _history(tracks, n)
    H = hist.shape[1]
    if hist.shape[2] != 3 or hv.shape != (n, H):  # what Tracks never holds; broadcast as sanitize_tracks does
        hist = np.broadcast_to(hist, (n, H, 3))
        hv = np.broadcast_to(hv, (n, H))
    hist = np.ascontiguousarray(hist)
    hv = np.ascontiguousarray(hv)
    misses = np.asarray(tracks.misses, np.float64).reshape(n)
    return boxes, vel, hist, hv, misses


_TIMES: dict[tuple[int, float], np.ndarray] = {}


def _times(steps: int, dt: float) -> np.ndarray:
    """(steps,) prediction times ``dt .. steps * dt`` (computed once per (steps, dt))."""
    key = (int(steps), float(dt))
    t = _TIMES.get(key)
    if t is None:
        t = np.arange(1, steps + 1) * dt
        t.flags.writeable = False
        _TIMES[key] = t
    return t


def _lane_arrays(index: LaneIndex) -> tuple:
    """The :class:`LaneIndex` arrays :func:`_features_kernel` reads."""
    return (True, index.seg_a, index.seg_u, index.seg_head, index.seg_len, index.seg_s, index.seg_w0, index.seg_w1,
            index.n_seg, index._lo, index._hi, index.length, index.left, index.right, index.limit, index.chain,
            index.chain_len, index.dead_end, index.ext_from, index.ext_dir, index.chain_step)


_NO_LANES = (False, np.zeros((0, 1, 2)), np.zeros((0, 1, 2)), np.zeros((0, 1)), np.zeros((0, 1)), np.zeros((0, 1)),
             np.zeros((0, 1)), np.zeros((0, 1)), np.zeros(0, np.int64), np.zeros((0, 1)), np.zeros((0, 1)),
             np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2, 2)),
             np.zeros(0), np.zeros(0, bool), np.zeros((0, 2)), np.zeros((0, 2)), CHAIN_STEP)


# numpy's semantics, written out for the kernels (see tests/test_predictor.py): what numpy's
# float -> int64 cast gives for NaN, for values >= 2**63 and for values < -2**63 on this machine
# (x86: the int64 minimum for all three; arm64 saturates)
with np.errstate(invalid="ignore"):
    _CAST = np.array([np.nan, np.inf, -np.inf]).astype(np.int64)
_TWO63 = 9.223372036854775808e18


@kernel
def _np_max(a: float, b: float) -> float:
    """``np.maximum(a, b)``: a NaN ``a`` wins, else the larger, else (ties, NaN ``b``) ``b``."""
    return a if (a > b or a != a) else b


@kernel
def _np_clip(x: float, lo: float, hi: float) -> float:
    """``np.clip(x, lo, hi)`` (numpy's ``_NPY_CLIP``: a NaN ``x`` stays NaN)."""
    if x != x:
        return x
    m = x if x > lo else lo
    return m if m < hi else hi


@kernel
def _np_wrap(a: float) -> float:
    """``geometry.angles.wrap_angle``: ``(a + pi) % (2 pi) - pi`` with numpy's float remainder."""
    x = a + np.pi
    b = 2 * np.pi
    mod = np.fmod(x, b)
    if mod != 0.0:
        if (b < 0) != (mod < 0):
            mod += b
    else:
        mod = math.copysign(0.0, b)
    return mod - np.pi


@kernel
def _floor_index(u: float, hi: int, cast: np.ndarray) -> int:
    """``np.clip(np.floor(u).astype(np.int64), 0, hi)``, a NaN or out-of-range float cast as
    numpy casts it (``cast``: ``_CAST``)."""
    fl = np.floor(u)
    if fl != fl:
        i = cast[0]
    elif fl >= _TWO63:
        i = cast[1]
    elif fl < -_TWO63:
        i = cast[2]
    else:
        i = np.int64(fl)
    return min(max(i, 0), hi)


@kernel
def _f32(x: float) -> np.float32:
    """``np.nan_to_num(x, nan=0, posinf=0, neginf=0).astype(np.float32)``."""
    return np.float32(x) if np.isfinite(x) else np.float32(0.0)


@kernel
def _sanitize_kernel(boxes_in, vel_in, hist_in, hv_in):
    """:func:`sanitize_tracks` on the arrays of :func:`_track_arrays`, plus the history's yaw
    relative to the box (n, HISTORY) and the pairwise offsets ``rel[i, j] = xy_j - xy_i``."""
    n = boxes_in.shape[0]
    H = hist_in.shape[1]
    k = min(H, HISTORY)
    boxes = np.empty((n, 5))
    vel = np.empty((n, 2))
    hist = np.zeros((n, HISTORY, 3))
    hv = np.zeros((n, HISTORY), np.bool_)
    ok = np.empty(n, np.bool_)
    dyaw = np.empty((n, HISTORY))
    rel = np.empty((n, n, 2))
    for i in range(n):
        good = True
        for j in range(5):
            if not np.isfinite(boxes_in[i, j]):
                good = False
        ok[i] = good
        for j in range(5):
            boxes[i, j] = boxes_in[i, j] if good else 0.0
        for j in range(2):
            v = vel_in[i, j]
            vel[i, j] = v if np.isfinite(v) else 0.0
        for h in range(k):
            src = H - k + h
            dst = HISTORY - k + h
            if hv_in[i, src] and np.isfinite(hist_in[i, src, 0]) and np.isfinite(hist_in[i, src, 1]) \
                    and np.isfinite(hist_in[i, src, 2]):
                hv[i, dst] = True
                for j in range(3):
                    hist[i, dst, j] = hist_in[i, src, j]
        for h in range(HISTORY):
            dyaw[i, h] = hist[i, h, 2] - boxes[i, 4]
    for i in range(n):
        for j in range(n):
            rel[i, j, 0] = boxes[j, 0] - boxes[i, 0]
            rel[i, j, 1] = boxes[j, 1] - boxes[i, 1]
    return boxes, vel, hist, hv, ok, dyaw, rel


@kernel
def _chain_point(chain, chain_len, dead_end, ext_from, ext_dir, step, cast, r, sv):
    """``LaneIndex.sample`` of one point: chain ``r`` at arc length ``sv`` -> x, y, and whether
    it lies past a dead end."""
    u = sv / step
    i = _floor_index(u, chain.shape[1] - 2, cast)
    f = u - i
    ax = chain[r, i, 0]
    ay = chain[r, i, 1]
    px = ax + f * (chain[r, i + 1, 0] - ax)
    py = ay + f * (chain[r, i + 1, 1] - ay)
    clen = chain_len[r]
    past = sv > clen
    if past:
        px = ext_from[r, 0] + (sv - clen) * ext_dir[r, 0]
        py = ext_from[r, 1] + (sv - clen) * ext_dir[r, 1]
    return px, py, past and dead_end[r]


@kernel
def _locate_one(x, y, yaw, seg_a, seg_u, seg_head, seg_len, seg_s, seg_w0, seg_w1, n_seg, seg_lo, seg_hi,
                length, ls, ld, lw):
    """``LaneIndex.locate`` of one pose: fills s, d, width on every lane (ls, ld, lw (L,)) and
    returns the lane row (-1: none)."""
    row = 0
    best_key = 0.0
    for l in range(len(n_seg)):
        # the nearest segment (np.argmin: the first NaN, else the first minimum; the padding
        # past a lane's n_seg segments, at infinity there, never is)
        kb = 0
        d2b = 0.0
        for k in range(n_seg[l]):
            rx = x - seg_a[l, k, 0]
            ry = y - seg_a[l, k, 1]
            t = rx * seg_u[l, k, 0] + ry * seg_u[l, k, 1]
            tc = _np_clip(t, seg_lo[l, k], seg_hi[l, k])
            d2 = rx * rx + ry * ry + tc * (tc - 2.0 * t)
            if k == 0 or (d2b == d2b and (d2 < d2b or d2 != d2)):
                kb = k
                d2b = d2
        rx = x - seg_a[l, kb, 0]
        ry = y - seg_a[l, kb, 1]
        t = rx * seg_u[l, kb, 0] + ry * seg_u[l, kb, 1]
        tb = _np_clip(t, seg_lo[l, kb], seg_hi[l, kb])
        s = seg_s[l, kb] + tb
        d = seg_u[l, kb, 0] * ry - seg_u[l, kb, 1] * rx
        frac = _np_clip(tb / _np_max(seg_len[l, kb], 1e-9), 0.0, 1.0)
        w = seg_w0[l, kb] * (1 - frac) + seg_w1[l, kb] * frac
        beyond = _np_max(_np_max(-s, s - length[l]), 0.0)
        herr = abs(_np_wrap(yaw - seg_head[l, kb]))
        inside = (abs(d) <= 0.5 * w) and (beyond == 0.0)
        key = (0.0 if inside else 1e6) + abs(d) + beyond
        if not herr <= np.pi / 2:
            key = np.inf
        ls[l] = s
        ld[l] = d
        lw[l] = w
        if l == 0 or (best_key == best_key and (key < best_key or key != key)):
            row = l
            best_key = key
    return row if np.isfinite(best_key) else -1


@kernel
def _features_kernel(boxes, vel, hist, hv, ok, c, s, cd, sd, speed, dist, rel, misses, times, offsets,
                     has_lanes, seg_a, seg_u, seg_head, seg_len, seg_s, seg_w0, seg_w1, n_seg, seg_lo, seg_hi,
                     length, left, right, limit, chain, chain_len, dead_end, ext_from, ext_dir, step, cast):
    """Everything of :func:`encode` after the numpy calls: features (n, NUM_FEATURES) and prior
    (n, T, 2), float32."""
    n = boxes.shape[0]
    T = times.shape[0]
    M = offsets.shape[0]
    L = n_seg.shape[0]
    feats = np.zeros((n, NUM_FEATURES), np.float32)
    prior = np.zeros((n, T, 2), np.float32)
    ls = np.zeros(max(L, 1))
    ld = np.zeros(max(L, 1))
    lw = np.zeros(max(L, 1))
    used = np.zeros(n, np.bool_)
    rows = np.zeros(3, np.int64)
    for i in range(n):
        f = feats[i]
        x0 = boxes[i, 0]
        y0 = boxes[i, 1]
        ci = c[i]
        si = s[i]
        # history (HISTORY x: x, y, cos, sin of the relative yaw, valid)
        nh = 0
        for h in range(HISTORY):
            if hv[i, h]:
                nh += 1
                dx = hist[i, h, 0] - x0
                dy = hist[i, h, 1] - y0
                f[5 * h] = _f32((ci * dx + si * dy) / 10.0)
                f[5 * h + 1] = _f32((-si * dx + ci * dy) / 10.0)
                f[5 * h + 2] = _f32(cd[i, h])
                f[5 * h + 3] = _f32(sd[i, h])
                f[5 * h + 4] = 1.0
        # agent
        o = _HIST_F
        vx = vel[i, 0]
        vy = vel[i, 1]
        f[o] = _f32((ci * vx + si * vy) / 10.0)
        f[o + 1] = _f32((-si * vx + ci * vy) / 10.0)
        f[o + 2] = _f32(speed[i] / 10.0)
        f[o + 3] = _f32(boxes[i, 2] / 10.0)
        f[o + 4] = _f32(boxes[i, 3] / 2.0)
        f[o + 5] = _f32(_np_clip(misses[i], 0.0, 10.0) / 3.0)
        f[o + 6] = _f32(nh / HISTORY)
        f[o + 7] = 1.0 if ok[i] else 0.0
        speed_h = _np_max(vx * ci + vy * si, 0.0)
        # lanes: the agent's, its left and right neighbours
        row = -1
        if has_lanes:
            row = _locate_one(x0, y0, boxes[i, 4], seg_a, seg_u, seg_head, seg_len, seg_s, seg_w0, seg_w1, n_seg,
                              seg_lo, seg_hi, length, ls, ld, lw)
            if not ok[i]:
                row = -1
            rows[0] = row
            rows[1] = left[row] if row >= 0 else -1
            rows[2] = right[row] if row >= 0 else -1
            for j in range(3):
                o = _HIST_F + _AGENT_F + j * _LANE_F
                rj = rows[j]
                has = rj >= 0
                r = max(rj, 0)
                f[o] = 1.0 if has else 0.0
                for m in range(M):
                    px, py, dead = _chain_point(chain, chain_len, dead_end, ext_from, ext_dir, step, cast, r,
                                                ls[r] + offsets[m])
                    if has and not dead:
                        dx = px - x0
                        dy = py - y0
                        f[o + 1 + 3 * m] = _f32((ci * dx + si * dy) / 50.0)
                        f[o + 2 + 3 * m] = _f32((-si * dx + ci * dy) / 10.0)
                        f[o + 3 + 3 * m] = 1.0
                if has:
                    f[o + _LANE_F - 3] = _f32(lw[r] / 4.0)
                    f[o + _LANE_F - 2] = _f32(_np_clip(ld[r], -20.0, 20.0) / 4.0)
                    f[o + _LANE_F - 1] = _f32(limit[r] / 30.0)
        # prior: along the lane chain when on (or near) the lane strip, else straight ahead
        if ok[i]:
            r = max(row, 0)
            d0 = ld[r]
            if row >= 0 and abs(d0) - 0.5 * lw[r] <= OFF_LANE:
                for k in range(T):
                    st = ls[r] + speed_h * times[k]
                    p0x, p0y, _ = _chain_point(chain, chain_len, dead_end, ext_from, ext_dir, step, cast, row, st)
                    p1x, p1y, _ = _chain_point(chain, chain_len, dead_end, ext_from, ext_dir, step, cast, row, st + 1.0)
                    tx = p1x - p0x
                    ty = p1y - p0y
                    nrm = _np_max(math.sqrt(tx * tx + ty * ty), 1e-9)
                    tx /= nrm
                    ty /= nrm
                    dx = (p0x + d0 * -ty) - x0
                    dy = (p0y + d0 * tx) - y0
                    px = ci * dx + si * dy
                    py = -si * dx + ci * dy
                    prior[i, k, 0] = 0.0 if px != px else np.float32(px)
                    prior[i, k, 1] = 0.0 if py != py else np.float32(py)
            else:
                for k in range(T):
                    px = speed_h * times[k]
                    prior[i, k, 0] = 0.0 if px != px else np.float32(px)
        # the nearest other tracks (np.argsort(kind="stable"): by distance, NaN last, then index)
        if n > 1:
            used[:] = False
            for q in range(min(NEIGHBOURS, n - 1)):
                jb = -1
                db = 0.0
                for j in range(n):
                    if used[j]:
                        continue
                    dj = dist[i, j]
                    if not (ok[i] and ok[j]) or i == j or dj > NEIGHBOUR_RANGE:
                        dj = np.inf
                    if jb < 0 or dj < db or (db != db and dj == dj):
                        jb = j
                        db = dj
                used[jb] = True
                if np.isfinite(db):
                    o = _HIST_F + _AGENT_F + 3 * _LANE_F + 5 * q
                    rx = rel[i, jb, 0]
                    ry = rel[i, jb, 1]
                    f[o] = _f32((ci * rx + si * ry) / 50.0)
                    f[o + 1] = _f32((-si * rx + ci * ry) / 10.0)
                    dvx = vel[jb, 0] - vel[i, 0]
                    dvy = vel[jb, 1] - vel[i, 1]
                    f[o + 2] = _f32((ci * dvx + si * dvy) / 10.0)
                    f[o + 3] = _f32((-si * dvx + ci * dvy) / 10.0)
                    f[o + 4] = 1.0
    return feats, prior


def no_reversing(local: np.ndarray) -> np.ndarray:
    """Agent-frame trajectories (N, K, T, 2) with the forward coordinate made non-decreasing and
    >= 0 (a running maximum): highway vehicles do not reverse. The network's residuals could
    move a slow or standing vehicle backwards by metres (seen on NGSIM US-101 stop-and-go,
    docs/autonomy.md), which the planner took for a car rolling back into the ego."""
    out = np.array(local, dtype=np.float64, copy=True)
    out[..., 0] = np.maximum.accumulate(np.maximum(out[..., 0], 0.0), axis=-1)
    return out


def to_map_frame(local: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Agent-frame positions (N, K, T, 2) -> map frame with the boxes' (N, 5) pose."""
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    c = c[:, None, None]
    s = s[:, None, None]
    x = c * local[..., 0] - s * local[..., 1] + boxes[:, 0, None, None]
    y = s * local[..., 0] + c * local[..., 1] + boxes[:, 1, None, None]
    return np.stack([x, y], axis=-1)


@kernel
def _map_frame_kernel(local, boxes, ok, c, s):
    """``to_map_frame(no_reversing(local), boxes)`` of the network's float32 (N, K, T, 2)
    output, rows of boxes that are not finite (``ok`` False) NaN: what :meth:`LearnedPredictor.predict`
    returns, in one pass. ``c``, ``s``: cos, sin of the boxes' yaw."""
    N, K, T, _ = local.shape
    out = np.empty((N, K, T, 2))
    for i in range(N):
        if not ok[i]:
            out[i] = np.nan
            continue
        x0 = boxes[i, 0]
        y0 = boxes[i, 1]
        ci = c[i]
        si = s[i]
        for k in range(K):
            acc = 0.0
            for t in range(T):
                x = _np_max(np.float64(local[i, k, t, 0]), 0.0)
                acc = x if t == 0 else _np_max(acc, x)
                y = np.float64(local[i, k, t, 1])
                out[i, k, t, 0] = ci * acc - si * y + x0
                out[i, k, t, 1] = si * acc + ci * y + y0
    return out


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
    # anchored models (empty for the prior-based ones): mode k's anchor follows the lane path at
    # max(anchor_scales[k] * speed + anchor_accels[k] * t, 0) m/s (anchor_trajectories)
    anchor_scales: tuple[float, ...] = ()
    anchor_accels: tuple[float, ...] = ()

    @property
    def anchored(self) -> bool:
        """The residuals refine one lane-following anchor per mode instead of the one prior."""
        return len(self.anchor_scales) > 0


def build_net(config: PredictorConfig):
    """The torch module for ``config`` (imports torch lazily)."""
    import torch
    from torch import nn

    class PredictorNet(nn.Module):
        """features (B, F) + prior (B, T, 2) or anchors (B, K, T, 2) -> trajectories (B, K, T, 2)
        m in the agent frame (prior or anchors + residuals), mode logits (B, K)."""

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
            if cfg.anchored:  # untrained, it predicts the anchors themselves
                nn.init.zeros_(self.traj.weight)
                nn.init.zeros_(self.traj.bias)

        def forward(self, feats, prior):
            h = self.body(feats)
            B = feats.shape[0]
            res = self.traj(h).view(B, self.cfg.num_modes, self.cfg.steps, 2) * self.cfg.residual_scale
            base = prior if prior.dim() == 4 else prior[:, None]
            return base + res, self.logits(h)

    return PredictorNet(config)


class LearnedPredictor:
    """Tracks -> multi-modal predictions with a trained :class:`PredictorNet`, on the lane map
    given to :meth:`reset`.

    Args:
        net: the torch module; config: its :class:`PredictorConfig`.
        threads: torch intra-op threads for inference (1: the episode loop is single-core).
    """

    def __init__(self, net, config: PredictorConfig, threads: int | None = 1):
        import torch

        self.net = net.eval()
        self.config = config
        self.threads = threads
        self.lane_map: LaneMap | None = None
        self._torch = torch
        self._plan_net = None
        self._plan = None

    @property
    def num_modes(self) -> int:
        return self.config.num_modes

    def reset(self, lane_map: LaneMap) -> None:
        """Predict on ``lane_map`` until the next reset."""
        self.lane_map = lane_map

    def base(self, feats: np.ndarray, prior: np.ndarray, path: np.ndarray | None = None) -> np.ndarray:
        """What the residuals are added to: the prior (N, T, 2), or for an anchored model the
        anchors (N, K, T, 2) float32 from the lane paths ``path`` (N, G, 2) and the features."""
        if not self.config.anchored:
            return prior
        if path is None:
            raise ValueError("an anchored predictor needs the tracks' lane paths (predictor.lane_paths)")
        cfg = self.config
        return anchor_trajectories(path, anchor_speed(feats), cfg.anchor_scales, cfg.anchor_accels, cfg.steps,
                                   cfg.dt).astype(np.float32)

    def predict_local(self, feats: np.ndarray, prior: np.ndarray,
                      path: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Network on precomputed features (N, F) and priors (N, T, 2) (an anchored model: and
        lane paths (N, G, 2)) -> agent-frame trajectories (N, K, T, 2) float64 and
        probabilities (N, K)."""
        torch = self._torch
        if self.threads:
            torch.set_num_threads(self.threads)
        base = self.base(feats, prior, path)
        with torch.inference_mode():
            traj, logits = self.net(torch.from_numpy(np.ascontiguousarray(feats, np.float32)),
                                    torch.from_numpy(np.ascontiguousarray(base, np.float32)))
            probs = torch.softmax(logits, dim=-1)
        return traj.numpy().astype(np.float64), probs.numpy().astype(np.float64)

    def _functional(self):
        """``self.net``'s forward as functional torch calls: the very ops its modules call (so the
        same bits) without the module-call overhead (~30 us per frame). None when the net is not
        a plain :func:`build_net` network; built once per net object. The plan also holds the
        hook tables that ``Module.__call__`` consults (the modules' own and torch's global ones),
        and :meth:`_forward` calls the module whenever any hook is registered."""
        net = self.net
        if self._plan_net is net:
            return self._plan
        from torch import nn
        from torch.nn.modules import module as torch_module

        plan = None
        body = list(getattr(net, "body", ()))
        mods = list(net.modules())
        if (type(net).__qualname__ == "build_net.<locals>.PredictorNet" and type(net).__module__ == __name__
                and len(body) % 3 == 0
                and all(type(a) is nn.Linear and type(b) is nn.LayerNorm and type(r) is nn.ReLU
                        for a, b, r in zip(body[0::3], body[1::3], body[2::3]))
                and type(net.traj) is nn.Linear and type(net.logits) is nn.Linear
                and all(type(m) in (nn.Linear, nn.LayerNorm, nn.ReLU) or m is net or m is net.body for m in mods)):
            try:
                hooks = [getattr(torch_module, name) for name in (
                    "_global_backward_pre_hooks", "_global_backward_hooks", "_global_forward_pre_hooks",
                    "_global_forward_hooks")]
                hooks += [getattr(m, name) for m in mods for name in (
                    "_backward_hooks", "_backward_pre_hooks", "_forward_hooks", "_forward_pre_hooks")]
            except AttributeError:  # another torch: call the module
                hooks = None
            if hooks is not None:
                layers = [(a.weight, a.bias, tuple(b.normalized_shape), b.weight, b.bias, b.eps)
                          for a, b in zip(body[0::3], body[1::3])]
                plan = (hooks, layers, net.traj.weight, net.traj.bias, net.logits.weight, net.logits.bias,
                        net.cfg.num_modes, net.cfg.steps, net.cfg.residual_scale)
        self._plan_net, self._plan = net, plan
        return plan

    def _forward(self, feats: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The network on float32 features and prior -> agent-frame trajectories (N, K, T, 2)
        and probabilities (N, K), float32 (:meth:`predict_local` before its float64 copies)."""
        torch = self._torch
        if self.threads:
            torch.set_num_threads(self.threads)
        plan = self._functional()
        with torch.inference_mode():
            x = torch.from_numpy(feats)
            p = torch.from_numpy(prior)
            if plan is None or any(plan[0]):
                traj, logits = self.net(x, p)
            else:
                F = torch.nn.functional
                _, layers, tw, tb, lw, lb, K, T, scale = plan
                h = x
                for w, b, shape, nw, nb, eps in layers:
                    h = torch.relu(F.layer_norm(F.linear(h, w, b), shape, nw, nb, eps))
                traj = (p if p.dim() == 4 else p[:, None]) + F.linear(h, tw, tb).view(x.shape[0], K, T, 2) * scale
                logits = F.linear(h, lw, lb)
            probs = torch.softmax(logits, dim=-1)
        return traj.numpy(), probs.numpy()

    def predict(self, tracks: Tracks) -> Predictions:
        """(N,) tracks -> Predictions (N, K, 60, 2) in the map frame, rows of probabilities
        summing to 1. All tracks go through the network in one batch."""
        if self.lane_map is None:
            raise RuntimeError("LearnedPredictor.reset(lane_map) must be called before predict")
        n = len(tracks)
        K, T = self.config.num_modes, self.config.steps
        if n == 0:
            return Predictions(np.zeros(0, np.int64), np.zeros((0, K, T, 2)), np.zeros((0, K)), self.config.dt)
        if self.config.anchored:
            feats, prior, boxes, ok, c, s, path = _encode(tracks, self.lane_map, T, self.config.dt, with_path=True)
            prior = self.base(feats, prior, path)
        else:
            feats, prior, boxes, ok, c, s = _encode(tracks, self.lane_map, T, self.config.dt)
        local, probs = self._forward(feats, prior)
        # no_reversing, then to_map_frame; a track without a (finite) pose has nothing sensible
        # to predict: its rows are kept but NaN
        traj = _map_frame_kernel(local, boxes, ok, c, s)
        probs = probs.astype(np.float64)
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
    cfg_doc = asdict(config)
    if not config.anchored:  # a prior-based model's file stays readable by version-1 readers
        del cfg_doc["anchor_scales"], cfg_doc["anchor_accels"]
    doc = {"format": MODEL_FORMAT, "version": ANCHORED_VERSION if config.anchored else MODEL_VERSION, "config": cfg_doc,
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
    path = Path(path)
    cfg_path = path / CONFIG_NAME
    if not cfg_path.is_file():
        raise FileFormatError(str(cfg_path), "$", "a predictor config.json (train one with `adv3d train predictor`)", "no file")
    doc = Node.load(cfg_path)
    version = check_header(doc, MODEL_FORMAT, (MODEL_VERSION, ANCHORED_VERSION))
    raw = doc["config"]
    raw.object()
    raw.check_keys(PredictorConfig.__dataclass_fields__ if version == ANCHORED_VERSION else
                   [k for k in PredictorConfig.__dataclass_fields__ if not k.startswith("anchor_")])
    dflt = PredictorConfig()
    num_modes = raw.get("num_modes", dflt.num_modes).integer(lo=1, hi=64)
    scales: tuple[float, ...] = ()
    accels: tuple[float, ...] = ()
    if version == ANCHORED_VERSION:
        sc, ac = raw["anchor_scales"], raw["anchor_accels"]
        scales = tuple(float(v) for v in sc.numbers())
        accels = tuple(float(v) for v in ac.numbers())
        if len(scales) != num_modes or not all(0.0 <= v <= 10.0 for v in scales):
            sc.fail(f"{num_modes} speed scales in [0, 10] (one per mode)", list(scales))
        if len(accels) != num_modes or not all(abs(v) <= 20.0 for v in accels):
            ac.fail(f"{num_modes} accelerations in [-20, 20] m/s^2 (one per mode)", list(accels))
    config = PredictorConfig(
        num_features=raw.get("num_features", dflt.num_features).integer(lo=NUM_FEATURES, hi=NUM_FEATURES),
        num_modes=num_modes,
        steps=raw.get("steps", dflt.steps).integer(lo=1, hi=1000),
        hidden=raw.get("hidden", dflt.hidden).integer(lo=1, hi=8192),
        layers=raw.get("layers", dflt.layers).integer(lo=1, hi=64),
        residual_scale=raw.get("residual_scale", dflt.residual_scale).number(lo=0.0, lo_open=True, hi=1000.0),
        dt=raw.get("dt", dflt.dt).number(lo=0.0, lo_open=True, hi=10.0),
        anchor_scales=scales, anchor_accels=accels)
    feats = doc.get("features", {})
    feats.object()
    offsets = feats.get("lane_offsets_m", LANE_OFFSETS.tolist()).numbers()
    if offsets.tolist() != LANE_OFFSETS.tolist():
        feats["lane_offsets_m"].fail(f"the lane offsets of this code version {LANE_OFFSETS.tolist()}", offsets.tolist())
    feats.get("history", HISTORY).integer(lo=HISTORY, hi=HISTORY, expected=f"{HISTORY} (this code's history)")
    from .detector import load_weights

    w_path = doc.get("weights", WEIGHTS_NAME).file_in(path, inside="the model folder")
    state = load_weights(w_path, "predictor weights")
    net = build_net(config)
    try:
        net.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as exc:
        raise FileFormatError(str(w_path), "$", f"weights matching {config}", str(exc)) from exc
    return LearnedPredictor(net, config, threads=threads)
