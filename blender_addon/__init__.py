# SPDX-License-Identifier: GPL-3.0-or-later
"""Adv3D Blender extension: curate the vehicle library, explore the shape space with live
sliders, author scenes and attack them, review attack runs. A thin UI over ``adv3d_runner``
(shapes, scene and the replay loader: numpy only), which ships with the extension as a wheel
(see ``docs/blender.md``); it never imports torch (attacks run in the runner, a separate process).

Layout follows glTF-Blender-IO: properties in PropertyGroups (``props``), preferences
(``prefs``), thin operators per area (``ops_library``, ``ops_shapes``, ``ops_scene``,
``ops_attack``, ``ops_review``), panels (``panels``); every class is in the ``classes`` tuple,
registered in order and unregistered in reverse. Long work runs as modal jobs (``jobs``).
"""
from __future__ import annotations

import bpy

from . import jobs, ops_attack, ops_library, ops_review, ops_scene, ops_shapes, panels, prefs, props

classes = (prefs.classes + props.classes + ops_library.classes + ops_shapes.classes + ops_scene.classes
           + ops_attack.classes + ops_review.classes + panels.classes)


def menu_import(self, context):
    self.layout.operator("adv3d.library_import", text="Adv3D vehicles to library (.glb/.obj/.fbx/.json/...)")
    self.layout.operator("adv3d.scene_load", text="Adv3D scene (.json/.json.gz)").browse = True


def menu_export(self, context):
    self.layout.operator("adv3d.scene_export", text="Adv3D scene (.json/.json.gz)")
    self.layout.operator("adv3d.shapes_export", text="Adv3D shape-space vehicle (.glb/.obj/.ply/.stl)")


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    props.register_pointers()
    ops_review.add_handlers()
    bpy.types.TOPBAR_MT_file_import.append(menu_import)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)


def unregister() -> None:
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    jobs.cancel_all()
    ops_shapes.cancel_timers()
    ops_review.remove_handlers()
    props.unregister_pointers()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
