"""The geometry a LiDAR sees: one static background BVH plus per-mesh actor BVHs.

:class:`LidarWorld` is built from plain arrays (:meth:`LidarWorld.__init__`,
:meth:`add_actor`) or from a scene file through the scene package (:func:`world_from_scene`).
Actor meshes live in their local frame (origin at the footprint centre on the ground, +x
front, per DESIGN.md); per-frame poses are given to
:func:`adv3d_runner.sensors.lidar.simulate_frame`, never baked into geometry, so moving an actor
costs nothing and replacing its shape (:meth:`set_actor_mesh`) builds only the new mesh's BVH.
Identical meshes share one BVH (cache keyed by content hash).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .raycast import MeshBVH, mesh_key

__all__ = ["LidarWorld", "ActorSlot", "DEFAULT_ACTOR_REFLECTIVITY", "world_from_scene"]

#: Diffuse reflectivity of a vehicle body (painted metal and glass averaged), in [0, 1].
DEFAULT_ACTOR_REFLECTIVITY = 0.35


@dataclass
class ActorSlot:
    """One actor of the world: its id, its mesh's BVH key and its reflectivity."""

    actor_id: object
    key: str | None
    reflectivity: float


class LidarWorld:
    """Static background + actor meshes for ray casting.

    Args:
        vertices: (V, 3) float64 background vertices in the map frame, metres.
        faces: (F, 3) int background faces (F may be 0: no background).
        reflectivity: per-face (F,) reflectivity in [0, 1], or one scalar for all faces.
        origin: (3,) point subtracted from the background before the float32 cast; defaults
            to the centre of the background's bounding box (x, y only) so large map
            coordinates keep float32 precision.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, reflectivity: np.ndarray | float = 0.2,
                 origin: np.ndarray | None = None):
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if origin is None:
            origin = np.zeros(3)
            if len(vertices):
                origin[:2] = 0.5 * (vertices[:, :2].min(axis=0) + vertices[:, :2].max(axis=0))
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.background = MeshBVH(vertices - self.origin, faces)
        refl = np.asarray(reflectivity, dtype=np.float32)
        if refl.ndim == 0:
            refl = np.full(len(faces), refl, np.float32)
        if refl.shape != (len(faces),):
            raise ValueError(f"reflectivity must be a scalar or ({len(faces)},), got {refl.shape}")
        # One extra slot at the end so a miss (face -1) indexes safely.
        self.background_reflectivity = np.append(refl, np.float32(0.0))
        self._bvh: dict[str, MeshBVH] = {}
        self._actors: list[ActorSlot] = []
        self._index: dict[str, int] = {}
        self.ego: MeshBVH | None = None

    # -- actors ------------------------------------------------------------------------------
    @property
    def actor_ids(self) -> tuple:
        """Actor ids in the order of :func:`simulate_frame`'s ``actor_poses`` rows and labels."""
        return tuple(a.actor_id for a in self._actors)

    def actor_index(self, actor_id) -> int:
        """Label (row index) of an actor id."""
        return self._index[actor_id]

    def _bvh_for(self, vertices: np.ndarray | None, faces: np.ndarray | None) -> str | None:
        if vertices is None or faces is None or len(faces) == 0:
            return None
        key = mesh_key(vertices, faces)
        if key not in self._bvh:
            self._bvh[key] = MeshBVH(vertices, faces)
        return key

    def add_actor(self, actor_id, vertices: np.ndarray | None, faces: np.ndarray | None,
                  reflectivity: float = DEFAULT_ACTOR_REFLECTIVITY) -> int:
        """Add an actor with its mesh in its local frame; returns its index (its label).

        A ``None`` or empty mesh gives an actor that is never hit (e.g. no asset yet).
        """
        if actor_id in self._index:
            raise ValueError(f"actor {actor_id!r} already in the world")
        self._index[actor_id] = len(self._actors)
        self._actors.append(ActorSlot(actor_id, self._bvh_for(vertices, faces), float(reflectivity)))
        self._prune()
        return self._index[actor_id]

    def set_actor_mesh(self, actor_id, vertices: np.ndarray | None, faces: np.ndarray | None,
                       reflectivity: float | None = None) -> None:
        """Replace one actor's mesh (e.g. by a decoded adversarial shape), local frame.

        Only the new mesh's BVH is built (none if an identical mesh is cached); the background
        and every other actor are untouched.
        """
        slot = self._actors[self._index[actor_id]]
        slot.key = self._bvh_for(vertices, faces)
        if reflectivity is not None:
            slot.reflectivity = float(reflectivity)
        self._prune()

    def set_ego_mesh(self, vertices: np.ndarray | None, faces: np.ndarray | None) -> None:
        """Give the ego its own mesh (ego frame): rays hitting it are blocked and return nothing."""
        self.ego = None if vertices is None or faces is None or len(faces) == 0 else MeshBVH(vertices, faces)

    def actor_bvh(self, index: int) -> MeshBVH | None:
        key = self._actors[index].key
        return None if key is None else self._bvh[key]

    def actor_reflectivity(self) -> np.ndarray:
        """(A,) float32 reflectivity per actor."""
        return np.array([a.reflectivity for a in self._actors], dtype=np.float32)

    @property
    def n_cached_meshes(self) -> int:
        """Number of distinct actor BVHs held."""
        return len(self._bvh)

    def _prune(self) -> None:
        # Drop BVHs no actor uses any more, so repeated attack queries do not grow memory.
        used = {a.key for a in self._actors}
        for key in [k for k in self._bvh if k not in used]:
            del self._bvh[key]


def world_from_scene(scene, library=None) -> LidarWorld:
    """Build the :class:`LidarWorld` of a scene: background mesh + one library mesh per actor.

    Uses the scene package (``background_mesh``, ``assign_assets``, ``actor_mesh``); imported
    here so the LiDAR core never depends on it.
    """
    from ..scene import background as bg_mod

    vertices, faces, kind = bg_mod.background_mesh(scene)
    refl_table = _reflectivity_table(bg_mod)
    kind = np.asarray(kind, dtype=np.int64)
    reflectivity = refl_table[np.clip(kind, 0, len(refl_table) - 1)] if len(kind) else np.zeros(0)
    world = LidarWorld(vertices, faces, reflectivity)
    from ..scene import actors as actors_mod

    assets = {}
    if library is not None:
        assets = actors_mod.assign_assets(scene, library) or {}
    for actor in scene.actors:
        asset_id = assets.get(actor.id) if isinstance(assets, dict) else None
        mesh = None
        if library is not None and asset_id is not None:
            mesh = actors_mod.actor_mesh(library, asset_id, actor.dimensions)
        if mesh is None:
            mesh = _box_mesh(actor.dimensions)
        world.add_actor(actor.id, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    return world


def _reflectivity_table(bg_mod) -> np.ndarray:
    """Reflectivity per surface kind from the background module (array, dict or callable)."""
    table = getattr(bg_mod, "SURFACE_REFLECTIVITY", None)
    if table is None:
        table = getattr(bg_mod, "REFLECTIVITY", None)
    if isinstance(table, dict):
        n = max(int(k) for k in table) + 1
        out = np.full(n, 0.2, np.float32)
        for k, v in table.items():
            out[int(k)] = float(v)
        return out
    if table is None:
        return np.array([0.2], np.float32)
    return np.asarray(table, dtype=np.float32).reshape(-1)


def _box_mesh(dimensions) -> "object":
    """A box of (length, width, height) standing on z=0: the fallback actor shape."""
    import trimesh

    length, width, height = (float(d) for d in dimensions)
    box = trimesh.creation.box((length, width, height))
    box.apply_translation((0.0, 0.0, height / 2.0))
    return box
