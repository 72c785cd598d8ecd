# SPDX-License-Identifier: GPL-3.0-or-later
"""Add-on state: PropertyGroups hung on ``Scene.adv3d`` and ``Object.adv3d``.

Everything the panels show lives here (saved with the .blend, undoable); operators read and write
these, never module globals, except for caches of loaded files (shape spaces) that can always be
rebuilt from the paths stored here.
"""
from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

# The class menus use the runner's one class list (pure Python, instant to import).
from adv3d_runner.vehicle_classes import DIMENSION_RANGES, VEHICLE_CLASSES

from .ops_attack import ALGORITHMS

# Room for the latent sliders: K shape dimensions (the paper uses K = 3); the width and length
# scales have their own properties. A vector property has a fixed size at registration, so it is
# sized for the largest K we support and the panel shows only the first K entries.
MAX_LATENT = 16

class ADV3D_PG_asset(bpy.types.PropertyGroup):
    """One library asset as shown in the Library panel (mirror of a ``VehicleAsset``)."""

    asset_id: StringProperty(name="Id")
    file: StringProperty(name="File", description="Mesh file, relative to the library folder")
    vehicle_class: EnumProperty(name="Class", items=[(c, c, "") for c in VEHICLE_CLASSES], default="sedan")
    length: FloatProperty(name="Length", min=0.0, soft_min=1.0, soft_max=20.0, unit="LENGTH", default=4.5)
    width: FloatProperty(name="Width", min=0.0, soft_min=0.5, soft_max=4.0, unit="LENGTH", default=1.8)
    height: FloatProperty(name="Height", min=0.0, soft_min=0.5, soft_max=5.0, unit="LENGTH", default=1.5)
    source: StringProperty(name="Source")
    licence: StringProperty(name="Licence")
    triangle_count: IntProperty(name="Triangles", min=0)
    in_shape_space: BoolProperty(name="In shape space", default=True,
                                 description="Use this asset when building the shape space")
    cleaning_report: StringProperty(name="Cleaning report", description="Cleaning report (one line per item)")
    edited: BoolProperty(default=False, options={"HIDDEN"})


class ADV3D_PG_library(bpy.types.PropertyGroup):
    path: StringProperty(name="Library", subtype="FILE_PATH",
                         description="library.json of the vehicle library")
    assets: CollectionProperty(type=ADV3D_PG_asset)
    active_index: IntProperty(name="Active asset", default=0)
    dirty: BoolProperty(default=False, options={"HIDDEN"})


def _latent_update(self, context):
    # Deferred import: the module imports bpy-heavy helpers and the shape space.
    from . import ops_shapes

    ops_shapes.schedule_preview_update(context)


class ADV3D_PG_shapes(bpy.types.PropertyGroup):
    space_path: StringProperty(name="Shape space", subtype="FILE_PATH",
                               description="Shape-space .npz built by `adv3d shapes build` or this panel")
    k: IntProperty(name="K", default=0, min=0, options={"HIDDEN"},
                   description="Number of shape dimensions of the loaded space")
    latent: FloatVectorProperty(name="Latent", size=MAX_LATENT, min=0.0, max=1.0, default=[0.5] * MAX_LATENT,
                                update=_latent_update,
                                description="Shape coordinates in [0, 1] (0 / 1 = library min / max)")
    width_scale: FloatProperty(name="Width scale", min=0.0, max=1.0, default=0.5, update=_latent_update,
                               description="Width scale in [0, 1] of the shape space's scale range")
    length_scale: FloatProperty(name="Length scale", min=0.0, max=1.0, default=0.5, update=_latent_update,
                                description="Length scale in [0, 1] of the shape space's scale range")
    live: BoolProperty(name="Live", default=True, description="Regenerate the preview as the sliders move")
    seed: IntProperty(name="Seed", default=0, min=0)
    build_resolution: IntProperty(name="Resolution", default=0, min=0, soft_max=128,
                                  description="SDF grid resolution for Build (0: the runner's default)")
    build_k: IntProperty(name="Components", default=3, min=1, max=MAX_LATENT)
    last_update_ms: FloatProperty(name="Last update", default=0.0, options={"HIDDEN"})
    nearest_asset: StringProperty(name="Nearest asset", options={"HIDDEN"})
    variance_text: StringProperty(options={"HIDDEN"})
    # Realism of the slider shape (docs/realism.md): live cheap figures, the full report on demand.
    show_realism: BoolProperty(name="Realism", default=True, update=_latent_update,
                               description="Measure the preview's realism (JSD, Mahalanobis, dimensions) live")
    realism_class: EnumProperty(
        name="Class", items=[("AUTO", "Nearest", "The class of the nearest library vehicle")]
        + [(c, c, "") for c in DIMENSION_RANGES], default="AUTO", update=_latent_update,
        description="Vehicle class whose real dimensions the shape is checked against")
    realism_live: StringProperty(options={"HIDDEN"})
    realism_full: StringProperty(options={"HIDDEN"})
    realism_ms: FloatProperty(name="Realism time", default=0.0, options={"HIDDEN"})


class ADV3D_PG_scene(bpy.types.PropertyGroup):
    path: StringProperty(name="Scene file", subtype="FILE_PATH")
    scene_id: StringProperty(name="Scene id", options={"HIDDEN"})
    text_name: StringProperty(options={"HIDDEN"},
                              description="Text datablock holding the scene file as loaded")
    # "Attack this scene" settings (the `adv3d attack` options of the same names)
    attack_algo: EnumProperty(name="Search", items=[(a, a, "") for a in ALGORITHMS], default="bo",
                              description="Search algorithm (--algo)")
    attack_budget: IntProperty(name="Budget", default=16, min=1, soft_max=200,
                               description="Queries to evaluate (--budget)")
    attack_seconds: FloatProperty(name="Seconds", default=3.0, min=0.1, soft_max=20.0,
                                  description="Episode length in s (--seconds)")
    attack_autonomy: EnumProperty(name="Autonomy", items=_stack_items,
                                  description="Stack under attack (--autonomy): every stack the runner lists "
                                              "(adv3d stacks list: its own and the registered plugins)")
    attack_seed: IntProperty(name="Seed", default=0, min=0, description="Search seed (--seed)")
    attack_error: StringProperty(options={"HIDDEN"},
                                 description="The runner's error line of the last failed attack")
    last_run: StringProperty(name="Last run", subtype="DIR_PATH", options={"HIDDEN"})


def _stack_items(self, context):
    """The runner's stacks (asked once; Blender keeps the strings of dynamic enum items only
    while Python holds them, which the runner module's cache does)."""
    from . import prefs, runner

    return runner.runner_stacks(prefs.runner_command())


def _review_items(self, context):
    from . import ops_review  # deferred: lists the replays of the chosen bundle

    return ops_review.replay_items(self, context)


class ADV3D_PG_review(bpy.types.PropertyGroup):
    path: StringProperty(name="Run bundle", subtype="FILE_PATH",
                         description="Run bundle folder (runs/NAME) or one replay file (replay.json.gz)")
    replay: EnumProperty(name="Replay", items=_review_items,
                         description="Scene and mode of the bundle to review")
    loaded: StringProperty(name="Loaded replay", options={"HIDDEN"})
    key: StringProperty(options={"HIDDEN"},
                        description="The replay the review shows: its path and content hash")
    stale: StringProperty(options={"HIDDEN"},
                          description="Why the review's replay could not be read again (file gone or changed)")


class ADV3D_PG_settings(bpy.types.PropertyGroup):
    library: PointerProperty(type=ADV3D_PG_library)
    shapes: PointerProperty(type=ADV3D_PG_shapes)
    scene: PointerProperty(type=ADV3D_PG_scene)
    review: PointerProperty(type=ADV3D_PG_review)


OBJECT_ROLES = [
    ("NONE", "None", ""),
    ("EGO", "Ego", "The ego vehicle"),
    ("ACTOR", "Actor", "A scene actor"),
    ("SENSOR", "Sensor", "A sensor mount"),
    ("ROAD", "Road", "Static background"),
    ("LANE", "Lane", "A lane centre line"),
    ("PREVIEW", "Preview", "The shape-space preview vehicle"),
    ("ASSET", "Asset", "A library asset"),
    ("PLACE", "Place", "Where a panel's objects are (their parent)"),
]


class ADV3D_PG_object(bpy.types.PropertyGroup):
    role: EnumProperty(name="Role", items=OBJECT_ROLES, default="NONE")
    key: StringProperty(name="Key", description="Actor id, sensor name, lane id or asset id")
    asset_id: StringProperty(name="Asset", description="Library asset id of an actor ('' = box)")


classes = (
    ADV3D_PG_asset,
    ADV3D_PG_library,
    ADV3D_PG_shapes,
    ADV3D_PG_scene,
    ADV3D_PG_review,
    ADV3D_PG_settings,
    ADV3D_PG_object,
)


def register_pointers() -> None:
    bpy.types.Scene.adv3d = PointerProperty(type=ADV3D_PG_settings)
    bpy.types.Object.adv3d = PointerProperty(type=ADV3D_PG_object)


def unregister_pointers() -> None:
    del bpy.types.Object.adv3d
    del bpy.types.Scene.adv3d
