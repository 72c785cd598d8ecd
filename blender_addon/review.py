# SPDX-License-Identifier: GPL-3.0-or-later
"""Review engine: per-frame episode data (poses, LiDAR points, detections, predictions, plan) as
Blender objects that follow the timeline.

This is the Blender side of the Review panel, written against in-memory arrays (``ReviewData``);
``ops_review`` fills them from a replay file ("adv3d-replay") of a run bundle.

How scrubbing stays cheap: ego and actors are keyframed once (their poses are known for every
frame); the per-frame geometry whose size changes from frame to frame (points, detection boxes,
trajectories, score labels) lives in a few objects whose data are rewritten in place by a
``frame_change_post`` handler from arrays kept in memory (whole-array ``foreach_set``; the
geometry is rebuilt only when the count changes). Nothing per frame is created up front, so
loading is fast even with points in every frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import bpy
import numpy as np

from . import meshdata, places

REVIEW_COLLECTION = "Adv3D Review"
OCCUPANCY_OBJECT = "review occupancy"
OCCUPANCY_ATTRIBUTE = "occupancy"
OCCUPANCY_Z = -0.03  # m, the heat map lies just under the ground: LiDAR points stay on top of it
# Colours (docs/blender.md, "Review"): the attacked shape is the only saturated red; benign
# actors are light grey so it stands out; the heat map runs from pale blue to orange (no red).
ADVERSARIAL_RGBA = (0.95, 0.05, 0.05, 1.0)
BENIGN_RGBA = (0.72, 0.72, 0.74, 1.0)
EGO_RGBA = (0.1, 0.35, 0.9, 1.0)
POINTS_RGBA = (0.05, 0.05, 0.05, 1.0)
DETECTIONS_RGBA = (0.05, 0.75, 0.15, 1.0)
PREDICTIONS_RGBA = (0.6, 0.1, 0.8, 1.0)
PLAN_RGBA = (0.95, 0.75, 0.0, 1.0)
LABEL_RGBA = (0.0, 0.45, 0.08, 1.0)
OCCUPANCY_FREE_RGBA = (0.80, 0.87, 1.0, 1.0)
OCCUPANCY_FULL_RGBA = (1.0, 0.5, 0.0, 1.0)
#: Occupancy bins shown in Solid / Workbench shading (one material each, lower edges).
OCCUPANCY_BINS = (0.0, 0.2, 0.4, 0.6, 0.8)
LABEL_COLLECTION = "Adv3D Review scores"
MAX_LABELS = 64  # score labels shown per frame (the highest-scoring first)
LABEL_SIZE = 0.5  # m: small, and beside its box, never over the shape
BOX_EDGE_M = 0.04  # detection boxes are drawn as edges this thick (they never hide a shape)
POINT_RADIUS = 0.05  # m, display size of a LiDAR point

#: What each colour means (the Review panel's legend; the same words in docs/blender.md).
LEGEND = (("attacked actor: the adversarial shape", ADVERSARIAL_RGBA), ("other actors", BENIGN_RGBA),
          ("ego vehicle", EGO_RGBA), ("LiDAR points", POINTS_RGBA),
          ("detections (edges) and scores", DETECTIONS_RGBA), ("predicted trajectories", PREDICTIONS_RGBA),
          ("ego plan", PLAN_RGBA), ("occupancy: free", OCCUPANCY_FREE_RGBA),
          ("occupancy: occupied", OCCUPANCY_FULL_RGBA))

# Review data in memory, keyed by the replay it came from (``ops_review.replay_key``: the file's
# path and content hash); a scene shows the entry its ``adv3d.review.key`` property names (saved
# with the .blend and restored by undo), so a scene never draws another file's replay. Not saved
# in .blend files: opening one, or an undo that brings a review back, reads the replay again
# (``ops_review`` handlers). Besides the entries scenes name, the one released last is kept, so
# undoing "Clear review" or a new load is instant.
_CACHE: dict[str, "ReviewData"] = {}
_RELEASED = {"key": ""}


@dataclass
class ReviewActor:
    """One actor: ``poses`` (T, 3) x, y, yaw (NaN where absent), ``dimensions`` (L, W, H) m,
    optional mesh ``vertices`` (V, 3) / ``faces`` (F, 3) in its local frame (else a box),
    ``adversarial`` to highlight the attacked shapes."""

    id: int
    poses: np.ndarray
    dimensions: np.ndarray
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    adversarial: bool = False


@dataclass
class ReviewData:
    """An episode to review, everything in the scene's map frame (metres, radians).

    Attributes:
        ego_poses: (T, 3) x, y, yaw of the ego per frame.
        ego_dimensions: (3,) L, W, H.
        actors: the actors.
        points: per frame (N_t, 3) float32 LiDAR points in the map frame (or in the ego frame
            when ``points_in_ego_frame``: the point cloud is then parented to the ego), or None.
        detections: per frame (D_t, 7) x, y, yaw, L, W, H, score, or None.
        predictions: per frame (M_t, P, 2) predicted trajectories, or None.
        plan: per frame (P, 2) the ego's chosen plan, or None.
        dt: seconds per frame.
        points_in_ego_frame: see ``points``.
        occupancy: per frame None or (values (nx, ny) occupancy probability in [0, 1], pose (3,)
            x, y, yaw of the grid's centre and axes, cell m): the predicted occupancy heat map
            of an instance-free stack (the same nx, ny and cell in every frame); or None.
    """

    ego_poses: np.ndarray
    ego_dimensions: np.ndarray
    actors: list[ReviewActor] = field(default_factory=list)
    points: list[np.ndarray] | None = None
    detections: list[np.ndarray] | None = None
    predictions: list[np.ndarray] | None = None
    plan: list[np.ndarray] | None = None
    dt: float = 0.1
    points_in_ego_frame: bool = False
    occupancy: list[tuple[np.ndarray, np.ndarray, float] | None] | None = None

    @property
    def frames(self) -> int:
        return len(self.ego_poses)


# --------------------------------------------------------------------------- building

def _animate(obj, poses: np.ndarray) -> None:
    """Keyframe (x, y, yaw) where finite; hide the object where the pose is NaN."""
    from .ops_scene import _set_visibility, set_keys

    valid = np.isfinite(poses).all(axis=1)
    frames = np.flatnonzero(valid)
    if not len(frames):
        obj.hide_viewport = obj.hide_render = True
        return
    set_keys(obj, "location", 0, frames, poses[valid, 0])
    set_keys(obj, "location", 1, frames, poses[valid, 1])
    set_keys(obj, "rotation_euler", 2, frames, np.unwrap(poses[valid, 2]))
    vis = np.concatenate([[False], valid, [False]])
    change = np.flatnonzero(vis[1:] != vis[:-1])
    key_frames = np.concatenate([[-1], change])
    hidden = np.concatenate([[True], ~vis[change + 1]])
    for path in ("hide_viewport", "hide_render"):
        _set_visibility(obj, path, key_frames, hidden)


def _colour(obj, rgba) -> None:
    obj.color = rgba  # Workbench "Object" colour; a material for other engines
    mat = bpy.data.materials.new(obj.name)
    mat.diffuse_color = rgba
    obj.data.materials.append(mat)


def _show_as_points(obj) -> None:
    """A "Mesh to Points" geometry-nodes modifier: loose vertices are invisible in object mode
    and in renders; as a point cloud they show in the viewport, Workbench and Eevee."""
    group = bpy.data.node_groups.get("adv3d review points")
    if group is None:
        group = bpy.data.node_groups.new("adv3d review points", "GeometryNodeTree")
        group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        n_in = group.nodes.new("NodeGroupInput")
        n_out = group.nodes.new("NodeGroupOutput")
        to_points = group.nodes.new("GeometryNodeMeshToPoints")
        to_points.inputs["Radius"].default_value = POINT_RADIUS
        group.links.new(n_in.outputs[0], to_points.inputs["Mesh"])
        group.links.new(to_points.outputs[0], n_out.inputs[0])
    mod = obj.modifiers.new("points", "NODES")
    mod.node_group = group


def occupancy_grid_arrays(nx: int, ny: int, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """A heat-map grid centred on the origin: every cell its own 4 vertices (so a per-vertex
    colour paints the cell flat), (4 nx ny, 3) vertices and (2 nx ny, 3) triangles; cell
    (i, j) is vertices 4 (i ny + j) .. + 3."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    x0 = (i.ravel() * cell - 0.5 * nx * cell)[:, None] + np.array([0.0, cell, cell, 0.0])
    y0 = (j.ravel() * cell - 0.5 * ny * cell)[:, None] + np.array([0.0, 0.0, cell, cell])
    verts = np.stack([x0, y0, np.zeros_like(x0)], axis=-1).reshape(-1, 3)
    base = 4 * np.arange(nx * ny)[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
    return verts, faces


def occupancy_rgba(p: np.ndarray) -> np.ndarray:
    """(n, 4) RGBA of occupancy probabilities (n,): pale blue (free) to orange (occupied)."""
    p = np.clip(np.asarray(p, dtype=np.float32), 0.0, 1.0).reshape(-1, 1)
    free, full = np.array(OCCUPANCY_FREE_RGBA, np.float32), np.array(OCCUPANCY_FULL_RGBA, np.float32)
    return (free + p * (full - free)).astype(np.float32)


def occupancy_colours(values: np.ndarray) -> np.ndarray:
    """Heat-map colours (4 nx ny, 4) RGBA float32 of occupancy probabilities (nx, ny) (the colour
    attribute Eevee and Cycles show), one colour per cell repeated on its 4 vertices."""
    return np.repeat(occupancy_rgba(np.asarray(values).reshape(-1)), 4, axis=0)


def occupancy_bins(values: np.ndarray) -> np.ndarray:
    """(2 nx ny,) material index of each heat-map triangle (its cell's ``OCCUPANCY_BINS`` bin):
    what Solid and Workbench shading show, which read material colours, not attributes."""
    p = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0).reshape(-1)
    b = np.searchsorted(np.asarray(OCCUPANCY_BINS), p, side="right") - 1
    return np.repeat(b.astype(np.int32), 2)


def _occupancy_object(root, data: ReviewData):
    """The heat-map object (a flat grid with a per-vertex colour attribute), or None when no
    frame has a map."""
    first = next((m for m in (data.occupancy or []) if m is not None), None)
    if first is None:
        return None
    values, _, cell = first
    nx, ny = np.asarray(values).shape
    obj = meshdata.new_mesh_object(OCCUPANCY_OBJECT, *occupancy_grid_arrays(nx, ny, float(cell)), root)
    mesh = obj.data
    attr = mesh.color_attributes.new(OCCUPANCY_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    mesh.color_attributes.active_color = attr
    # One material per occupancy bin: its viewport colour is what Solid / Workbench shading show
    # (per triangle, by material index); its nodes read the attribute for Eevee / Cycles.
    centres = np.append(np.asarray(OCCUPANCY_BINS[1:]), 1.0) - 0.5 * np.diff(OCCUPANCY_BINS + (1.0,))
    for i, rgba in enumerate(occupancy_rgba(centres)):
        mat = bpy.data.materials.new(f"{OCCUPANCY_OBJECT} {i}")
        if mat.node_tree is None:  # Blender 4.x (node-based by default from 5.0)
            mat.use_nodes = True
        mat.diffuse_color = tuple(float(c) for c in rgba)
        nodes = mat.node_tree.nodes
        bsdf = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
        col = nodes.new("ShaderNodeAttribute")
        col.attribute_name = OCCUPANCY_ATTRIBUTE
        mat.node_tree.links.new(col.outputs["Color"], bsdf.inputs["Base Color"])
        mat.node_tree.links.new(col.outputs["Color"], bsdf.inputs["Emission Color"])
        bsdf.inputs["Emission Strength"].default_value = 0.5
        mesh.materials.append(mat)
    obj["adv3d_occupancy_shape"] = [int(nx), int(ny)]
    return obj


def car_arrays(length: float, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A simple car (origin at the footprint centre on the ground, front +x): a body of the full
    length and 55 % of the height under a cabin set back, so the ego reads as a vehicle with a
    front. Returns (16, 3) vertices in metres and (24, 3) triangles."""
    body_v, body_f = meshdata.box_arrays(length, width, 0.55 * height)
    cab_v, cab_f = meshdata.box_arrays(0.5 * length, 0.85 * width, 0.45 * height)
    cab_v = cab_v + np.array([-0.1 * length, 0.0, 0.55 * height])
    return np.concatenate([body_v, cab_v]), np.concatenate([body_f, cab_f + len(body_v)])


def build_review(bscene, data: ReviewData, key: str = "") -> dict:
    """Create the review objects in ``bscene`` (replacing a previous review) and show frame 0.

    Args:
        key: the replay the data came from (``ops_review.replay_key``); '' for data made in
            memory (a key unique to this object).

    Returns:
        counts of what was created.
    """
    _validate(data)
    clear_review(bscene)
    root = places.panel_collection(bscene, REVIEW_COLLECTION)
    place = places.make_place(bscene, root, _review_bounds(data))
    bscene.frame_start = 0
    bscene.frame_end = data.frames - 1
    ego = meshdata.new_mesh_object("review ego", *car_arrays(*data.ego_dimensions), root)
    _colour(ego, EGO_RGBA)
    _animate(ego, data.ego_poses)
    for actor in data.actors:
        if actor.vertices is not None:
            v, f = actor.vertices, actor.faces
        else:
            v, f = meshdata.box_arrays(*actor.dimensions)
        obj = meshdata.new_mesh_object(f"review actor {actor.id}", v, f, root)
        obj["adv3d_adversarial"] = bool(actor.adversarial)
        _colour(obj, ADVERSARIAL_RGBA if actor.adversarial else BENIGN_RGBA)
        if actor.adversarial:
            obj.show_in_front = True  # drawn over points and boxes in the viewport
        _animate(obj, actor.poses)
    points = bpy.data.objects.new("review lidar", bpy.data.meshes.new("review lidar"))
    root.objects.link(points)
    if data.points_in_ego_frame:
        points.parent = ego  # the ego's keyframes carry the ego-frame points into the map
    _show_as_points(points)
    _colour(points, POINTS_RGBA)
    boxes = meshdata.new_mesh_object("review detections", np.zeros((0, 3)), np.zeros((0, 3), int), root)
    _colour(boxes, DETECTIONS_RGBA)
    # edges as thin beams (a wire display is neither rendered nor drawn the same in every shading)
    boxes.modifiers.new("edges", "WIREFRAME").thickness = BOX_EDGE_M
    for name, rgba, width in (("review predictions", PREDICTIONS_RGBA, 0.05), ("review plan", PLAN_RGBA, 0.1)):
        curve = bpy.data.curves.new(name, "CURVE")
        curve.dimensions = "3D"
        curve.bevel_depth = width  # a thickness, so the line shows in renders too
        obj = bpy.data.objects.new(name, curve)
        root.objects.link(obj)
        _colour(obj, rgba)
    _occupancy_object(root, data)
    if data.detections is not None:
        most = max((len(d) for d in data.detections), default=0)
        labels = meshdata.get_collection(LABEL_COLLECTION, root)
        for i in range(min(most, MAX_LABELS)):
            curve = bpy.data.curves.new(f"review score {i}", "FONT")
            curve.size = LABEL_SIZE
            curve.align_x = "LEFT"
            obj = bpy.data.objects.new(f"review score {i}", curve)
            labels.objects.link(obj)
            _colour(obj, LABEL_RGBA)
    places.adopt(root, place)
    attach(bscene, data, key or f"memory:{id(data)}")
    bscene.frame_set(0)
    return {"frames": data.frames, "actors": len(data.actors),
            "adversarial": sum(a.adversarial for a in data.actors)}


def _review_bounds(data: ReviewData, margin: float = 30.0) -> np.ndarray:
    """x0, y0, x1, y1 (m) around the ego's and the actors' poses, plus ``margin``."""
    poses = np.concatenate([data.ego_poses[:, :2]] + [a.poses[:, :2] for a in data.actors])
    poses = poses[np.isfinite(poses).all(axis=1)]
    if not len(poses):
        return np.array([-margin, -margin, margin, margin])
    return np.r_[poses.min(axis=0) - margin, poses.max(axis=0) + margin]


def attach(bscene, data: ReviewData, key: str) -> None:
    """Make the frame handler draw ``data`` in ``bscene`` (its objects already exist) and record
    on the scene which replay it shows."""
    props = bscene.adv3d.review
    old = props.key
    _CACHE[key] = data
    props.key = key
    props.stale = ""
    if old and old != key:
        _RELEASED["key"] = old
    prune()
    add_handler()


def data_of(bscene) -> "ReviewData | None":
    """The review data ``bscene`` shows (None when it has none in memory)."""
    key = bscene.adv3d.review.key
    return _CACHE.get(key) if key else None


def prune() -> None:
    """Drop the data no scene shows (but the one released last, for undo)."""
    used = {s.adv3d.review.key for s in bpy.data.scenes if hasattr(s, "adv3d")}
    for key in list(_CACHE):
        if key not in used and key != _RELEASED["key"]:
            del _CACHE[key]


def forget_all() -> None:
    """Drop every review in memory (another .blend file was opened)."""
    _CACHE.clear()
    _RELEASED["key"] = ""


def add_handler() -> None:
    if on_frame_change not in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.append(on_frame_change)


def _validate(data: ReviewData) -> None:
    from adv3d_runner.errors import Adv3dError

    t = data.frames
    for name in ("points", "detections", "predictions", "plan", "occupancy"):
        seq = getattr(data, name)
        if seq is not None and len(seq) != t:
            raise Adv3dError(f"review {name}: expected one entry per frame ({t}), got {len(seq)}")
    shapes = {(np.asarray(m[0]).shape, float(m[2])) for m in (data.occupancy or []) if m is not None}
    if len(shapes) > 1:
        raise Adv3dError(f"review occupancy: every frame's map needs the same grid, got {sorted(shapes)}")
    for actor in data.actors:
        if actor.poses.shape != (t, 3):
            raise Adv3dError(f"review actor {actor.id}: poses must be ({t}, 3), got {actor.poses.shape}")


def clear_review(bscene) -> None:
    """Remove the review objects; the data stays in memory as the last released (undo)."""
    props = bscene.adv3d.review
    if props.key:
        _RELEASED["key"] = props.key
    props.key = ""
    props.stale = ""
    prune()
    coll = bpy.data.collections.get(REVIEW_COLLECTION)
    if coll is not None:
        for obj in list(coll.objects):
            ad = obj.animation_data
            if ad is not None and ad.action is not None:
                action = ad.action
                ad.action = None
                if action.users == 0:
                    bpy.data.actions.remove(action)
        meshdata.remove_collection(LABEL_COLLECTION)
        meshdata.remove_collection(REVIEW_COLLECTION)


def remove_handler() -> None:
    while on_frame_change in bpy.app.handlers.frame_change_post:
        bpy.app.handlers.frame_change_post.remove(on_frame_change)


# --------------------------------------------------------------------------- per-frame update

def _set_points(mesh, pts: np.ndarray) -> None:
    pts = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 3)
    if len(mesh.vertices) != len(pts) or len(mesh.polygons):
        mesh.clear_geometry()
        mesh.vertices.add(len(pts))
    mesh.vertices.foreach_set("co", pts.ravel())
    mesh.update()


def _boxes_arrays(dets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Detection boxes (D, 7) -> one mesh: (8D, 3) vertices, (12D, 3) triangles."""
    d = np.asarray(dets, dtype=np.float64).reshape(-1, 7)
    base_v, base_f = meshdata.box_arrays(1.0, 1.0, 1.0)
    v = base_v[None] * d[:, None, 3:6]  # (D, 8, 3) scaled unit boxes
    c, s = np.cos(d[:, 2]), np.sin(d[:, 2])
    x = v[..., 0] * c[:, None] - v[..., 1] * s[:, None] + d[:, None, 0]
    y = v[..., 0] * s[:, None] + v[..., 1] * c[:, None] + d[:, None, 1]
    verts = np.stack([x, y, v[..., 2]], axis=-1).reshape(-1, 3)
    faces = (base_f[None] + 8 * np.arange(len(d))[:, None, None]).reshape(-1, 3)
    return verts, faces


def _set_polylines(curve, lines: list[np.ndarray], z: float = 0.3) -> None:
    """Replace a curve's splines by 2-D polylines (each (P, 2)) at height ``z``."""
    curve.splines.clear()
    for line in lines:
        line = np.asarray(line, dtype=np.float64).reshape(-1, 2)
        line = line[np.isfinite(line).all(axis=1)]
        if len(line) < 2:
            continue
        spline = curve.splines.new("POLY")
        spline.points.add(len(line) - 1)
        co = np.empty((len(line), 4), dtype=np.float32)
        co[:, :2] = line
        co[:, 2] = z
        co[:, 3] = 1.0
        spline.points.foreach_set("co", co.ravel())


def update_frame(bscene, frame: int) -> None:
    """Write frame ``frame``'s points, detection boxes, predictions and plan into the objects
    (nothing when the scene's replay is not in memory)."""
    data = data_of(bscene) if hasattr(bscene, "adv3d") else None
    if data is None:
        return
    f = int(np.clip(frame, 0, data.frames - 1))
    objs = bpy.data.objects
    if data.points is not None and "review lidar" in objs:
        _set_points(objs["review lidar"].data, data.points[f])
    if data.detections is not None and "review detections" in objs:
        meshdata.set_mesh_arrays(objs["review detections"].data, *_boxes_arrays(data.detections[f]))
    if data.predictions is not None and "review predictions" in objs:
        pred = np.asarray(data.predictions[f], dtype=np.float64)
        _set_polylines(objs["review predictions"].data, list(pred) if pred.ndim == 3 else [])
    if data.plan is not None and "review plan" in objs:
        _set_polylines(objs["review plan"].data, [data.plan[f]], z=0.35)
    if data.occupancy is not None and OCCUPANCY_OBJECT in objs:
        _set_occupancy(objs[OCCUPANCY_OBJECT], data.occupancy[f])
    if data.detections is not None:
        _set_labels(data.detections[f])


def _set_occupancy(obj, entry) -> None:
    """Place the heat map at the frame's grid pose and paint its cells (hidden without a map)."""
    obj.hide_viewport = obj.hide_render = entry is None
    if entry is None:
        return
    values, pose, _ = entry
    obj.location = (float(pose[0]), float(pose[1]), OCCUPANCY_Z)
    obj.rotation_euler = (0.0, 0.0, float(pose[2]))
    attr = obj.data.color_attributes[OCCUPANCY_ATTRIBUTE]
    attr.data.foreach_set("color", occupancy_colours(values).ravel())
    obj.data.polygons.foreach_set("material_index", occupancy_bins(values))
    obj.data.update()


def _set_labels(dets: np.ndarray) -> None:
    """Score labels above the detection boxes (highest scores first; unused labels hidden)."""
    coll = bpy.data.collections.get(LABEL_COLLECTION)
    if coll is None:
        return
    d = np.asarray(dets, dtype=np.float64).reshape(-1, 7)
    d = d[np.argsort(-d[:, 6], kind="stable")]
    for i in range(MAX_LABELS):
        obj = bpy.data.objects.get(f"review score {i}")
        if obj is None:
            break
        shown = i < len(d)
        obj.hide_viewport = obj.hide_render = not shown
        if shown:  # on the ground beside the box's left side, never over the shape
            x, y, yaw, _, w = d[i, :5]
            obj.data.body = f"{d[i, 6]:.2f}"
            obj.location = (x - np.sin(yaw) * (0.5 * w + 0.3), y + np.cos(yaw) * (0.5 * w + 0.3), 0.05)
            obj.rotation_euler = (0.0, 0.0, yaw)


def blank_frame() -> None:
    """Empty the per-frame geometry (points, boxes, curves, labels, heat map): shown when the replay a
    review came from is missing or changed, so nothing stale is drawn."""
    objs = bpy.data.objects
    if "review lidar" in objs:
        _set_points(objs["review lidar"].data, np.zeros((0, 3), np.float32))
    if "review detections" in objs:
        meshdata.set_mesh_arrays(objs["review detections"].data, np.zeros((0, 3)), np.zeros((0, 3), int))
    for name in ("review predictions", "review plan"):
        if name in objs:
            objs[name].data.splines.clear()
    _set_labels(np.zeros((0, 7)))
    if OCCUPANCY_OBJECT in objs:
        _set_occupancy(objs[OCCUPANCY_OBJECT], None)


@bpy.app.handlers.persistent
def on_frame_change(scene, depsgraph=None) -> None:
    update_frame(scene, scene.frame_current)
