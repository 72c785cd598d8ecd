"""Review panel operators: load a run bundle (or one replay file) into the review engine.

A replay file ("adv3d-replay", ``adv3d_runner.sim.replay``, numpy only) is converted into the
engine's :class:`~blender_addon.review.ReviewData`:

* map coordinates are shifted by an integer-metre origin near the ego's first pose (kept on the
  review collection as ``adv3d_origin``), so Blender's float32 locations keep millimetres in
  UTM-sized map frames;
* the LiDAR points stay in the **ego frame**, as stored: the point-cloud object is parented to
  the ego, whose keyframes put them in place (no per-frame transform on load);
* an adversarial actor gets the mesh of its substituted shape (the replay's ``mesh`` entry,
  the bundle's ``actor<ID>.glb``), the others a box of their dimensions;
* detections (x, y, length, width, yaw, score) become boxes of a nominal height with a score
  label; every predicted mode becomes one polyline; the plan another;
* an instance-free stack's occupancy heat map (replay version 2) becomes a coloured grid on
  the ground, the map of the frame's current time (t = 0: what the stack believes is occupied
  now, around the attacked actors), blue (free) to red (occupied).

Bundle layout (docs/formats.md, "Run bundle"): ``summary.json`` lists per scene and mode the
replay file; without it, ``scenes/*/*/replay.json[.gz]`` and ``replay.json[.gz]`` in the folder
itself (the output of ``adv3d simulate``) are offered.
"""
from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty

from . import review, runner

DETECTION_HEIGHT = 1.6  # m; the replay's boxes are 2-D (BEV), drawn with a nominal height
REPLAY_NAMES = ("replay.json.gz", "replay.json")


# --------------------------------------------------------------------------- finding replays

def find_replays(path: str | Path) -> list[tuple[str, Path]]:
    """Replay files of a run bundle folder, a simulate output folder, or one replay file.

    Returns:
        (label, path) pairs, label ``"<scene> / <mode>"`` for bundle entries.
    """
    p = Path(path).expanduser()
    if p.is_file():
        return [(p.name, p)]
    if not p.is_dir():
        raise runner.FileFormatError(p, "$", "a run bundle folder or a replay file", "not found")
    found: list[tuple[str, Path]] = []
    summary = p / "summary.json"
    if summary.is_file():
        try:
            doc = json.loads(summary.read_text())
            for sid, entry in sorted(doc.get("scenes", {}).items()):
                for mode, m in sorted(entry.get("modes", {}).items()):
                    rel = (m.get("files") or {}).get("replay")
                    if rel and (p / rel).is_file():
                        found.append((f"{sid} / {mode}", p / rel))
        except (ValueError, AttributeError, TypeError):
            found = []  # a damaged summary: fall back to the folder layout below
    if not found:
        for name in REPLAY_NAMES:
            for f in sorted(p.glob(f"scenes/*/*/{name}")):
                found.append((f"{f.parent.parent.name} / {f.parent.name}", f))
            if (p / name).is_file():
                found.append((name, p / name))
    if not found:
        raise runner.FileFormatError(p, "$", "a run bundle (summary.json or scenes/*/*/replay.json.gz) "
                                     "or a folder with replay.json.gz", "no replay file")
    return found


# --------------------------------------------------------------------------- conversion

def _actor_mesh(replay_dir: Path, rel: str | None):
    """(V, 3), (F, 3) of an actor's substituted shape (convention frame), or None."""
    if not rel:
        return None
    from adv3d_runner.shapes.mesh_io import read_library_mesh

    mesh = read_library_mesh(replay_dir / rel)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def replay_to_review(replay, replay_dir: str | Path) -> tuple[review.ReviewData, np.ndarray]:
    """A loaded ``Replay`` -> (``ReviewData`` in origin-shifted map coordinates, origin (2,)).

    Adversarial actors whose mesh file is missing or unreadable raise ``MeshImportError``.
    """
    replay_dir = Path(replay_dir)
    first = replay.ego_poses[np.isfinite(replay.ego_poses).all(axis=1)]
    origin = np.floor(first[0, :2]) if len(first) else np.zeros(2)
    shift = np.array([origin[0], origin[1], 0.0])
    actors = []
    for a in replay.actors:
        mesh = _actor_mesh(replay_dir, a.mesh) if a.adversarial else None
        actors.append(review.ReviewActor(a.id, a.poses - shift, np.asarray(a.dimensions, float),
                                         None if mesh is None else mesh[0], None if mesh is None else mesh[1],
                                         adversarial=a.adversarial))
    dets, preds, plans = [], [], []
    for f in replay.frames:
        b = f.det_boxes
        d = np.empty((len(b), 7))
        d[:, 0:2] = b[:, 0:2] - origin
        d[:, 2] = b[:, 4]
        d[:, 3:5] = b[:, 2:4]
        d[:, 5] = DETECTION_HEIGHT
        d[:, 6] = f.det_scores
        dets.append(d)
        t = f.pred_trajectories
        preds.append(t.reshape(-1, t.shape[2], 2) - origin if t.size else np.zeros((0, 2, 2)))
        plans.append(f.plan[:, :2] - origin)
    points = None if replay.points is None else [p[:, :3] for p in replay.points]
    occupancy = None
    if any(f.occupancy is not None for f in replay.frames):
        occupancy = []
        for f in replay.frames:
            m = f.occupancy
            occupancy.append(None if m is None else (m.probabilities[0], m.poses[0] - shift, m.cell))
    data = review.ReviewData(replay.ego_poses - shift, np.asarray(replay.ego_dimensions, float), actors,
                             points, dets, preds, plans, dt=replay.dt, points_in_ego_frame=True,
                             occupancy=occupancy)
    return data, origin


def load_review(bscene, path: str | Path) -> dict:
    """Load a replay file (and its points) and build the review in ``bscene``.

    Raises:
        Adv3dError (FileFormatError, MeshImportError) for bad files.
    """
    from adv3d_runner.sim.replay import load_replay

    path = Path(path).expanduser()
    replay = load_replay(path, points=True)
    data, origin = replay_to_review(replay, path.parent)
    counts = review.build_review(bscene, data)
    coll = bpy.data.collections[review.REVIEW_COLLECTION]
    coll["adv3d_origin"] = [float(origin[0]), float(origin[1])]
    coll["adv3d_replay"] = str(path)
    coll["adv3d_scene_id"] = replay.scene_id
    bscene.render.fps = max(1, int(round(1.0 / replay.dt)))
    counts["points"] = replay.points is not None
    return counts


def reattach(bscene) -> bool:
    """After opening a .blend that holds a review: read its replay again so the per-frame
    geometry follows the timeline (the arrays are not saved in the .blend). False when the
    scene holds no review or its replay file is gone or changed shape (the objects then keep
    the last frame shown)."""
    from adv3d_runner.sim.replay import load_replay

    coll = bpy.data.collections.get(review.REVIEW_COLLECTION)
    if coll is None or "adv3d_replay" not in coll or bscene.name in review._LOADED:
        return False
    path = Path(coll["adv3d_replay"])
    try:
        replay = load_replay(path, points=True)
        data, origin = replay_to_review(replay, path.parent)
    except (runner.Adv3dError, OSError, ValueError):
        return False
    if not np.allclose(origin, list(coll.get("adv3d_origin", origin))):
        return False
    review.attach(bscene, data)
    return True


@bpy.app.handlers.persistent
def on_load_post(*_args) -> None:
    for bscene in bpy.data.scenes:
        reattach(bscene)


def add_handlers() -> None:
    if on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(on_load_post)


def remove_handlers() -> None:
    while on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(on_load_post)


# --------------------------------------------------------------------------- operators

# Enum items must stay referenced while Blender shows them (a known bpy pitfall).
_ITEMS: list[tuple[str, str, str]] = []
NO_REPLAY = "NONE"


def replay_items(self, context):
    _ITEMS.clear()
    path = bpy.path.abspath(self.path) if self.path else ""
    try:
        found = find_replays(path) if path else []
    except runner.Adv3dError:
        found = []
    _ITEMS.extend((str(p), label, str(p)) for label, p in found)
    if not _ITEMS:
        _ITEMS.append((NO_REPLAY, "(no replay)", "Choose a run bundle folder or a replay file"))
    return _ITEMS


class ADV3D_OT_review_load(bpy.types.Operator):
    """Load a run bundle's replay (or one replay file): ego, actors, points, detections, predictions, plan"""

    bl_idname = "adv3d.review_load"
    bl_label = "Load review"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"},
                             description="Replay file or run bundle folder (default: the panel's)")
    replay: StringProperty(options={"SKIP_SAVE"},
                           description="Which replay of the bundle (default: the panel's choice, else the first)")

    def execute(self, context):
        props = context.scene.adv3d.review
        path = bpy.path.abspath(self.filepath or props.path)
        if not path:
            self.report({"ERROR"}, "Choose a run bundle folder or a replay file")
            return {"CANCELLED"}
        try:
            found = find_replays(path)
            # the panel's choice lists the panel's bundle; an explicit filepath has its own
            want = self.replay or ("" if self.filepath else props.replay)
            want = "" if want == NO_REPLAY else want
            chosen = next((p for label, p in found if want and (str(p) == want or label == want)), found[0][1])
            counts = load_review(context.scene, chosen)
        except runner.Adv3dError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        except (OSError, ValueError) as exc:  # e.g. an unreadable mesh the importer rejects
            self.report({"ERROR"}, f"{path}: {exc}")
            return {"CANCELLED"}
        props.loaded = str(chosen)
        self.report({"INFO"}, f"{chosen.name}: {counts['frames']} frames, {counts['actors']} actors "
                              f"({counts['adversarial']} adversarial)" + (", points" if counts["points"] else ""))
        return {"FINISHED"}


class ADV3D_OT_review_clear(bpy.types.Operator):
    """Remove the review objects"""

    bl_idname = "adv3d.review_clear"
    bl_label = "Clear review"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        review.clear_review(context.scene)
        context.scene.adv3d.review.loaded = ""
        return {"FINISHED"}


classes = (ADV3D_OT_review_load, ADV3D_OT_review_clear)
