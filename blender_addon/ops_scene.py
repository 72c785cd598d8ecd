# SPDX-License-Identifier: GPL-3.0-or-later
"""Scenes panel: load an adv3d scene file as Blender objects, edit it, export it back.

Loading keeps the file's document verbatim in a text datablock; exporting starts from that
document and overwrites only what differs in Blender by more than the file's rounding (1 mm,
1 mrad), so load -> export with no edit gives an identical scene file.

Mapping (scene -> Blender):
  * scene frame i -> Blender frame i (frame_start 0, fps = 1 / dt);
  * map coordinates are shifted by an integer-metre origin (stored on the root collection) so
    Blender's float32 locations keep millimetres even in large UTM-like map frames;
  * ego and actors: box meshes (or library meshes) keyframed on location x/y and rotation z
    (linear), the yaw unwrapped so interpolation never spins; actor gaps hide the object;
  * sensors: empties parented to the ego at their mount pose (roll, pitch, yaw = XYZ Euler);
  * lanes: poly curves along the centre lines; road: ``adv3d_runner.scene.background``.
"""
from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras import anim_utils
from bpy_extras.io_utils import ImportHelper

from . import meshdata, places, runner, uiutil

ROOT_COLLECTION = "Adv3D Scene"
INTERP_CONSTANT, INTERP_LINEAR = 0, 1  # Keyframe.interpolation enum order


# --------------------------------------------------------------------------- animation helpers

def _fcurves(obj, create: bool = True):
    """The F-curve collection animating ``obj`` (Blender 4.4+ slotted actions, or legacy)."""
    ad = obj.animation_data
    if ad is None:
        if not create:
            return None
        ad = obj.animation_data_create()
    if ad.action is None:
        if not create:
            return None
        ad.action = bpy.data.actions.new(f"{obj.name} track")
    action = ad.action
    if hasattr(action, "fcurves") and not hasattr(action, "slots"):  # Blender < 4.4
        return action.fcurves
    if ad.action_slot is None:
        if not create:
            return None
        ad.action_slot = action.slots.new(id_type="OBJECT", name=obj.name)
    if create:
        return _ensure_channelbag(action, ad.action_slot).fcurves
    bag = anim_utils.action_get_channelbag_for_slot(action, ad.action_slot)
    return None if bag is None else bag.fcurves


def _ensure_channelbag(action, slot):
    """The action's channelbag for ``slot`` (created if missing): Blender 5.0 has a helper for
    it; 4.4/4.5 go through the layer / keyframe strip API it wraps."""
    if hasattr(anim_utils, "action_ensure_channelbag_for_slot"):
        return anim_utils.action_ensure_channelbag_for_slot(action, slot)
    layer = action.layers[0] if action.layers else action.layers.new("Layer")
    strip = layer.strips[0] if layer.strips else layer.strips.new(type="KEYFRAME")
    return strip.channelbag(slot, ensure=True)


def set_keys(obj, data_path: str, index: int, frames: np.ndarray, values: np.ndarray,
             interpolation: int = INTERP_LINEAR) -> None:
    """Replace the F-curve ``data_path[index]`` by keys (frames, values), in bulk."""
    fcurves = _fcurves(obj)
    fc = fcurves.find(data_path, index=index)
    if fc is not None:
        fcurves.remove(fc)
    fc = fcurves.new(data_path, index=index)
    n = len(frames)
    fc.keyframe_points.add(n)
    co = np.empty(2 * n, dtype=np.float32)
    co[0::2] = frames
    co[1::2] = values
    fc.keyframe_points.foreach_set("co", co)
    fc.keyframe_points.foreach_set("interpolation", np.full(n, interpolation, dtype=np.int32))
    fc.update()


def eval_curve(obj, data_path: str, index: int, frames: np.ndarray) -> np.ndarray | None:
    """F-curve values at ``frames`` (None when the channel is not animated)."""
    fcurves = _fcurves(obj, create=False)
    fc = None if fcurves is None else fcurves.find(data_path, index=index)
    if fc is None:
        return None
    return np.array([fc.evaluate(float(f)) for f in frames], dtype=np.float64)


# --------------------------------------------------------------------------- load

def _origin_of(scene) -> np.ndarray:
    """Integer-metre origin near the ego's start (keeps Blender float32 coordinates small)."""
    return np.round(np.array([scene.ego.track.x[0], scene.ego.track.y[0]]))


def _road_object(scene, origin, coll, scene_dir: Path):
    try:
        from adv3d_runner.scene.background import background_mesh
    except ImportError:  # background geometry not available in this runner version
        return None
    mesh = background_mesh(scene, scene_dir)
    kinds = None
    if isinstance(mesh, tuple):
        vertices, faces = mesh[0], mesh[1]
        kinds = mesh[2] if len(mesh) > 2 else None
    else:
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    vertices = np.array(vertices, dtype=np.float64)
    vertices[:, :2] -= origin
    obj = meshdata.new_mesh_object("road", vertices, faces, coll)
    obj.adv3d.role = "ROAD"
    if kinds is not None:  # colour by surface kind (Workbench "Attribute" colouring shows it)
        palette = np.array([SURFACE_COLOURS.get(k, (0.5, 0.5, 0.5, 1.0)) for k in _surface_kinds()], np.float32)
        attr = obj.data.color_attributes.new("surface", "FLOAT_COLOR", "CORNER")
        attr.data.foreach_set("color", np.repeat(palette[np.asarray(kinds, dtype=np.int64)], 3, axis=0).ravel())
        obj.data.color_attributes.active_color = attr
    return obj


# Linear RGBA per background surface kind (adv3d_runner.scene.background.SURFACE_KINDS).
SURFACE_COLOURS = {
    "asphalt": (0.06, 0.06, 0.065, 1.0), "lane_paint": (0.9, 0.9, 0.85, 1.0), "concrete": (0.45, 0.45, 0.43, 1.0),
    "metal": (0.55, 0.57, 0.6, 1.0), "ground": (0.18, 0.22, 0.08, 1.0), "vegetation": (0.05, 0.2, 0.04, 1.0),
}


def _surface_kinds() -> tuple[str, ...]:
    from adv3d_runner.scene.background import SURFACE_KINDS

    return SURFACE_KINDS


def _lane_object(lane, origin, coll):
    curve = bpy.data.curves.new(f"lane {lane.id}", "CURVE")
    curve.dimensions = "3D"
    spline = curve.splines.new("POLY")
    pts = lane.centerline - origin
    spline.points.add(len(pts) - 1)
    co = np.zeros((len(pts), 4), dtype=np.float32)
    co[:, :2] = pts
    co[:, 2] = 0.05  # just above the road so the line shows
    co[:, 3] = 1.0
    spline.points.foreach_set("co", co.ravel())
    obj = bpy.data.objects.new(f"lane {lane.id}", curve)
    coll.objects.link(obj)
    obj.adv3d.role = "LANE"
    obj.adv3d.key = str(lane.id)
    return obj


def _vehicle_mesh(name: str, dims, asset_id: str | None, library):
    """A library mesh when the asset is known, else a box of the given dimensions."""
    if asset_id and library is not None:
        from adv3d_runner.shapes.library import load_asset_mesh

        try:
            library.get(asset_id)
        except KeyError:
            pass
        else:
            key = f"asset:{asset_id}"
            mesh = bpy.data.meshes.get(key)
            if mesh is None:
                tm = load_asset_mesh(library, asset_id)
                mesh = bpy.data.meshes.new(key)
                meshdata.set_mesh_arrays(mesh, np.asarray(tm.vertices), np.asarray(tm.faces))
            return mesh
    mesh = bpy.data.meshes.new(name)
    meshdata.set_mesh_arrays(mesh, *meshdata.box_arrays(*[float(d) for d in dims]))
    return mesh


def _animate_track(obj, track, origin) -> None:
    """Keyframe a track's valid frames; hide the object outside them."""
    n = len(track)
    frames = track.start + np.arange(n)
    valid = track.valid
    fr = frames[valid]
    yaw = np.unwrap(track.yaw[valid])
    set_keys(obj, "location", 0, fr, track.x[valid] - origin[0])
    set_keys(obj, "location", 1, fr, track.y[valid] - origin[1])
    set_keys(obj, "location", 2, fr[:1], np.zeros(1))
    set_keys(obj, "rotation_euler", 2, fr, yaw)
    # Visibility: hidden before the first frame, after the last and in gaps (constant keys).
    vis = np.zeros(n + 2, dtype=bool)  # vis[j] is frame start - 1 + j
    vis[1:-1] = valid
    change = np.flatnonzero(vis[1:] != vis[:-1])  # visibility switches at frame start + j
    key_frames = np.concatenate([[frames[0] - 1], frames[0] + change])
    hidden = np.concatenate([[True], ~vis[change + 1]])
    for path in ("hide_viewport", "hide_render"):
        _set_visibility(obj, path, key_frames, hidden)


def _set_visibility(obj, path: str, frames: np.ndarray, hidden: np.ndarray) -> None:
    fcurves = _fcurves(obj)
    fc = fcurves.find(path)
    if fc is not None:
        fcurves.remove(fc)
    fc = fcurves.new(path)
    n = len(frames)
    fc.keyframe_points.add(n)
    co = np.empty(2 * n, dtype=np.float32)
    co[0::2] = frames
    co[1::2] = hidden
    fc.keyframe_points.foreach_set("co", co)
    fc.keyframe_points.foreach_set("interpolation", np.full(n, INTERP_CONSTANT, dtype=np.int32))
    fc.update()


def load_scene_objects(bscene, path: str, library=None) -> dict:
    """Build the objects of the scene file ``path`` in ``bscene`` (replacing a loaded one).

    Returns:
        counts of what was created: lanes, actors, sensors, road (0/1).
    """
    from adv3d_runner.fileio import read_json
    from adv3d_runner.scene.schema import Scene

    doc = read_json(path)
    scene = Scene.from_dict(doc, path)  # validates; FileFormatError names the bad field
    clear_scene_objects(bscene)
    origin = _origin_of(scene)
    root = places.panel_collection(bscene, ROOT_COLLECTION)
    place = places.make_place(bscene, root, _scene_bounds(scene, origin))
    root["adv3d_origin"] = [float(origin[0]), float(origin[1])]
    text = bpy.data.texts.new(f"adv3d_scene {scene.id}.json")
    text.write(json.dumps(doc, indent=1))
    props = bscene.adv3d.scene
    props.path = str(path)
    props.scene_id = scene.id
    props.text_name = text.name

    bscene.frame_start = 0
    bscene.frame_end = scene.frames - 1
    fps = 1.0 / scene.dt
    bscene.render.fps = max(1, int(round(fps)))
    bscene.render.fps_base = bscene.render.fps / fps

    counts = {"road": 0, "lanes": 0, "actors": 0, "sensors": 0}
    if _road_object(scene, origin, root, Path(path).parent) is not None:
        counts["road"] = 1
    lanes = meshdata.get_collection(f"{ROOT_COLLECTION} lanes", root)
    for lane in scene.lanes:
        _lane_object(lane, origin, lanes)
        counts["lanes"] += 1

    ego = bpy.data.objects.new("ego", _vehicle_mesh("ego", scene.ego.dimensions, None, None))
    root.objects.link(ego)
    ego.adv3d.role = "EGO"
    ego.adv3d.key = "ego"
    _animate_track(ego, scene.ego.track, origin)
    ego.color = (0.1, 0.4, 1.0, 1.0)
    for lidar in scene.ego.sensors:
        empty = bpy.data.objects.new(f"sensor {lidar.name}", None)
        empty.empty_display_type = "ARROWS"
        empty.empty_display_size = 0.5
        root.objects.link(empty)
        empty.parent = ego
        empty.location = lidar.mount[:3]
        empty.rotation_euler = lidar.mount[3:]
        empty.adv3d.role = "SENSOR"
        empty.adv3d.key = lidar.name
        counts["sensors"] += 1

    actors = meshdata.get_collection(f"{ROOT_COLLECTION} actors", root)
    for actor in scene.actors:
        name = f"actor {actor.id}"
        obj = bpy.data.objects.new(name, _vehicle_mesh(name, actor.dimensions, actor.asset, library))
        actors.objects.link(obj)
        obj.adv3d.role = "ACTOR"
        obj.adv3d.key = str(actor.id)
        obj.adv3d.asset_id = actor.asset or ""
        obj["adv3d_dimensions"] = [float(d) for d in actor.dimensions]
        _animate_track(obj, actor.track, origin)
        counts["actors"] += 1
    places.adopt(root, place)
    bscene.frame_set(0)
    return counts


def _scene_bounds(scene, origin: np.ndarray, margin: float = 30.0) -> np.ndarray:
    """x0, y0, x1, y1 (m, origin-shifted) around the lanes and every track, plus ``margin``
    (the road's shoulders and background)."""
    pts = [lane.centerline for lane in scene.lanes]
    for track in [scene.ego.track] + [a.track for a in scene.actors]:
        pts.append(np.c_[track.x[track.valid], track.y[track.valid]])
    xy = np.concatenate([p for p in pts if len(p)]) - origin
    return np.r_[xy.min(axis=0) - margin, xy.max(axis=0) + margin]


def clear_scene_objects(bscene) -> None:
    """Remove a previously loaded scene (objects, its text datablock, actions)."""
    props = bscene.adv3d.scene
    for coll_name in (f"{ROOT_COLLECTION} lanes", f"{ROOT_COLLECTION} actors", ROOT_COLLECTION):
        coll = bpy.data.collections.get(coll_name)
        if coll is not None:
            for obj in list(coll.objects):
                if obj.animation_data and obj.animation_data.action:
                    action = obj.animation_data.action
                    obj.animation_data.action = None
                    if action.users == 0:
                        bpy.data.actions.remove(action)
    meshdata.remove_collection(ROOT_COLLECTION)
    text = bpy.data.texts.get(props.text_name) if props.text_name else None
    if text is not None:
        bpy.data.texts.remove(text)
    props.text_name = ""
    props.scene_id = ""


# --------------------------------------------------------------------------- export

def _tolerance(values: np.ndarray, decimals: int = 3) -> np.ndarray:
    """Differences below this are float32 storage noise, not edits (half the file's rounding
    step plus a few float32 ulps of the value)."""
    return 0.5 * 10.0 ** -decimals + 8 * np.finfo(np.float32).eps * np.abs(values)


def _read_track_edits(obj, track, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Poses from Blender at the track's valid frames and the mask of frames that were edited."""
    from adv3d_runner.geometry.angles import wrap_angle

    frames = (track.start + np.arange(len(track)))[track.valid]
    x = eval_curve(obj, "location", 0, frames)
    y = eval_curve(obj, "location", 1, frames)
    yaw = eval_curve(obj, "rotation_euler", 2, frames)
    if x is None or y is None or yaw is None:
        return None
    x = x + origin[0]
    y = y + origin[1]
    yaw = wrap_angle(yaw)
    ox, oy, oyaw = track.x[track.valid], track.y[track.valid], track.yaw[track.valid]
    edited = (np.abs(x - ox) > _tolerance(ox - origin[0])) \
        | (np.abs(y - oy) > _tolerance(oy - origin[1])) \
        | (np.abs(wrap_angle(yaw - oyaw)) > _tolerance(np.full_like(oyaw, np.pi)))
    return x, y, yaw, edited


def _apply_edits(track, x, y, yaw, edited, recompute_speed: bool, dt: float) -> int:
    """Write edited frames into ``track`` (in place); returns the number of edited frames."""
    if not edited.any():
        return 0
    idx = np.flatnonzero(track.valid)[edited]
    new_x, new_y = np.round(x[edited], 3) + 0.0, np.round(y[edited], 3) + 0.0
    moved = idx[(new_x != track.x[idx]) | (new_y != track.y[idx])]  # a turned heading moves nothing
    track.x[idx] = new_x
    track.y[idx] = new_y
    track.yaw[idx] = np.round(yaw[edited], 3) + 0.0
    if recompute_speed and track.speed is not None and len(moved):
        # The ego log carries speeds: re-derive them from positions around frames that moved.
        vx = np.gradient(track.x, dt)
        vy = np.gradient(track.y, dt)
        speed = np.hypot(vx, vy)
        touch = np.zeros(len(track), dtype=bool)
        for i in moved:
            touch[max(i - 1, 0): i + 2] = True
        track.speed[touch] = np.round(speed[touch], 3) + 0.0
    return int(edited.sum())


def export_scene(bscene):
    """The scene as loaded, with the edits made in Blender applied (a ``Scene``).

    Returns:
        (scene, summary) where summary counts edited frames / assets / sensors.
    """
    from adv3d_runner.geometry.angles import wrap_angle
    from adv3d_runner.scene.schema import Scene

    props = bscene.adv3d.scene
    text = bpy.data.texts.get(props.text_name) if props.text_name else None
    root = bpy.data.collections.get(ROOT_COLLECTION)
    if text is None or root is None:
        raise runner.Adv3dError("no scene loaded (use Load scene first)")
    doc = json.loads(text.as_string())
    scene = Scene.from_dict(doc, props.path)
    origin = np.asarray(root.get("adv3d_origin", [0.0, 0.0]), dtype=np.float64)
    summary = {"frames": 0, "assets": 0, "sensors": 0}
    for obj in root.all_objects:
        role = obj.adv3d.role
        if role == "EGO":
            edits = _read_track_edits(obj, scene.ego.track, origin)
            if edits is not None:
                summary["frames"] += _apply_edits(scene.ego.track, *edits, recompute_speed=True, dt=scene.dt)
        elif role == "ACTOR":
            try:
                actor = scene.actor(int(obj.adv3d.key))
            except (KeyError, ValueError):
                continue
            edits = _read_track_edits(obj, actor.track, origin)
            if edits is not None:
                summary["frames"] += _apply_edits(actor.track, *edits, recompute_speed=False, dt=scene.dt)
            asset = obj.adv3d.asset_id or None
            if asset != actor.asset:
                _check_asset(asset, actor.id, bscene)
                actor.asset = asset
                summary["assets"] += 1
        elif role == "SENSOR":
            for lidar in scene.ego.sensors:
                if lidar.name != obj.adv3d.key:
                    continue
                mount = np.concatenate([np.array(obj.location), np.array(obj.rotation_euler)])
                diff = np.abs(mount - lidar.mount)
                diff[3:] = np.abs(wrap_angle(mount[3:] - lidar.mount[3:]))
                if (diff > _tolerance(lidar.mount)).any():
                    lidar.mount = np.round(mount, 3) + 0.0
                    summary["sensors"] += 1
    return scene, summary


# --------------------------------------------------------------------------- operators

class ADV3D_OT_scene_load(bpy.types.Operator, ImportHelper):
    """Load a scene file as objects: road, lanes, ego and actors with keyframed tracks, sensors"""

    bl_idname = "adv3d.scene_load"
    bl_label = "Load scene"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default="*.json;*.json.gz", options={"HIDDEN"})
    browse: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"},
                         description="Always choose the file in the file browser (File > Import)")

    def invoke(self, context, event):
        if not self.browse and (self.filepath or context.scene.adv3d.scene.path):
            return self.execute(context)
        return ImportHelper.invoke(self, context, event)

    @uiutil.reported
    def execute(self, context):
        props = context.scene.adv3d.scene
        path = bpy.path.abspath(self.filepath or props.path)
        if not path:
            raise runner.Adv3dError("choose a scene file")
        library = _library_or_none(context)
        counts = load_scene_objects(context.scene, path, library)
        self.report({"INFO"}, ", ".join(f"{v} {k}" for k, v in counts.items()))
        return {"FINISHED"}


SCENE_FORMATS = {"JSON_GZ": ".json.gz", "JSON": ".json"}


class ADV3D_OT_scene_export(bpy.types.Operator, uiutil.FormatExportHelper):
    """Write the loaded scene with the edits made in Blender (unedited data is kept exactly)"""

    bl_idname = "adv3d.scene_export"
    bl_label = "Export scene"
    bl_options = {"REGISTER"}

    FORMATS = SCENE_FORMATS
    file_format: EnumProperty(name="Format", default="JSON",
                              items=[("JSON", "JSON (.json)", "Plain JSON"),
                                     ("JSON_GZ", "Compressed JSON (.json.gz)", "gzip-compressed JSON, "
                                                                                "as the bundled scenes")])
    filter_glob: StringProperty(default="*.json;*.json.gz", options={"HIDDEN"})

    def invoke(self, context, event):
        props = context.scene.adv3d.scene
        if not self.filepath and props.path:  # start from the loaded file's name and format
            self.filepath = bpy.path.abspath(props.path)
            self.file_format = self.format_of(self.filepath) or "JSON"
        return super().invoke(context, event)

    @uiutil.reported
    def execute(self, context):
        from adv3d_runner.scene.schema import save_scene

        path = self.target_path()
        scene, summary = export_scene(context.scene)
        save_scene(scene, path)
        self.report({"INFO"}, f"Wrote {path}: {summary['frames']} edited frames, "
                              f"{summary['assets']} asset changes, {summary['sensors']} sensor changes")
        return {"FINISHED"}


class ADV3D_OT_scene_apply_asset(bpy.types.Operator):
    """Show the active actor with its library asset's mesh (or a box when the asset is empty)"""

    bl_idname = "adv3d.scene_apply_asset"
    bl_label = "Apply asset"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.adv3d.role == "ACTOR"

    @uiutil.reported
    def execute(self, context):
        obj = context.active_object
        asset_id = obj.adv3d.asset_id
        library = _library_or_none(context)
        if asset_id and (library is None or asset_id not in library.ids()):
            raise runner.Adv3dError(f"asset {asset_id!r} is not in the loaded library "
                                    "(load one in the Library panel)")
        dims = obj.get("adv3d_dimensions", [4.5, 1.8, 1.5])
        obj.data = _vehicle_mesh(obj.name, dims, asset_id or None, library)
        return {"FINISHED"}


def _check_asset(asset_id: str | None, actor_id: int, bscene) -> None:
    """Refuse an actor asset id that the library the runner will use lacks (the Library panel's,
    else the bundled one): typed into the field without Apply, it would only fail in the runner.

    Raises:
        Adv3dError: naming the actor, the id and the library.
    """
    if asset_id is None:
        return
    from adv3d_runner.shapes.library import DEFAULT_LIBRARY, load_library

    from .ops_library import library_path

    path = library_path(bscene.adv3d.library) or str(DEFAULT_LIBRARY)
    if not Path(path).is_file() or asset_id not in load_library(path).ids():
        raise runner.Adv3dError(f"actor {actor_id}: asset {asset_id!r} is not in the library {path} "
                                "(load the library that has it, or clear the field)")


def _library_or_none(context):
    from .ops_library import library_path

    lib_path = library_path(context.scene.adv3d.library)
    if not lib_path or not Path(lib_path).exists():
        return None
    from adv3d_runner.shapes.library import load_library

    return load_library(lib_path)


classes = (
    ADV3D_OT_scene_load,
    ADV3D_OT_scene_export,
    ADV3D_OT_scene_apply_asset,
)
