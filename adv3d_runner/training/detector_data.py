"""Training / evaluation data for the BEV detector, made with the simulator (numpy only).

Recipe (deterministic in its arguments):

* scenes: ``generate_scene(seed, split="train")`` for a range of seeds of the **training split**
  (seeds >= 100 000, their own namespace: never equal to a benchmark scene). The default
  training seeds are 100 000 + [0, N) and the held-out evaluation seeds 900 000 + [0, M):
  disjoint ranges of the same split (see ``TRAIN_SEED0`` / ``VAL_SEED0``). Layouts and
  densities cycle with the seed, so any 20 consecutive seeds cover every combination.
* actors get the benign vehicle library's meshes: each actor draws one from every asset of its
  class (``scene.actors.assign_assets``, seeded by scene and actor id; :func:`frames_scene`).
* vehicle hold-out (:func:`default_holdout`, :func:`without_assets`): training scenes may draw
  from the library *without* some assets, while evaluation scenes draw from all of them, so
  AP can be split into vehicles whose mesh was seen in training and vehicles left out
  (:func:`box_assets` gives each ground-truth box its asset id).
* frames: ``frames_per_scene`` frames per scene, evenly spaced over the 200 recorded frames with
  an offset drawn from ``default_rng([seed, 1])``; the LiDAR (the scene's rig, HDL-64E) with
  noise and ray drop from ``default_rng([seed, frame])``.
* stored per frame: the points in the ego frame inside ``CROP`` (x in [-20, 80] m,
  |y| <= 35 m, z in [0.15, 5] m: ground returns are never used by the detector), and every
  valid actor whose centre is inside the crop as an ego-frame box (x, y, length, width, yaw) with
  its number of LiDAR returns.

What counts as ground truth is decided when the data is used (:func:`split_gt`): boxes with at
least ``min_points`` returns are targets; the others (occluded or out of range, including
zero-point actors) are "ignore" boxes: no training loss inside them, and detections on them are
neither true nor false positives in the evaluation. The same rule serves training and
evaluation.

Cache: one ``.npz`` per scene (``np.savez_compressed``, loaded with ``allow_pickle=False``) in
``cache_dir`` (default ``~/.cache/adv3d/detector``), named by scene id, frame count and the data
version, so a second run reuses the work.
"""
from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..geometry.frames import boxes_to_frame
from .seeds import TRAIN_SEED0, VAL_SEED0  # noqa: F401  (re-exported)

DATA_VERSION = 1
CROP = {"x": (-20.0, 80.0), "y": (-35.0, 35.0), "z": (0.15, 5.0)}
DEFAULT_MIN_POINTS = 5
HOLDOUT_FRACTION = 0.2            # share of each class's assets left out of training by default
HOLDOUT_SALT = "adv3d-detector-holdout"  # names the default split (change it: another split)


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "adv3d" / "detector"


@dataclass
class FrameSet:
    """Frames flattened into arrays (what one cache file holds, or several concatenated).

    Attributes:
        points: (P, 3) float32 ego-frame x, y, z of all frames.
        offsets: (F + 1,) int64: frame f's points are ``points[offsets[f]:offsets[f + 1]]``.
        boxes: (B, 5) float64 ego-frame boxes of all frames; box_frame (B,) int64 their frame.
        box_points: (B,) int64 LiDAR returns on each box's actor.
        box_actor: (B,) int64 scene actor id.
        scene_seed: (F,) int64 and frame_index (F,) int64: where each frame came from.
    """

    points: np.ndarray
    offsets: np.ndarray
    boxes: np.ndarray
    box_frame: np.ndarray
    box_points: np.ndarray
    box_actor: np.ndarray
    scene_seed: np.ndarray
    frame_index: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def frame_points(self, f: int) -> np.ndarray:
        return self.points[self.offsets[f]:self.offsets[f + 1]]

    def frame_boxes(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(G, 5) boxes and (G,) point counts of frame ``f``."""
        m = self.box_frame == f
        return self.boxes[m], self.box_points[m]

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    @staticmethod
    def concat(sets: Sequence["FrameSet"]) -> "FrameSet":
        if not sets:
            return empty_frameset()
        pts, offs, fr = [], [np.zeros(1, np.int64)], []
        n_pts, n_frames = 0, 0
        for s in sets:
            pts.append(s.points)
            offs.append(s.offsets[1:] + n_pts)
            fr.append(s.box_frame + n_frames)
            n_pts += len(s.points)
            n_frames += len(s)
        cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
        return FrameSet(np.concatenate(pts), np.concatenate(offs), cat("boxes"), np.concatenate(fr),
                        cat("box_points"), cat("box_actor"), cat("scene_seed"), cat("frame_index"))


def empty_frameset() -> FrameSet:
    return FrameSet(np.zeros((0, 3), np.float32), np.zeros(1, np.int64), np.zeros((0, 5)), np.zeros(0, np.int64),
                    np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))


def split_gt(boxes: np.ndarray, n_points: np.ndarray, min_points: int = DEFAULT_MIN_POINTS
             ) -> tuple[np.ndarray, np.ndarray]:
    """(targets, ignore) boxes: actors with >= ``min_points`` returns, and the rest."""
    ok = np.asarray(n_points) >= min_points
    return np.asarray(boxes).reshape(-1, 5)[ok], np.asarray(boxes).reshape(-1, 5)[~ok]


def frame_indices(seed: int, frames_per_scene: int, n_frames: int = 200) -> np.ndarray:
    """Evenly spaced frame indices with a seeded offset."""
    k = max(1, min(int(frames_per_scene), n_frames))
    stride = n_frames // k
    offset = int(np.random.default_rng([seed, 1]).integers(stride))
    return offset + stride * np.arange(k)


def simulate_scene_frames(scene, world, rig, frames: Iterable[int], seed: int) -> FrameSet:
    """LiDAR frames of one scene with their ego-frame ground-truth boxes (see module doc).

    Args:
        scene: a loaded scene. world, rig: its ``LidarWorld`` / ``LidarRig``.
        frames: frame indices. seed: seeds the LiDAR noise per frame (``[seed, frame]``).
    """
    from ..sensors.lidar import simulate_frame

    poses, valid = scene.all_actor_poses()           # (A, T, 3), (A, T)
    dims = scene.actor_dimensions()                  # (A, 3)
    ids = np.array(scene.actor_ids, np.int64)
    ego = scene.ego_poses()
    pts_all, offs, boxes, bframe, bpts, bact, fidx = [], [0], [], [], [], [], []
    (x0, x1), (y0, y1), (z0, z1) = CROP["x"], CROP["y"], CROP["z"]
    index_of = {a: i for i, a in enumerate(world.actor_ids)}
    for k, f in enumerate(frames):
        f = int(f)
        rng = np.random.default_rng([seed, f])
        fr = simulate_frame(world, rig, ego[f], poses[:, f], rng)
        p = fr.points[:, :3]
        keep = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (np.abs(p[:, 1]) <= y1) & (p[:, 2] >= z0) & (p[:, 2] <= z1)
        pts_all.append(np.ascontiguousarray(p[keep], np.float32))
        offs.append(offs[-1] + int(keep.sum()))
        counts = np.bincount(fr.label[fr.label >= 0], minlength=len(world.actor_ids))
        ok = valid[:, f]
        if ok.any():
            world_boxes = np.c_[poses[ok, f, :2], dims[ok, :2], poses[ok, f, 2]]
            local = boxes_to_frame(world_boxes, ego[f])
            inside = (local[:, 0] >= x0) & (local[:, 0] <= x1) & (local[:, 1] >= y0) & (local[:, 1] <= y1)
            a_ids = ids[ok][inside]
            boxes.append(local[inside])
            bframe.append(np.full(int(inside.sum()), k, np.int64))
            bpts.append(np.array([counts[index_of[a]] if a in index_of else 0 for a in a_ids], np.int64))
            bact.append(a_ids)
        fidx.append(f)
    cat = lambda xs, shape, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(shape, dt)  # noqa: E731
    n = len(fidx)
    return FrameSet(cat(pts_all, (0, 3), np.float32), np.array(offs, np.int64), cat(boxes, (0, 5), np.float64),
                    cat(bframe, (0,), np.int64), cat(bpts, (0,), np.int64), cat(bact, (0,), np.int64),
                    np.full(n, seed, np.int64), np.array(fidx, np.int64))


def default_holdout(library, fraction: float = HOLDOUT_FRACTION) -> list[str]:
    """The default vehicle hold-out: about ``fraction`` of each class's assets (stratified).

    Per class with ``n`` assets, ``min(n - 1, floor(fraction * n + 1/2))`` are held out (round
    half up, and never a class's last asset, so every class keeps a mesh in training): for the
    bundled 38-asset library 2 of 12 sedans and 1 of the 4 hatchbacks, sports cars, pickups and
    trucks and of the 3 SUVs, 7 in all; classes of 1-2 assets keep all of them. Which ones: the
    class's assets ranked by ``sha256(HOLDOUT_SALT + "\\0" + id)``, the first ones held out, so
    the split depends on the ids only (not on the library's order) and adding an asset to a
    class changes the split of that class only.

    Returns:
        the held-out asset ids, sorted.
    """
    by_class: dict[str, list[str]] = {}
    for a in library.assets:
        by_class.setdefault(a.vehicle_class, []).append(a.id)
    out = []
    for ids in by_class.values():
        ranked = sorted(ids, key=lambda i: (hashlib.sha256(f"{HOLDOUT_SALT}\0{i}".encode()).hexdigest(), i))
        n_hold = min(len(ids) - 1, int(np.floor(fraction * len(ids) + 0.5)))
        out.extend(ranked[:n_hold])
    return sorted(out)


def resolve_holdout(arg: str | None, library) -> list[str]:
    """The asset ids a ``--holdout-assets`` value names: ``none`` / empty -> [], ``default`` ->
    :func:`default_holdout`, else comma-separated asset ids of ``library``.

    Raises:
        ConfigError: an unknown id, no library, or a class left without any asset.
    """
    from ..errors import ConfigError

    text = (arg or "").strip()
    if text.lower() in ("", "none"):
        return []
    if library is None:
        raise ConfigError("--holdout-assets needs a vehicle library (not --library none)")
    if text.lower() == "default":
        return default_holdout(library)
    ids = sorted({t.strip() for t in text.split(",") if t.strip()})
    unknown = [i for i in ids if i not in set(library.ids())]
    if unknown:
        raise ConfigError(f"--holdout-assets: no asset {', '.join(unknown)} in the vehicle library at {library.root} "
                          "(see `adv3d assets list`)")
    kept = {a.vehicle_class for a in library.assets if a.id not in ids}
    emptied = sorted({a.vehicle_class for a in library.assets} - kept)
    if emptied:
        raise ConfigError(f"--holdout-assets leaves no asset of class {', '.join(emptied)} for training "
                          "(keep at least one per class)")
    return ids


def without_assets(library, asset_ids: Sequence[str]):
    """A copy of ``library`` (same folder) without the assets ``asset_ids``: the training
    library of a hold-out. Its fingerprint differs, so its frames are cached apart; an actor
    that drew a held-out asset from the full library draws again among the class's other
    assets (rendezvous hashing: every other actor keeps its mesh)."""
    from ..shapes.library import VehicleLibrary

    drop = set(asset_ids)
    return VehicleLibrary(root=library.root, assets=[a for a in library.assets if a.id not in drop],
                          excluded=[dict(e) for e in library.excluded])


def frames_scene(seed: int, split: str, library):
    """The scene :func:`make_frames` simulates for ``seed``: ``generate_scene(seed, split)``
    with every actor's asset drawn from ``library`` (None: actors stay boxes)."""
    from ..scene.actors import assign_assets
    from ..scene.generate import generate_scene

    scene = generate_scene(int(seed), split)
    return assign_assets(scene, library) if library is not None else scene


def box_assets(fs: FrameSet, library, split: str = "train") -> np.ndarray:
    """The asset id of every box of ``fs`` (frames of ``split`` scenes made with ``library``):
    (B,) str, "" for actors without a mesh. Re-generates each scene (about 0.35 s) instead of
    storing ids in the frame cache."""
    asset_of: dict[tuple[int, int], str] = {}
    for seed in np.unique(fs.scene_seed):
        scene = frames_scene(int(seed), split, library)
        for actor in scene.actors:
            asset_of[(int(seed), int(actor.id))] = actor.asset or ""
    seeds = fs.scene_seed[fs.box_frame] if len(fs.box_frame) else np.zeros(0, np.int64)
    return np.array([asset_of.get((int(s), int(a)), "") for s, a in zip(seeds, fs.box_actor)], dtype=str)


def _cache_path(cache_dir: Path, split: str, seed: int, frames_per_scene: int, library_tag: str) -> Path:
    return cache_dir / f"v{DATA_VERSION}-{split}-{seed:09d}-f{frames_per_scene}-{library_tag}.npz"


def save_frameset(fs: FrameSet, path: Path) -> None:
    from ..fileio import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, format=np.array("adv3d-detector-frames"), version=np.array(DATA_VERSION),
                                **fs.arrays())


def load_frameset(path: Path) -> FrameSet:
    from ..validate import read_npz

    z = read_npz(path, "detector frame cache (.npz)")
    z.header("adv3d-detector-frames", DATA_VERSION)
    z.require(FrameSet.__dataclass_fields__)
    return FrameSet(**{k: z.members[k] for k in FrameSet.__dataclass_fields__})


def make_frames(seeds: Sequence[int], frames_per_scene: int, split: str = "train", library="default",
                cache_dir: str | Path | None = None, desc: str = "scenes", stats: dict | None = None) -> FrameSet:
    """Simulated frames of the scenes ``seeds`` (generated on the fly), cached per scene.

    Args:
        seeds: scene seeds of ``split`` (training split: >= 100 000).
        frames_per_scene: frames taken from each 200-frame scene.
        library: "default" (the bundled benign vehicle library), None (actors as boxes), or a
            ``VehicleLibrary``.
        cache_dir: cache folder (None: :func:`default_cache_dir`; False-y string "" disables).
        stats: if a dict, ``cached`` / ``simulated`` scene counts and ``simulate_s`` are added.
    """
    from ..progress import progress
    from ..sensors.world import rig_from_scene, world_from_scene

    if isinstance(library, str) and library == "default":
        from ..shapes.library import load_library
        library = load_library()
    # the cache is keyed by the library's fingerprint: actors draw their meshes from it
    # (``scene.actors.assign_assets``), so another library (or assignment) means other frames
    if library is not None:
        from ..shapes.library import library_fingerprint

        tag = "lib-" + library_fingerprint(library).split(":", 1)[1][:12]
    else:
        tag = "box"
    cache = default_cache_dir() if cache_dir is None else (Path(cache_dir) if cache_dir != "" else None)
    sets = []
    for seed in progress(list(seeds), desc=desc, unit="scene"):
        path = _cache_path(cache, split, int(seed), frames_per_scene, tag) if cache else None
        if path is not None and path.is_file():
            sets.append(load_frameset(path))
            if stats is not None:
                stats["cached"] = stats.get("cached", 0) + 1
            continue
        t0 = time.perf_counter()
        scene = frames_scene(int(seed), split, library)
        world = world_from_scene(scene, library)
        rig = rig_from_scene(scene)
        fs = simulate_scene_frames(scene, world, rig, frame_indices(int(seed), frames_per_scene, scene.frames), int(seed))
        if path is not None:
            save_frameset(fs, path)
        sets.append(fs)
        if stats is not None:
            stats["simulated"] = stats.get("simulated", 0) + 1
            stats["simulate_s"] = stats.get("simulate_s", 0.0) + time.perf_counter() - t0
    return FrameSet.concat(sets)
