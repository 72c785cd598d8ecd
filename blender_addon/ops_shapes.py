# SPDX-License-Identifier: GPL-3.0-or-later
"""Shape-space panel operators and the live preview vehicle.

The latent sliders are properties whose ``update`` callback calls ``schedule_preview_update``:
while Blender runs interactively the update is coalesced with a ``bpy.app.timers`` callback
(every slider event inside ``DEBOUNCE_S`` collapses into one decode), in background mode (tests,
scripts) it runs at once. The preview mesh is written in place with ``foreach_set``.

Realism (docs/realism.md): each update also measures the cheap figures of the slider shape
(JSD, Mahalanobis, dimensions against a class; ~2 ms), the full report is an operator.
"""
from __future__ import annotations

import time
from pathlib import Path

import bpy
import numpy as np
from bpy.props import EnumProperty, StringProperty

from . import jobs, meshdata, places, prefs, runner, uiutil
from .props import MAX_LATENT

DEBOUNCE_S = 0.03
PREVIEW_NAME = "Adv3D preview"
PREVIEW_COLLECTION = "Adv3D Shape preview"

REFERENCE_POLL_S = 0.5  # how often the panel looks whether a background reference build is done

_state = {"scene": None, "suspend": False, "error": "", "pending": None}


# --------------------------------------------------------------------------- preview updates

def current_unit(shapes) -> np.ndarray:
    """The unit input [z_1..z_K, width, length] the sliders describe."""
    return runner.unit_vector(np.array(shapes.latent), shapes.k, shapes.width_scale, shapes.length_scale)


def preview_object(scene: "bpy.types.Scene", create: bool = True) -> "bpy.types.Object | None":
    """The scene's preview vehicle (created empty if missing and ``create``)."""
    for obj in scene.objects:
        if obj.adv3d.role == "PREVIEW" and obj.type == "MESH":
            return obj
    if not create:
        return None
    coll = places.panel_collection(scene, PREVIEW_COLLECTION)
    obj = bpy.data.objects.new(PREVIEW_NAME, bpy.data.meshes.new(PREVIEW_NAME))
    coll.objects.link(obj)
    obj.adv3d.role = "PREVIEW"
    # a vehicle-sized place of its own (a shape-space car fits in 8 m x 4 m)
    obj.parent = places.make_place(scene, coll, np.array([-4.0, -2.0, 4.0, 2.0]))
    return obj


def update_preview(scene: "bpy.types.Scene") -> float:
    """Decode the sliders' latent and write it into the preview mesh.

    Returns:
        wall time of decode + mesh update, in milliseconds.
    """
    shapes = scene.adv3d.shapes
    space = runner.load_space(space_path(shapes))
    if shapes.k != space.k:
        shapes.k = space.k
    t0 = time.perf_counter()
    u = current_unit(shapes)
    vertices, faces = space.decode_arrays(u)
    obj = preview_object(scene)
    meshdata.set_mesh_arrays(obj.data, vertices, faces)
    ms = (time.perf_counter() - t0) * 1000.0
    shapes.last_update_ms = ms
    shapes.realism_full = ""  # the full report described the previous shape
    if shapes.show_realism:
        update_realism(scene, space, u, vertices, faces)
    return ms


def update_realism(scene, space, u: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> None:
    """The live realism lines of the preview shape; while the space's reference is built in the
    background they say so, and (interactively) a timer fills them in once it is there."""
    shapes = scene.adv3d.shapes
    t1 = time.perf_counter()
    try:
        lines = runner.live_realism(space, u, vertices, faces, realism_class(shapes), _library_path(scene))
    except runner.ReferencePending as exc:
        lines = [f"Realism: {exc}"]
        _state["pending"] = scene.name
        if not bpy.app.background and not bpy.app.timers.is_registered(_poll_reference):
            bpy.app.timers.register(_poll_reference, first_interval=REFERENCE_POLL_S)
    except runner.Adv3dError as exc:
        lines = [f"Realism: {exc}"]
    shapes.realism_live = "\n".join(lines)
    shapes.realism_ms = (time.perf_counter() - t1) * 1000.0


def _poll_reference():
    """Timer: once the background reference build is done, measure the preview shape again."""
    if runner.reference_building():
        return REFERENCE_POLL_S
    name, _state["pending"] = _state["pending"], None
    scene = bpy.data.scenes.get(name) if name else None
    if scene is not None and scene.adv3d.shapes.show_realism and space_path(scene.adv3d.shapes):
        obj = preview_object(scene, create=False)
        if obj is not None:
            try:
                space = runner.load_space(space_path(scene.adv3d.shapes))
                v, f = meshdata.mesh_arrays(obj.data)
                update_realism(scene, space, current_unit(scene.adv3d.shapes), v, f)
            except runner.Adv3dError as exc:
                scene.adv3d.shapes.realism_live = f"Realism: {exc}"
        for window in bpy.context.window_manager.windows:
            for area in window.screen.areas:
                area.tag_redraw()
    return None


def realism_class(shapes) -> str | None:
    """The class the panel checks dimensions against (None: the nearest library vehicle's)."""
    return None if shapes.realism_class == "AUTO" else shapes.realism_class


def _library_path(scene) -> str | None:
    """The Library panel's library.json, else the preferences' default (None when neither)."""
    from .ops_library import library_path

    return library_path(scene.adv3d.library) or None


def _run_pending() -> None:
    name, _state["scene"] = _state["scene"], None
    scene = bpy.data.scenes.get(name) if name else None
    if scene is None:
        return None
    try:
        update_preview(scene)
        _state["error"] = ""
    except runner.Adv3dError as exc:  # a latent with no surface, a missing file: show, never raise
        _state["error"] = str(exc)
    return None  # one-shot timer


def schedule_preview_update(context) -> None:
    """Slider callback: regenerate the preview now (background) or coalesced (interactive)."""
    scene = context.scene
    shapes = scene.adv3d.shapes
    if _state["suspend"] or not shapes.live or not space_path(shapes):
        return
    _state["scene"] = scene.name
    if bpy.app.background:
        _run_pending()
        return
    if not bpy.app.timers.is_registered(_run_pending):
        bpy.app.timers.register(_run_pending, first_interval=DEBOUNCE_S)


def space_path(shapes) -> str:
    """The panel's shape space, else the preferences' default ('' when neither is set)."""
    return bpy.path.abspath(shapes.space_path) if shapes.space_path else prefs.default_space()


def cancel_timers() -> None:
    for fn in (_run_pending, _poll_reference):
        if bpy.app.timers.is_registered(fn):
            bpy.app.timers.unregister(fn)
    _state["scene"] = None


def last_error() -> str:
    return _state["error"]


def set_unit(shapes, u: np.ndarray) -> None:
    """Assign a whole unit vector to the sliders with a single preview update afterwards."""
    k = shapes.k
    latent = np.full(MAX_LATENT, 0.5)
    latent[:k] = u[:k]
    _state["suspend"] = True
    try:
        shapes.latent = latent.tolist()  # whole-vector assignment, one RNA write
        shapes.width_scale = float(u[k])
        shapes.length_scale = float(u[k + 1])
    finally:
        _state["suspend"] = False


def _explained_variance_text(space) -> str:
    ev = getattr(space, "explained_variance_ratio", None)
    if ev is None:
        ev = getattr(space, "explained_variance", None)
    if ev is None:
        return ""
    ev = np.asarray(ev, dtype=np.float64)
    if ev.sum() > 1.0 + 1e-6:  # absolute variances: show shares
        ev = ev / ev.sum()
    return "  ".join(f"z{i + 1} {100 * v:.1f}%" for i, v in enumerate(ev[:MAX_LATENT]))


# --------------------------------------------------------------------------- operators

class ADV3D_OT_shapes_load(bpy.types.Operator):
    """Load the shape space and show the preview vehicle at the current sliders"""

    bl_idname = "adv3d.shapes_load"
    bl_label = "Load shape space"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"})

    @uiutil.reported
    def execute(self, context):
        shapes = context.scene.adv3d.shapes
        if self.filepath:
            shapes.space_path = self.filepath
        elif not shapes.space_path and prefs.default_space():
            shapes.space_path = prefs.default_space()
        if not space_path(shapes):
            raise runner.Adv3dError("choose a shape-space .npz (or a default in the add-on preferences)")
        space = runner.load_space(space_path(shapes))
        if space.k > MAX_LATENT:
            raise runner.Adv3dError(f"shape space has K={space.k} > {MAX_LATENT} supported sliders")
        shapes.k = space.k
        shapes.variance_text = _explained_variance_text(space)
        ms = update_preview(context.scene)
        self.report({"INFO"}, f"Shape space K={space.k}; preview in {ms:.1f} ms")
        return {"FINISHED"}


class ADV3D_OT_shapes_reset(bpy.types.Operator):
    """Set every slider to the middle of its range"""

    bl_idname = "adv3d.shapes_reset"
    bl_label = "Reset sliders"
    bl_options = {"REGISTER", "UNDO"}

    @uiutil.reported
    def execute(self, context):
        shapes = context.scene.adv3d.shapes
        set_unit(shapes, np.full(shapes.k + 2, 0.5))
        return _refresh(context)


class ADV3D_OT_shapes_random(bpy.types.Operator):
    """Draw a random shape (seeded: the same seed gives the same shape); the seed then advances"""

    bl_idname = "adv3d.shapes_random"
    bl_label = "Random sample"
    bl_options = {"REGISTER", "UNDO"}

    @uiutil.reported
    def execute(self, context):
        shapes = context.scene.adv3d.shapes
        space = runner.load_space(space_path(shapes))
        shapes.k = space.k
        u = np.asarray(space.sample_unit(np.random.default_rng(shapes.seed)), dtype=np.float64)
        set_unit(shapes, u)
        shapes.seed += 1
        return _refresh(context)


class ADV3D_OT_shapes_nearest(bpy.types.Operator):
    """Find the library asset whose latent is nearest to the sliders' shape"""

    bl_idname = "adv3d.shapes_nearest"
    bl_label = "Nearest library asset"
    bl_options = {"REGISTER"}

    @uiutil.reported
    def execute(self, context):
        shapes = context.scene.adv3d.shapes
        space = runner.load_space(space_path(shapes))
        shapes.k = space.k
        found = space.nearest_asset(current_unit(shapes))
        # nearest_asset may return the id alone or (id, distance).
        if isinstance(found, (tuple, list)):
            asset_id, dist = str(found[0]), float(found[1])
            shapes.nearest_asset = f"{asset_id} (distance {dist:.3f})"
        else:
            shapes.nearest_asset = str(found)
        self.report({"INFO"}, f"Nearest library asset: {shapes.nearest_asset}")
        return {"FINISHED"}


class ADV3D_OT_shapes_realism(bpy.types.Operator):
    """Measure every realism figure of the preview shape (JSD, nearest vehicle, Mahalanobis,
    parts, genus, thinnest wall, dimensions); takes a fraction of a second"""

    bl_idname = "adv3d.shapes_realism"
    bl_label = "Full realism report"
    bl_options = {"REGISTER"}

    def execute(self, context):
        shapes = context.scene.adv3d.shapes
        if not bpy.app.background and runner.reference_building():  # never freeze the window for it
            self.report({"WARNING"}, "the realism reference is being built in the background: try again "
                                     "when the live figures show")
            return {"CANCELLED"}
        try:
            space = runner.load_space(space_path(shapes))
            shapes.k = space.k
            rep, lines = runner.full_realism(space, current_unit(shapes), realism_class(shapes),
                                             _library_path(context.scene))
        except runner.Adv3dError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        shapes.realism_full = "\n".join(lines)
        self.report({"INFO"}, "Realistic" if rep["realistic"] else "Fails: " + ", ".join(rep["flags"]))
        return {"FINISHED"}


MESH_FORMATS = {"GLB": ".glb", "GLTF": ".gltf", "OBJ": ".obj", "PLY": ".ply", "STL": ".stl"}


class ADV3D_OT_shapes_export(bpy.types.Operator, uiutil.FormatExportHelper):
    """Export the decoded preview vehicle as a mesh file (metres, +x front, origin on the ground)"""

    bl_idname = "adv3d.shapes_export"
    bl_label = "Export shape"
    bl_options = {"REGISTER"}

    FORMATS = MESH_FORMATS
    file_format: EnumProperty(
        name="Format", default="GLB",
        items=[("GLB", "glTF binary (.glb)", "One file, y up (glTF's frame: opens upright anywhere)"),
               ("GLTF", "glTF (.gltf)", "JSON glTF, y up"),
               ("OBJ", "Wavefront (.obj)", "Up axis as chosen (Auto: y up, as Blender's OBJ importer expects)"),
               ("PLY", "Stanford (.ply)", "Up axis as chosen (Auto: z up, as Blender's PLY importer expects)"),
               ("STL", "STL (.stl)", "Up axis as chosen (Auto: z up, as Blender's STL importer expects)")])
    up_axis: EnumProperty(
        name="Up", default="AUTO",
        items=[("AUTO", "Auto", "What Blender's importer of the format expects with its defaults: y up for glTF "
                                "and OBJ, z up for PLY and STL (the vehicle's front is +x in every case)"),
               ("Y", "Y up", "y up, +x front (glTF's frame; Blender's OBJ importer defaults)"),
               ("Z", "Z up", "z up, +x front (adv3d's and Blender's frame; not for glTF)")])
    filter_glob: StringProperty(default="*.glb;*.gltf;*.obj;*.ply;*.stl", options={"HIDDEN"})

    @uiutil.reported
    def execute(self, context):
        import trimesh
        from adv3d_runner.shapes.mesh_io import write_mesh  # same writer as `adv3d shapes decode`

        shapes = context.scene.adv3d.shapes
        path = self.target_path()
        space = runner.load_space(space_path(shapes))
        shapes.k = space.k
        vertices, faces = space.decode_arrays(current_unit(shapes))
        write_mesh(trimesh.Trimesh(vertices=vertices, faces=faces, process=False), path,
                   up=export_up_axis(self.file_format, self.up_axis))
        self.report({"INFO"}, f"Wrote {path} ({len(faces)} triangles)")
        return {"FINISHED"}


#: The up axis each of Blender's importers expects with its default settings.
IMPORTER_UP = {"GLB": "Y", "GLTF": "Y", "OBJ": "Y", "PLY": "Z", "STL": "Z"}


def export_up_axis(file_format: str, choice: str) -> str:
    """The up axis to write (``Y`` or ``Z``) for an export format and the panel's choice.

    Raises:
        Adv3dError: Z up chosen for glTF (its frame is y up by the specification).
    """
    up = IMPORTER_UP[file_format] if choice == "AUTO" else choice
    if file_format in ("GLB", "GLTF") and up != "Y":
        raise runner.Adv3dError("glTF is always y up (its specification): choose Auto or Y up")
    return up


def check_components(k: int, n_assets: int) -> None:
    """Refuse a K the included assets cannot fill: the principal components of n shapes span at
    most n - 1 directions, so further sliders would change nothing (0 % variance).

    Raises:
        Adv3dError: naming K and the number of included assets.
    """
    if n_assets < 2:
        raise runner.Adv3dError(f"the shape space needs at least 2 included assets (the library has {n_assets})")
    if k > n_assets - 1:
        raise runner.Adv3dError(f"Components K={k} is more than {n_assets} included assets can give "
                                f"(at most {n_assets - 1}: n shapes span n - 1 directions); lower K or "
                                "include more assets")


def build_steps(library, out: str, options: dict):
    """Steps of Build: the runner's stepwise build (SDF per asset in pieces, PCA), then the
    atomic write. Cancelling before the write leaves the old file untouched."""
    from adv3d_runner.shapes.shape_space import build_shape_space_steps

    yield from jobs.import_steps()
    space = yield from build_shape_space_steps(library, **options)
    yield 1.0, f"writing {Path(out).name}"
    runner.save_space(space, out)
    return space


class ADV3D_OT_shapes_build(jobs.JobOperator, bpy.types.Operator):
    """Build the shape space from the library's included assets and load it (runs in the
    background: progress in the status bar, Esc cancels)"""

    bl_idname = "adv3d.shapes_build"
    bl_label = "Build shape space"
    bl_options = {"REGISTER"}  # writes a file: Blender undo cannot take that back
    job_label = "Build shape space"

    def start_job(self, context):
        from .ops_library import library_from_props, library_path, save_library_props

        settings = context.scene.adv3d
        shapes = settings.shapes
        lib_path = library_path(settings.library)
        out = space_path(shapes)
        if not lib_path or not out:
            raise runner.Adv3dError("set the library file and the shape-space output path first")
        uiutil.writable_target(out)
        if not settings.library.path:
            settings.library.path = lib_path
        if settings.library.dirty:  # build from what the panel shows
            save_library_props(settings.library)
        library = library_from_props(settings.library)
        check_components(shapes.build_k, sum(1 for a in library.assets if a.in_shape_space))
        options = {"k": shapes.build_k}
        if shapes.build_resolution:
            options["resolution"] = shapes.build_resolution
        self._out = out
        return build_steps(library, out, options)

    def finish_job(self, context, job):
        shapes = context.scene.adv3d.shapes
        if not shapes.space_path:
            shapes.space_path = self._out
        result = bpy.ops.adv3d.shapes_load()
        space = job.result
        self.report({"INFO"}, f"Built {Path(self._out).name}: {len(space.asset_ids)} assets, K={space.k} "
                              f"in {time.perf_counter() - job.started:.1f} s")
        return result


def _refresh(context):
    shapes = context.scene.adv3d.shapes
    if space_path(shapes):
        update_preview(context.scene)
    return {"FINISHED"}


classes = (
    ADV3D_OT_shapes_load,
    ADV3D_OT_shapes_reset,
    ADV3D_OT_shapes_random,
    ADV3D_OT_shapes_nearest,
    ADV3D_OT_shapes_realism,
    ADV3D_OT_shapes_export,
    ADV3D_OT_shapes_build,
)
