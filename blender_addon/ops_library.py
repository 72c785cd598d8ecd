"""Library panel operators: load / save library.json, edit assets, import vehicle files.

The panel mirrors the library in ``Scene.adv3d.library.assets``; the file stays the source of
truth: saving re-reads library.json with ``adv3d_runner.shapes.library.load_library``, applies
only the edited fields (class, in-shape-space flag) and writes it back with ``save_library``, so
every field the panel does not show (source, licence, curation, cleaning, excluded) is kept.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import meshdata, runner
from .props import VEHICLE_CLASSES

ASSET_COLLECTION = "Adv3D Library"


# --------------------------------------------------------------------------- props <-> library

def _class_for_ui(cls: str) -> str:
    return cls if cls in VEHICLE_CLASSES else "other"


def fill_props(lib_props, library) -> None:
    """Mirror a ``VehicleLibrary`` into the panel's collection (replacing its content)."""
    lib_props.assets.clear()
    for asset in library.assets:
        item = lib_props.assets.add()
        item.asset_id = asset.id
        item.file = asset.file
        item.vehicle_class = _class_for_ui(asset.vehicle_class)
        item.length, item.width, item.height = asset.dimensions
        item.source = ", ".join(f"{k}: {v}" for k, v in asset.source.items() if isinstance(v, (str, int, float)))
        item.licence = str(asset.licence.get("name", ""))
        item.triangle_count = asset.triangle_count
        item.in_shape_space = asset.in_shape_space
        item.cleaning_report = json.dumps(asset.cleaning, sort_keys=True)
        item.edited = False
    lib_props.active_index = min(lib_props.active_index, max(len(lib_props.assets) - 1, 0))
    lib_props.dirty = False


def library_from_props(lib_props):
    """The library file with the panel's edits applied (not written)."""
    from adv3d_runner.shapes.library import load_library

    library = load_library(bpy.path.abspath(lib_props.path))
    for item in lib_props.assets:
        try:
            asset = library.get(item.asset_id)
        except KeyError:
            continue
        cls = asset.vehicle_class
        # "other" in the UI stands for any class outside the fixed menu: keep the file's value.
        if item.vehicle_class != _class_for_ui(cls):
            cls = item.vehicle_class
        if cls != asset.vehicle_class or item.in_shape_space != asset.in_shape_space:
            library.put(replace(asset, vehicle_class=cls, in_shape_space=bool(item.in_shape_space)))
    return library


def save_library_props(lib_props) -> Path:
    from adv3d_runner.shapes.library import save_library

    library = library_from_props(lib_props)
    path = save_library(library, bpy.path.abspath(lib_props.path))
    fill_props(lib_props, library)
    return path


def cleaning_lines(report_json: str, limit: int = 24) -> list[str]:
    """The cleaning report flattened into 'key: value' lines for the panel."""
    try:
        report = json.loads(report_json) if report_json else {}
    except json.JSONDecodeError:
        return [report_json[:120]]
    lines: list[str] = []

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}{k}." if isinstance(v, dict) else f"{prefix}{k}", v)
        else:
            if isinstance(value, float):
                value = f"{value:.4g}"
            elif isinstance(value, list):
                value = ", ".join(str(v) for v in value[:8]) + (" ..." if len(value) > 8 else "")
            lines.append(f"{prefix.rstrip('.')}: {value}")

    walk("", report)
    return lines[:limit]


# --------------------------------------------------------------------------- operators

class ADV3D_OT_library_load(bpy.types.Operator):
    """Load library.json into the panel"""

    bl_idname = "adv3d.library_load"
    bl_label = "Load library"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"})

    def execute(self, context):
        from adv3d_runner.shapes.library import load_library

        lib_props = context.scene.adv3d.library
        if self.filepath:
            lib_props.path = self.filepath
        try:
            library = load_library(bpy.path.abspath(lib_props.path))
        except runner.Adv3dError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        fill_props(lib_props, library)
        self.report({"INFO"}, f"{len(library.assets)} assets")
        return {"FINISHED"}


class ADV3D_OT_library_save(bpy.types.Operator):
    """Write the panel's edits (class, include in shape space) to library.json"""

    bl_idname = "adv3d.library_save"
    bl_label = "Save library"
    bl_options = {"REGISTER"}

    def execute(self, context):
        try:
            path = save_library_props(context.scene.adv3d.library)
        except runner.Adv3dError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


class ADV3D_OT_library_show(bpy.types.Operator):
    """Show the active asset's mesh in the viewport (converted frame: +x front, on the ground)"""

    bl_idname = "adv3d.library_show"
    bl_label = "Show asset"
    bl_options = {"REGISTER", "UNDO"}

    asset_id: StringProperty(options={"SKIP_SAVE"})

    def execute(self, context):
        from adv3d_runner.shapes.library import load_asset_mesh

        lib_props = context.scene.adv3d.library
        asset_id = self.asset_id
        if not asset_id:
            if not lib_props.assets:
                self.report({"ERROR"}, "Load a library first")
                return {"CANCELLED"}
            asset_id = lib_props.assets[lib_props.active_index].asset_id
        try:
            obj = show_asset(context.scene, lib_props, asset_id)
        except (runner.Adv3dError, KeyError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for other in context.view_layer.objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        return {"FINISHED"}


def asset_mesh_object(library, asset_id: str, collection) -> "bpy.types.Object":
    """An object showing a library asset (the mesh datablock is shared between users)."""
    from adv3d_runner.shapes.library import load_asset_mesh

    name = f"asset:{asset_id}"
    mesh = bpy.data.meshes.get(name)
    if mesh is None:
        tm = load_asset_mesh(library, asset_id)
        mesh = bpy.data.meshes.new(name)
        meshdata.set_mesh_arrays(mesh, np.asarray(tm.vertices), np.asarray(tm.faces))
    obj = bpy.data.objects.new(asset_id, mesh)
    collection.objects.link(obj)
    obj.adv3d.role = "ASSET"
    obj.adv3d.key = asset_id
    obj.adv3d.asset_id = asset_id
    return obj


def show_asset(scene, lib_props, asset_id: str) -> "bpy.types.Object":
    from adv3d_runner.shapes.library import load_library

    library = load_library(bpy.path.abspath(lib_props.path))
    library.get(asset_id)  # KeyError with the known ids
    coll = meshdata.get_collection(ASSET_COLLECTION, scene.collection)
    for obj in list(coll.objects):
        if obj.adv3d.key == asset_id:
            return obj
    return asset_mesh_object(library, asset_id, coll)


classes = (
    ADV3D_OT_library_load,
    ADV3D_OT_library_save,
    ADV3D_OT_library_show,
)
