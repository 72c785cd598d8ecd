"""Library meshes for the benign actors of a scene.

``assign_assets`` gives every actor without an asset the library asset of its class whose
dimensions are closest (scale-free distance ``sum_i |log(asset_i / actor_i)|`` over length,
width, height; ties broken by asset id), so the choice is deterministic and independent of the
library's order. Classes missing from the library fall back along ``CLASS_FALLBACK`` and finally
to every asset. ``actor_mesh`` loads the asset and scales it (per axis) to the actor's box.
``check_assets`` checks the asset ids a scene names against a library (``scenes validate``,
and every world built from a scene), so an unknown id is one clear error, not a KeyError.
"""
from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FileFormatError
from .schema import Scene

if TYPE_CHECKING:  # the library module is optional at import time (numpy-only users)
    from ..shapes.library import VehicleLibrary

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


def choose_asset(library: "VehicleLibrary", vehicle_class: str, dimensions: np.ndarray) -> str | None:
    """The asset id for a vehicle of ``vehicle_class`` and ``dimensions`` (L, W, H) m, or None
    for an empty library."""
    candidates = list(library.by_class(vehicle_class))
    for alt in CLASS_FALLBACK.get(vehicle_class, ()):
        if candidates:
            break
        candidates = list(library.by_class(alt))
    if not candidates:
        candidates = list(library.assets)
    if not candidates:
        return None
    candidates.sort(key=lambda a: a.id)
    dims = np.array([a.dimensions for a in candidates], dtype=np.float64)
    dist = np.round(_dimension_distance(dims, dimensions), 9)  # rounding: ties are exact ties
    return candidates[int(np.argmin(dist))].id  # argmin takes the first: smallest id


def assign_assets(scene: Scene, library: "VehicleLibrary", overwrite: bool = False) -> Scene:
    """Copy of ``scene`` where every actor (without an asset, or all with ``overwrite``) has a
    library asset chosen by class and closest dimensions."""
    out = copy.deepcopy(scene)
    for actor in out.actors:
        if actor.asset is None or overwrite:
            actor.asset = choose_asset(library, actor.cls, actor.dimensions)
    return out


_MESH_CACHE: dict[tuple[str, str], object] = {}


def actor_mesh(library: "VehicleLibrary", asset_id: str, dimensions: np.ndarray):
    """The asset's mesh scaled per axis to ``dimensions`` (L, W, H) m: its bounding box becomes
    exactly the actor's box, origin at the footprint centre on the ground, +x forward.

    Returns:
        a new ``trimesh.Trimesh`` (the caller may modify it).
    """
    from ..shapes.library import load_asset_mesh

    key = (str(library.path_of(asset_id)), asset_id)
    if key not in _MESH_CACHE:
        _MESH_CACHE[key] = load_asset_mesh(library, asset_id)
    mesh = _MESH_CACHE[key].copy()
    lo, hi = mesh.bounds
    extent = np.maximum(hi - lo, 1e-9)
    scale = np.asarray(dimensions, dtype=np.float64).reshape(3) / extent
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    mesh.vertices = (np.asarray(mesh.vertices) - centre) * scale
    return mesh
