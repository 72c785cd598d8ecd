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

from adv3d_runner.vehicle_classes import VEHICLE_CLASSES, plausibility_warning

from . import meshdata, runner

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


# --------------------------------------------------------------------------- import through Blender

_IMPORTERS = {
    ".glb": lambda path: bpy.ops.import_scene.gltf(filepath=path),
    ".gltf": lambda path: bpy.ops.import_scene.gltf(filepath=path),
    ".obj": lambda path: bpy.ops.wm.obj_import(filepath=path, forward_axis="NEGATIVE_Z", up_axis="Y"),
    ".fbx": lambda path: bpy.ops.import_scene.fbx(filepath=path),
    ".ply": lambda path: bpy.ops.wm.ply_import(filepath=path),
    ".stl": lambda path: bpy.ops.wm.stl_import(filepath=path),
}
IMPORT_SUFFIXES = tuple(_IMPORTERS) + (".blend",)
_FORWARD = {"X": "+x", "NEG_X": "-x", "Y": "+y", "NEG_Y": "-y"}


def _import_objects(path: Path) -> list:
    """Import a file with Blender's own importer; returns the new objects (a .blend's objects
    are appended)."""
    before = set(bpy.data.objects)
    suffix = path.suffix.lower()
    try:
        if suffix == ".blend":
            with bpy.data.libraries.load(str(path), link=False) as (src, dst):
                dst.objects = list(src.objects)
            new = [o for o in dst.objects if o is not None]
            for obj in new:
                bpy.context.scene.collection.objects.link(obj)
        else:
            result = _IMPORTERS[suffix](str(path))
            if "FINISHED" not in result:
                raise runner.Adv3dError(f"{path}: Blender's importer did not finish ({result})")
            new = [o for o in bpy.data.objects if o not in before]
    except (RuntimeError, OSError) as exc:  # Blender importers raise RuntimeError on bad files
        raise _mesh_error(f"{path}: cannot import ({str(exc).strip().splitlines()[-1] if str(exc).strip() else exc})")
    return new


def _mesh_error(message: str):
    from adv3d_runner.errors import MeshImportError

    return MeshImportError(message)


def objects_arrays(objects) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of the mesh objects (modifiers applied), concatenated (Z up, m)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, faces, offset = [], [], 0
    for obj in objects:
        if obj.type != "MESH":
            continue
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            v, f = meshdata.mesh_arrays(mesh)
        finally:
            evaluated.to_mesh_clear()
        if not len(f):
            continue
        m = np.array(obj.matrix_world, dtype=np.float64)
        verts.append(v @ m[:3, :3].T + m[:3, 3])
        faces.append(f + offset)
        offset += len(v)
    if not faces:
        raise _mesh_error("the file holds no mesh with faces")
    return np.concatenate(verts), np.concatenate(faces)


def _remove_objects(objects) -> None:
    for obj in objects:
        data = obj.data
        bpy.data.objects.remove(obj, do_unlink=True)
        if isinstance(data, bpy.types.Mesh) and data.users == 0:
            bpy.data.meshes.remove(data)


def blender_reader(forward: str, length: float):
    """A ``MeshReader`` for ``add_asset``: the file through Blender's own importer, then the
    runner's conversion and cleaning (``mesh_io.convert_vehicle``), so an asset added here is
    stored exactly like one added by ``adv3d assets import``.

    Args:
        forward: the panel's front axis (``"X"``, ``"NEG_Y"``, ...).
        length: real length in m to scale to (uniformly); 0 keeps the file's size.
    """
    import trimesh
    from adv3d_runner.shapes.mesh_io import convert_vehicle

    def read(path: Path):
        objects = _import_objects(path)
        try:
            vertices, faces = objects_arrays(objects)
        finally:
            _remove_objects(objects)
        raw = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        # Blender's importers already brought the model to Z up and metres.
        return convert_vehicle(raw, "blender", path.suffix.lower()[1:], up="+z", forward=_FORWARD[forward],
                               unit="m", length=length if length > 0 else None)

    return read


def import_vehicle_file(lib_props, path: Path, vehicle_class: str, forward: str, length: float,
                        licence_name: str = "", licence_file: str = "", asset_id: str = "", pack: str = ""):
    """Import one vehicle file through Blender into the library (``add_asset``: mesh written,
    library saved) and show the library with the new asset active.

    Returns:
        the new ``VehicleAsset``.
    """
    from adv3d_runner.errors import ConfigError
    from adv3d_runner.shapes.library import add_asset, load_or_new_library

    if not lib_props.path:
        raise ConfigError("set the library file (library.json) first")
    lib_path = Path(bpy.path.abspath(lib_props.path))
    library = load_or_new_library(lib_path)
    if path.suffix.lower() not in IMPORT_SUFFIXES:
        raise _mesh_error(f"{path}: unsupported file type (use {', '.join(IMPORT_SUFFIXES)})")
    asset = add_asset(library, lib_path, path, vehicle_class, blender_reader(forward, length),
                      asset_id=asset_id or None, pack=pack or None, licence_file=licence_file or None,
                      licence_name=licence_name or None)
    fill_props(lib_props, library)
    lib_props.active_index = library.ids().index(asset.id)
    return asset


def _edit_asset_mesh(lib_props, asset_id: str, edit, note: dict):
    """Apply ``edit(vertices) -> vertices`` to a stored asset mesh and update the library."""
    from adv3d_runner.shapes.library import load_library, save_library
    from adv3d_runner.shapes.mesh_io import mesh_dimensions, read_library_mesh, write_library_glb

    lib_path = Path(bpy.path.abspath(lib_props.path))
    library = library_from_props(lib_props)  # keep unsaved panel edits
    asset = library.get(asset_id)
    mesh = read_library_mesh(library.path_of(asset))
    v = edit(np.asarray(mesh.vertices, dtype=np.float64))
    lo, hi = v.min(axis=0), v.max(axis=0)
    mesh.vertices = v - np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    write_library_glb(mesh, library.path_of(asset))
    stored = read_library_mesh(library.path_of(asset))
    curation = dict(asset.curation)
    curation.setdefault("blender_edits", []).append(note)
    library.put(replace(asset, dimensions=tuple(round(x, 4) for x in mesh_dimensions(stored)),
                        triangle_count=int(len(stored.faces)), curation=curation))
    save_library(library, lib_path)
    stale = bpy.data.meshes.get(f"asset:{asset_id}")
    if stale is not None and stale.users == 0:
        bpy.data.meshes.remove(stale)
    fill_props(lib_props, library)


class ADV3D_OT_library_import(bpy.types.Operator, ImportHelper):
    """Import a vehicle file (glb/gltf/obj/fbx/ply/stl/.blend) through Blender's importers into the library"""

    bl_idname = "adv3d.library_import"
    bl_label = "Import vehicle"
    bl_options = {"REGISTER"}  # writes files: Blender undo cannot take that back

    filter_glob: StringProperty(default="*.glb;*.gltf;*.obj;*.fbx;*.ply;*.stl;*.blend", options={"HIDDEN"})
    asset_id: StringProperty(name="Id", description="Asset id (default: <folder>.<file name>)")
    licence_name: StringProperty(name="Licence", description="SPDX name such as CC0-1.0 (default: from the licence text)")
    licence_file: StringProperty(name="Licence file", subtype="FILE_PATH",
                                 description="Licence text (default: License.txt or similar beside the file)")

    def execute(self, context):
        lib_props = context.scene.adv3d.library
        try:
            asset = import_vehicle_file(lib_props, Path(self.filepath), lib_props.import_class,
                                        lib_props.import_forward, lib_props.import_length,
                                        self.licence_name, bpy.path.abspath(self.licence_file), self.asset_id)
        except runner.Adv3dError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        L, W, H = asset.dimensions
        self.report({"INFO"}, f"{asset.id}: {L:.2f} x {W:.2f} x {H:.2f} m, {asset.triangle_count} triangles")
        warning = plausibility_warning(asset.vehicle_class, asset.dimensions,
                                       hint="consider Real length or Set real size")
        if warning:
            self.report({"WARNING"}, warning)
        return {"FINISHED"}


class ADV3D_OT_library_rescale(bpy.types.Operator):
    """Scale the asset's stored mesh to real-world dimensions (uniformly from the length, or per axis)"""

    bl_idname = "adv3d.library_rescale"
    bl_label = "Set real size"
    bl_options = {"REGISTER"}  # writes files: Blender undo cannot take that back

    asset_id: StringProperty(options={"SKIP_SAVE"})
    length: FloatProperty(name="Length", min=0.5, max=30.0, default=4.5, unit="LENGTH")
    width: FloatProperty(name="Width", min=0.0, max=5.0, default=0.0, unit="LENGTH",
                         description="0: scale with the length (keep proportions)")
    height: FloatProperty(name="Height", min=0.0, max=6.0, default=0.0, unit="LENGTH",
                          description="0: scale with the length (keep proportions)")

    def invoke(self, context, event):
        lib_props = context.scene.adv3d.library
        for item in lib_props.assets:
            if item.asset_id == self.asset_id:
                self.length = item.length
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        lib_props = context.scene.adv3d.library
        try:
            asset = library_from_props(lib_props).get(self.asset_id)
            L, W, H = asset.dimensions
            s = self.length / L
            factors = np.array([s, self.width / W if self.width > 0 else s, self.height / H if self.height > 0 else s])
            _edit_asset_mesh(lib_props, self.asset_id, lambda v: v * factors,
                             {"scale": [round(float(f), 6) for f in factors],
                              "dimensions": [float(self.length), float(self.width or W * s), float(self.height or H * s)]})
        except (runner.Adv3dError, KeyError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class ADV3D_OT_library_turn(bpy.types.Operator):
    """Turn the asset's stored mesh about the vertical axis (fix a model whose front is not +x)"""

    bl_idname = "adv3d.library_turn"
    bl_label = "Turn front"
    bl_options = {"REGISTER"}  # writes files: Blender undo cannot take that back

    asset_id: StringProperty(options={"SKIP_SAVE"})
    angle: EnumProperty(name="Turn", items=[("180", "180°", ""), ("90", "90° left", ""), ("-90", "90° right", "")],
                        default="180")

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        a = np.radians(float(self.angle))
        rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        try:
            _edit_asset_mesh(context.scene.adv3d.library, self.asset_id, lambda v: v @ rot.T,
                             {"turn_deg": int(self.angle)})
        except (runner.Adv3dError, KeyError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


classes = (
    ADV3D_OT_library_load,
    ADV3D_OT_library_save,
    ADV3D_OT_library_show,
    ADV3D_OT_library_import,
    ADV3D_OT_library_rescale,
    ADV3D_OT_library_turn,
)
