"""Ready-made autonomy stacks for episodes: Autonomy-A, Autonomy-B and an oracle-perception stack.

* ``make_stack("A")``: :class:`~adv3d_runner.autonomy.modular.ModularStack` with the learned BEV
  detector (``adv3d_runner.autonomy.detector.load_detector``) and the learned predictor
  (``adv3d_runner.autonomy.predictor.load_predictor``). If either module or its shipped weights
  are missing this raises :class:`~adv3d_runner.errors.ConfigError` saying so: Autonomy-A is
  never silently replaced by something else.
* ``make_stack("A-fast")``: Autonomy-A with the detector trained at 0.4 m cells
  (``assets/models/detector-fast/``): its network costs 2.9 instead of 6.5 ms per frame, for
  long attack campaigns; offline AP 0.973 against 0.964, but on the real benchmark
  part closed-loop AP 0.965 against 0.978 and a rougher ride (docs/detector.md).
* ``make_stack("A-lanefollow")``: the learned detector with the lane-following predictor
  baseline (to tell detector problems from predictor problems).
* ``make_stack("B")``: :class:`~.instance_free.OccupancyStack`, the instance-free Autonomy-B:
  the learned implicit occupancy-and-flow model (``adv3d_runner.autonomy.occupancy.load_occupancy``,
  weights in ``assets/models/occupancy/``) and the same sampling planner planning on its
  occupancy. Missing weights raise :class:`~adv3d_runner.errors.ConfigError`, as for A.
* ``make_stack("oracle")``: the same tracker and planner, but the detector is
  :class:`~.oracle.OracleDetector` (the ground-truth boxes of the actors the LiDAR actually hit)
  and the predictor is :class:`~.baselines.LaneFollowingPredictor`. Needs no torch and no
  weights; used by tests, benchmarks and when the models are not trained yet. It gets the
  frame's ground truth through ``AutonomyStack.observe_ground_truth``, which the episode loop
  calls on every stack before each ``step`` (:class:`~.modular.ModularStack` forwards it to a
  detector that takes it).
"""
from __future__ import annotations

import functools
from pathlib import Path

from ..errors import ConfigError
from .oracle import OracleDetector

AUTONOMY_CHOICES = ("A", "oracle", "A-lanefollow", "B", "A-fast")
#: The detector model folder (under assets/models/) of each learned-detector stack.
DETECTOR_MODELS = {"A": "detector", "A-lanefollow": "detector", "A-fast": "detector-fast"}
#: The stacks that plan on occupancy instead of detected and predicted actors.
INSTANCE_FREE = ("B",)

#: Detections below this score never start a track in Autonomy-A (they may still update an
#: existing one). With a detector threshold of 0.1 (the first shipped model) its low-score
#: false positives became tracks in the ego's lane and the planner braked for them
#: (bench/sanity.py, docs/episode.md); the gate keeps that from coming back.
TRACK_MIN_SCORE = 0.5


#: What each of adv3d's own stacks provides (``api.StackInfo.provides``) and the model folders
#: its fingerprint covers.
_OWN = {"A": (("detector", "predictor"), ("detections", "tracks", "predictions")),
        "A-fast": (("detector-fast", "predictor"), ("detections", "tracks", "predictions")),
        "A-lanefollow": (("detector",), ("detections", "tracks", "predictions")),
        "B": (("occupancy",), ("occupancy",)),
        "oracle": ((), ("detections", "tracks", "predictions"))}


def own_stack(name: str, **options):
    """One of adv3d's own stacks, carrying its ``stack_info`` (:func:`.plugins.builtin_info`)."""
    from .plugins import with_info

    return with_info(_make_own(name, **options), own_info(name))


@functools.lru_cache(maxsize=None)
def own_info(name: str):
    """The :class:`~.api.StackInfo` of one of adv3d's own stacks (None for any other name),
    without building it."""
    from .plugins import builtin_info

    return builtin_info(name, *_OWN[name]) if name in _OWN else None


# The factories registered in the ``adv3d.stacks`` entry-point group (pyproject.toml).
def autonomy_a():
    return own_stack("A")


def autonomy_a_fast():
    return own_stack("A-fast")


def autonomy_a_lanefollow():
    return own_stack("A-lanefollow")


def autonomy_b():
    return own_stack("B")


def oracle():
    return own_stack("oracle")


def make_stack(autonomy: str = "A", **options):
    """Build a fresh stack (call once per worker; ``run_episode`` resets it per episode): one of
    adv3d's own by name (``options`` go to it), or any stack ``autonomy`` names
    (:mod:`.plugins`: a registered plugin, ``package.module:factory``, or a stack in its own
    process). The stack carries ``stack_info`` (:class:`~.api.StackInfo`).

    Raises:
        ConfigError: unknown name, a plugin that cannot be built, or Autonomy-A's models or
            weights are not available.
    """
    if autonomy in _OWN:
        return own_stack(autonomy, **options)
    from .plugins import build

    stack, info = build(autonomy)
    stack.stack_info = info
    return stack


def _make_own(autonomy: str = "A", *, detector_options: dict | None = None,
              track_min_score: float = TRACK_MIN_SCORE):
    """Build one of adv3d's own stacks.

    Args:
        autonomy: ``"A"`` (learned detector + learned predictor), ``"A-lanefollow"``, ``"oracle"``
            or ``"B"`` (learned implicit occupancy model).
        detector_options: keyword arguments for ``load_detector`` (decoding overrides such as
            ``score_threshold``).
        track_min_score: learned-detector stacks: the tracker's ``min_score`` (see
            :data:`TRACK_MIN_SCORE`).

    Raises:
        ConfigError: unknown name, or Autonomy-A's models or weights are not available.
    """
    from .modular import ModularStack

    if autonomy == "oracle":
        from .baselines import LaneFollowingPredictor

        return ModularStack(OracleDetector(), LaneFollowingPredictor())
    if autonomy == "B":
        from .instance_free import OccupancyStack

        return OccupancyStack(_load("occupancy", "load_occupancy", {}, stack="Autonomy-B"))
    if autonomy not in DETECTOR_MODELS:
        raise ConfigError(f"unknown autonomy {autonomy!r}; choose one of {', '.join(AUTONOMY_CHOICES)}")
    from .tracker import MultiObjectTracker, TrackerConfig

    detector = _load("detector", "load_detector", detector_options or {}, folder=DETECTOR_MODELS[autonomy])
    tracker = MultiObjectTracker(TrackerConfig(min_score=float(track_min_score)))
    if autonomy == "A-lanefollow":
        from .baselines import LaneFollowingPredictor

        return ModularStack(detector, LaneFollowingPredictor(), tracker=tracker)
    predictor = _load("predictor", "load_predictor", {})
    return ModularStack(detector, predictor, tracker=tracker)


def _load(module: str, func: str, options: dict, stack: str = "Autonomy-A", folder: str | None = None):
    """Import ``adv3d_runner.autonomy.<module>.<func>`` and call it on the model in
    ``assets/models/<folder>`` (default: the module's own folder), turning a missing module or
    missing weights into a ConfigError that says what to do."""
    import importlib

    where = f"assets/models/{folder or module}/"
    hint = (f"{stack} needs the learned {module} and its weights in {where} "
            f"(train them with `adv3d train {module} --out {where}`); use --autonomy oracle to run with oracle perception")
    try:
        mod = importlib.import_module(f"adv3d_runner.autonomy.{module}")
        loader = getattr(mod, func)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"{hint} ({exc})") from None
    from ..fileio import REPO_ROOT

    if folder is None:
        path = Path(getattr(mod, "DEFAULT_MODEL_DIR", REPO_ROOT / "assets" / "models" / module))
    else:
        path = REPO_ROOT / "assets" / "models" / folder
        options = {"path": path, **options}
    if not (path / "config.json").is_file():
        raise ConfigError(f"{hint} (no {path / 'config.json'})")
    try:
        return loader(**options)
    except (FileNotFoundError, OSError) as exc:
        raise ConfigError(f"{hint} ({exc})") from None
