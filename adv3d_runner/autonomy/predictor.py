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
:class:`~adv3d_runner.scene.lanemap.LaneMap`), so a frame with 20 tracks costs
about 2-3 ms on one core (features ~1.3 ms, network ~0.3 ms). Tracks with short or invalid history, non-finite states,
and frames with no lanes are handled (their features are zero with validity flags 0).

Weights are a plain ``state_dict`` (``torch.load(weights_only=True)``) next to a
``config.json``; nothing is pickled.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import FileFormatError
from ..fileio import REPO_ROOT
from ..scene.lanemap import LaneIndex, LaneMap
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
DEFAULT_SPEED_LIMIT = 29.0                            # m/s when a lane has none (feature "limit")
OFF_LANE = 1.0                                        # m outside a lane strip still lane-bound (prior)

# feature block sizes (kept in one place so the layout is documented and checked)
_HIST_F = HISTORY * 5
_AGENT_F = 8
_LANE_F = 1 + 3 * len(LANE_OFFSETS) + 3               # exists, (x, y, valid) per point, width, d, limit
_NEIGH_F = NEIGHBOURS * 5
NUM_FEATURES = _HIST_F + _AGENT_F + 3 * _LANE_F + _NEIGH_F


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
    if len(lane_map):
        index = lane_index(lane_map)
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


def no_reversing(local: np.ndarray) -> np.ndarray:
    """Agent-frame trajectories (N, K, T, 2) with the forward coordinate made non-decreasing and
    >= 0 (a running maximum): highway vehicles do not reverse. The network's residuals could
    move a slow or standing vehicle backwards by metres (seen on NGSIM US-101 stop-and-go,
    issue 17), which the planner took for a car rolling back into the ego."""
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

    @property
    def num_modes(self) -> int:
        return self.config.num_modes

    def reset(self, lane_map: LaneMap) -> None:
        """Predict on ``lane_map`` until the next reset."""
        self.lane_map = lane_map

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

    def predict(self, tracks: Tracks) -> Predictions:
        """(N,) tracks -> Predictions (N, K, 60, 2) in the map frame, rows of probabilities
        summing to 1. All tracks go through the network in one batch."""
        if self.lane_map is None:
            raise RuntimeError("LearnedPredictor.reset(lane_map) must be called before predict")
        n = len(tracks)
        K, T = self.config.num_modes, self.config.steps
        if n == 0:
            return Predictions(np.zeros(0, np.int64), np.zeros((0, K, T, 2)), np.zeros((0, K)), self.config.dt)
        feats, prior = encode(tracks, self.lane_map, T, self.config.dt)
        local, probs = self.predict_local(feats, prior)
        local = no_reversing(local)
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
    path = Path(path)
    cfg_path = path / CONFIG_NAME
    if not cfg_path.is_file():
        raise FileFormatError(str(cfg_path), "$", "a predictor config.json (train one with `adv3d train predictor`)", "no file")
    doc = Node.load(cfg_path)
    check_header(doc, MODEL_FORMAT, (MODEL_VERSION,))
    raw = doc["config"]
    raw.object()
    raw.check_keys(PredictorConfig.__dataclass_fields__)
    dflt = PredictorConfig()
    config = PredictorConfig(
        num_features=raw.get("num_features", dflt.num_features).integer(lo=NUM_FEATURES, hi=NUM_FEATURES),
        num_modes=raw.get("num_modes", dflt.num_modes).integer(lo=1, hi=64),
        steps=raw.get("steps", dflt.steps).integer(lo=1, hi=1000),
        hidden=raw.get("hidden", dflt.hidden).integer(lo=1, hi=8192),
        layers=raw.get("layers", dflt.layers).integer(lo=1, hi=64),
        residual_scale=raw.get("residual_scale", dflt.residual_scale).number(lo=0.0, lo_open=True, hi=1000.0),
        dt=raw.get("dt", dflt.dt).number(lo=0.0, lo_open=True, hi=10.0))
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
