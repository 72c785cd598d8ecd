"""Incremental LiDAR simulation: reuse what the dynamic actors cannot change.

An attack simulates the same scene over and over with only a few actors' shapes changed (the
*dynamic* actors). Every ray's nearest hit on the background, the ego body and every other
actor (the *static* layers) is the same whenever the frame's geometry is: the ego pose and the
static actors' poses, bit for bit (open loop always; closed loop until the new shape changes a
decision of the stack). :class:`StaticRayCache` keeps, per such frame, the hits of the static
layers alone and casts again only the rays that can reach a dynamic actor.

Exactness. :func:`~adv3d_runner.sensors.lidar.cast_rays` casts the layers one after the other
(background, ego body, actors in row order), each with the current nearest distances as
Embree's ``tfar``. The cache replays exactly that sequence, ray by ray:

* the static fold S (every static layer in order, the dynamic ones skipped) is stored, with,
  for each dynamic actor a, the rays whose distance a later static layer changed and their
  distance just before a (so the limit a's cast gets, S patched back, is the plain path's);
* a ray that no dynamic actor takes saw every static layer with the same limits as in S, so
  its S entry is the plain result;
* a ray that a dynamic actor takes continues through the static layers after it, cast again
  for that ray with its new limit, in the plain path's order and only where the plain path
  casts (each static actor's culling window is stored with the entry).

Every per-ray value is computed by the same elementwise code as the plain path, so the hits,
and therefore the points after the sensor effects (which use the caller's random generator in
the same order), are identical (tested frame by frame and on whole attack journals).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .lidar import LidarRig, RayHits, _Cast, _take_hits

__all__ = ["StaticRayCache"]

#: Default memory bound of one cache (bytes): about 70 frames of a 133k-ray HDL-64E with 30 actors
#: (a whole 5 s open-loop path and the first frames of the closed-loop ones).
DEFAULT_MAX_BYTES = 128 * 2**20


@dataclass
class _Entry:
    """The static layers' hits of one sensor in one frame geometry."""

    t: np.ndarray                      # (N,) float32, the static fold S
    label: np.ndarray                  # (N,) int32
    prim_bg: np.ndarray                # (N,) int32
    cos_rows: np.ndarray               # (H,) int32 rays whose nearest static hit is an actor
    cos_vals: np.ndarray               # (H,) float32 their |cos incidence|
    before: dict                       # dynamic row -> (rays (D,) int32, t (D,) float32) where S differs
    windows: dict                      # static row after the first dynamic one -> rays (int32)
    nbytes: int = 0
    used: int = 0                      # times served from the cache


class StaticRayCache:
    """Static-layer hits of a :class:`~adv3d_runner.sensors.world.LidarWorld`, per frame
    geometry, for frames that differ only in the shapes of the ``dynamic`` actors.

    Pass it to :func:`~adv3d_runner.sensors.lidar.simulate_frame` (``cache=``) for every frame
    of every episode in this world and rig; it is checked on each use: a different rig object,
    or a static actor whose mesh changed, empties it.

    Args:
        world: the world it caches (its background, ego body and static actors' meshes).
        dynamic: world rows (labels) of the actors whose meshes change between episodes.
        max_bytes: memory bound; frames never served from the cache are dropped first (the
            newest first), then the least recently used ones.

    Attributes:
        hits, misses: frames served from the cache / simulated and stored.
    """

    def __init__(self, world, dynamic, max_bytes: int = DEFAULT_MAX_BYTES):
        self.world = world
        self.dynamic = np.array(sorted({int(i) for i in dynamic}), dtype=np.int64)
        n = len(world.actor_ids)
        if self.dynamic.size and (self.dynamic[0] < 0 or self.dynamic[-1] >= n):
            raise ValueError(f"dynamic actor rows must be in 0..{n - 1}, got {self.dynamic.tolist()}")
        self.max_bytes = int(max_bytes)
        self._is_dynamic = np.zeros(n, bool)
        self._is_dynamic[self.dynamic] = True
        self._entries: OrderedDict[bytes, _Entry] = OrderedDict()
        self._bytes = 0
        self._rig: LidarRig | None = None
        self._signature = self._static_signature()
        self.hits = 0
        self.misses = 0

    # ------------------------------------------------------------------ bookkeeping
    def _static_signature(self) -> tuple:
        w = self.world
        keys = tuple(None if self._is_dynamic[i] else w._actors[i].key for i in range(len(w.actor_ids)))
        return (w.background, w.ego, keys)  # the BVH objects themselves (compared by identity)

    def clear(self) -> None:
        """Forget every stored frame."""
        self._entries.clear()
        self._bytes = 0

    @property
    def nbytes(self) -> int:
        """Memory held by the stored frames."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._entries)

    def _key(self, k: int, ego: np.ndarray, poses: np.ndarray) -> bytes:
        static = poses.copy()
        static[self.dynamic] = 0.0
        static[~np.isfinite(static).all(axis=1)] = np.nan  # one NaN pattern for "absent"
        return b"".join([np.int64(k).tobytes(), ego.tobytes(), static.tobytes()])

    def _store(self, key: bytes, entry: _Entry) -> None:
        entry.nbytes = (entry.t.nbytes + entry.label.nbytes + entry.prim_bg.nbytes + entry.cos_rows.nbytes
                        + entry.cos_vals.nbytes + sum(a.nbytes + b.nbytes for a, b in entry.before.values())
                        + sum(0 if w is None else w.nbytes for w in entry.windows.values()))
        if entry.nbytes > self.max_bytes:
            return
        self._entries[key] = entry
        self._bytes += entry.nbytes
        while self._bytes > self.max_bytes:
            # Frames never served yet go first, the newest of them first: once a closed-loop
            # path has diverged from every earlier one its frames are not seen again, while
            # the first frames, which every query shares, were stored first. Then the least
            # recently used frame. (Frames never served keep their insertion order here: only
            # a hit moves an entry.)
            victim = next((k for k in reversed(self._entries) if self._entries[k].used == 0), None)
            if victim is None:
                victim = next(iter(self._entries))
            self._bytes -= self._entries.pop(victim).nbytes

    # ------------------------------------------------------------------ casting
    def cast(self, world, rig: LidarRig, k: int, ego: np.ndarray, poses: np.ndarray, present: np.ndarray,
             stats: dict | None = None) -> RayHits:
        """The hits of sensor ``k`` (as :func:`~adv3d_runner.sensors.lidar.cast_rays` with
        culling), from the stored static hits of this frame geometry when there are some."""
        if world is not self.world:
            raise ValueError("StaticRayCache used with another world")
        signature = self._static_signature()
        if rig is not self._rig or signature != self._signature:
            self.clear()
            self._rig, self._signature = rig, signature
        cast = _Cast(rig.sensors[k], ego, stats)
        key = self._key(k, ego, poses)
        entry = self._entries.get(key)
        if entry is None:
            self.misses += 1
            entry = self._static_fold(cast, poses, present)
            self._store(key, entry)
        else:
            self.hits += 1
            entry.used += 1
            self._entries.move_to_end(key)
        hits = self._dynamic(cast, entry, poses, present)
        cast.record(stats)
        return hits

    def _static_fold(self, cast: _Cast, poses: np.ndarray, present: np.ndarray) -> _Entry:
        """S: the background, the ego body and the static actors in row order (the plain
        path with the dynamic actors left out), plus what replaying needs."""
        world = self.world
        hits = cast.background(world)
        first_dynamic = int(self.dynamic[0]) if self.dynamic.size else None
        snapshots: dict[int, np.ndarray] = {}
        windows: dict[int, np.ndarray] = {}
        pending = list(self.dynamic)

        def before_cast(i: int, rays: np.ndarray) -> None:
            # the limits a dynamic actor before this one would get (nothing changes hits.t
            # between two casts, so the moment of the next cast is the moment of its row)
            while pending and pending[0] < i:
                snapshots[int(pending.pop(0))] = hits.t.copy()
            if first_dynamic is not None and i > first_dynamic:
                windows[i] = rays.astype(np.int32)

        static = [int(i) for i in present if not self._is_dynamic[i]]
        cast.actors(world, hits, static, poses, True, before_cast)
        before = {}
        for a in self.dynamic:
            snap = snapshots.get(int(a))
            if snap is None:  # no static actor after it: S is what it would see
                before[int(a)] = (np.zeros(0, np.int32), np.zeros(0, np.float32))
                continue
            changed = np.flatnonzero(snap != hits.t)
            before[int(a)] = (changed.astype(np.int32), snap[changed])
        if hits.cos_actor is None:
            cos_rows, cos_vals = np.zeros(0, np.int32), np.zeros(0, np.float32)
        else:
            cos_rows = np.flatnonzero(hits.label >= 0).astype(np.int32)
            cos_vals = hits.cos_actor[cos_rows]
        return _Entry(hits.t, hits.label, hits.prim_bg, cos_rows, cos_vals, before, windows)

    def _dynamic(self, cast: _Cast, entry: _Entry, poses: np.ndarray, present: np.ndarray) -> RayHits:
        """The plain path's hits from S: cast the dynamic actors with the limits they would
        have had, and carry the rays they take through the static layers after them."""
        world = self.world
        n = len(entry.t)
        hits = RayHits(entry.t.copy(), entry.label, entry.prim_bg, None)
        if entry.cos_rows.size:
            hits.cos_actor = np.zeros(n, np.float32)
            hits.cos_actor[entry.cos_rows] = entry.cos_vals
        taken = None  # bool (N,): rays a dynamic actor took (their limits now differ from S)
        label_copied = False
        for i in present:
            i = int(i)
            if self._is_dynamic[i]:
                bvh = world.actor_bvh(i)
                if bvh is None:
                    continue
                rays = cast.window(bvh, poses[i], True)
                if rays is False:
                    continue
                # the limits the plain path gives this actor: S before the later static
                # layers, except for rays already taken by an earlier dynamic actor
                limits = hits.t
                back_rays, back_t = entry.before[i]
                if back_rays.size:
                    limits = hits.t.copy()
                    if taken is None:
                        limits[back_rays] = back_t
                    else:
                        keep = ~taken[back_rays]
                        limits[back_rays[keep]] = back_t[keep]
                actor = cast.actor(bvh, poses[i], rays, limits)
                if (actor.prim >= 0).any():
                    if not label_copied:  # the entry's labels are shared until written
                        hits.label = hits.label.copy()
                        label_copied = True
                    rows = _take_hits(hits, i, actor)
                    if taken is None:
                        taken = np.zeros(n, bool)
                    taken[rows] = True
            elif taken is not None and i in entry.windows:
                # a static actor after a dynamic one: again for the rays that one took
                win = entry.windows[i]
                rays = win[taken[win]].astype(np.intp)
                if rays.size == 0:
                    continue
                _take_hits(hits, i, cast.actor(world.actor_bvh(i), poses[i], rays, hits.t))
        return hits
