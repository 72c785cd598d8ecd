"""Adv3D Blender extension: curate the vehicle library, explore the shape space with live
sliders, author scenes, review attack runs. A thin UI over ``adv3d_runner`` (shapes + scene, numpy only), which
ships with the extension as a wheel (see ``docs/blender.md``); it never imports torch.

Layout follows glTF-Blender-IO: properties in PropertyGroups (``props``), thin operators per
area (``ops_library``, ``ops_shapes``, ``ops_scene``, ``ops_review``), panels (``panels``); every class is in
the ``classes`` tuple, registered in order and unregistered in reverse.
"""
from __future__ import annotations

import bpy

from . import ops_library, ops_review, ops_scene, ops_shapes, panels, props, review

classes = props.classes + ops_library.classes + ops_shapes.classes + ops_scene.classes + ops_review.classes + panels.classes


def register() -> None:
    for cls in classes:
        bpy.utils.register_class(cls)
    props.register_pointers()
    ops_review.add_handlers()


def unregister() -> None:
    ops_shapes.cancel_timers()
    review.remove_handler()
    ops_review.remove_handlers()
    props.unregister_pointers()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
