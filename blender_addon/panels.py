# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Adv3D" sidebar tab (View3D > N): Library, Shape space, Scenes and Review panels.

Panels only draw properties and operator buttons; all work is in the ``ops_*`` modules.
"""
from __future__ import annotations

import bpy

from . import jobs, ops_shapes, prefs
from .ops_library import cleaning_lines


class _Adv3dPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Adv3D"


class ADV3D_UL_assets(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        row = layout.row(align=True)
        row.prop(item, "in_shape_space", text="")
        row.label(text=item.asset_id, icon="AUTO")
        row.label(text=item.vehicle_class)


class ADV3D_PT_library(_Adv3dPanel, bpy.types.Panel):
    bl_idname = "ADV3D_PT_library"
    bl_label = "Library"

    def draw(self, context):
        lib = context.scene.adv3d.library
        layout = self.layout
        row = layout.row(align=True)
        row.prop(lib, "path", text="")
        row.operator("adv3d.library_load", text="", icon="FILE_REFRESH")
        if not lib.path and prefs.default_library():
            layout.label(text=f"Default: {prefs.default_library()}", icon="PREFERENCES")
        layout.template_list("ADV3D_UL_assets", "", lib, "assets", lib, "active_index", rows=4)
        row = layout.row(align=True)
        row.operator("adv3d.library_save", icon="FILE_TICK")
        row.operator("adv3d.library_show", icon="HIDE_OFF")
        if lib.assets and 0 <= lib.active_index < len(lib.assets):
            item = lib.assets[lib.active_index]
            box = layout.box()
            box.label(text=item.asset_id)
            box.prop(item, "vehicle_class")
            box.prop(item, "in_shape_space")
            col = box.column(align=True)
            col.label(text=f"Size {item.length:.2f} x {item.width:.2f} x {item.height:.2f} m")
            col.label(text=f"{item.triangle_count} triangles, licence {item.licence}")
            if item.source:
                col.label(text=item.source)
            row = box.row(align=True)
            row.operator("adv3d.library_rescale", text="Set size").asset_id = item.asset_id
            row.operator("adv3d.library_turn", text="Turn front").asset_id = item.asset_id
            report = box.box()
            report.label(text="Cleaning report", icon="INFO")
            col = report.column(align=True)
            col.scale_y = 0.8
            for line in cleaning_lines(item.cleaning_report):
                col.label(text=line)
        row = layout.row(align=True)
        row.operator("adv3d.library_import", text="Import vehicle files...", icon="IMPORT")
        row.operator("adv3d.library_new", text="", icon="FILE_NEW")


class ADV3D_PT_shapes(_Adv3dPanel, bpy.types.Panel):
    bl_idname = "ADV3D_PT_shapes"
    bl_label = "Shape space"

    def draw(self, context):
        settings = context.scene.adv3d
        shapes = settings.shapes
        layout = self.layout
        row = layout.row(align=True)
        row.prop(shapes, "space_path", text="")
        row.operator("adv3d.shapes_load", text="", icon="FILE_REFRESH")
        if not shapes.space_path and prefs.default_space():
            layout.label(text=f"Default: {prefs.default_space()}", icon="PREFERENCES")
        box = layout.box()
        row = box.row(align=True)
        row.prop(shapes, "build_k")
        row.prop(shapes, "build_resolution")
        _job_button(box, "adv3d.shapes_build", "MOD_REMESH")
        if shapes.variance_text:
            box.label(text="Explained variance:")
            box.label(text=shapes.variance_text)
        if shapes.k == 0:
            layout.label(text="Load a shape space to get sliders")
            return
        col = layout.column(align=True)
        for i in range(shapes.k):
            col.prop(shapes, "latent", index=i, text=f"z{i + 1}", slider=True)
        col.prop(shapes, "width_scale", slider=True)
        col.prop(shapes, "length_scale", slider=True)
        row = layout.row(align=True)
        row.prop(shapes, "live")
        row.label(text=f"{shapes.last_update_ms:.1f} ms")
        if ops_shapes.last_error():
            layout.label(text=ops_shapes.last_error(), icon="ERROR")
        row = layout.row(align=True)
        row.operator("adv3d.shapes_random", icon="RNDCURVE")
        row.prop(shapes, "seed")
        row = layout.row(align=True)
        row.operator("adv3d.shapes_reset", icon="LOOP_BACK")
        row.operator("adv3d.shapes_nearest", icon="VIEWZOOM")
        if shapes.nearest_asset:
            layout.label(text=f"Nearest: {shapes.nearest_asset}")
        _draw_realism(layout, shapes)
        layout.operator("adv3d.shapes_export", icon="EXPORT")


def _draw_realism(layout, shapes) -> None:
    """The realism box: live figures of the slider shape, the full report on demand."""
    box = layout.box()
    row = box.row(align=True)
    row.prop(shapes, "show_realism")
    row.prop(shapes, "realism_class", text="")
    if shapes.show_realism and shapes.realism_live:
        col = box.column(align=True)
        col.scale_y = 0.8
        for line in shapes.realism_live.splitlines():
            col.label(text=line, icon="ERROR" if "OUT" in line else "NONE")
    box.operator("adv3d.shapes_realism", icon="VIEWZOOM")
    if shapes.realism_full:
        col = box.column(align=True)
        col.scale_y = 0.8
        for line in shapes.realism_full.splitlines():
            col.label(text=line)


class ADV3D_PT_scenes(_Adv3dPanel, bpy.types.Panel):
    bl_idname = "ADV3D_PT_scenes"
    bl_label = "Scenes"

    def draw(self, context):
        sc = context.scene.adv3d.scene
        layout = self.layout
        row = layout.row(align=True)
        row.prop(sc, "path", text="")
        row.operator("adv3d.scene_load", text="", icon="FILE_REFRESH")
        if sc.scene_id:
            layout.label(text=f"Scene {sc.scene_id}")
            layout.operator("adv3d.scene_export", icon="EXPORT")
            box = layout.box()
            box.label(text="Attack this scene", icon="PLAY")
            col = box.column(align=True)
            for name in ("attack_algo", "attack_budget", "attack_seconds", "attack_autonomy", "attack_seed"):
                col.prop(sc, name)
            _draw_attack_files(box, context)
            _job_button(box, "adv3d.scene_attack", "PLAY")
            if sc.attack_error:
                col = box.column(align=True)
                col.alert = True
                col.label(text=sc.attack_error, icon="ERROR")
            if not prefs.runner_command():
                box.label(text="No adv3d runner: set one in the preferences", icon="ERROR")
            if sc.last_run:
                box.label(text=f"Run: {sc.last_run}", icon="FILE_FOLDER")
        obj = context.active_object
        if obj is not None and obj.adv3d.role in {"ACTOR", "EGO"}:
            box = layout.box()
            box.label(text=f"{obj.adv3d.role.title()} {obj.adv3d.key}", icon="AUTO")
            if obj.adv3d.role == "ACTOR":
                box.prop(obj.adv3d, "asset_id")
                box.operator("adv3d.scene_apply_asset", icon="MESH_DATA")
            box.label(text="Edit the pose keyframes, then Export")


class ADV3D_PT_review(_Adv3dPanel, bpy.types.Panel):
    bl_idname = "ADV3D_PT_review"
    bl_label = "Review"

    def draw(self, context):
        rv = context.scene.adv3d.review
        layout = self.layout
        layout.prop(rv, "path", text="")
        layout.prop(rv, "replay", text="")
        row = layout.row(align=True)
        _job_button(row, "adv3d.review_load", "PLAY")
        row.operator("adv3d.review_clear", text="", icon="X")
        if rv.stale:
            layout.label(text=rv.stale, icon="ERROR")
        elif rv.key and rv.key not in _review_cache():
            layout.label(text="Reading the replay...", icon="SORTTIME")
        if rv.loaded:
            box = layout.box()
            box.label(text=" / ".join(rv.loaded.replace("\\", "/").split("/")[-3:]), icon="FILE")
            _draw_legend(box)
            box.label(text="Scrub the timeline to step through the episode")


#: Icons of Blender's colour tags for the review's legend (review.LEGEND, in order).
_LEGEND_ICONS = ("COLLECTION_COLOR_01", "MESH_CUBE", "COLLECTION_COLOR_05", "OUTLINER_OB_POINTCLOUD",
                 "COLLECTION_COLOR_04", "COLLECTION_COLOR_06", "COLLECTION_COLOR_03", "MATFLUID",
                 "COLLECTION_COLOR_02")


def _draw_legend(layout) -> None:
    """What the review's colours mean (the same in Solid, Workbench and Eevee shading)."""
    from .review import LEGEND

    col = layout.column(align=True)
    col.scale_y = 0.8
    col.label(text="Legend", icon="INFO")
    for (text, _), icon in zip(LEGEND, _LEGEND_ICONS):
        col.label(text=text, icon=icon)


def _draw_attack_files(layout, context) -> None:
    """Which library and shape space the attack passes to the runner (the panels' files)."""
    from .ops_library import library_path
    from .ops_shapes import space_path

    col = layout.column(align=True)
    col.scale_y = 0.8
    lib, space = library_path(context.scene.adv3d.library), space_path(context.scene.adv3d.shapes)
    col.label(text=f"Library: {lib or 'bundled'}")
    col.label(text=f"Shape space: {space or 'bundled'}")


def _job_button(layout, idname: str, icon: str) -> None:
    """An operator button, or its progress while its job runs (Esc cancels)."""
    job = jobs.JobOperator._active.get(idname.replace("adv3d.", "ADV3D_OT_"))
    if job is None:
        layout.operator(idname, icon=icon)
    else:
        layout.label(text=f"{job.message or job.label}  {100 * job.fraction:.0f}%  (Esc)", icon="SORTTIME")


def _review_cache():
    from . import review

    return review._CACHE


classes = (
    ADV3D_UL_assets,
    ADV3D_PT_library,
    ADV3D_PT_shapes,
    ADV3D_PT_scenes,
    ADV3D_PT_review,
)
