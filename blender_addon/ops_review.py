# SPDX-License-Identifier: GPL-3.0-or-later
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

from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty

from . import jobs, review, runner, uiutil

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
            from adv3d_runner.fileio import read_json

            doc = read_json(summary)  # bounded read
            for sid, entry in sorted(doc.get("scenes", {}).items()):
                for mode, m in sorted(entry.get("modes", {}).items()):
                    rel = (m.get("files") or {}).get("replay")
                    if not rel:
                        continue
                    # the summary's paths stay inside the run folder (symlinks included)
                    target = runner_resolve_inside(p, rel, summary, f"$.scenes.{sid}.modes.{mode}.files.replay")
                    if target.is_file():
                        found.append((f"{sid} / {mode}", target))
        except (runner.FileFormatError, ValueError, AttributeError, TypeError):
            found = []  # a damaged summary (or a path leading out of the folder): use the folder layout
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

def runner_resolve_inside(root: Path, rel, file: Path, field: str) -> Path:
    """``root / rel`` checked to stay inside ``root`` (``adv3d_runner.fileio.resolve_inside``)."""
    from adv3d_runner.fileio import resolve_inside

    return resolve_inside(root, rel, file=file, field=field)


def _actor_mesh(replay_dir: Path, rel: str | None, index: int = 0):
    """(V, 3), (F, 3) of an actor's substituted shape (convention frame), or None. The file
    stays inside the replay's folder (symlinks included)."""
    if not rel:
        return None
    from adv3d_runner.shapes.mesh_io import read_library_mesh

    mesh = read_library_mesh(runner_resolve_inside(replay_dir, rel, replay_dir / "replay", f"$.actors[{index}].mesh"))
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
    for i, a in enumerate(replay.actors):
        mesh = _actor_mesh(replay_dir, a.mesh, i) if a.adversarial else None
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


HASH_STEP_BYTES = 1 << 23  # hashed per step (~20 ms)


def replay_files(path: Path) -> list[Path]:
    """The files a replay is made of: the JSON and, when there, its points file."""
    from adv3d_runner.sim.replay import points_path

    pts = points_path(path)
    return [path] + ([pts] if pts.is_file() else [])


def replay_key_steps(path: str | Path):
    """Steps generator -> the key of a replay: its absolute path and the SHA-256 of its files
    (``"/abs/replay.json.gz#sha256:..."``). Raises ``FileFormatError`` for a missing file."""
    import hashlib

    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise runner.FileFormatError(path, "$", "an existing replay file", "file not found")
    h = hashlib.sha256()
    for f in replay_files(path):
        h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            while chunk := fh.read(HASH_STEP_BYTES):
                h.update(chunk)
                yield 0.0, f"hashing {f.name}"
    return f"{path}#sha256:{h.hexdigest()}"


def key_path(key: str) -> Path:
    return Path(key.rsplit("#sha256:", 1)[0])


def load_review_steps(bscene, path: str | Path):
    """Steps generator: read a replay file (and its points) in pieces, then build the review in
    ``bscene`` (the last step). Returns the counts of what was built.

    Raises:
        Adv3dError (FileFormatError, MeshImportError) for bad files; nothing is built then.
    """
    from adv3d_runner.progress import span
    from adv3d_runner.sim.replay import load_replay_steps

    path = Path(path).expanduser()
    yield from jobs.import_steps(("scipy.spatial", "trimesh"))  # adversarial shapes are glb files
    key = yield from span(replay_key_steps(path), 0.0, 0.05, f"hashing {path.name}")
    replay = yield from span(load_replay_steps(path, points=True), 0.05, 0.95, f"reading {path.name}")
    yield 0.95, "building the review"
    data, origin = replay_to_review(replay, path.parent)
    counts = review.build_review(bscene, data, key)
    coll = bpy.data.collections[review.REVIEW_COLLECTION]
    coll["adv3d_origin"] = [float(origin[0]), float(origin[1])]
    coll["adv3d_scene_id"] = replay.scene_id
    bscene.adv3d.review.loaded = str(path)
    bscene.render.fps = max(1, int(round(1.0 / replay.dt)))
    counts["points"] = replay.points is not None
    return counts


def load_review(bscene, path: str | Path) -> dict:
    """Load a replay file (and its points) and build the review in ``bscene`` (all at once)."""
    from adv3d_runner.progress import run_steps

    return run_steps(load_review_steps(bscene, path))


def needs_reattach(bscene) -> bool:
    """The scene shows a review whose replay is not in memory (a .blend just opened, an undo)."""
    props = bscene.adv3d.review
    return bool(props.key) and props.key not in review._CACHE and not props.stale


def reattach_steps(bscenes):
    """Steps generator: read again the replays of the scenes that show a review (the arrays are
    not saved in a .blend), checking each file is the one the review was made from (same
    content hash). A scene whose replay is gone or changed gets ``review.stale`` set and its
    per-frame geometry emptied: nothing from another file is ever drawn. Returns
    {scene name: True (attached) / message (stale)}."""
    from adv3d_runner.progress import span
    from adv3d_runner.sim.replay import load_replay_steps

    done = {}
    for bscene in bscenes:
        props = bscene.adv3d.review
        key = props.key
        path = key_path(key)
        coll = bpy.data.collections.get(review.REVIEW_COLLECTION)
        yield from jobs.import_steps(("scipy.spatial", "trimesh"))
        try:
            now = yield from span(replay_key_steps(path), 0.0, 0.05, f"checking {path.name}")
            if now != key:
                raise runner.Adv3dError(f"{path}: the replay file changed since the review was loaded")
            replay = yield from span(load_replay_steps(path, points=True), 0.05, 1.0, f"reading {path.name}")
            data, origin = replay_to_review(replay, path.parent)
            if coll is None or not np.allclose(origin, list(coll.get("adv3d_origin", origin))):
                raise runner.Adv3dError(f"{path}: the review objects do not match the replay")
        except (runner.Adv3dError, OSError, ValueError) as exc:
            props.stale = f"{exc}; use Load review to read it again"
            review.blank_frame()
            done[bscene.name] = props.stale
            continue
        review.attach(bscene, data, key)
        review.update_frame(bscene, bscene.frame_current)
        done[bscene.name] = True
    return done


def reattach(bscene) -> bool:
    """Reattach one scene's review at once (see :func:`reattach_steps`); True when attached."""
    from adv3d_runner.progress import run_steps

    if not needs_reattach(bscene):
        return False
    return run_steps(reattach_steps([bscene])).get(bscene.name) is True


def _reattach_pending() -> None:
    """Start reading the replays of scenes that need it: modally in the UI (progress in the
    status bar), at once in background mode (scripts, tests)."""
    scenes = [s for s in bpy.data.scenes if hasattr(s, "adv3d") and needs_reattach(s)]
    if not scenes:
        return None
    if bpy.app.background:
        from adv3d_runner.progress import run_steps

        run_steps(reattach_steps(scenes))
        return None
    wm = bpy.context.window_manager
    window = wm.windows[0] if wm and wm.windows else None
    if window is None:
        return None
    with bpy.context.temp_override(window=window):
        bpy.ops.adv3d.review_reattach("INVOKE_DEFAULT")
    return None


@bpy.app.handlers.persistent
def on_load_post(*_args) -> None:
    # another file: nothing in memory belongs to it
    review.forget_all()
    if bpy.app.background:
        _reattach_pending()
    elif not bpy.app.timers.is_registered(_reattach_pending):
        bpy.app.timers.register(_reattach_pending, first_interval=0.0)  # after the file is shown


@bpy.app.handlers.persistent
def on_undo_post(*_args) -> None:
    # an undo / redo may bring back a review (undo of Clear) or take one away (undo of Load)
    review.prune()
    if bpy.app.background:
        _reattach_pending()
    elif not bpy.app.timers.is_registered(_reattach_pending):
        bpy.app.timers.register(_reattach_pending, first_interval=0.0)


_HANDLERS = (("load_post", on_load_post), ("undo_post", on_undo_post), ("redo_post", on_undo_post))


def add_handlers() -> None:
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)
    review.add_handler()


def remove_handlers() -> None:
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        while fn in lst:
            lst.remove(fn)
    review.remove_handler()
    if bpy.app.timers.is_registered(_reattach_pending):
        bpy.app.timers.unregister(_reattach_pending)


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


class ADV3D_OT_review_load(jobs.JobOperator, bpy.types.Operator):
    """Load a run bundle's replay (or one replay file): ego, actors, points, detections,
    predictions, plan (reads in the background: progress in the status bar, Esc cancels)"""

    bl_idname = "adv3d.review_load"
    bl_label = "Load review"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Load review"

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"},
                             description="Replay file or run bundle folder (default: the panel's)")
    replay: StringProperty(options={"SKIP_SAVE"},
                           description="Which replay of the bundle (default: the panel's choice, else the first)")

    def start_job(self, context):
        props = context.scene.adv3d.review
        path = bpy.path.abspath(self.filepath or props.path)
        if not path:
            raise runner.Adv3dError("choose a run bundle folder or a replay file")
        found = find_replays(path)
        # the panel's choice lists the panel's bundle; an explicit filepath has its own
        want = self.replay or ("" if self.filepath else props.replay)
        want = "" if want == NO_REPLAY else want
        self._chosen = next((p for label, p in found if want and (str(p) == want or label == want)), found[0][1])
        return load_review_steps(context.scene, self._chosen)

    def finish_job(self, context, job):
        counts = job.result
        self.report({"INFO"}, f"{self._chosen.name}: {counts['frames']} frames, {counts['actors']} actors "
                              f"({counts['adversarial']} adversarial)" + (", points" if counts["points"] else ""))
        return {"FINISHED"}


class ADV3D_OT_review_reattach(jobs.JobOperator, bpy.types.Operator):
    """Read again the replays of reviews whose data is not in memory (after opening a .blend or
    an undo)"""

    bl_idname = "adv3d.review_reattach"
    bl_label = "Read review replays"
    bl_options = {"INTERNAL"}
    job_label = "Reading the review's replay"

    def start_job(self, context):
        scenes = [s for s in bpy.data.scenes if needs_reattach(s)]
        return reattach_steps(scenes) if scenes else None

    def finish_job(self, context, job):
        for name, result in job.result.items():
            if result is not True:
                self.report({"WARNING"}, f"{name}: {result}")
        return {"FINISHED"}


class ADV3D_OT_review_clear(bpy.types.Operator):
    """Remove the review objects"""

    bl_idname = "adv3d.review_clear"
    bl_label = "Clear review"
    bl_options = {"REGISTER", "UNDO"}

    @uiutil.reported
    def execute(self, context):
        review.clear_review(context.scene)
        context.scene.adv3d.review.loaded = ""
        return {"FINISHED"}


classes = (ADV3D_OT_review_load, ADV3D_OT_review_reattach, ADV3D_OT_review_clear)
