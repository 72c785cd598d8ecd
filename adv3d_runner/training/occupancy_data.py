"""Training / evaluation data of Autonomy-B's occupancy model, made with the simulator.

Recipe (deterministic in its arguments; the same split discipline as the detector's,
:mod:`.detector_data`):

* scenes: ``generate_scene(seed, split="train")``, training seeds ``TRAIN_SEED0 + [0, N)`` and
  held-out seeds ``VAL_SEED0 + [0, M)`` (disjoint ranges of the training split; the benchmark
  scenes are never used); actors get the benign vehicle library's meshes.
* samples: ``frames_per_scene`` frames f per scene, evenly spaced over the frames that have
  ``FLOW_LAG`` s of history and the model's horizon of future in the log, with an offset drawn
  from ``default_rng([seed, 1])``. Each sample's input is :func:`~adv3d_runner.autonomy.occupancy.bev_input`
  of the sweeps at f - lag for the model's ``sweep_lags`` (the scene's rig at the logged ego
  poses, LiDAR noise and ray drop from ``default_rng([seed, frame])``, as the detector's data).
* queries: ``queries`` points per sample (``default_rng([seed, f, 2])``), half uniform over the
  input grid in the frame that moves with the ego's speed ((x - v t, y) uniform, t uniform on
  the 0.1 s steps of the horizon), half uniform in an actor's footprint widened by
  ``NEAR_MARGIN`` m (a random actor of that time whose reference point is near the grid), with
  their ground truth from the logged boxes (:func:`adv3d_runner.metrics.occupancy.occupancy_targets`:
  occupancy and the backward flow over ``FLOW_LAG`` s) in the ego frame of frame f.

Inputs are stored exactly as uint8 (height-slice occupancies 0/1 and the per-column point count
the density channel is made from), so training sees the same arrays as the runtime.

Cache: one ``.npz`` per scene (``np.savez_compressed``, read with ``allow_pickle=False``) in
``cache_dir`` (default ``~/.cache/adv3d/occupancy``), named by seed, frame count, query count and
the data version.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..autonomy.occupancy import OccupancyConfig, bev_input, keep_points
from ..geometry.frames import boxes_to_frame
from ..metrics.occupancy import FLOW_LAG, occupancy_targets
from .detector_data import TRAIN_SEED0, VAL_SEED0

DATA_VERSION = 1
NEAR_MARGIN = 1.5  # m around an actor's footprint for the near-actor queries
_LOG64 = np.log(64.0)

__all__ = ["TRAIN_SEED0", "VAL_SEED0", "SampleSet", "make_samples", "encode_grid", "decode_grid", "sample_frames"]


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "adv3d" / "occupancy"


@dataclass
class SampleSet:
    """Samples as arrays (one cache file, or several concatenated).

    Attributes:
        grids: (S, C, nx, ny) uint8 encoded inputs (:func:`encode_grid`).
        speed: (S,) float32 ego speed, m/s.
        queries: (S, Q, 3) float32 ego-frame x, y (m), t (s).
        occupied: (S, Q) bool. flow: (S, Q, 2) float32 m/s. flow_valid: (S, Q) bool.
        scene_seed, frame_index: (S,) int64, where each sample came from.
    """

    grids: np.ndarray
    speed: np.ndarray
    queries: np.ndarray
    occupied: np.ndarray
    flow: np.ndarray
    flow_valid: np.ndarray
    scene_seed: np.ndarray
    frame_index: np.ndarray

    def __len__(self) -> int:
        return len(self.speed)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def subset(self, idx: np.ndarray) -> "SampleSet":
        return SampleSet(**{k: v[idx] for k, v in self.arrays().items()})

    @staticmethod
    def concat(sets: Sequence["SampleSet"]) -> "SampleSet":
        return SampleSet(**{k: np.concatenate([getattr(s, k) for s in sets]) for k in SampleSet.__dataclass_fields__})


def encode_grid(grid: np.ndarray, cfg: OccupancyConfig) -> np.ndarray:
    """float32 network input (C, nx, ny) -> uint8: slices as 0/1, density as the point count it
    was made from (<= 63, where the density saturates). :func:`decode_grid` inverts it exactly."""
    g = np.asarray(grid, np.float32)
    per = cfg.channels_per_sweep
    out = np.rint(g).astype(np.uint8)
    for i in range(len(cfg.sweep_lags)):
        d = g[i * per + per - 1].astype(np.float64)
        out[i * per + per - 1] = np.clip(np.rint(np.expm1(d * _LOG64)), 0, 63).astype(np.uint8)
    return out


def decode_grid(enc: np.ndarray, cfg: OccupancyConfig) -> np.ndarray:
    """uint8 (..., C, nx, ny) from :func:`encode_grid` -> the float32 network input."""
    e = np.asarray(enc)
    out = e.astype(np.float32)
    per = cfg.channels_per_sweep
    for i in range(len(cfg.sweep_lags)):
        c = i * per + per - 1
        # the voxeliser's arithmetic (float64, then stored as float32)
        out[..., c, :, :] = np.minimum(np.log1p(e[..., c, :, :].astype(np.int64)) / _LOG64, 1.0)
    return out


def sample_frames(seed: int, frames_per_scene: int, n_frames: int, cfg: OccupancyConfig) -> np.ndarray:
    """Evenly spaced sample frames with a seeded offset, each with the sweeps and flow history
    before it and the horizon after it in the log."""
    lo = max(max(cfg.sweep_lags), int(round(FLOW_LAG / cfg.dt)))
    hi = n_frames - int(round(cfg.horizon / cfg.dt))  # exclusive
    span = max(1, hi - lo)
    k = max(1, min(int(frames_per_scene), span))
    stride = span // k
    offset = int(np.random.default_rng([seed, 1]).integers(stride))
    return lo + offset + stride * np.arange(k)


def make_queries(rng: np.random.Generator, n: int, speed: float, boxes: np.ndarray, cfg: OccupancyConfig
                 ) -> np.ndarray:
    """(n, 3) ego-frame query points (see module docstring).

    Args:
        boxes: (H + 1, N, 5) the actors' boxes at t = 0, dt, ..., horizon in the ego frame.
    """
    steps = boxes.shape[0]
    n_uni = n // 2
    t_idx = rng.integers(0, steps, size=n)
    t = t_idx * cfg.dt
    x0, x1 = cfg.x_range
    y0, y1 = cfg.y_range
    q = np.empty((n, 3))
    q[:, 2] = t
    q[:n_uni, 0] = rng.uniform(x0, x1, n_uni) + speed * t[:n_uni]
    q[:n_uni, 1] = rng.uniform(y0, y1, n_uni)
    u = rng.uniform(-0.5, 0.5, (n - n_uni, 2))
    pick = rng.random(n - n_uni)
    for j in range(n - n_uni):
        i = n_uni + j
        b = boxes[t_idx[i]]
        ok = np.isfinite(b).all(axis=1)
        ok[ok] &= (b[ok, 0] - speed * t[i] >= x0 - 10.0) & (b[ok, 0] - speed * t[i] <= x1 + 10.0)
        ok[ok] &= (b[ok, 1] >= y0) & (b[ok, 1] <= y1)
        cand = np.flatnonzero(ok)
        if not len(cand):
            q[i, 0] = rng.uniform(x0, x1) + speed * t[i]
            q[i, 1] = rng.uniform(y0, y1)
            continue
        x, y, length, width, yaw = b[cand[min(int(pick[j] * len(cand)), len(cand) - 1)]]
        lu = u[j, 0] * (length + 2 * NEAR_MARGIN)
        lv = u[j, 1] * (width + 2 * NEAR_MARGIN)
        q[i, 0] = x + np.cos(yaw) * lu - np.sin(yaw) * lv
        q[i, 1] = y + np.sin(yaw) * lu + np.cos(yaw) * lv
    return q


def targets(queries: np.ndarray, boxes: np.ndarray, history: np.ndarray, cfg: OccupancyConfig
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth of queries (Q, 3) from the boxes at t = 0 .. horizon (H + 1, N, 5) and the
    ``lag`` steps before t = 0 (lag, N, 5), all in the same frame."""
    lag = int(round(FLOW_LAG / cfg.dt))
    allb = np.concatenate([history, boxes], axis=0)  # index k + lag = time k dt
    t_idx = np.rint(queries[:, 2] / cfg.dt).astype(np.int64)
    occ = np.zeros(len(queries), bool)
    flow = np.zeros((len(queries), 2))
    valid = np.zeros(len(queries), bool)
    for k in np.unique(t_idx):
        m = np.flatnonzero(t_idx == k)
        o, f, v = occupancy_targets(queries[m, :2], allb[k + lag], allb[k], FLOW_LAG)
        occ[m], flow[m], valid[m] = o, f, v
    return occ, flow, valid


def simulate_scene_samples(seed: int, frames_per_scene: int, queries: int, cfg: OccupancyConfig,
                           library, split: str = "train") -> SampleSet:
    """The samples of one generated scene (see module docstring)."""
    from ..scene.generate import generate_scene
    from ..sensors.lidar import simulate_frame
    from ..sensors.world import rig_from_scene, world_from_scene

    scene = generate_scene(int(seed), split)
    world = world_from_scene(scene, library)
    rig = rig_from_scene(scene)
    poses, valid = scene.all_actor_poses()      # (A, T, 3), (A, T)
    dims = scene.actor_dimensions()             # (A, 3)
    ego = scene.ego_poses()
    ego_v = scene.ego_speeds()
    frames = sample_frames(seed, frames_per_scene, scene.frames, cfg)
    lag = int(round(FLOW_LAG / cfg.dt))
    H = int(round(cfg.horizon / cfg.dt))
    sweeps_cache: dict[int, np.ndarray] = {}

    def sweep(f: int) -> np.ndarray:
        if f not in sweeps_cache:
            fr = simulate_frame(world, rig, ego[f], poses[:, f], np.random.default_rng([seed, f]))
            sweeps_cache[f] = keep_points(fr.points, cfg)
        return sweeps_cache[f]

    def boxes_at(f: int, ref: np.ndarray) -> np.ndarray:
        b = np.full((len(dims), 5), np.nan)
        if 0 <= f < scene.frames:
            ok = valid[:, f]
            b[ok] = np.c_[poses[ok, f, :2], dims[ok, :2], poses[ok, f, 2]]
        return boxes_to_frame(b, ref)

    out = {k: [] for k in SampleSet.__dataclass_fields__}
    for f in frames:
        f = int(f)
        grid = bev_input([(sweep(f - k), ego[f - k]) for k in cfg.sweep_lags], ego[f], cfg)
        fut = np.stack([boxes_at(f + s, ego[f]) for s in range(H + 1)])
        hist = np.stack([boxes_at(f - lag + s, ego[f]) for s in range(lag)])
        rng = np.random.default_rng([seed, f, 2])
        q = make_queries(rng, queries, float(ego_v[f]), fut, cfg)
        occ, flow, fv = targets(q, fut, hist, cfg)
        out["grids"].append(encode_grid(grid, cfg))
        out["speed"].append(np.float32(ego_v[f]))
        out["queries"].append(q.astype(np.float32))
        out["occupied"].append(occ)
        out["flow"].append(flow.astype(np.float32))
        out["flow_valid"].append(fv)
        out["scene_seed"].append(int(seed))
        out["frame_index"].append(f)
    return SampleSet(**{k: np.asarray(np.stack(v) if k in ("grids", "queries", "occupied", "flow", "flow_valid")
                                      else np.array(v)) for k, v in out.items()})


def _cache_path(cache_dir: Path, split: str, seed: int, frames_per_scene: int, queries: int) -> Path:
    return cache_dir / f"v{DATA_VERSION}-{split}-{seed:09d}-f{frames_per_scene}-q{queries}.npz"


def save_samples(s: SampleSet, path: Path, cfg: OccupancyConfig) -> None:
    from ..fileio import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, format=np.array("adv3d-occupancy-samples"), version=np.array(DATA_VERSION),
                                grid_config=np.array(repr(cfg.to_dict())), **s.arrays())


def load_samples(path: Path, cfg: OccupancyConfig) -> SampleSet | None:
    """The cached samples, or None when the file was made for another model grid."""
    from ..errors import FileFormatError

    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["format"]) != "adv3d-occupancy-samples" or int(z["version"]) != DATA_VERSION:
                raise FileFormatError(path, "$.format", f"adv3d-occupancy-samples v{DATA_VERSION}",
                                      f"{z['format']} v{z['version']}")
            if str(z["grid_config"]) != repr(cfg.to_dict()):
                return None
            return SampleSet(**{k: z[k] for k in SampleSet.__dataclass_fields__})
    except (KeyError, ValueError, OSError) as exc:
        raise FileFormatError(path, "$", "an occupancy sample cache (.npz)", str(exc)) from None


def make_samples(seeds: Sequence[int], frames_per_scene: int, queries: int, cfg: OccupancyConfig,
                 split: str = "train", library="default", cache_dir: str | Path | None = None,
                 desc: str = "scenes", stats: dict | None = None) -> SampleSet:
    """Samples of the scenes ``seeds`` (generated on the fly), cached per scene.

    Args:
        seeds: scene seeds of ``split`` (training split: >= 100 000).
        library: "default" (the bundled benign library), None (boxes) or a ``VehicleLibrary``.
        cache_dir: cache folder (None: :func:`default_cache_dir`; "" disables the cache).
        stats: if a dict, ``cached`` / ``simulated`` scene counts and ``simulate_s`` are added.
    """
    from ..progress import progress

    if isinstance(library, str) and library == "default":
        from ..shapes.library import load_library
        library = load_library()
    cache = default_cache_dir() if cache_dir is None else (Path(cache_dir) if cache_dir != "" else None)
    sets = []
    for seed in progress(list(seeds), desc=desc, unit="scene"):
        path = _cache_path(cache, split, int(seed), frames_per_scene, queries) if cache else None
        if path is not None and path.is_file() and library is not None:
            got = load_samples(path, cfg)
            if got is not None:
                sets.append(got)
                if stats is not None:
                    stats["cached"] = stats.get("cached", 0) + 1
                continue
        t0 = time.perf_counter()
        s = simulate_scene_samples(int(seed), frames_per_scene, queries, cfg, library, split)
        if path is not None and library is not None:
            save_samples(s, path, cfg)
        sets.append(s)
        if stats is not None:
            stats["simulated"] = stats.get("simulated", 0) + 1
            stats["simulate_s"] = stats.get("simulate_s", 0.0) + time.perf_counter() - t0
    return SampleSet.concat(sets)
