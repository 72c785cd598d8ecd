"""Ready-made autonomy stacks for episodes: Autonomy-A and an oracle-perception stack.

* ``make_stack("A")``: :class:`~adv3d_runner.autonomy.modular.ModularStack` with the learned BEV
  detector (``adv3d_runner.autonomy.detector.load_detector``) and the learned predictor
  (``adv3d_runner.autonomy.predictor.load_predictor``). If either module or its shipped weights
  are missing this raises :class:`~adv3d_runner.errors.ConfigError` saying so: Autonomy-A is
  never silently replaced by something else.
* ``make_stack("A-lanefollow")``: the learned detector with the lane-following predictor
  baseline (to tell detector problems from predictor problems).
* ``make_stack("oracle")``: the same tracker and planner, but the detector is
  :class:`OracleDetector` (the ground-truth boxes of the actors the LiDAR actually hit) and the
  predictor is :class:`~adv3d_runner.autonomy.baselines.LaneFollowingPredictor`. Needs no
  torch and no weights; used by tests, benchmarks and when the models are not trained yet.

The oracle needs the ground truth of the frame, which a detector never sees through
``detect(points)``. The episode loop therefore calls ``detector.observe(boxes_ego, n_points)``
before each ``stack.step`` on any detector that has an ``observe`` method.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..autonomy.interface import Detections
from ..errors import ConfigError

AUTONOMY_CHOICES = ("A", "oracle", "A-lanefollow")

#: Detections below this score never start a track in Autonomy-A (they may still update an
#: existing one). With a detector threshold of 0.1 (the first shipped model) its low-score
#: false positives became tracks in the ego's lane and the planner braked for them
#: (bench/sanity.py, docs/episode.md); the gate keeps that from coming back.
TRACK_MIN_SCORE = 0.5


class OracleDetector:
    """Ground-truth boxes of the actors hit by at least ``min_points`` LiDAR returns.

    Scores grow with the number of returns (0.5 at ``min_points``, 1.0 from 50 returns), so a
    shape that reflects fewer rays gets a lower confidence, as it would from a real detector.

    Args:
        min_points: returns an actor needs to be detected.
        max_range: m, actors whose centre is farther from the ego are not detected.
    """

    def __init__(self, min_points: int = 5, max_range: float = 100.0):
        self.min_points = int(min_points)
        self.max_range = float(max_range)
        self._boxes = np.zeros((0, 5))
        self._counts = np.zeros(0, np.int64)

    def observe(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        """Ground truth of the coming frame: (N, 5) boxes in the ego frame (NaN rows for absent
        actors) and (N,) returns per actor."""
        self._boxes = np.asarray(boxes_ego, dtype=np.float64).reshape(-1, 5)
        self._counts = np.asarray(n_points, dtype=np.int64).reshape(-1)

    def detect(self, points: np.ndarray) -> Detections:
        """Boxes in the ego frame; nothing when the frame has no points."""
        if len(points) == 0 or len(self._boxes) == 0:
            return Detections()
        b = self._boxes
        ok = np.isfinite(b).all(axis=1) & (self._counts >= self.min_points)
        ok &= np.hypot(np.nan_to_num(b[:, 0], nan=np.inf), np.nan_to_num(b[:, 1], nan=np.inf)) <= self.max_range
        n = self._counts[ok].astype(np.float64)
        scores = np.clip(0.5 + 0.5 * (n - self.min_points) / max(50.0 - self.min_points, 1.0), 0.5, 1.0)
        return Detections(b[ok], scores)


def make_stack(autonomy: str = "A", *, detector_options: dict | None = None,
               track_min_score: float = TRACK_MIN_SCORE):
    """Build a fresh stack (call once per worker; ``run_episode`` resets it per episode).

    Args:
        autonomy: ``"A"`` (learned detector + learned predictor), ``"A-lanefollow"`` or ``"oracle"``.
        detector_options: keyword arguments for ``load_detector`` (decoding overrides such as
            ``score_threshold``).
        track_min_score: learned-detector stacks: the tracker's ``min_score`` (see
            :data:`TRACK_MIN_SCORE`).

    Raises:
        ConfigError: unknown name, or Autonomy-A's models or weights are not available.
    """
    from ..autonomy.modular import ModularStack

    if autonomy == "oracle":
        from ..autonomy.baselines import LaneFollowingPredictor

        return ModularStack(OracleDetector(), LaneFollowingPredictor())
    if autonomy not in ("A", "A-lanefollow"):
        raise ConfigError(f"unknown autonomy {autonomy!r}; choose one of {', '.join(AUTONOMY_CHOICES)}")
    from ..autonomy.tracker import MultiObjectTracker, TrackerConfig

    detector = _load("detector", "load_detector", detector_options or {})
    tracker = MultiObjectTracker(TrackerConfig(min_score=float(track_min_score)))
    if autonomy == "A-lanefollow":
        from ..autonomy.baselines import LaneFollowingPredictor

        return ModularStack(detector, LaneFollowingPredictor(), tracker=tracker)
    predictor = _load("predictor", "load_predictor", {})
    return ModularStack(detector, predictor, tracker=tracker)


def _load(module: str, func: str, options: dict):
    """Import ``adv3d_runner.autonomy.<module>.<func>`` and call it, turning a missing module or
    missing weights into a ConfigError that says what to do."""
    import importlib

    hint = (f"Autonomy-A needs the learned {module} and its weights in assets/models/{module}/ "
            f"(train them with `adv3d train {module}`); use --autonomy oracle to run with oracle perception")
    try:
        mod = importlib.import_module(f"adv3d_runner.autonomy.{module}")
        loader = getattr(mod, func)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"{hint} ({exc})") from None
    from ..fileio import REPO_ROOT

    folder = Path(getattr(mod, "DEFAULT_MODEL_DIR", REPO_ROOT / "assets" / "models" / module))
    if not (folder / "config.json").is_file():
        raise ConfigError(f"{hint} (no {folder / 'config.json'})")
    try:
        return loader(**options)
    except (FileNotFoundError, OSError) as exc:
        raise ConfigError(f"{hint} ({exc})") from None
