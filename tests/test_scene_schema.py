"""Scene file contract: validation errors name file + JSON path, exact round trip, accessors."""
from __future__ import annotations

import copy
import gzip
import json
import math

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.scene.schema import (Actor, Background, Barrier, Ego, Lane, Scene, Source, StaticMesh, Track,
                                       default_sensors, load_scene, local_slope, save_scene, scene_equal)

T = 30


def make_scene() -> Scene:
    t = np.arange(T) * 0.1
    lanes = [
        Lane(1, [[0, 0], [50, 0], [50, 0], [120, 1.0]], 3.7, left=2, successors=[3], speed_limit=29.1),
        Lane(2, [[0, 3.7], [120, 4.7]], [3.6, 3.5], right=1),
        Lane(3, [[120, 1.0], [200, 2.0]], 3.7),
    ]
    ego = Ego([4.8, 1.9, 1.55], 2.85, Track(x=10 + 20 * t, y=0 * t, yaw=0.001 * t, speed=20 + 0 * t), default_sensors())
    a1 = Actor(7, "sedan", [4.5, 1.8, 1.45], Track(x=40 + 18 * t, y=3.7 + 0 * t, yaw=0 * t, speed=18 + 0 * t))
    valid = np.ones(12, bool)
    valid[4:6] = False
    synthetic = np.zeros(12, bool)
    synthetic[9:] = True
    a2 = Actor(9, "truck", [14.0, 2.5, 3.9],
               Track(x=np.linspace(60, 80, 12), y=np.zeros(12), yaw=np.full(12, math.pi), start=5, valid=valid,
                     synthetic=synthetic), asset="lib.truck")
    bg = Background(1.0, 2.5, 30.0, True, [Barrier("concrete", [[0, 6], [200, 7]], 0.81)],
                    [StaticMesh("sign.glb", [5, 6, 0, 0.5], "metal")])
    return Scene("test-scene", Source("generated", {"seed": 1}, "CC0-1.0", None), 0.1, T, lanes, bg, ego, [a1, a2])


def write_doc(tmp_path, doc, name="scene.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def test_round_trip_exact_json_and_gz(tmp_path):
    scene = make_scene()
    for name in ("a.json", "a.json.gz"):
        p1 = tmp_path / name
        p2 = tmp_path / ("b" + name[1:])
        save_scene(scene, p1)
        loaded = load_scene(p1)
        assert scene_equal(scene, loaded)
        save_scene(loaded, p2)
        assert p1.read_bytes() == p2.read_bytes()
        again = load_scene(p2)
        np.testing.assert_array_equal(again.ego_poses(), loaded.ego_poses())
        np.testing.assert_array_equal(again.actor_poses(9), loaded.actor_poses(9))


def test_rounding_is_idempotent_near_pi(tmp_path):
    yaw = np.array([math.pi, -math.pi, 3.14159, -3.1416, 7.0, -7.0, 0.0005, -0.0004])
    scene = make_scene()
    scene.actors[0].track = Track(x=np.zeros(8), y=np.zeros(8), yaw=yaw, start=0)
    save_scene(scene, tmp_path / "s.json")
    loaded = load_scene(tmp_path / "s.json")
    assert np.all(np.abs(loaded.actors[0].track.yaw) <= math.pi + 1e-3)
    save_scene(loaded, tmp_path / "t.json")
    assert (tmp_path / "s.json").read_bytes() == (tmp_path / "t.json").read_bytes()
    assert "-0.0," not in (tmp_path / "s.json").read_text()


def test_accessors_shapes_and_masks():
    scene = make_scene()
    assert scene.ego_poses().shape == (T, 3)
    poses = scene.actor_poses(9)
    valid = scene.actor_valid(9)
    assert poses.shape == (T, 3) and valid.shape == (T,)
    assert not valid[:5].any() and not valid[9:11].any() and valid[5:9].all() and valid[11:17].all()
    assert np.isnan(poses[~valid]).all() and np.isfinite(poses[valid]).all()
    syn = scene.actor_synthetic(9)
    assert syn[14:17].all() and not syn[:14].any()
    all_poses, all_valid = scene.all_actor_poses()
    assert all_poses.shape == (2, T, 3) and all_valid.shape == (2, T)
    lanes = scene.lane_polylines()
    assert set(lanes) == {1, 2, 3} and lanes[1].shape == (4, 2)
    assert scene.actor_dimensions().shape == (2, 3)


def test_local_slope_is_exact_on_lines_and_damps_noise():
    t = np.arange(40) * 0.1
    line = 3.0 - 1.5 * t
    assert np.allclose(local_slope(line, 0.1, 1.0), -1.5, atol=1e-12)  # at the ends too (shifted windows)
    assert np.allclose(local_slope(line[:4], 0.1, 1.0), -1.5)          # shorter than the window
    assert np.array_equal(local_slope(line[:1], 0.1, 1.0), [0.0])
    noisy = 10.0 + 0.3 * np.random.default_rng(0).standard_normal(40)   # a steady speed, tracked
    assert np.abs(np.diff(noisy) / 0.1).max() > 4.0 and np.abs(local_slope(noisy, 0.1, 1.0)).max() < 1.0


def test_ego_accelerations_difference_exact_tracks_and_fit_measured_ones():
    """Generated (exact) tracks: the forward difference, bit for bit as the episode had it;
    measured (CommonRoad/NGSIM) ones: the 1 s local fit, because a one-frame difference of
    speeds differentiated from video tracks is mostly noise (docs/autonomy.md, real traffic)."""
    scene = make_scene()
    v = 20.0 + 0.5 * np.sin(np.arange(T))  # jittery speeds
    scene.ego.track.speed = v
    a = scene.ego_accelerations()
    assert a.shape == (T,) and np.array_equal(a[:-1], np.diff(v) / 0.1) and a[-1] == a[-2]
    measured = Scene(scene.id, Source("commonroad", {}, "BSD-3-Clause", None), scene.dt, scene.frames, scene.lanes,
                     scene.background, scene.ego, scene.actors)
    assert np.array_equal(measured.ego_accelerations(), local_slope(v, 0.1, 1.0))
    assert np.abs(measured.ego_accelerations()).max() < 0.5 * np.abs(a).max()


def test_gzip_file_is_deterministic(tmp_path):
    save_scene(make_scene(), tmp_path / "a.json.gz")
    save_scene(make_scene(), tmp_path / "b.json.gz")
    assert (tmp_path / "a.json.gz").read_bytes() == (tmp_path / "b.json.gz").read_bytes()
    json.loads(gzip.decompress((tmp_path / "a.json.gz").read_bytes()))


def _set(path_keys, value):
    def mutate(doc):
        obj = doc
        for key in path_keys[:-1]:
            obj = obj[key]
        obj[path_keys[-1]] = value
    return mutate


def _delete(path_keys):
    def mutate(doc):
        obj = doc
        for key in path_keys[:-1]:
            obj = obj[key]
        del obj[path_keys[-1]]
    return mutate


NAN = float("nan")
MALFORMED = [
    # (mutation, JSON path the error must name)
    (_set(["format"], "other"), "$.format"),
    (_set(["version"], 99), "$.version"),
    (_delete(["id"]), "$.id"),
    (_set(["id"], 5), "$.id"),
    (_set(["source", "kind"], "video"), "$.source.kind"),
    (_set(["source", "details"], []), "$.source.details"),
    (_delete(["dt"]), "$.dt"),
    (_set(["dt"], 0), "$.dt"),
    (_set(["dt"], "0.1"), "$.dt"),
    (_set(["frames"], 2.5), "$.frames"),
    (_set(["frames"], 0), "$.frames"),
    (_delete(["map"]), "$.map"),
    (_set(["map", "lanes"], []), "$.map.lanes"),
    (_set(["map", "lanes", 0, "id"], "one"), "$.map.lanes[0].id"),
    (_set(["map", "lanes", 1, "id"], 1), "$.map.lanes[1].id"),
    (_set(["map", "lanes", 0, "centerline"], [[0, 0]]), "$.map.lanes[0].centerline"),
    (_set(["map", "lanes", 0, "centerline", 1], [1, 2, 3]), "$.map.lanes[0].centerline[1]"),
    (_set(["map", "lanes", 0, "centerline", 1, 0], NAN), "$.map.lanes[0].centerline[1][0]"),
    (_set(["map", "lanes", 0, "width"], -1), "$.map.lanes[0].width"),
    (_set(["map", "lanes", 1, "width"], [3.5]), "$.map.lanes[1].width"),
    (_set(["map", "lanes", 0, "left"], 42), "$.map.lanes[0].left"),
    (_set(["map", "lanes", 1, "right"], 2), "$.map.lanes[1].right"),
    (_set(["map", "lanes", 0, "successors"], [3, 77]), "$.map.lanes[0].successors[1]"),
    (_set(["map", "lanes", 0, "successors"], 3), "$.map.lanes[0].successors"),
    (_set(["map", "lanes", 0, "speed_limit"], -3), "$.map.lanes[0].speed_limit"),
    (_delete(["background", "shoulder_left"]), "$.background.shoulder_left"),
    (_set(["background", "shoulder_right"], -1), "$.background.shoulder_right"),
    (_set(["background", "lane_markings"], "yes"), "$.background.lane_markings"),
    (_set(["background", "barriers", 0, "kind"], "hedge"), "$.background.barriers[0].kind"),
    (_set(["background", "barriers", 0, "polyline"], [[1, 1]]), "$.background.barriers[0].polyline"),
    (_set(["background", "meshes", 0, "pose"], [1, 2]), "$.background.meshes[0].pose"),
    (_set(["background", "barriers"], "guardrail"), "$.background.barriers"),
    (_set(["background", "meshes"], {"file": "a.glb"}), "$.background.meshes"),
    (_set(["ego", "sensors"], {"name": "top"}), "$.ego.sensors"),
    (_set(["ego", "sensors", 0], "top"), "$.ego.sensors[0]"),
    (_set(["background", "meshes", 0, "surface"], "glass"), "$.background.meshes[0].surface"),
    (_set(["ego", "dimensions"], [4.8, 1.9]), "$.ego.dimensions"),
    (_set(["ego", "dimensions", 1], 0), "$.ego.dimensions[1]"),
    (_set(["ego", "wheelbase"], None), "$.ego.wheelbase"),
    (_set(["ego", "sensors", 0, "mount"], [0, 0, 1.7]), "$.ego.sensors[0].mount"),
    (_delete(["ego", "sensors", 0, "model"]), "$.ego.sensors[0].model"),
    (_set(["ego", "track", "start"], 1), "$.ego.track.x"),
    (_delete(["ego", "track", "speed"]), "$.ego.track.speed"),
    (_set(["ego", "track", "valid"], [1] * (T - 1) + [0]), "$.ego.track.valid"),
    (_set(["actors"], {}), "$.actors"),
    (_set(["actors", 1, "id"], 7), "$.actors[1].id"),
    (_set(["actors", 1, "id"], -2), "$.actors[1].id"),
    (_set(["actors", 0, "class"], "Sedan!"), "$.actors[0].class"),
    (_set(["actors", 0, "asset"], 3), "$.actors[0].asset"),
    (_set(["actors", 0, "dimensions", 2], NAN), "$.actors[0].dimensions[2]"),
    (_delete(["actors", 0, "track"]), "$.actors[0].track"),
    (_set(["actors", 0, "track", "start"], -1), "$.actors[0].track.start"),
    (_set(["actors", 0, "track", "start"], 5), "$.actors[0].track.x"),
    (_set(["actors", 0, "track", "x"], "fast"), "$.actors[0].track.x"),
    (_set(["actors", 0, "track", "x", 3], NAN), "$.actors[0].track.x[3]"),
    (_set(["actors", 0, "track", "x", 3], True), "$.actors[0].track.x[3]"),
    (_set(["actors", 0, "track", "y"], [0.0] * 3), "$.actors[0].track.y"),
    (_set(["actors", 0, "track", "yaw", 2], 9.0), "$.actors[0].track.yaw[2]"),
    (_set(["actors", 0, "track", "speed", 1], -1.0), "$.actors[0].track.speed[1]"),
    (_set(["actors", 1, "track", "valid"], [1, 0]), "$.actors[1].track.valid"),
    (_set(["actors", 1, "track", "valid", 0], 2), "$.actors[1].track.valid[0]"),
    (_set(["actors", 1, "track", "synthetic"], [0] * 11), "$.actors[1].track.synthetic"),
    (_set(["actors", 1, "track", "mystery"], 1), "$.actors[1].track.mystery"),
]


@pytest.mark.parametrize("mutate,field", MALFORMED, ids=[f for _, f in MALFORMED])
def test_malformed_field_names_file_and_path(tmp_path, mutate, field):
    doc = copy.deepcopy(make_scene().to_dict())
    mutate(doc)
    path = tmp_path / "bad_scene.json"
    path.write_text(json.dumps(doc, allow_nan=True))
    with pytest.raises(FileFormatError) as exc:
        load_scene(path)
    assert exc.value.field == field
    assert "bad_scene.json" in str(exc.value) and field in str(exc.value)


def test_unmodified_document_is_valid(tmp_path):
    """The malformed cases above start from a valid document (so each failure is the edit's)."""
    load_scene(write_doc(tmp_path, make_scene().to_dict()))


def test_not_json_and_missing_file(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text("{")
    with pytest.raises(FileFormatError, match="x.json"):
        load_scene(bad)
    with pytest.raises(FileFormatError, match="missing.json"):
        load_scene(tmp_path / "missing.json")


def test_failed_save_keeps_existing_file(tmp_path):
    path = tmp_path / "keep.json"
    save_scene(make_scene(), path)
    before = path.read_bytes()
    broken = make_scene()
    broken.frames = 5  # tracks longer than the scene: invalid
    with pytest.raises(FileFormatError):
        save_scene(broken, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.json"]


def test_docs_example_is_a_valid_scene(repo_root):
    import re
    text = (repo_root / "docs" / "formats.md").read_text()
    section = text[text.index("## Scene"):]
    doc = json.loads(re.search(r"```json\n(.*?)```", section, re.S).group(1))
    scene = Scene.from_dict(doc, "docs/formats.md")
    assert scene.frames == 3 and scene.actor_valid(1).tolist() == [False, True, True]


def test_actor_speeds_recorded_or_from_positions():
    scene = make_scene()
    np.testing.assert_allclose(scene.actor_speeds(7), 18.0)
    speeds = scene.actor_speeds(9)  # no recorded speed: from positions (20 m over 11 frames)
    valid = scene.actor_valid(9)
    assert np.isnan(speeds[~valid]).all()
    np.testing.assert_allclose(speeds[valid], 20.0 / 11 / 0.1, rtol=1e-2)
