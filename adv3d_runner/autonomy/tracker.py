"""Multi-object tracker over BEV detections (map frame).

Each track has a constant-velocity Kalman filter on the centre ``(x, y, vx, vy)``; box size
and yaw are smoothed separately (exponential averages; yaw on the circle). Per frame:

1. every track predicts ``dt`` ahead;
2. detections are associated to tracks by the Hungarian algorithm
   (``scipy.optimize.linear_sum_assignment``) on the centre distance to the predicted position,
   gated twice: the distance must be below ``max_distance`` m and the squared Mahalanobis
   distance under the innovation covariance below ``gate_chi2`` (a new track with unknown speed
   has a wide gate; a settled one a tight gate, which keeps identities when objects cross);
3. matched tracks update; unmatched tracks count a miss and coast on their prediction;
   unmatched detections above ``min_score`` start tentative tracks;
4. a tentative track is confirmed after ``min_hits`` matched frames and deleted if it misses
   before that; a confirmed track is deleted after more than ``max_misses`` consecutive misses.

Confirmed tracks (including coasting ones, flagged by ``misses > 0``) are output with a fixed
length history of their filtered states for the predictor. The tracker is deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry.angles import wrap_angle
from .interface import DT, Detections, Tracks


def _load_linear_sum_assignment():
    """``scipy.optimize.linear_sum_assignment``, loaded from its own extension module.

    ``scipy.optimize`` re-exports this C function from ``scipy/optimize/_lsap*.so``; importing
    the package costs ~0.26 CPU-s of linear-programming and FFT modules every process (the
    tracker's share of ``adv3d simulate``'s start-up, docs/performance.md), loading the one
    extension 1.5 ms. The same function object, so the same assignments; if the layout of
    scipy changes, the package import is the fallback."""
    import importlib.machinery
    import importlib.util

    try:
        spec = importlib.util.find_spec("scipy")
        folder = next(iter(spec.submodule_search_locations)) if spec and spec.submodule_search_locations else None
        for suffix in importlib.machinery.EXTENSION_SUFFIXES if folder else ():
            path = f"{folder}/optimize/_lsap{suffix}"
            try:
                loader = importlib.machinery.ExtensionFileLoader("scipy.optimize._lsap", path)
                ext_spec = importlib.util.spec_from_loader("scipy.optimize._lsap", loader, origin=path)
                module = importlib.util.module_from_spec(ext_spec)
                loader.exec_module(module)
            except (ImportError, OSError):
                continue
            fn = getattr(module, "linear_sum_assignment", None)
            if callable(fn):
                return fn
    except (ImportError, ValueError, StopIteration):
        pass
    from scipy.optimize import linear_sum_assignment

    return linear_sum_assignment


linear_sum_assignment = _load_linear_sum_assignment()


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker parameters (units: m, s, m/s, m/s^2).

    Attributes:
        min_hits: matched frames (including the first) before a track is confirmed.
        max_misses: consecutive missed frames after which a confirmed track dies.
        max_distance: hard association gate on centre distance, m.
        gate_chi2: gate on the squared Mahalanobis distance (2 dof; 13.8 = 99.9 %).
        min_score: detections below this confidence never start a track.
        pos_std: measurement noise of a detected centre, m.
        accel_std: process noise (white acceleration), m/s^2.
        init_speed_std: prior speed uncertainty of a new track, m/s.
        size_alpha, yaw_alpha: smoothing factors (weight of the new measurement).
        history: number of frames kept in the output history (10 = 1 s).
    """

    min_hits: int = 2
    max_misses: int = 3
    max_distance: float = 8.0
    gate_chi2: float = 13.8
    min_score: float = 0.0
    pos_std: float = 0.3
    accel_std: float = 2.0
    init_speed_std: float = 15.0
    size_alpha: float = 0.3
    yaw_alpha: float = 0.5
    history: int = 10


@dataclass
class _Track:
    id: int
    x: np.ndarray  # (4,) x, y, vx, vy
    P: np.ndarray  # (4, 4)
    length: float
    width: float
    yaw: float
    score: float
    hits: int = 1
    misses: int = 0
    confirmed: bool = False
    history: list = field(default_factory=list)  # list of (x, y, yaw)


def _wrap(a: float) -> float:
    return float(wrap_angle(a))


class MultiObjectTracker:
    """Constant-velocity Kalman tracker with Hungarian association (see module docstring)."""

    def __init__(self, config: TrackerConfig = TrackerConfig(), dt: float = DT):
        self.config = config
        self.dt = dt
        c = config
        self._F = np.eye(4)
        self._F[0, 2] = self._F[1, 3] = dt
        # discrete white-noise acceleration model
        q = np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]]) * c.accel_std ** 2
        self._Q = np.zeros((4, 4))
        self._Q[np.ix_([0, 2], [0, 2])] = q
        self._Q[np.ix_([1, 3], [1, 3])] = q
        self._H = np.eye(2, 4)
        self._R = np.eye(2) * c.pos_std ** 2
        self.reset()

    def reset(self) -> None:
        """Drop every track; ids restart at 0."""
        self._tracks: list[_Track] = []
        self._next_id = 0
        self.frame = 0

    # ------------------------------------------------------------------ one frame
    def update(self, detections: Detections, prior_speed: float | None = None) -> Tracks:
        """Advance one frame with this frame's detections (may be empty); returns confirmed tracks.

        ``prior_speed`` (m/s): new tracks start moving at this speed along their detected yaw
        instead of standing still (still with ``init_speed_std`` uncertainty). On a highway the
        ego's own speed is a good prior: without it, vehicles seen for the first time look
        parked for a few frames and a planner downstream brakes for them.
        """
        c = self.config
        boxes = np.asarray(detections.boxes, dtype=np.float64).reshape(-1, 5)
        scores = np.asarray(detections.scores, dtype=np.float64).reshape(-1)
        ok = np.all(np.isfinite(boxes), axis=1) & np.isfinite(scores)  # garbage in is dropped
        boxes, scores = boxes[ok], scores[ok]

        for t in self._tracks:
            t.x = self._F @ t.x
            t.P = self._F @ t.P @ self._F.T + self._Q

        rows, cols = self._associate(boxes)
        matched_tracks = set(rows.tolist())
        matched_dets = set(cols.tolist())
        for r, k in zip(rows, cols):
            self._correct(self._tracks[r], boxes[k], scores[k])
        for i, t in enumerate(self._tracks):
            if i not in matched_tracks:
                t.misses += 1
        # deaths: tentative tracks die on their first miss, confirmed ones after max_misses
        self._tracks = [t for t in self._tracks
                        if (t.confirmed and t.misses <= c.max_misses) or (not t.confirmed and t.misses == 0)]
        for k in range(len(boxes)):
            if k not in matched_dets and scores[k] >= c.min_score:
                self._birth(boxes[k], scores[k], prior_speed)
        for t in self._tracks:
            if t.hits >= c.min_hits:
                t.confirmed = True
            t.history.append((t.x[0], t.x[1], t.yaw))
            del t.history[:-c.history]
        self.frame += 1
        return self.tracks()

    def _associate(self, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        if not self._tracks or len(boxes) == 0:
            return np.zeros(0, int), np.zeros(0, int)
        pred = np.array([t.x[:2] for t in self._tracks])  # (T, 2)
        diff = boxes[None, :, :2] - pred[:, None, :]  # (T, D, 2)
        dist = np.linalg.norm(diff, axis=-1)
        S = np.array([self._H @ t.P @ self._H.T + self._R for t in self._tracks])  # (T, 2, 2)
        Sinv = np.linalg.inv(S)
        maha = np.einsum("tdi,tij,tdj->td", diff, Sinv, diff)
        allowed = (dist <= c.max_distance) & (maha <= c.gate_chi2)
        big = 1e6
        cost = np.where(allowed, dist, big)
        r, k = linear_sum_assignment(cost)
        keep = allowed[r, k]
        return r[keep], k[keep]

    def _correct(self, t: _Track, box: np.ndarray, score: float) -> None:
        c = self.config
        z = box[:2]
        S = self._H @ t.P @ self._H.T + self._R
        K = t.P @ self._H.T @ np.linalg.inv(S)
        t.x = t.x + K @ (z - self._H @ t.x)
        t.P = (np.eye(4) - K @ self._H) @ t.P
        t.P = 0.5 * (t.P + t.P.T)  # keep symmetric against rounding
        t.length += c.size_alpha * (max(box[2], 0.0) - t.length)
        t.width += c.size_alpha * (max(box[3], 0.0) - t.width)
        t.yaw = _wrap(t.yaw + c.yaw_alpha * _wrap(box[4] - t.yaw))
        t.score = float(score)
        t.hits += 1
        t.misses = 0

    def _birth(self, box: np.ndarray, score: float, prior_speed: float | None = None) -> None:
        c = self.config
        P = np.diag([c.pos_std ** 2, c.pos_std ** 2, c.init_speed_std ** 2, c.init_speed_std ** 2])
        v = 0.0 if prior_speed is None or not np.isfinite(prior_speed) else float(prior_speed)
        x0 = np.array([box[0], box[1], v * np.cos(box[4]), v * np.sin(box[4])])
        t = _Track(self._next_id, x0, P, max(box[2], 0.0), max(box[3], 0.0), _wrap(box[4]), float(score))
        self._next_id += 1
        self._tracks.append(t)

    # ------------------------------------------------------------------ output
    def tracks(self) -> Tracks:
        """The confirmed tracks now (coasting ones included, ``misses > 0``)."""
        H = self.config.history
        out = [t for t in self._tracks if t.confirmed]
        n = len(out)
        hist = np.zeros((n, H, 3))
        hval = np.zeros((n, H), bool)
        for i, t in enumerate(out):
            h = np.asarray(t.history, dtype=np.float64).reshape(-1, 3)
            hist[i, H - len(h):] = h
            hval[i, H - len(h):] = True
            if len(h) < H:  # pad the past with the oldest state so arrays stay finite
                hist[i, :H - len(h)] = h[0]
        return Tracks(
            ids=np.array([t.id for t in out], np.int64),
            boxes=np.array([[t.x[0], t.x[1], t.length, t.width, t.yaw] for t in out]).reshape(n, 5),
            velocities=np.array([t.x[2:4] for t in out]).reshape(n, 2),
            scores=np.array([t.score for t in out]),
            misses=np.array([t.misses for t in out], np.int64),
            history=hist,
            history_valid=hval,
        )
