"""Training data for the learned predictor, made by the simulator from training-split scenes.

Per scene (``generate_scene(seed, "train")``, seeds >= 100 000, never the benchmark):

1. **Detections as a detector would give them**: every actor within ``DETECT_RANGE`` m of the
   ego is detected in each frame with probability ``1 - miss``, its box perturbed by Gaussian
   noise (centre ``pos_std``, yaw ``yaw_std``, size 3 %). The noise levels are drawn per scene
   (``NOISE_RANGES``) so the model sees clean and noisy perception alike. Occlusion is not
   modelled (the misses stand in for it).
2. **The real tracker** (:class:`~adv3d_runner.autonomy.tracker.MultiObjectTracker`, default
   config, ego speed as the prior speed like :class:`~adv3d_runner.autonomy.modular.ModularStack`) runs on them frame by frame, so histories,
   Kalman velocities, young tracks and coasting tracks look exactly as at run time.
3. Every ``FRAME_STRIDE``-th frame, each confirmed track is matched to a ground-truth actor
   (Hungarian on centre distance, ``metrics.prediction.match_to_ground_truth``, <= 3 m) and
   becomes a sample if that actor has at least ``MIN_FUTURE`` valid future frames: features
   and lane-following prior (:func:`~adv3d_runner.autonomy.predictor.encode` on the scene's
   :class:`~adv3d_runner.scene.lanemap.LaneMap`, computed with all tracks of the
   frame, as at run time), and the actor's true future (60 steps, agent frame,
   with validity; actors leave the scene at 100 m from the ego or at the recording's end).
4. Both baselines (:class:`~adv3d_runner.autonomy.baselines.ConstantVelocityPredictor`,
   :class:`~adv3d_runner.autonomy.baselines.LaneFollowingPredictor`) predict the same tracks in the map frame; their
   per-sample ADE/FDE are stored so reports compare all models on identical samples.

Everything is deterministic for a scene seed (``SeedSequence([DATA_TAG, seed])``). Each scene's
samples are cached as one ``.npz`` (``allow_pickle=False``) under
``$ADV3D_CACHE/predictor_data/<data key>/`` (default ``~/.cache/adv3d``), outside the repo; the
data key hashes every constant here and the feature layout, so a change never reuses stale data.

**Real scenes** (:func:`real_scene_samples`, :func:`build_real_dataset`): the same pipeline on a
recorded scene of ``scenes/real/`` (NGSIM US-101). Only recorded frames count: an actor's
``synthetic`` frames (the ``--extend``-ed tail of a short recording) are treated as absent, so
no detection, no sample and no future step comes from the IDM extrapolation. The noise stream
is ``SeedSequence([DATA_TAG, REAL_TAG, crc32(scene id)])``; the ``seed`` column holds
``-1 - crc32(scene id)`` (negative: never a generator seed). The cache file name carries a hash
of the scene file's bytes (``real-<stem>-<sha1[:10]>.npz``), so a re-imported scene is never
read stale. Which real scenes may be used for training is the caller's business:
``adv3d train predictor`` takes the *train* part of ``scenes/real/split.json`` and evaluates
on the *benchmark* part only.
"""
from __future__ import annotations

import hashlib
import json
import os
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from ..autonomy.interface import PREDICTION_STEPS, Detections
from ..autonomy.interface import DT
from ..autonomy.predictor import HISTORY, LANE_OFFSETS, NEIGHBOURS, NUM_FEATURES, OFF_LANE, PATH_S, _encode
from ..fileio import atomic_path
from ..metrics.prediction import displacement_errors, match_to_ground_truth
from ..scene.lanemap import LaneMap

DATA_VERSION = 2                 # 2: every sample carries its lane path (anchored models)
DATA_TAG = 0x9D1C7               # SeedSequence namespace of the perception noise
REAL_TAG = 0x4EA1                # sub-namespace of real (recorded) scenes
DETECT_RANGE = 80.0              # m around the ego
FRAME_STRIDE = 2                 # frames between samples (consecutive frames are near duplicates)
MIN_FUTURE = 30                  # valid future steps a sample needs (3 s)
MATCH_DISTANCE = 3.0             # m, track <-> ground truth
NOISE_RANGES = {"pos_std": (0.05, 0.25), "yaw_std": (0.01, 0.05), "miss": (0.0, 0.15)}
SIZE_NOISE = 0.03                # relative std of detected length / width
BASELINES = ("constant_velocity", "lane_following")
METRIC_COLUMNS = ("min_ade", "mean_ade", "min_fde", "mean_fde", "top1_ade", "top1_fde")
ARRAYS = ("features", "prior", "path", "future", "future_valid", "boxes", "frame", "seed") + tuple(
    f"{b}_metrics" for b in BASELINES)


def data_key() -> str:
    """Short hash of everything that shapes a sample (constants + feature layout)."""
    doc = {"v": DATA_VERSION, "tag": DATA_TAG, "range": DETECT_RANGE, "stride": FRAME_STRIDE,
           "min_future": MIN_FUTURE, "match": MATCH_DISTANCE, "noise": NOISE_RANGES, "size": SIZE_NOISE,
           "features": NUM_FEATURES, "off_lane": OFF_LANE, "history": HISTORY, "lanes": LANE_OFFSETS.tolist(), "neigh": NEIGHBOURS,
           "steps": PREDICTION_STEPS, "path": PATH_S.tolist()}
    return hashlib.sha1(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:12]


def cache_dir(root: str | Path | None = None) -> Path:
    """``<root or $ADV3D_CACHE or ~/.cache/adv3d>/predictor_data/<data_key()>``."""
    base = Path(root) if root is not None else Path(os.environ.get("ADV3D_CACHE", Path.home() / ".cache" / "adv3d"))
    return base / "predictor_data" / data_key()


def _empty() -> dict[str, np.ndarray]:
    T = PREDICTION_STEPS
    out = {"features": np.zeros((0, NUM_FEATURES), np.float32), "prior": np.zeros((0, T, 2), np.float32),
           "path": np.zeros((0, len(PATH_S), 2), np.float32),
           "future": np.zeros((0, T, 2), np.float32), "future_valid": np.zeros((0, T), bool),
           "boxes": np.zeros((0, 5)), "frame": np.zeros(0, np.int32), "seed": np.zeros(0, np.int64)}
    for b in BASELINES:
        out[f"{b}_metrics"] = np.zeros((0, len(METRIC_COLUMNS)))
    return out


def per_sample_metrics(pred: np.ndarray, probs: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, K, T, 2) predictions, (N, K) probabilities, (N, T, 2) truth + (N, T) validity ->
    (N, 6) columns ``METRIC_COLUMNS`` (top1 = the most probable mode)."""
    ade, fde = displacement_errors(pred, gt, valid)
    top = np.argmax(probs, axis=1)
    rows = np.arange(len(ade))
    return np.stack([ade.min(1), ade.mean(1), fde.min(1), fde.mean(1), ade[rows, top], fde[rows, top]], axis=1)


def scene_samples(seed: int, scene=None) -> dict[str, np.ndarray]:
    """All samples of training scene ``seed`` (see the module docstring); deterministic.

    Args:
        seed: training-split scene seed (>= 100 000).
        scene: the already generated scene (optional, to save regenerating it).
    Returns:
        dict of arrays (M rows): features (M, F) float32, prior (M, 60, 2) float32 (agent frame), future (M, 60, 2)
        float32 agent frame, future_valid (M, 60), boxes (M, 5) map frame, frame (M,), seed
        (M,), ``<baseline>_metrics`` (M, 6).
    """
    from ..scene.generate import generate_scene

    if scene is None:
        scene = generate_scene(int(seed), "train")
    rng = np.random.default_rng(np.random.SeedSequence([DATA_TAG, int(seed)]))
    return _samples(scene, rng, int(seed))


def _scene_crc(scene) -> int:
    return zlib.crc32(scene.id.encode())


def real_scene_samples(scene) -> dict[str, np.ndarray]:
    """All samples of a recorded (real) scene, from its recorded frames only (see the module
    docstring); deterministic for the scene id. Same arrays as :func:`scene_samples`."""
    crc = _scene_crc(scene)
    rng = np.random.default_rng(np.random.SeedSequence([DATA_TAG, REAL_TAG, crc]))
    recorded = np.ones((len(scene.actors), scene.frames), bool)
    for i, actor in enumerate(scene.actors):
        recorded[i] = ~scene.actor_synthetic(actor.id)
    return _samples(scene, rng, -1 - crc, recorded)


def recording_samples(scene, draw: int = 0) -> dict[str, np.ndarray]:
    """Samples of *every* vehicle of a recorded scene, not only those near its ego: the ego's
    own track joins the actors and nothing is out of detection range, recorded frames only
    (:func:`real_scene_samples`). ``draw`` picks the perception-noise stream
    (``SeedSequence([DATA_TAG, REAL_TAG, crc32(scene id), 1 + draw])``), so that several draws
    of one recording are different noisy views of the same traffic. The ``seed`` column holds
    ``-1 - crc32(scene id)``."""
    import dataclasses

    from ..scene.schema import Actor

    crc = _scene_crc(scene)
    rng = np.random.default_rng(np.random.SeedSequence([DATA_TAG, REAL_TAG, crc, 1 + int(draw)]))
    ego_id = 1 + max((a.id for a in scene.actors), default=-1)
    as_actor = Actor(id=ego_id, cls="sedan", dimensions=scene.ego.dimensions, track=scene.ego.track)
    whole = dataclasses.replace(scene, actors=list(scene.actors) + [as_actor])
    recorded = np.ones((len(whole.actors), whole.frames), bool)
    for i, actor in enumerate(whole.actors):
        recorded[i] = ~whole.actor_synthetic(actor.id)
    return _samples(whole, rng, -1 - crc, recorded, detect_range=np.inf)


def _samples(scene, rng: np.random.Generator, seed_value: int, recorded: np.ndarray | None = None,
             detect_range: float = DETECT_RANGE) -> dict[str, np.ndarray]:
    """The pipeline of :func:`scene_samples` on a loaded scene with its noise stream ``rng``;
    ``recorded`` (A, F) bool, when given, marks the actor frames that may be used (others are
    absent); ``seed_value`` fills the ``seed`` column; actors within ``detect_range`` m of the
    ego are detected."""
    from ..autonomy.baselines import ConstantVelocityPredictor, LaneFollowingPredictor
    from ..autonomy.tracker import MultiObjectTracker

    seed = seed_value
    noise = {k: float(rng.uniform(*v)) for k, v in NOISE_RANGES.items()}
    poses, valid = scene.all_actor_poses()                       # (A, F, 3), (A, F)
    if recorded is not None:
        valid = valid & recorded
        poses = np.where(valid[..., None], poses, np.nan)
    dims = scene.actor_dimensions()
    ego = scene.ego_poses()
    ego_v = scene.ego_speeds()
    F, T = scene.frames, PREDICTION_STEPS
    lane_map = LaneMap.from_scene(scene)
    tracker = MultiObjectTracker()
    cv, lf = ConstantVelocityPredictor(), LaneFollowingPredictor()
    cv.reset(lane_map)
    lf.reset(lane_map)
    # future positions per actor and frame, padded with NaN past the recording
    pad = np.concatenate([poses[..., :2], np.full((len(poses), T, 2), np.nan)], axis=1)
    vpad = np.concatenate([valid, np.zeros((len(poses), T), bool)], axis=1)
    chunks = []
    for f in range(F):
        vis = np.flatnonzero(valid[:, f] & (np.hypot(poses[:, f, 0] - ego[f, 0], poses[:, f, 1] - ego[f, 1]) <= detect_range))
        # draw the same number of random values every frame for every visible actor (stable streams)
        u = rng.random(len(vis))
        eps = rng.normal(size=(len(vis), 5))
        keep = u >= noise["miss"]
        det = np.c_[poses[vis, f, :2], dims[vis, :2], poses[vis, f, 2]]
        det[:, :2] += eps[:, :2] * noise["pos_std"]
        det[:, 2:4] *= 1.0 + SIZE_NOISE * eps[:, 2:4]
        det[:, 4] += eps[:, 4] * noise["yaw_std"]
        det = det[keep]
        tracks = tracker.update(Detections(det, np.full(len(det), 0.9)), prior_speed=float(ego_v[f]))
        if f % FRAME_STRIDE or len(tracks) == 0:
            continue
        gt_idx = np.flatnonzero(valid[:, f])
        gt_boxes = np.c_[poses[gt_idx, f, :2], dims[gt_idx, :2], poses[gt_idx, f, 2]]
        m = match_to_ground_truth(tracks.boxes, gt_boxes, MATCH_DISTANCE)
        rows = np.flatnonzero(m >= 0)
        if len(rows) == 0:
            continue
        actor = gt_idx[m[rows]]
        fut = pad[actor, f + 1:f + 1 + T]                        # (R, T, 2) map frame
        fval = vpad[actor, f + 1:f + 1 + T]
        enough = fval.sum(axis=1) >= MIN_FUTURE
        rows, fut, fval = rows[enough], fut[enough], fval[enough]
        if len(rows) == 0:
            continue
        feats, prior, *_, path = _encode(tracks, lane_map, T, DT, with_path=True)
        feats, prior, path = feats[rows], prior[rows], path[rows]
        boxes = tracks.boxes[rows]
        c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
        rel = fut - boxes[:, None, :2]
        local = np.stack([c[:, None] * rel[..., 0] + s[:, None] * rel[..., 1],
                          -s[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]], axis=-1)
        local = np.where(fval[..., None], local, 0.0)
        chunk = {"features": feats, "prior": prior, "path": path, "future": local.astype(np.float32),
                 "future_valid": fval, "boxes": boxes, "frame": np.full(len(rows), f, np.int32),
                 "seed": np.full(len(rows), int(seed), np.int64)}
        for name, model in zip(BASELINES, (cv, lf)):
            p = model.predict(tracks)
            chunk[f"{name}_metrics"] = per_sample_metrics(p.trajectories[rows], p.probabilities[rows],
                                                          np.nan_to_num(fut), fval)
        chunks.append(chunk)
    if not chunks:
        return _empty()
    return {k: np.concatenate([c[k] for c in chunks]) for k in ARRAYS}


def tracked_evaluation_frames(scene, rng: np.random.Generator, *, frames: range, every: int, first: int = 10,
                              pos_std: float = 0.15, yaw_std: float = 0.02, miss: float = 0.0):
    """Noisy detections -> the real tracker, over ``frames`` of ``scene``; for model evaluation
    (benches, tests) with fixed noise, unlike the per-scene noise draws of :func:`scene_samples`.

    Every ``every``-th frame from ``first`` on with at least one track, yields
    ``(frame, tracks, rows, future, future_valid)``: ``rows`` (R,) indexes the tracks matched to a
    ground-truth actor; ``future`` (R, 60, 2) m map frame (NaN -> 0) and ``future_valid`` (R, 60)
    are that actor's next 60 steps. Detection noise: centre ``pos_std`` m, yaw ``yaw_std`` rad;
    each visible actor is missed with probability ``miss`` (no draw when 0, so streams stay
    comparable).
    """
    from ..autonomy.tracker import MultiObjectTracker

    poses, valid = scene.all_actor_poses()
    dims = scene.actor_dimensions()
    ego, ego_v = scene.ego_poses(), scene.ego_speeds()
    T = PREDICTION_STEPS
    tracker = MultiObjectTracker()
    for f in frames:
        vis = np.flatnonzero(valid[:, f] & (np.hypot(*(poses[:, f, :2] - ego[f, :2]).T) <= DETECT_RANGE))
        det = np.c_[poses[vis, f, :2] + rng.normal(0, pos_std, (len(vis), 2)), dims[vis, :2],
                    poses[vis, f, 2] + rng.normal(0, yaw_std, len(vis))]
        if miss > 0:
            det = det[rng.random(len(vis)) >= miss]
        tracks = tracker.update(Detections(det, np.full(len(det), 0.9)), prior_speed=float(ego_v[f]))
        if f < first or f % every or len(tracks) == 0:
            continue
        gi = np.flatnonzero(valid[:, f])
        m = match_to_ground_truth(tracks.boxes, np.c_[poses[gi, f, :2], dims[gi, :2], poses[gi, f, 2]])
        rows = np.flatnonzero(m >= 0)
        actor = gi[m[rows]]
        yield f, tracks, rows, np.nan_to_num(poses[actor, f + 1:f + 1 + T, :2]), valid[actor, f + 1:f + 1 + T]


def save_samples(path: str | Path, samples: dict[str, np.ndarray]) -> None:
    """Write one scene's samples as an npz atomically (plain arrays, no pickle)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **samples)


def load_samples(path: str | Path) -> dict[str, np.ndarray]:
    """Read a cached scene npz (``allow_pickle=False``); raises FileFormatError when arrays are
    missing or malformed."""
    from ..validate import read_npz

    z = read_npz(path, "predictor sample cache (.npz)")
    z.require(ARRAYS)
    z.array("features", shape=(None, NUM_FEATURES))
    return dict(z.members)


def build_dataset(seeds: Sequence[int], cache: str | Path | None = None, use_cache: bool = True,
                  desc: str = "predictor data", stats: dict | None = None) -> dict[str, np.ndarray]:
    """Samples of every scene seed, concatenated (cached per scene under ``cache_dir(cache)``).
    ``stats`` (optional dict) receives the counts of scenes ``generated`` and read from ``cached``."""
    stats = {} if stats is None else stats
    stats.setdefault("generated", 0)
    stats.setdefault("cached", 0)
    from ..progress import progress

    folder = cache_dir(cache)
    parts = []
    for seed in progress(list(seeds), desc=desc, unit="scene"):
        path = folder / f"highway-train-{int(seed):06d}.npz"
        if use_cache and path.is_file():
            try:
                parts.append(load_samples(path))
                stats["cached"] += 1
                continue
            except Exception:  # a broken cache entry is rebuilt, never trusted
                pass
        samples = scene_samples(int(seed))
        stats["generated"] += 1
        if use_cache:
            save_samples(path, samples)
        parts.append(samples)
    if not parts:
        return _empty()
    return {k: np.concatenate([p[k] for p in parts]) for k in ARRAYS}


def real_cache_name(path: str | Path) -> str:
    """Cache file name of a real scene: ``real-<stem>-<sha1 of the file's bytes, 10 hex>.npz``."""
    path = Path(path)
    digest = hashlib.sha1(path.read_bytes()).hexdigest()[:10]
    stem = path.name.split(".json")[0]
    return f"real-{stem}-{digest}.npz"


def build_real_dataset(paths: Sequence[str | Path], cache: str | Path | None = None, use_cache: bool = True,
                       desc: str = "real scenes", stats: dict | None = None) -> dict[str, np.ndarray]:
    """Samples of every real scene file in ``paths`` (:func:`real_scene_samples`), concatenated,
    cached per file under ``cache_dir(cache)``. ``stats`` as in :func:`build_dataset`."""
    from ..progress import progress
    from ..scene.schema import load_scene

    stats = {} if stats is None else stats
    stats.setdefault("generated", 0)
    stats.setdefault("cached", 0)
    folder = cache_dir(cache)
    parts = []
    for path in progress([Path(p) for p in paths], desc=desc, unit="scene"):
        cpath = folder / real_cache_name(path)
        if use_cache and cpath.is_file():
            try:
                parts.append(load_samples(cpath))
                stats["cached"] += 1
                continue
            except Exception:  # a broken cache entry is rebuilt, never trusted
                pass
        samples = real_scene_samples(load_scene(path))
        stats["generated"] += 1
        if use_cache:
            save_samples(cpath, samples)
        parts.append(samples)
    if not parts:
        return _empty()
    return {k: np.concatenate([p[k] for p in parts]) for k in ARRAYS}
