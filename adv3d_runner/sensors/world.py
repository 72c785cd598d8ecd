"""The geometry a LiDAR sees: one static background BVH plus per-mesh actor BVHs.

:class:`LidarWorld` is built from plain arrays (:meth:`LidarWorld.__init__`,
:meth:`add_actor`) or from a scene file through the scene package (:func:`world_from_scene`).
Actor meshes live in their local frame (origin at the footprint centre on the ground, +x
front, docs/architecture.md "Conventions"); per-frame poses are given to
:func:`adv3d_runner.sensors.lidar.simulate_frame`, never baked into geometry, so moving an actor
costs nothing and replacing its shape (:meth:`set_actor_mesh`) builds only the new mesh's BVH.
Identical meshes share one BVH (cache keyed by content hash).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import embree
from .raycast import MeshBVH, mesh_key

__all__ = ["LidarWorld", "ActorSlot", "DEFAULT_ACTOR_REFLECTIVITY", "world_from_scene", "rig_from_scene"]

#: Diffuse reflectivity of a vehicle body (painted metal and glass averaged), in [0, 1].
DEFAULT_ACTOR_REFLECTIVITY = 0.35


@dataclass
class ActorSlot:
    """One actor of the world: its id, its mesh's BVH key, its reflectivity, and the key and
    reflectivity it was added with (kept so :meth:`LidarWorld.reset_actor_mesh` rebuilds nothing)."""

    actor_id: object
    key: str | None
    reflectivity: float
    original_key: str | None = None
    original_reflectivity: float = DEFAULT_ACTOR_REFLECTIVITY


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
        # Coherent: a frame's background rays come in packets of neighbouring azimuths; it pays
        # with AVX-512 and AVX2 kernels, not SSE4.2 (embree.coherent_pays); the hits are the same.
        self.background = MeshBVH(vertices - self.origin, faces, coherent=embree.coherent_pays())
        refl = np.asarray(reflectivity, dtype=np.float32)
        if refl.ndim == 0:
            refl = np.full(len(faces), refl, np.float32)
        if refl.shape != (len(faces),):
            raise ValueError(f"reflectivity must be a scalar or ({len(faces)},), got {refl.shape}")
        # One extra slot at the end so a miss (face -1) indexes safely.
        self.background_reflectivity = np.append(refl, np.float32(0.0))
        # Per face: unit normal and reflectivity in one 16-byte row (a trailing zero row for a
        # miss): (F + 1, 4) float32, read per return by the effects kernel (one cache line).
        table = np.zeros((len(faces) + 1, 4), np.float32)
        table[:, :3] = self.background.face_normals
        table[:, 3] = self.background_reflectivity
        self.background_table = table
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
        key = self._bvh_for(vertices, faces)
        self._actors.append(ActorSlot(actor_id, key, float(reflectivity), key, float(reflectivity)))
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

    def reset_actor_mesh(self, actor_id=None) -> None:
        """Give one actor (or every actor, for None) back the mesh it was added with; its BVH
        was kept, so nothing is built."""
        slots = self._actors if actor_id is None else [self._actors[self._index[actor_id]]]
        for slot in slots:
            slot.key, slot.reflectivity = slot.original_key, slot.original_reflectivity
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
        # Drop BVHs no actor uses any more (the meshes actors were added with stay), so
        # repeated attack queries do not grow memory.
        used = {a.key for a in self._actors} | {a.original_key for a in self._actors}
        for key in [k for k in self._bvh if k not in used]:
            del self._bvh[key]


def world_from_scene(scene, library=None, scene_dir=None) -> LidarWorld:
    """Build the :class:`LidarWorld` of a scene: background mesh + one mesh per actor.

    Actors get the library mesh chosen by ``assign_assets`` (class and closest dimensions,
    scaled to their box) when a vehicle ``library`` is given, else (or for an empty library)
    their box. Uses the scene package, imported here so the LiDAR core never depends on it.

    Args:
        scene: a loaded ``adv3d_runner.scene.schema.Scene``.
        library: a ``VehicleLibrary`` or None.
        scene_dir: folder of the scene file (for extra static meshes it references).
    """
    from ..scene import background as bg_mod

    vertices, faces, kind = bg_mod.background_mesh(scene, scene_dir=scene_dir)
    refl_table = np.asarray(bg_mod.REFLECTIVITY, dtype=np.float32)
    kind = np.asarray(kind, dtype=np.int64)
    reflectivity = refl_table[np.clip(kind, 0, len(refl_table) - 1)] if len(kind) else np.zeros(0, np.float32)
    world = LidarWorld(vertices, faces, reflectivity)
    if library is not None:
        from ..scene import actors as actors_mod

        actors_mod.check_assets(scene, library)
        scene = actors_mod.assign_assets(scene, library)
    for actor in scene.actors:
        mesh = None
        if library is not None and actor.asset is not None:
            mesh = actors_mod.actor_mesh(library, actor.asset, actor.dimensions)
        if mesh is None:
            mesh = _box_mesh(actor.dimensions)
        world.add_actor(actor.id, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    return world


def rig_from_scene(scene, model: str | None = None, path=None, **model_overrides):
    """The ego's :class:`~adv3d_runner.sensors.lidar.LidarRig` from the scene's sensor list.

    Args:
        scene: a loaded scene (``scene.ego.sensors``: model names and mount poses).
        model: replace every sensor's model by this one (e.g. ``"vlp32c"``), keeping mounts.
        path: the scene file, named in the error for an unknown model.
        model_overrides: fields changed on every model (e.g. ``ray_drop=0``).

    Raises:
        FileFormatError: a sensor names a model that is not in the model table.
    """
    from ..errors import ConfigError, FileFormatError
    from .beams import get_model, model_names
    from .lidar import LidarRig, MountedLidar

    mounts = [(s.model, np.asarray(s.mount, dtype=np.float64)) for s in scene.ego.sensors]
    if not mounts:
        mounts = [("hdl64", np.array([0.0, 0.0, 1.73, 0.0, 0.0, 0.0]))]
    rig = []
    for i, (name, mount) in enumerate(mounts):
        if model is None:
            try:
                get_model(name)
            except ConfigError:
                raise FileFormatError(path, f"$.ego.sensors[{i}].model",
                                      f"a LiDAR model ({', '.join(model_names())}, generic-N)", name) from None
        rig.append(MountedLidar(get_model(model or name, **model_overrides), mount))
    return LidarRig(rig, ego_dimensions=tuple(float(d) for d in scene.ego.dimensions))


class _Mesh:
    """Minimal vertices/faces holder (same attribute names as ``trimesh.Trimesh``)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces


_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int32)


def _box_mesh(dimensions) -> _Mesh:
    """A closed box of (length, width, height) standing on z=0, centred on its footprint: the
    fallback actor shape (outward-facing triangles)."""
    half_l, half_w, height = 0.5 * float(dimensions[0]), 0.5 * float(dimensions[1]), float(dimensions[2])
    corners = np.array([[-half_l, -half_w], [half_l, -half_w], [half_l, half_w], [-half_l, half_w]])
    vertices = np.concatenate([np.c_[corners, np.zeros(4)], np.c_[corners, np.full(4, height)]])
    return _Mesh(vertices, _BOX_FACES.copy())
