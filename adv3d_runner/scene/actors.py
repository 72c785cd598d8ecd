"""Library meshes for the benign actors of a scene.

An actor's mesh is the library asset its scene file names (``actor.asset``). Where a scene
names none, :func:`assign_assets` *draws* one from every asset of the actor's class
(:func:`choose_asset`, rule ``"draw"``): rendezvous hashing of ``"<scene id>/<actor id>"``
with each candidate's id, so the draw is seeded by scene and actor, independent of the
library's order, uniform over the class, and when an asset is added only the actors the new
asset wins change (about 1 in n + 1 of its class). Generated scenes record the drawn id in the
file, so a scene keeps its meshes whatever the library becomes.

The rule of shape space v1 (``"nearest-size"``: the asset of the class with the closest
dimensions, scale-free distance ``sum_i |log(asset_i / actor_i)|``, ties by id) put the same
few meshes on almost every actor; it is kept to record the meshes the shipped scenes were
simulated with (docs/scenes.md). Classes missing from the library fall back along
``CLASS_FALLBACK`` and finally to every asset. ``actor_mesh`` loads the asset and scales it
(per axis) to the actor's box.
"""
from __future__ import annotations

import copy
import hashlib
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError, FileFormatError
from .schema import Scene

if TYPE_CHECKING:  # the library module is optional at import time (numpy-only users)
    from ..shapes.library import VehicleLibrary
    from ..shapes.mesh_cache import MeshArrays

CLASS_FALLBACK = {
    "sedan": ("hatchback", "sports", "suv"),
    "hatchback": ("sedan", "suv"),
    "sports": ("sedan", "hatchback"),
    "suv": ("pickup", "van", "sedan"),
    "van": ("suv", "pickup", "truck"),
    "pickup": ("suv", "van"),
    "truck": ("bus", "van", "garbage_truck", "fire_truck"),
    "bus": ("truck", "van"),
    "motorcycle": ("sports", "hatchback"),
    "taxi": ("sedan",),
    "police": ("sedan", "suv"),
    "ambulance": ("van",),
}


#: How an actor without a recorded asset gets one (see the module docstring).
ASSIGNMENT_RULES = ("draw", "nearest-size")


def _dimension_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Scale-free distance between boxes: sum |log(a / b)| over the 3 axes. a (N,3), b (3,)."""
    return np.abs(np.log(np.asarray(a, dtype=np.float64) / np.asarray(b, dtype=np.float64))).sum(axis=-1)


def check_assets(scene: Scene, library: "VehicleLibrary", file: str | None = None) -> None:
    """Every actor's ``asset`` (when set) is an asset of ``library``.

    Raises:
        FileFormatError: naming ``file`` (default ``scene <id>``) and ``$.actors[i].asset``.
    """
    known = set(library.ids())
    for i, actor in enumerate(scene.actors):
        if actor.asset is not None and actor.asset not in known:
            raise FileFormatError(file or f"scene {scene.id}", f"$.actors[{i}].asset",
                                  f"null or an asset id of the vehicle library {library.root / 'library.json'}",
                                  actor.asset)


def class_candidates(library: "VehicleLibrary", vehicle_class: str) -> list:
    """Assets an actor of ``vehicle_class`` may take, sorted by id: its class, else the first
    fallback class (``CLASS_FALLBACK``) the library has, else every asset."""
    candidates = list(library.by_class(vehicle_class))
    for alt in CLASS_FALLBACK.get(vehicle_class, ()):
        if candidates:
            break
        candidates = list(library.by_class(alt))
    if not candidates:
        candidates = list(library.assets)
    return sorted(candidates, key=lambda a: a.id)


def _draw_score(key: str, asset_id: str) -> int:
    """Rendezvous weight of an asset for a draw key (first 8 bytes of a SHA-256)."""
    return int.from_bytes(hashlib.sha256(f"{key}\0{asset_id}".encode()).digest()[:8], "big")


def choose_asset(library: "VehicleLibrary", vehicle_class: str, dimensions: np.ndarray | None = None,
                 key: str | None = None, rule: str = "draw") -> str | None:
    """The asset id for a vehicle of ``vehicle_class``, or None for an empty library.

    Args:
        dimensions: (L, W, H) m of the actor (rule ``"nearest-size"``).
        key: the draw's seed, ``"<scene id>/<actor id>"`` (rule ``"draw"``).
        rule: one of :data:`ASSIGNMENT_RULES`.
    Raises:
        ConfigError: unknown rule, or a rule without its argument.
    """
    if rule not in ASSIGNMENT_RULES:
        raise ConfigError(f"unknown asset rule {rule!r}; choose one of {', '.join(ASSIGNMENT_RULES)}")
    candidates = class_candidates(library, vehicle_class)
    if not candidates:
        return None
    if rule == "draw":
        if key is None:
            raise ConfigError("drawing an asset needs a key (scene id / actor id)")
        return max(candidates, key=lambda a: (_draw_score(key, a.id), a.id)).id
    if dimensions is None:
        raise ConfigError("the nearest-size rule needs the actor's dimensions")
    dims = np.array([a.dimensions for a in candidates], dtype=np.float64)
    dist = np.round(_dimension_distance(dims, dimensions), 9)  # rounding: ties are exact ties
    return candidates[int(np.argmin(dist))].id  # argmin takes the first: smallest id


def assign_assets(scene: Scene, library: "VehicleLibrary", overwrite: bool = False, rule: str = "draw") -> Scene:
    """Copy of ``scene`` where every actor without an asset (every actor with ``overwrite``)
    has one from ``library`` (:func:`choose_asset`, drawn by scene and actor id by default).

    Raises:
        ConfigError: an actor's recorded asset is not in ``library`` (names the scene, the
            actor and the library), or an unknown rule.
    """
    out = copy.deepcopy(scene)
    known = set(library.ids())
    for actor in out.actors:
        if actor.asset is None or overwrite:
            actor.asset = choose_asset(library, actor.cls, actor.dimensions, key=f"{scene.id}/{actor.id}", rule=rule)
        elif actor.asset not in known:
            raise ConfigError(f"scene {scene.id}: actor {actor.id} uses asset {actor.asset!r}, which the vehicle "
                              f"library at {library.root} does not have (give the library the scene was made "
                              "with, or reassign with `adv3d scenes assign-assets --overwrite`)")
    return out


_MESH_CACHE: dict[tuple[str, str], "MeshArrays"] = {}


def actor_mesh(library: "VehicleLibrary", asset_id: str, dimensions: np.ndarray) -> "MeshArrays":
    """The asset's mesh scaled per axis to ``dimensions`` (L, W, H) m: its bounding box becomes
    exactly the actor's box, origin at the footprint centre on the ground, +x forward.

    The library mesh comes from the content-keyed mesh cache (:mod:`adv3d_runner.shapes.mesh_cache`:
    the same arrays as reading the glb with trimesh, without importing trimesh).

    Returns:
        a new :class:`~adv3d_runner.shapes.mesh_cache.MeshArrays` (vertices (n, 3) float64,
        faces (m, 3) int64, bounds; the caller may modify it).
    """
    from ..shapes.mesh_cache import library_mesh_arrays

    key = (str(library.path_of(asset_id)), asset_id)
    if key not in _MESH_CACHE:
        _MESH_CACHE[key] = library_mesh_arrays(library.path_of(asset_id))
    mesh = _MESH_CACHE[key].copy()
    lo, hi = mesh.bounds
    extent = np.maximum(hi - lo, 1e-9)
    scale = np.asarray(dimensions, dtype=np.float64).reshape(3) / extent
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    mesh.vertices = (mesh.vertices - centre) * scale
    mesh.bounds = np.array([(lo - centre) * scale, (hi - centre) * scale])
    return mesh
