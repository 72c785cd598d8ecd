# SPDX-License-Identifier: GPL-3.0-or-later
"""Where each panel puts its objects: its own collection under the scene, and its own *place*.

Every panel (Library, Shape space, Scenes, Review) builds into one collection of its own, and
the collection's top-level objects are parented to a *place*: an empty (``<collection> place``)
whose location is where that panel's content sits in the world. Keyframes and mesh data stay in
the place's frame, so exporting reads the same numbers wherever the place is; the user may move
a place like any object.

A new place is put where it overlaps none of the other panels' content: each place records the
extent of its content (``adv3d_bounds``: x0, y0, x1, y1 in its own frame, metres); a panel whose
content would overlap another's is moved along +y past it with ``MARGIN_M`` between them. So a
review loaded next to the scene it came from sits beside it, not on top of it, and the library
row and the shape preview never land on a road.
"""
from __future__ import annotations

import bpy
import numpy as np

from . import meshdata

MARGIN_M = 20.0
PLACE_SUFFIX = " place"


def place_of(collection) -> "bpy.types.Object | None":
    """The place empty of a panel collection (None if it has none)."""
    return bpy.data.objects.get(collection.name + PLACE_SUFFIX)


def _world_bounds(place) -> np.ndarray | None:
    b = place.get("adv3d_bounds")
    if b is None or len(b) != 4:
        return None
    loc = np.array(place.matrix_world.translation)[:2]
    return np.array([b[0] + loc[0], b[1] + loc[1], b[2] + loc[0], b[3] + loc[1]])


def make_place(bscene, collection, bounds: np.ndarray) -> "bpy.types.Object":
    """Create (or reuse) the collection's place for content of local extent ``bounds``
    (x0, y0, x1, y1, metres) and put it clear of every other panel's content."""
    name = collection.name + PLACE_SUFFIX
    place = bpy.data.objects.get(name)
    if place is None:
        place = bpy.data.objects.new(name, None)
        place.empty_display_type = "PLAIN_AXES"
        place.empty_display_size = 1.0
        place.hide_render = True
        collection.objects.link(place)
        place.adv3d.role = "PLACE"
    place["adv3d_bounds"] = [float(v) for v in bounds]
    place.location = (0.0, 0.0, 0.0)
    others = []
    for obj in bscene.objects:
        if obj.adv3d.role == "PLACE" and obj is not place:
            wb = _world_bounds(obj)
            if wb is not None:
                others.append(wb)
    if others:
        o = np.array(others)
        lo, hi = o[:, :2].min(axis=0), o[:, 2:].max(axis=0)
        overlaps = not (bounds[2] + MARGIN_M <= lo[0] or bounds[0] >= hi[0] + MARGIN_M
                        or bounds[3] + MARGIN_M <= lo[1] or bounds[1] >= hi[1] + MARGIN_M)
        if overlaps:  # beside everything else, along +y (integer metres keep coordinates exact)
            place.location = (0.0, float(np.ceil(hi[1] + MARGIN_M - bounds[1])), 0.0)
    return place


def grow_place(place, bounds: np.ndarray) -> None:
    """Extend a place's recorded content extent by ``bounds`` (x0, y0, x1, y1)."""
    b = place.get("adv3d_bounds")
    if b is None:
        place["adv3d_bounds"] = [float(v) for v in bounds]
        return
    place["adv3d_bounds"] = [min(b[0], bounds[0]), min(b[1], bounds[1]), max(b[2], bounds[2]), max(b[3], bounds[3])]


def adopt(collection, place) -> None:
    """Parent the collection's top-level objects (its children collections too) to ``place``,
    keeping their local transforms (so keyframes keep their values)."""
    for obj in collection.all_objects:
        if obj.parent is None and obj is not place:
            obj.parent = place


def panel_collection(bscene, name: str) -> "bpy.types.Collection":
    """The panel's collection, linked under the scene's master collection."""
    return meshdata.get_collection(name, bscene.collection)


def world_to_place(place, xyz) -> np.ndarray:
    """World coordinates -> the place's frame (places are only translated)."""
    loc = np.zeros(3) if place is None else np.array(place.matrix_world.translation)
    return np.asarray(xyz, dtype=np.float64) - loc
