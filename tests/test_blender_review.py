"""The Review panel on the ``bpy`` module: a run bundle written with the runner's replay writer
(under tmp_path) loads as animated objects that follow the timeline; bad files are reported.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

T = 12
ORIGIN_XY = (500123.4, 5400000.7)  # a UTM-sized map frame: the loader must shift it


def make_replay(seed: int = 0, frames: int = T):
    """A small replay: ego along +x, an adversarial actor (leaves at frame 9) and a benign one,
    points, detections, predictions and a plan in every frame."""
    from adv3d_runner.sim.replay import Replay, ReplayActor, ReplayFrame

    rng = np.random.default_rng(seed)
    x0, y0 = ORIGIN_XY
    t = np.arange(frames)
    ego = np.stack([x0 + 1.0 * t, np.full(frames, y0), np.full(frames, 0.05)], axis=1)
    adv = np.stack([x0 + 20 + 0.8 * t, np.full(frames, y0 + 3.5), np.zeros(frames)], axis=1)
    adv[9:] = np.nan
    benign = np.stack([x0 + 35 + 0.9 * t, np.full(frames, y0 - 3.5), np.full(frames, 0.1)], axis=1)
    actors = [ReplayActor(7, "sedan", [4.4, 1.8, 1.4], adv, adversarial=True, mesh="actor7.glb"),
              ReplayActor(8, "suv", [4.8, 1.9, 1.7], benign)]
    out = []
    for k in range(frames):
        d = k % 3 + 1
        boxes = np.column_stack([x0 + 10 + rng.random(d) * 30, y0 + rng.random(d) * 5,
                                 np.full(d, 4.5), np.full(d, 1.8), rng.random(d) * 0.2])
        traj = x0 + rng.random((2, 3, 6, 2)) * 40
        traj[..., 1] += y0 - x0
        plan = np.column_stack([ego[k, 0] + np.linspace(0, 20, 10), np.full(10, y0), np.zeros(10)])
        out.append(ReplayFrame(boxes, rng.random(d), [0], [[x0 + 20, y0, 4.5, 1.8, 0.0]], [[8.0, 0.0]],
                               [0, 1], traj, np.full((2, 3), 1 / 3), plan, np.full(10, 10.0), "keep", 0.5))
    points = [np.column_stack([rng.uniform(-40, 40, (40 + 10 * k, 2)), rng.uniform(0, 2, 40 + 10 * k),
                               rng.random(40 + 10 * k), np.full(40 + 10 * k, -1.0)]).astype(np.float32)
              for k in range(frames)]
    return Replay("fixture-scene", 0.1, [4.8, 1.9, 1.55], ego, np.full(frames, 10.0), actors, out,
                  autonomy="oracle", points=points)


def write_bundle(root: Path, replay=None) -> tuple[Path, object]:
    """``root`` as a run bundle: summary.json + scenes/<id>/closed/{replay.json.gz, actor7.glb}."""
    import trimesh

    from adv3d_runner.shapes.mesh_io import write_library_glb
    from adv3d_runner.sim.replay import save_replay

    replay = replay or make_replay()
    folder = root / "scenes" / replay.scene_id / "closed"
    folder.mkdir(parents=True)
    body = trimesh.creation.cylinder(radius=0.8, height=4.0, sections=12)
    body.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    body.apply_translation([0, 0, 0.8])
    write_library_glb(body, folder / "actor7.glb")
    save_replay(replay, folder / "replay.json.gz")
    rel = f"scenes/{replay.scene_id}/closed"
    (root / "summary.json").write_text(json.dumps({
        "format": "adv3d.attack_summary", "version": 1,
        "scenes": {replay.scene_id: {"modes": {"closed": {"files": {
            "meshes": {"7": f"{rel}/actor7.glb"}, "replay": f"{rel}/replay.json.gz"}}}}}}))
    return folder / "replay.json.gz", replay


@pytest.fixture
def ctx(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy.context
    from blender_addon import review

    review.clear_review(bpy.context.scene)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory, addon):
    root = tmp_path_factory.mktemp("adv3d_review") / "run"
    path, _ = write_bundle(root)
    from adv3d_runner.sim.replay import load_replay

    return root, path, load_replay(path)  # the replay as stored (quantised)


def _world_points(obj) -> np.ndarray:
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world)
    return co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]


def _origin() -> np.ndarray:
    from blender_addon import review

    return np.array([*bpy.data.collections[review.REVIEW_COLLECTION]["adv3d_origin"], 0.0])


def _fcurve_keys(obj, data_path: str, index: int) -> int:
    from blender_addon.ops_scene import _fcurves

    return next(len(fc.keyframe_points) for fc in _fcurves(obj, create=False)
                if fc.data_path == data_path and fc.array_index == index)


def test_finds_the_replays_of_a_bundle(bundle, tmp_path):
    from adv3d_runner.errors import FileFormatError
    from blender_addon import ops_review

    root, path, _ = bundle
    assert ops_review.find_replays(root) == [("fixture-scene / closed", path)]
    assert ops_review.find_replays(path) == [(path.name, path)]
    with pytest.raises(FileFormatError, match="no replay file"):
        ops_review.find_replays(tmp_path)


def test_review_import_creates_objects_and_keyframes(ctx, bundle):
    from adv3d_runner.shapes.mesh_io import read_library_mesh
    from blender_addon import meshdata

    root, path, replay = bundle
    ctx.scene.adv3d.review.path = str(root)
    assert ctx.scene.adv3d.review.replay == str(path)
    assert bpy.ops.adv3d.review_load() == {"FINISHED"}
    objs = bpy.data.objects
    for name in ("review ego", "review actor 7", "review actor 8", "review lidar", "review detections",
                 "review predictions", "review plan", "review score 0", "review score 2"):
        assert name in objs, name
    assert "review score 3" not in objs  # at most 3 detections per frame
    assert (ctx.scene.frame_start, ctx.scene.frame_end) == (0, T - 1)
    # the adversarial actor carries its substituted shape, highlighted; the benign one is a box
    adv, benign = objs["review actor 7"], objs["review actor 8"]
    glb = read_library_mesh(path.parent / "actor7.glb")
    assert len(adv.data.vertices) == len(glb.vertices) and len(benign.data.vertices) == 8
    assert adv["adv3d_adversarial"] and not benign["adv3d_adversarial"]
    assert tuple(adv.color) != tuple(benign.color)
    # keyframes: one per frame where present (the adversarial actor leaves at frame 9)
    assert _fcurve_keys(objs["review ego"], "location", 0) == T
    assert _fcurve_keys(adv, "location", 1) == 9 and _fcurve_keys(benign, "rotation_euler", 2) == T
    origin = _origin()
    assert np.all(np.abs(replay.ego_poses[0, :2] - origin[:2]) < 1.0)  # shifted to near zero
    for f in (0, 4, 11):
        ctx.scene.frame_set(f)
        ego = np.array(objs["review ego"].matrix_world.translation) + origin
        np.testing.assert_allclose(ego[:2], replay.ego_poses[f, :2], atol=1e-3)
        pts = _world_points(objs["review lidar"]) + origin
        assert len(pts) == len(replay.points[f])
        np.testing.assert_allclose(pts, replay.points_in_map(f), atol=2e-3)
        v, _ = meshdata.mesh_arrays(objs["review detections"].data)
        boxes = replay.frames[f].det_boxes
        assert len(v) == 8 * len(boxes)
        np.testing.assert_allclose(v.reshape(-1, 8, 3).mean(axis=1)[:, :2] + origin[:2], boxes[:, :2], atol=1e-3)
        scores = sorted(f"{s:.2f}" for s in replay.frames[f].det_scores)
        shown = sorted(o.data.body for o in objs if o.name.startswith("review score") and not o.hide_render)
        assert shown == scores
        plan = np.array([p.co[:2] for p in objs["review plan"].data.splines[0].points]) + origin[:2]
        np.testing.assert_allclose(plan, replay.frames[f].plan[:, :2], atol=1e-3)
        assert len(objs["review predictions"].data.splines) == 2 * 3  # tracks x modes
        assert adv.hide_render == (f >= 9)
        if f < 9:
            np.testing.assert_allclose(np.array(adv.matrix_world.translation)[:2] + origin[:2],
                                       replay.actors[0].poses[f, :2], atol=1e-3)


def test_scrubbing_updates_points_and_boxes(ctx, bundle):
    root, path, replay = bundle
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    objs = bpy.data.objects
    seen = {}
    for f in (2, 7, 2):
        ctx.scene.frame_set(f)
        pts = _world_points(objs["review lidar"])
        v = np.empty(len(objs["review detections"].data.vertices) * 3)
        objs["review detections"].data.vertices.foreach_get("co", v)
        if f in seen:  # back to the same frame: the same geometry
            np.testing.assert_array_equal(pts, seen[f][0])
            np.testing.assert_array_equal(v, seen[f][1])
        seen[f] = (pts, v)
    assert seen[2][0].shape != seen[7][0].shape  # 60 vs 110 points
    assert not np.array_equal(seen[2][1][:24], seen[7][1][:24])


def test_panel_draws_review(ctx, bundle):
    from types import SimpleNamespace

    from blender_addon import panels

    class Layout:
        seen: list = []

        def prop(self, data, name, **kw):
            assert name in data.bl_rna.properties, name
            Layout.seen.append(name)

        def operator(self, idname, **kw):
            mod, op = idname.split(".")
            assert hasattr(getattr(bpy.ops, mod), op), idname
            Layout.seen.append(idname)

        def label(self, **kw):
            pass

        def __getattr__(self, name):
            return lambda *a, **kw: Layout()

    ctx.scene.adv3d.review.path = str(bundle[0])
    bpy.ops.adv3d.review_load()
    panels.ADV3D_PT_review.draw(SimpleNamespace(layout=Layout()), ctx)
    assert {"path", "replay", "adv3d.review_load", "adv3d.review_clear"} <= set(Layout.seen)
    assert bpy.ops.adv3d.review_clear() == {"FINISHED"}
    assert "review lidar" not in bpy.data.objects and not ctx.scene.adv3d.review.loaded


def test_malformed_replay_is_reported(ctx, bundle, tmp_path):
    import gzip

    root, path, _ = bundle
    doc = json.loads(gzip.decompress(path.read_bytes()))
    doc["outputs"][3]["detections"]["scores"].append(0.5)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(RuntimeError, match=r"\$\.outputs\[3\]\.detections\.scores") as info:
        bpy.ops.adv3d.review_load(filepath=str(bad))
    assert "Traceback" not in str(info.value)
    assert "Adv3D Review" not in bpy.data.collections
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(RuntimeError, match="junk.json"):
        bpy.ops.adv3d.review_load(filepath=str(tmp_path / "junk.json"))
    # a points file that does not match the replay
    run = tmp_path / "run"
    p2, _ = write_bundle(run)
    np.savez(p2.parent / "replay.points.npz", format=np.array("adv3d-replay-points"), version=np.array(1))
    with pytest.raises(RuntimeError, match=r"replay\.points\.npz.*\$\.xyz_cm"):
        bpy.ops.adv3d.review_load(filepath=str(run))
    # a missing adversarial mesh
    (p2.parent / "replay.points.npz").unlink()
    doc = json.loads(gzip.decompress(p2.read_bytes()))
    doc["points"] = None
    doc["actors"][0]["mesh"] = "gone.glb"
    p2.write_bytes(gzip.compress(json.dumps(doc).encode()))
    with pytest.raises(RuntimeError, match="gone.glb"):
        bpy.ops.adv3d.review_load(filepath=str(run))


def test_replay_loading_does_not_import_torch(repo_root):
    code = ("import sys; import adv3d_runner.sim.replay, adv3d_runner.shapes.mesh_io; "
            "sys.exit(int('torch' in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], cwd=repo_root).returncode == 0


def test_render_review_frame(bundle, tmp_path, repo_root):
    """``python -m blender_addon.render --what review`` (what ``adv3d blender render`` runs)."""
    out = tmp_path / "review.png"
    cmd = [sys.executable, "-m", "blender_addon.render", "--what", "review", "--run", str(bundle[0]),
           "--frame", "4", "--size", "160x90", "--out", str(out)]
    done = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    from PIL import Image

    pixels = np.asarray(Image.open(out).convert("RGB"), dtype=np.int64)
    assert pixels.shape == (90, 160, 3)
    red = (pixels[..., 0] > 120) & (pixels[..., 1] < 90) & (pixels[..., 2] < 110)
    assert red.sum() > 0  # the adversarial shape is drawn in red
    bad = subprocess.run(cmd[:-4] + ["--frame", "99", "--out", str(out)], cwd=repo_root, capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "--frame must be in [0, 11]" in bad.stderr


def _lidar_map(scene, frame: int) -> np.ndarray:
    scene.frame_set(frame)
    return _world_points(bpy.data.objects["review lidar"]) + _origin()


def test_review_follows_the_timeline_after_reopening_the_blend(ctx, bundle, tmp_path):
    from blender_addon import review

    root, path, replay = bundle
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    blend = tmp_path / "review.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    review.forget_all()  # as in a fresh Blender
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    assert review.data_of(scene) is not None and not scene.adv3d.review.stale
    lidar = bpy.data.objects["review lidar"]
    assert len(_lidar_map(scene, 6)) == len(replay.points[6])
    np.testing.assert_allclose(_world_points(lidar) + _origin(), replay.points_in_map(6), atol=2e-3)


def with_occupancy_maps(replay, absent=(5,)):
    """The fixture replay with an occupancy heat map in every frame but ``absent`` (Autonomy-B's
    replays, version 2): 3 times, 8 x 4 cells of 0.5 m, the grid moving with the adversarial actor."""
    from adv3d_runner.sim.replay import OccupancyMap

    rng = np.random.default_rng(5)
    for k, f in enumerate(replay.frames):
        if k in absent:
            continue
        centre = np.array([ORIGIN_XY[0] + 20 + 0.8 * k, ORIGIN_XY[1] + 3.5])
        poses = np.array([[*(centre + [10.0 * t, 0.0]), 0.05] for t in (0.0, 1.0, 2.0)])
        f.occupancy = OccupancyMap([0.0, 1.0, 2.0], poses, 0.5, rng.integers(0, 256, (3, 8, 4)))
    return replay


def test_review_shows_the_occupancy_heat_map(ctx, tmp_path):
    """An instance-free stack's replay: the t = 0 heat map of each frame is a coloured grid at
    the map's pose; scrubbing repaints it; a frame without a map hides it."""
    from adv3d_runner.sim.replay import load_replay
    from blender_addon import review

    path, _ = write_bundle(tmp_path / "run", with_occupancy_maps(make_replay()))
    stored = load_replay(path)
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    obj = bpy.data.objects[review.OCCUPANCY_OBJECT]
    assert len(obj.data.vertices) == 4 * 8 * 4 and len(obj.data.polygons) == 2 * 8 * 4
    origin = _origin()
    for f in (3, 8, 3):
        ctx.scene.frame_set(f)
        m = stored.frames[f].occupancy
        np.testing.assert_allclose(np.array(obj.matrix_world.translation)[:2] + origin[:2], m.poses[0, :2], atol=1e-3)
        col = np.empty(len(obj.data.vertices) * 4, np.float32)
        obj.data.color_attributes[review.OCCUPANCY_ATTRIBUTE].data.foreach_get("color", col)
        np.testing.assert_allclose(col.reshape(-1, 4)[::4], review.occupancy_rgba(m.values[0] / 255.0), atol=1e-6)
        # Solid / Workbench shading read materials: each cell's triangles carry its bin's material
        idx = np.empty(len(obj.data.polygons), np.int32)
        obj.data.polygons.foreach_get("material_index", idx)
        want = np.minimum((m.values[0] / 255.0 * 5).astype(int), 4).ravel()
        np.testing.assert_array_equal(idx.reshape(-1, 2)[:, 0], want)
        assert _world_points(obj)[:, 2].max() < 0.0  # under the ground: the points stay visible
        # the most occupied cell is where the map says (grid vertices follow the cell layout)
        i, j = np.unravel_index(np.argmax(m.values[0]), m.values[0].shape)
        cell = _world_points(obj).reshape(-1, 4, 3).mean(axis=1)[i * 4 + j]
        np.testing.assert_allclose(cell[:2] + origin[:2], m.cell_centres(0)[i, j], atol=1e-3)
        assert not obj.hide_render
    ctx.scene.frame_set(5)
    assert obj.hide_render and obj.hide_viewport


def test_review_rejects_maps_of_different_grids(ctx):
    from adv3d_runner.errors import Adv3dError
    from blender_addon import review

    data = review.ReviewData(np.zeros((2, 3)), np.array([4.8, 1.9, 1.5]),
                             occupancy=[(np.zeros((4, 2)), np.zeros(3), 0.5), (np.zeros((4, 3)), np.zeros(3), 0.5)])
    with pytest.raises(Adv3dError, match="same grid"):
        review.build_review(ctx.scene, data)


def test_opening_another_file_never_shows_its_review(ctx, tmp_path):
    """a.blend and b.blend both have a scene called "Scene" reviewing different replays: after
    File > Open, every frame shows the opened file's own points, never the other's."""
    from blender_addon import review

    runs = {}
    for name, seed in (("a", 1), ("b", 2)):
        runs[name] = write_bundle(tmp_path / f"run_{name}", make_replay(seed=seed))
    for name in ("a", "b"):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        assert bpy.context.scene.name == "Scene"
        assert bpy.ops.adv3d.review_load(filepath=str(runs[name][0])) == {"FINISHED"}
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / f"{name}.blend"))
    for name in ("a", "b", "a"):
        bpy.ops.wm.open_mainfile(filepath=str(tmp_path / f"{name}.blend"))
        scene = bpy.context.scene
        assert len(review._CACHE) == 1  # only the opened file's replay is in memory
        want = runs[name][1]
        for f in (5, 2):
            np.testing.assert_allclose(_lidar_map(scene, f), want.points_in_map(f), atol=2e-3)


def test_undo_of_clear_brings_a_live_review_back(ctx, bundle):
    """Clear review, then undo: the objects come back and still follow the timeline."""
    from blender_addon import review

    root, path, replay = bundle
    bpy.ops.ed.undo_push(message="start")
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Load review")
    key = ctx.scene.adv3d.review.key
    assert bpy.ops.adv3d.review_clear() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Clear review")
    assert "review lidar" not in bpy.data.objects and not bpy.context.scene.adv3d.review.key
    bpy.ops.ed.undo()
    scene = bpy.context.scene
    assert "review lidar" in bpy.data.objects and scene.adv3d.review.key == key
    for f in (3, 8):
        np.testing.assert_allclose(_lidar_map(scene, f), replay.points_in_map(f), atol=2e-3)
    # undo once more (before the load): the review is gone and nothing is drawn
    bpy.ops.ed.undo()
    assert "review lidar" not in bpy.data.objects and not bpy.context.scene.adv3d.review.key
    assert review.data_of(bpy.context.scene) is None


def test_a_changed_replay_is_not_reattached(ctx, tmp_path):
    """Save, change the replay file on disk, reopen: the review is marked stale and its
    per-frame geometry emptied (the old points would be another replay's)."""
    from blender_addon import review

    path, _ = write_bundle(tmp_path / "run", make_replay(seed=3))
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "r.blend"))
    from adv3d_runner.sim.replay import save_replay

    save_replay(make_replay(seed=4), path)  # another episode under the same name
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "r.blend"))
    scene = bpy.context.scene
    assert "changed" in scene.adv3d.review.stale and review.data_of(scene) is None
    scene.frame_set(5)
    assert len(bpy.data.objects["review lidar"].data.vertices) == 0
    assert len(bpy.data.objects["review plan"].data.splines) == 0
    # the panel's Load review reads it again
    assert bpy.ops.adv3d.review_load(filepath=str(path)) == {"FINISHED"}
    assert not scene.adv3d.review.stale and review.data_of(scene) is not None


def test_review_load_runs_in_short_steps_and_cancels(ctx, bundle):
    """The modal Load review's work, driven as Blender's timer drives it: every step is short,
    the status bar shows progress, Esc cancels and nothing is built."""
    from blender_addon import jobs, ops_review

    root, path, replay = bundle
    job = jobs.Job("Load review", ops_review.load_review_steps(ctx.scene, path))
    states = [jobs.handle_event(ctx, job, "TIMER", slice_s=0.0)]  # one step per tick
    assert states[0] == jobs.RUNNING and "Load review" in job.status_text()
    while states[-1] == jobs.RUNNING:
        states.append(jobs.handle_event(ctx, job, "TIMER", slice_s=0.0))
    assert states[-1] == jobs.DONE and job.result["frames"] == T and len(states) > 3
    assert job.max_step_s < jobs.MAX_STEP_S
    bpy.ops.adv3d.review_clear()
    job = jobs.Job("Load review", ops_review.load_review_steps(ctx.scene, path))
    jobs.handle_event(ctx, job, "TIMER", slice_s=0.0)
    assert jobs.handle_event(ctx, job, "ESC") == jobs.CANCELLED
    assert "Adv3D Review" not in bpy.data.collections
    jobs.show_progress(ctx, None)


def test_review_in_workbench_shows_the_attacked_shape_first_with_a_legend(ctx, bundle, tmp_path, repo_root):
    """The review as Solid / Workbench shading draws it (material colours), rendered from above
    the attacked actor: its red shape is the largest coloured thing in the frame (no detection box
    or score label over it); the ego is a car (a cabin on a body); the panel has a legend."""
    from blender_addon import review

    assert bpy.ops.adv3d.review_load(filepath=str(bundle[0])) == {"FINISHED"}
    objs = bpy.data.objects
    ego = objs["review ego"]
    assert len(ego.data.vertices) == 16 and len(ego.data.polygons) == 24  # body + cabin
    adv = next(o for o in objs if o.get("adv3d_adversarial"))
    assert adv.data.materials[0].diffuse_color[:] == pytest.approx(review.ADVERSARIAL_RGBA)
    assert objs["review detections"].modifiers[0].type == "WIREFRAME"
    assert all(o.data.size <= review.LABEL_SIZE for o in objs if o.name.startswith("review score"))
    frames = [f for f in range(ctx.scene.frame_end + 1) if not _hidden_at(ctx.scene, adv, f)]
    for f in frames[:: max(1, len(frames) // 3)]:
        ctx.scene.frame_set(f)
        centre = np.array(adv.matrix_world.translation)
        for lab in (o for o in objs if o.name.startswith("review score") and not o.hide_render):
            assert np.linalg.norm(np.array(lab.matrix_world.translation)[:2] - centre[:2]) > 0.5 * adv.dimensions[1]
            assert lab.matrix_world.translation.z < 0.2  # on the ground, not over the shape
    # rendered in Workbench by the render command (a child Blender: rendering needs one)
    out = tmp_path / "review.png"
    cmd = [sys.executable, "-m", "blender_addon.render", "--what", "review", "--run", str(bundle[0]),
           "--frame", str(frames[len(frames) // 2]), "--size", "320x180", "--out", str(out)]
    done = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    from PIL import Image

    px = np.asarray(Image.open(out).convert("RGB"), dtype=np.int64)
    red = (px[..., 0] > 120) & (px[..., 1] < 70) & (px[..., 2] < 70)
    green = (px[..., 1] > 100) & (px[..., 0] < 90) & (px[..., 1] > px[..., 2] + 20)
    assert red.sum() > 100 and red.sum() > 2 * green.sum(), (red.sum(), green.sum())
    from blender_addon import panels

    seen = []

    class Layout:
        def __getattr__(self, name):
            return lambda *a, **k: self
        def label(self, **kw):
            seen.append(kw.get("text", ""))
            return self

    panels._draw_legend(Layout())
    assert seen[1:] == [text for text, _ in review.LEGEND]


def _hidden_at(scene, obj, frame: int) -> bool:
    scene.frame_set(frame)
    return obj.hide_render
