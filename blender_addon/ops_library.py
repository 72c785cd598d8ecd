# SPDX-License-Identifier: GPL-3.0-or-later
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
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from adv3d_runner.shapes.mesh_io import SUPPORTED_FORMATS
from adv3d_runner.vehicle_classes import VEHICLE_CLASSES, plausibility_warning

from . import meshdata, places, prefs, runner, uiutil

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

    library = load_library(library_path(lib_props))
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
    path = save_library(library, library_path(lib_props))
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

    @uiutil.reported
    def execute(self, context):
        from adv3d_runner.shapes.library import load_library

        lib_props = context.scene.adv3d.library
        if self.filepath:
            lib_props.path = self.filepath
        if not library_path(lib_props):
            raise runner.Adv3dError("choose a library.json (or a default in the add-on preferences)")
        library = load_library(library_path(lib_props))
        lib_props.path = lib_props.path or library_path(lib_props)
        fill_props(lib_props, library)
        self.report({"INFO"}, f"{len(library.assets)} assets")
        return {"FINISHED"}


class ADV3D_OT_library_save(bpy.types.Operator):
    """Write the panel's edits (class, include in shape space) to library.json"""

    bl_idname = "adv3d.library_save"
    bl_label = "Save library"
    bl_options = {"REGISTER"}

    @uiutil.reported
    def execute(self, context):
        path = save_library_props(context.scene.adv3d.library)
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


class ADV3D_OT_library_show(bpy.types.Operator):
    """Show the active asset's mesh in the viewport (converted frame: +x front, on the ground)"""

    bl_idname = "adv3d.library_show"
    bl_label = "Show asset"
    bl_options = {"REGISTER", "UNDO"}

    asset_id: StringProperty(options={"SKIP_SAVE"})

    @uiutil.reported
    def execute(self, context):
        lib_props = context.scene.adv3d.library
        asset_id = self.asset_id
        if not asset_id:
            if not lib_props.assets:
                raise runner.Adv3dError("load a library first")
            asset_id = lib_props.assets[lib_props.active_index].asset_id
        obj = show_asset(context.scene, lib_props, asset_id)
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


SHOW_GAP_M = 1.5  # between shown assets, along +x


def show_asset(scene, lib_props, asset_id: str) -> "bpy.types.Object":
    """Show a library asset in the Library panel's collection and place: shown assets stand in a
    row along +x (front to the right), each once."""
    from adv3d_runner.shapes.library import load_library

    library = load_library(library_path(lib_props))
    asset = library.get(asset_id)  # KeyError with the known ids
    coll = places.panel_collection(scene, ASSET_COLLECTION)
    shown = [o for o in coll.objects if o.adv3d.role == "ASSET"]
    for obj in shown:
        if obj.adv3d.key == asset_id:
            return obj
    place = places.place_of(coll)
    x = 0.0
    if place is None:
        place = places.make_place(scene, coll, np.array([0.0, -2.0, 6.0, 2.0]))
    else:
        x = float(place["adv3d_bounds"][2]) + SHOW_GAP_M
    obj = asset_mesh_object(library, asset_id, coll)
    length, width = float(asset.dimensions[0]), float(asset.dimensions[1])
    obj.parent = place
    obj.location = (x + length / 2.0, 0.0, 0.0)
    places.grow_place(place, np.array([x, -width / 2.0, x + length, width / 2.0]))
    return obj


# --------------------------------------------------------------------------- import through Blender

# Axis choices named as Blender's own importers name them (OBJ / PLY / STL importers).
AXES = [("X", "X", ""), ("Y", "Y", ""), ("Z", "Z", ""),
        ("NEGATIVE_X", "-X", ""), ("NEGATIVE_Y", "-Y", ""), ("NEGATIVE_Z", "-Z", "")]
UP_ITEMS = [("AUTO", "Auto", "As Blender's importer does for the format: OBJ Y up, FBX as the file declares, "
                             "glTF Y up (the standard), PLY / STL / .blend Z up")] + AXES
FRONT_ITEMS = [("AUTO", "Auto", "The longest horizontal axis (its sign is a guess: use Turn front if the "
                                "vehicle faces backwards)")] + AXES
_AXIS_VECTORS = {"X": (1, 0, 0), "Y": (0, 1, 0), "Z": (0, 0, 1),
                 "NEGATIVE_X": (-1, 0, 0), "NEGATIVE_Y": (0, -1, 0), "NEGATIVE_Z": (0, 0, -1)}
# Where a file's axes land after Blender's importer (blender = M @ file): OBJ / PLY / STL are
# imported with forward -> Y, up -> Z (no conversion) so the user's file axes apply as they are;
# the glTF importer always turns glTF's y-up into z-up ((x, y, z) -> (x, -z, y)); FBX with
# given axes is read with a manual identity orientation, with Auto axes as the file declares
# them (z up afterwards); a .blend is in Blender's frame.
_IDENTITY = np.eye(3)
_GLTF_TO_BLENDER = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
_AUTO_UP = {".obj": "Y", ".fbx": "Y", ".ply": "Z", ".stl": "Z", ".glb": "Y", ".gltf": "Y", ".blend": "Z"}
#: What Import vehicle takes: the CLI importer's formats (``mesh_io.SUPPORTED_FORMATS``).
IMPORT_SUFFIXES = tuple(SUPPORTED_FORMATS)


def _importer(path: Path, manual_axes: bool):
    """(call, M): the Blender importer for ``path`` and where the file's axes land (see above)."""
    p = str(path)
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return (lambda: bpy.ops.import_scene.gltf(filepath=p)), _GLTF_TO_BLENDER
    if suffix == ".obj":
        return (lambda: bpy.ops.wm.obj_import(filepath=p, forward_axis="Y", up_axis="Z")), _IDENTITY
    if suffix == ".ply":
        return (lambda: bpy.ops.wm.ply_import(filepath=p, forward_axis="Y", up_axis="Z")), _IDENTITY
    if suffix == ".stl":
        return (lambda: bpy.ops.wm.stl_import(filepath=p, forward_axis="Y", up_axis="Z")), _IDENTITY
    if suffix == ".fbx":
        if manual_axes:
            return (lambda: bpy.ops.import_scene.fbx(filepath=p, use_manual_orientation=True, axis_forward="Y",
                                                     axis_up="Z")), _IDENTITY
        return (lambda: bpy.ops.import_scene.fbx(filepath=p)), None  # the file's own axes: z up after it
    return None, _IDENTITY  # .blend


def blender_axes(path: Path, up: str, front: str) -> tuple[str, str | None]:
    """The file's up and front axes (the operator's choices) as axes of the imported objects
    (``"+z"``, ``"-y"``... for ``convert_vehicle``; front None = guess it)."""
    suffix = path.suffix.lower()
    _, m = _importer(path, manual_axes=up != "AUTO" or front != "AUTO")
    if m is None:  # FBX read with its declared axes: up is Blender's +z
        return "+z", None

    def name(axis: str) -> str:
        v = m @ np.array(_AXIS_VECTORS[axis], dtype=np.float64)
        i = int(np.argmax(np.abs(v)))
        return ("+" if v[i] > 0 else "-") + "xyz"[i]

    return name(_AUTO_UP[suffix] if up == "AUTO" else up), None if front == "AUTO" else name(front)


def _import_objects(path: Path, manual_axes: bool = False) -> list:
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
            call, _ = _importer(path, manual_axes)
            result = call()
            if "FINISHED" not in result:
                raise runner.Adv3dError(f"{path}: Blender's importer did not finish ({result})")
            new = [o for o in bpy.data.objects if o not in before]
    except (RuntimeError, OSError) as exc:  # Blender importers raise RuntimeError on bad files
        new = [o for o in bpy.data.objects if o not in before]
        _remove_objects(new)
        raise _mesh_error(f"{path}: cannot import ({str(exc).strip().splitlines()[-1] if str(exc).strip() else exc})")
    return new


def _mesh_error(message: str):
    from adv3d_runner.errors import MeshImportError

    return MeshImportError(message)


def objects_arrays(objects) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World-space triangles of the mesh objects (modifiers applied), concatenated (Z up, m),
    with one RGBA colour per triangle from its material's base colour (the colours the CLI's
    Blender reader keeps: ``bpy_export``)."""
    from adv3d_runner.shapes.bpy_export import _material_rgba

    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, faces, colours, offset = [], [], [], 0
    for obj in objects:
        if obj.type != "MESH":
            continue
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            v, f = meshdata.mesh_arrays(mesh)
            mat_index = np.zeros(len(mesh.loop_triangles), dtype=np.int32)
            mesh.loop_triangles.foreach_get("material_index", mat_index)
        finally:
            evaluated.to_mesh_clear()
        if not len(f):
            continue
        palette = np.array([_material_rgba(slot.material) for slot in obj.material_slots]
                           or [_material_rgba(None)], dtype=np.uint8)
        m = np.array(obj.matrix_world, dtype=np.float64)
        if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform: keep the normals outward
            f = f[:, ::-1]
        verts.append(v @ m[:3, :3].T + m[:3, 3])
        faces.append(f + offset)
        colours.append(palette[np.minimum(mat_index, len(palette) - 1)])
        offset += len(v)
    if not faces:
        raise _mesh_error("the file holds no mesh with faces")
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(colours)


def _remove_objects(objects) -> None:
    for obj in objects:
        data = obj.data
        bpy.data.objects.remove(obj, do_unlink=True)
        if isinstance(data, bpy.types.Mesh) and data.users == 0:
            bpy.data.meshes.remove(data)


#: The axis names of the CLI (``adv3d assets import --up/--forward``) for the operator's.
_CLI_AXES = {"X": "+x", "Y": "+y", "Z": "+z", "NEGATIVE_X": "-x", "NEGATIVE_Y": "-y", "NEGATIVE_Z": "-z"}


def blender_reader(up: str = "AUTO", front: str = "AUTO", length: float = 0.0):
    """A ``MeshReader`` for ``add_asset``: an asset added here is stored exactly like one added
    by ``adv3d assets import``. Formats the CLI reads itself (glTF, OBJ, PLY, STL, ApolloCar3D
    .json, AC3D...: ``mesh_io.read_mesh``'s dispatch) go through the CLI's own reader (materials
    and textures kept as face colours, its dataset conventions); FBX and .blend, which the CLI
    reads through Blender, through Blender's importer here, with the material colours.

    Args:
        up, front: the file's up axis and the axis the vehicle's front points along, named as
            in Blender's importers (``"Y"``, ``"NEGATIVE_Z"``) or ``"AUTO"``.
        length: real length in m to scale to (uniformly); 0 keeps the file's size.
    """
    import trimesh
    from adv3d_runner.shapes.mesh_io import BLENDER_FORMATS, convert_vehicle, detect_convention, import_vehicle

    def read(path: Path):
        if path.suffix.lower() not in BLENDER_FORMATS:
            up_file = _CLI_AXES.get(up)
            if up_file is None and path.suffix.lower() == ".obj" and detect_convention(path) is None:
                up_file = "+y"  # Auto: y up, as Blender's OBJ importer takes an OBJ (UP_ITEMS)
            return import_vehicle(path, up=up_file, forward=_CLI_AXES.get(front),
                                  length=length if length > 0 else None)
        up_b, front_b = blender_axes(path, up, front)
        objects = _import_objects(path, manual_axes=up != "AUTO" or front != "AUTO")
        try:
            vertices, faces, colours = objects_arrays(objects)
        finally:
            _remove_objects(objects)
        raw = trimesh.Trimesh(vertices=vertices, faces=faces, face_colors=colours, process=False)
        # Blender's importers brought the model to metres; the axes are mapped above
        return convert_vehicle(raw, "blender", path.suffix.lower()[1:], up=up_b, forward=front_b,
                               unit="m", length=length if length > 0 else None)

    return read


def import_suffixes() -> tuple[str, ...]:
    """Every file type the CLI's importer reads (``mesh_io.SUPPORTED_FORMATS``): new formats
    there are importable here too."""
    return IMPORT_SUFFIXES


def library_path(lib_props) -> str:
    """The panel's library.json, else the preferences' default ('' when neither is set)."""
    return bpy.path.abspath(lib_props.path) if lib_props.path else prefs.default_library()


def import_vehicle_file(lib_props, path: Path, vehicle_class: str, up: str, front: str, length: float,
                        licence_name: str = "", licence_file: str = "", asset_id: str = "", pack: str = "",
                        replace: bool = False):
    """Import one vehicle file into the library (``add_asset``: mesh written, library saved) and
    show the library with the new asset active. An asset id already in the library is refused
    unless ``replace``.

    Returns:
        the new ``VehicleAsset``.
    """
    from adv3d_runner.errors import ConfigError
    from adv3d_runner.shapes.library import add_asset, load_or_new_library

    if not library_path(lib_props):
        raise ConfigError("set the library file (library.json) first, or a default in the add-on preferences "
                          "(New library makes one)")
    lib_path = Path(library_path(lib_props))
    lib_props.path = str(lib_path)
    library = load_or_new_library(lib_path)
    if path.suffix.lower() not in import_suffixes():
        raise _mesh_error(f"{path}: unsupported file type (use {', '.join(import_suffixes())})")
    asset = add_asset(library, lib_path, path, vehicle_class, blender_reader(up, front, length),
                      asset_id=asset_id or None, pack=pack or None, licence_file=licence_file or None,
                      licence_name=licence_name or None, replace=replace)
    fill_props(lib_props, library)
    lib_props.active_index = library.ids().index(asset.id)
    return asset


def _edit_asset_mesh(lib_props, asset_id: str, edit, note: dict):
    """Apply ``edit(vertices) -> vertices`` to a stored asset mesh and update the library."""
    from adv3d_runner.shapes.library import save_library
    from adv3d_runner.shapes.mesh_io import mesh_dimensions, read_library_mesh, write_library_glb

    lib_path = Path(library_path(lib_props))
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
    """Import vehicle files (every format `adv3d assets import` reads, plus FBX and .blend
    through Blender's importers) into the library; several at once, or dropped onto the viewport"""

    bl_idname = "adv3d.library_import"
    bl_label = "Import vehicle"
    bl_options = {"REGISTER"}  # writes files: Blender undo cannot take that back

    filter_glob: StringProperty(default=";".join("*" + x for x in SUPPORTED_FORMATS), options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    vehicle_class: EnumProperty(name="Class", items=[(c, c, "") for c in VEHICLE_CLASSES], default="sedan")
    axis_up: EnumProperty(name="Up", items=UP_ITEMS, default="AUTO", description="The file's up axis")
    axis_forward: EnumProperty(name="Front", items=FRONT_ITEMS, default="AUTO",
                               description="The file axis the vehicle's front points along")
    length: FloatProperty(name="Real length", min=0.0, soft_max=20.0, unit="LENGTH", default=0.0,
                          description="Scale the model to this length (0: keep the file's size)")
    asset_id: StringProperty(name="Id", description="Asset id (default: <folder>.<file name>; one file only)")
    licence_name: StringProperty(name="Licence",
                                 description="SPDX name such as CC0-1.0 (default: from the licence text); "
                                             "named, a pack without a licence file can be imported")
    licence_file: StringProperty(name="Licence file", subtype="FILE_PATH",
                                 description="Licence text (default: License.txt or similar beside the file)")
    replace: BoolProperty(name="Replace existing", default=False,
                          description="Replace an asset with the same id (otherwise such an import is refused)")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        for name in ("vehicle_class", "axis_forward", "axis_up", "length", "asset_id", "licence_name",
                     "licence_file", "replace"):
            layout.prop(self, name)

    def invoke(self, context, event):
        if self.directory and self.files:  # dropped onto the viewport (FileHandler): options, then import
            if context.window is None or not hasattr(self, "invoke_popup"):
                return self.execute(context)
            return self.invoke_popup(context)
        return ImportHelper.invoke(self, context, event)

    def paths(self) -> list[Path]:
        """The chosen files: several (``directory`` + ``files``) or one (``filepath``)."""
        if self.directory and self.files:
            return [Path(bpy.path.abspath(self.directory)) / f.name for f in self.files if f.name]
        return [Path(bpy.path.abspath(self.filepath))] if self.filepath else []

    @uiutil.reported
    def execute(self, context):
        lib_props = context.scene.adv3d.library
        paths = self.paths()
        if not paths:
            raise runner.Adv3dError("choose one or more vehicle files")
        if self.asset_id and len(paths) > 1:
            raise runner.Adv3dError("an asset id names one file: leave Id empty to import several")
        done = []
        for path in paths:
            asset = import_vehicle_file(lib_props, path, self.vehicle_class, self.axis_up, self.axis_forward,
                                        self.length, self.licence_name,
                                        bpy.path.abspath(self.licence_file) if self.licence_file else "",
                                        self.asset_id, replace=self.replace)
            done.append(asset)
            L, W, H = asset.dimensions
            self.report({"INFO"}, f"{asset.id}: {L:.2f} x {W:.2f} x {H:.2f} m, {asset.triangle_count} triangles")
            warning = plausibility_warning(asset.vehicle_class, asset.dimensions,
                                           hint="consider Real length or Set real size")
            if warning:
                self.report({"WARNING"}, warning)
        if len(done) > 1:
            self.report({"INFO"}, f"Imported {len(done)} vehicles: {', '.join(a.id for a in done)}")
        return {"FINISHED"}


class ADV3D_FH_vehicle(bpy.types.FileHandler):
    """Vehicle files dropped onto the 3D viewport go to Import vehicle (Blender >= 4.1)."""

    bl_idname = "ADV3D_FH_vehicle"
    bl_label = "Adv3D vehicle to library"
    bl_import_operator = "adv3d.library_import"
    bl_file_extensions = ";".join(SUPPORTED_FORMATS)

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


class ADV3D_OT_library_new(bpy.types.Operator):
    """Make a new, empty vehicle library (library.json in a folder of its own) and open it"""

    bl_idname = "adv3d.library_new"
    bl_label = "New library"
    bl_options = {"REGISTER"}

    directory: StringProperty(subtype="DIR_PATH", description="Folder of the new library")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    @uiutil.reported
    def execute(self, context):
        from adv3d_runner.shapes.library import VehicleLibrary, save_library

        if not self.directory:
            raise runner.Adv3dError("choose a folder for the new library")
        folder = Path(bpy.path.abspath(self.directory))
        path = folder / "library.json"
        if path.exists():
            raise runner.Adv3dError(f"{path} exists already: open it with the Library field instead")
        folder.mkdir(parents=True, exist_ok=True)
        save_library(VehicleLibrary(root=folder), path)
        lib_props = context.scene.adv3d.library
        lib_props.path = str(path)
        fill_props(lib_props, VehicleLibrary(root=folder))
        self.report({"INFO"}, f"New library {path}: import vehicles into it")
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

    @uiutil.reported
    def execute(self, context):
        lib_props = context.scene.adv3d.library
        asset = library_from_props(lib_props).get(self.asset_id)
        L, W, H = asset.dimensions
        s = self.length / L
        factors = np.array([s, self.width / W if self.width > 0 else s, self.height / H if self.height > 0 else s])
        _edit_asset_mesh(lib_props, self.asset_id, lambda v: v * factors,
                         {"scale": [round(float(f), 6) for f in factors],
                          "dimensions": [float(self.length), float(self.width or W * s), float(self.height or H * s)]})
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

    @uiutil.reported
    def execute(self, context):
        a = np.radians(float(self.angle))
        rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        _edit_asset_mesh(context.scene.adv3d.library, self.asset_id, lambda v: v @ rot.T,
                         {"turn_deg": int(self.angle)})
        return {"FINISHED"}


classes = (
    ADV3D_OT_library_load,
    ADV3D_OT_library_save,
    ADV3D_OT_library_show,
    ADV3D_OT_library_import,
    ADV3D_OT_library_new,
    ADV3D_FH_vehicle,
    ADV3D_OT_library_rescale,
    ADV3D_OT_library_turn,
)
