"""LiDAR pipeline: analytic scenes, exact culling, rigs, effects, ego masking, determinism."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from adv3d_runner.sensors.beams import generic_model, get_model
from adv3d_runner.sensors.lidar import BACKGROUND, LidarFrame, LidarRig, MountedLidar, simulate_frame
from adv3d_runner.sensors.world import LidarWorld

RTOL = 16 * np.finfo(np.float32).eps
FIELDS = ("points", "ring", "label", "sensor", "distance")
# Far from the map origin on purpose: the world must centre before its float32 cast.
EGO = np.array([5123.4, -2871.9, 0.7])


def plane(size=1000.0, z=0.0, centre=(0.0, 0.0)):
    cx, cy = centre
    v = np.array([[cx - size, cy - size, z], [cx + size, cy - size, z], [cx + size, cy + size, z],
                  [cx - size, cy + size, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def ground_world(refl=0.2):
    return LidarWorld(*plane(centre=EGO[:2]), reflectivity=refl)


def box_mesh(length=4.5, width=1.9, height=1.5):
    box = trimesh.creation.box((length, width, height))
    box.apply_translation((0, 0, height / 2))
    return box.vertices, box.faces


def small_sensor(**kw):
    kw.setdefault("range_noise", 0.0)
    kw.setdefault("ray_drop", 0.0)
    return generic_model(16, 5.0, -25.0, 360, 80.0, **kw)


def to_world(ego, rel):
    """Map-frame pose of an actor at ego-frame (x, y, yaw) ``rel``."""
    c, s = np.cos(ego[2]), np.sin(ego[2])
    return np.array([ego[0] + c * rel[0] - s * rel[1], ego[1] + s * rel[0] + c * rel[1], ego[2] + rel[2]])


def assert_frames_equal(a: LidarFrame, b: LidarFrame):
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# -- analytic scenes ----------------------------------------------------------------------------
def test_plane_at_known_height():
    h = 1.73
    rig = LidarRig.single(small_sensor(), mount=(0.3, -0.2, h, 0, 0, 0))
    frame = simulate_frame(ground_world(), rig, EGO, None, None)
    model = rig.sensors[0].model
    below = np.array(model.elevations) < -np.deg2rad(1.2)  # those reach the plane within 80 m
    assert len(frame) == below.sum() * model.columns
    el = np.sort(model.elevations)[frame.ring]
    expected = h / np.sin(-el)
    np.testing.assert_allclose(frame.distance, expected, rtol=RTOL)
    # Points in the ego frame lie on the ground plane z = 0 (up to float32 of the range).
    assert np.all(np.abs(frame.xyz[:, 2]) <= 4 * RTOL * expected)
    assert (frame.label == BACKGROUND).all() and (frame.sensor == 0).all()


def test_box_actor_at_known_range():
    world = ground_world()
    world.add_actor(7, *box_mesh(2.0, 2.0, 2.0))
    rig = LidarRig.single(generic_model(32, 2.0, -10.0, 3600, 80.0, range_noise=0, ray_drop=0),
                          mount=(0, 0, 1.0, 0, 0, 0))
    poses = to_world(EGO, (15.0, 0.0, 0.0))[None]
    frame = simulate_frame(world, rig, EGO, poses, None)
    on = frame.label == 0
    assert on.sum() > 100
    x, y = frame.xyz[on, 0], frame.xyz[on, 1]
    front = (np.abs(y) < 0.99) & (x < 14.5)
    assert front.sum() > 100
    # Front face at ego x = 14: range = 14 / (cos(el) cos(az)) exactly, in float32.
    d = frame.xyz[on][front] - [0, 0, 1.0]
    direction = d / np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(frame.distance[on][front], 14.0 / direction[:, 0], rtol=4 * RTOL)
    np.testing.assert_allclose(x[front], 14.0, atol=14 * 4 * RTOL)
    assert frame.actor_ids == (7,) and set(frame.label_names()[on]) == {"7"}


def test_sphere_actor_at_known_range():
    radius, dist, h = 1.0, 12.0, 1.5
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    # Turn a vertex (exactly on the analytic sphere) towards the sensor.
    yaw = 0.3  # actor yaw relative to the ego: the sensor lies at local azimuth pi - yaw
    sphere.apply_transform(trimesh.geometry.align_vectors(sphere.vertices[0], [-np.cos(yaw), np.sin(yaw), 0.0]))
    world = LidarWorld(np.zeros((0, 3)), np.zeros((0, 3), int))  # no background
    world.add_actor("ball", sphere.vertices + [0, 0, h], sphere.faces)
    rig = LidarRig.single(generic_model(9, 4.0, -4.0, 7200, 50.0, range_noise=0, ray_drop=0),
                          mount=(0, 0, h, 0, 0, 0))
    frame = simulate_frame(world, rig, EGO, to_world(EGO, (dist, 0, yaw))[None], None)
    assert len(frame) > 20 and (frame.label == 0).all()
    # Analytic sphere: every return within the faceting error (sagitta) of the true surface.
    r = np.linalg.norm(frame.xyz - [dist, 0, h], axis=1)
    assert np.all(r <= radius + 1e-4) and np.all(r >= radius * np.cos(np.deg2rad(4)) - 1e-4)
    # The ray through the centre (elevation 0, azimuth 0) hits that vertex: range dist - radius.
    centre_ray = (np.abs(frame.xyz[:, 1]) < 1e-6) & (np.abs(frame.xyz[:, 2] - h) < 1e-6)
    assert centre_ray.sum() == 1
    np.testing.assert_allclose(frame.distance[centre_ray], dist - radius, rtol=RTOL)


def test_no_hits_gives_empty_frame():
    empty = LidarWorld(np.zeros((0, 3)), np.zeros((0, 3), int))
    frame = simulate_frame(empty, LidarRig.single(small_sensor()), EGO, None, np.random.default_rng(0))
    assert len(frame) == 0 and frame.points.shape == (0, 4) and frame.label.dtype == np.int32
    # Upward-looking sensor over a ground plane: nothing either.
    up = generic_model(4, 60.0, 10.0, 90, 50.0)
    frame = simulate_frame(ground_world(), LidarRig.single(up), EGO, None, np.random.default_rng(0))
    assert len(frame) == 0


# -- culling ------------------------------------------------------------------------------------
def crowded_world_and_poses(ego):
    world = ground_world()
    rels = [
        (-12.0, 0.0, 0.2),    # straight behind: straddles the +-pi azimuth seam
        (-6.0, 3.5, 1.5),     # close behind-left, rotated
        (0.8, 0.4, 0.1),      # the sensor is inside its bounding circle (overlaps the ego)
        (3.5, 2.5, -0.4),     # very close, wide window
        (25.0, 3.5, 0.0), (40.0, -3.5, 0.05), (60.0, 0.0, 0.0),
        (70.0, 7.0, 0.0),     # beyond max range for part of its body
        (250.0, 0.0, 0.0),    # out of range entirely
        (-30.0, -3.5, np.pi), (10.0, -7.0, 3.0),
    ]
    for i, _ in enumerate(rels):
        v, f = box_mesh(4.0 + 0.3 * (i % 3), 1.8, 1.4 + 0.5 * (i % 2))
        world.add_actor(i, v, f)
    world.add_actor("absent", *box_mesh())
    poses = np.array([to_world(ego, r) for r in rels] + [[np.nan] * 3])
    return world, poses


@pytest.mark.parametrize("ego_yaw", [0.0, np.pi - 1e-3, -2.2])
def test_culling_is_exact(ego_yaw):
    ego = np.array([EGO[0], EGO[1], ego_yaw])
    world, poses = crowded_world_and_poses(ego)
    rig = LidarRig([
        MountedLidar(get_model("vlp32c", columns=600), (0.5, 0.0, 1.9, 0.0, 0.0, 0.0)),
        MountedLidar(small_sensor(range_noise=0.02, ray_drop=0.1), (1.5, 0.6, 1.2, 0.05, -0.1, 0.7)),
        MountedLidar(get_model("hdl64", columns=500), (0.0, 0.0, 1.73, 0.0, 0.0, 0.0)),
    ], ego_dimensions=(4.6, 1.9, 1.5))
    # Both window searches are exercised: per-row (azimuth offsets, tilt) and shared columns.
    assert rig.sensors[0]._common_azimuth is None and rig.sensors[1]._common_azimuth is None
    assert rig.sensors[2]._common_azimuth is not None
    stats_cull, stats_all = {}, {}
    a = simulate_frame(world, rig, ego, poses, np.random.default_rng(5), cull=True, stats=stats_cull)
    b = simulate_frame(world, rig, ego, poses, np.random.default_rng(5), cull=False, stats=stats_all)
    assert_frames_equal(a, b)
    assert stats_cull["actor_rays"] < stats_all["actor_rays"] / 3  # culling did cull
    seen = set(np.unique(a.label))
    assert {0, 1, 3, 4}.issubset(seen)  # the seam-straddling and close actors are seen
    assert 8 not in seen and 11 not in seen  # out of range / absent


def test_culling_exact_for_sensor_inside_actor_circle():
    world = ground_world()
    world.add_actor("bus", *box_mesh(12.0, 2.5, 3.2))
    rig = LidarRig.single(small_sensor(), mount=(0, 0, 3.6, 0, 0, 0))
    poses = to_world(EGO, (1.0, 0.0, 0.3))[None]  # sensor above the bus roof
    a = simulate_frame(world, rig, EGO, poses, None, cull=True)
    b = simulate_frame(world, rig, EGO, poses, None, cull=False)
    assert_frames_equal(a, b)
    assert (a.label == 0).sum() > 100


def test_background_rays_that_stay_above_it_are_skipped_exactly():
    """Rays that stay above the whole background up to max range are not cast against it; the
    hits equal those of casting every ray, and a background reaching above the sensor (a
    gantry) turns the skip off."""
    from adv3d_runner.sensors.lidar import cast_rays

    world, poses = crowded_world_and_poses(EGO)
    sensor = MountedLidar(get_model("hdl64", columns=500), (0.0, 0.0, 1.73, 0.0, 0.0, 0.0))
    present = np.flatnonzero(np.isfinite(poses).all(axis=1))
    skipped, every = {}, {}
    a = cast_rays(world, sensor, EGO, poses, present, stats=skipped)
    sensor._dz_suffix_min = np.full(sensor.n_rays, -np.inf)  # no ray qualifies: all are cast
    b = cast_rays(world, sensor, EGO, poses, present, stats=every)
    for name in ("t", "label", "prim_bg", "cos_actor"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert skipped["rays_cast"] < every["rays_cast"] - 8 * 500  # the upper rows were skipped
    # A canopy 2.5 m up over the road: the upward rays that reach it within range hit it.
    gv, gf = plane(size=200.0, z=2.5, centre=EGO[:2])
    ground_v, ground_f = plane(centre=EGO[:2])
    gantry = LidarWorld(np.concatenate([ground_v, gv]), np.concatenate([ground_f, gf + 4]), 0.2)
    sensor = MountedLidar(get_model("hdl64", columns=500), (0.0, 0.0, 1.73, 0.0, 0.0, 0.0))
    hits = cast_rays(gantry, sensor, EGO, np.zeros((0, 3)), np.zeros(0, np.intp))
    up = (sensor.dz > 0) & ((2.5 - 1.73) / np.maximum(sensor.dz, 1e-9) < 110.0)
    assert up.sum() >= 3 * 500
    assert (hits.prim_bg[up] >= 2).all() and np.allclose(hits.t[up] * sensor.dz[up], 2.5 - 1.73, atol=1e-3)


# -- rigs and effects ---------------------------------------------------------------------------
def test_multi_lidar_merge():
    world, poses = crowded_world_and_poses(EGO)
    s1 = MountedLidar(small_sensor(), (1.0, 0.0, 1.8, 0, 0, 0))
    s2 = MountedLidar(get_model("vlp32c", columns=300, range_noise=0, ray_drop=0), (-1.0, 0.5, 1.6, 0, 0.1, np.pi))
    both = simulate_frame(world, LidarRig([s1, s2]), EGO, poses, None)
    one = simulate_frame(world, LidarRig([s1]), EGO, poses, None)
    two = simulate_frame(world, LidarRig([s2]), EGO, poses, None)
    assert len(both) == len(one) + len(two) > 0
    assert_frames_equal(both.select(both.sensor == 0), one)
    sel = both.select(both.sensor == 1)
    for name in ("points", "ring", "label", "distance"):
        np.testing.assert_array_equal(getattr(sel, name), getattr(two, name))
    # Both sensors see the same ground: points from each lie on z = 0 in the ego frame.
    bg = both.label == BACKGROUND
    assert np.abs(both.xyz[bg, 2]).max() < 1e-3


def test_ego_masking_box_and_mesh():
    world = ground_world()
    ego_dims = (4.6, 1.9, 1.5)
    sensor = generic_model(16, 0.0, -70.0, 360, 80.0, min_range=0.0, range_noise=0, ray_drop=0)
    mount = (1.2, 0.0, 1.9, 0, 0, 0)  # on the roof, forward of the centre
    raw = simulate_frame(world, LidarRig.single(sensor, mount=mount), EGO, None, None)
    L, W, H = ego_dims

    def inside(frame, margin):
        p = frame.xyz
        return ((np.abs(p[:, 0]) <= L / 2 + margin) & (np.abs(p[:, 1]) <= W / 2 + margin)
                & (p[:, 2] <= H + margin) & (p[:, 2] >= -margin))

    assert inside(raw, 0.0).sum() > 10  # ground under the car is seen without masking
    masked = simulate_frame(world, LidarRig.single(sensor, mount=mount, ego_dimensions=ego_dims, ego_margin=0.1),
                            EGO, None, None)
    assert inside(masked, 0.1).sum() == 0
    assert len(masked) == len(raw) - inside(raw, 0.1).sum()
    # A mesh for the ego's body blocks the rays that hit it: they return nothing.
    world.set_ego_mesh(*box_mesh(L, W, H))
    blocked = simulate_frame(world, LidarRig.single(sensor, mount=mount), EGO, None, None)
    assert inside(blocked, 0.05).sum() == 0 and len(blocked) < len(masked)


def test_deterministic_for_a_seed_and_seeds_differ():
    world, poses = crowded_world_and_poses(EGO)
    rig = LidarRig.single(small_sensor(range_noise=0.03, ray_drop=0.1))
    a = simulate_frame(world, rig, EGO, poses, np.random.default_rng(11))
    b = simulate_frame(world, rig, EGO, poses, np.random.default_rng(11))
    c = simulate_frame(world, rig, EGO, poses, np.random.default_rng(12))
    assert_frames_equal(a, b)
    assert len(a) != len(c) or not np.array_equal(a.points, c.points)


def test_range_noise_and_ray_drop_statistics():
    h, p, sigma = 1.8, 0.25, 0.05
    model = generic_model(16, -5.0, -40.0, 720, 80.0, range_noise=sigma, ray_drop=p)
    rig = LidarRig.single(model, mount=(0, 0, h, 0, 0, 0))
    ideal = simulate_frame(ground_world(), rig, EGO, None, None)
    noisy = simulate_frame(ground_world(), rig, EGO, None, np.random.default_rng(3))
    n = len(ideal)
    kept = len(noisy) / n
    assert abs(kept - (1 - p)) < 4 * np.sqrt(p * (1 - p) / n)
    el = np.sort(model.elevations)[noisy.ring]
    residual = noisy.distance - h / np.sin(-el)
    assert abs(residual.std() - sigma) < 0.05 * sigma and abs(residual.mean()) < 4 * sigma / np.sqrt(len(noisy))
    # Switches: noise / drop off even with an rng.
    plain = simulate_frame(ground_world(), rig, EGO, None, np.random.default_rng(3), noise=False, drop=False)
    assert_frames_equal(plain, ideal)


def test_intensity_falls_with_incidence_angle():
    refl = 0.4
    model = generic_model(24, -3.0, -70.0, 90, 200.0, range_noise=0, ray_drop=0)
    rig = LidarRig.single(model, mount=(0, 0, 2.0, 0, 0, 0), attenuation=0.0)
    frame = simulate_frame(ground_world(refl), rig, EGO, None, None)
    el = np.sort(model.elevations)[frame.ring]
    cos_incidence = np.sin(-el)  # ground normal is +z
    np.testing.assert_allclose(frame.intensity, refl * cos_incidence, rtol=1e-5)
    order = np.argsort(-el)  # grazing first
    assert np.all(np.diff(frame.intensity[order]) >= -1e-7)
    # Attenuation: the same geometry with attenuation gives lower intensity, more so far away.
    att = simulate_frame(ground_world(refl), LidarRig.single(model, mount=(0, 0, 2.0, 0, 0, 0), attenuation=0.01),
                         EGO, None, None)
    ratio = att.intensity / frame.intensity
    np.testing.assert_allclose(ratio, np.exp(-0.01 * frame.distance), rtol=1e-5)


def test_replacing_an_actor_mesh_changes_only_its_points():
    world = ground_world()
    world.add_actor("a", *box_mesh())
    world.add_actor("b", *box_mesh())
    poses = np.array([to_world(EGO, (15, 6, 0)), to_world(EGO, (15, -6, 0))])
    rig = LidarRig.single(small_sensor())
    before = simulate_frame(world, rig, EGO, poses, None)
    bvh_b = world.actor_bvh(1)
    world.set_actor_mesh("a", *box_mesh(3.0, 1.6, 2.4))
    after = simulate_frame(world, rig, EGO, poses, None)
    assert world.actor_bvh(1) is bvh_b  # nothing rebuilt for b
    for frame in (before, after):
        assert (frame.label == 0).sum() > 0 and (frame.label == 1).sum() > 0
    b0, b1 = before.select(before.label == 1), after.select(after.label == 1)
    assert_frames_equal(b0, b1)
    a0, a1 = before.select(before.label == 0), after.select(after.label == 0)
    assert len(a0) != len(a1) or not np.array_equal(a0.points, a1.points)
    # Background returns away from actor a (left side, y > 2) are unchanged.
    far0 = before.select((before.label == BACKGROUND) & (before.xyz[:, 1] < 2))
    far1 = after.select((after.label == BACKGROUND) & (after.xyz[:, 1] < 2))
    assert_frames_equal(far0, far1)
    # Identical meshes share one BVH; replaced ones are released, the original kept.
    world.set_actor_mesh("b", *box_mesh(3.0, 1.6, 2.4))
    assert world.actor_bvh(0) is world.actor_bvh(1)
    world.set_actor_mesh("b", *box_mesh(3.1, 1.6, 2.4))
    assert world.n_cached_meshes == 3  # original + a's + b's current
    # Resetting restores the benign frame without building anything.
    world.reset_actor_mesh()
    assert world.actor_bvh(1) is bvh_b and world.n_cached_meshes == 1
    assert_frames_equal(simulate_frame(world, rig, EGO, poses, None), before)


def test_actor_poses_shape_checked():
    world, poses = crowded_world_and_poses(EGO)
    with pytest.raises(ValueError):
        simulate_frame(world, LidarRig.single(small_sensor()), EGO, poses[:3], None)


# -- files and the command ----------------------------------------------------------------------
def test_ply_round_trip_and_validation(tmp_path):
    from adv3d_runner.errors import FileFormatError
    from adv3d_runner.sensors.pointio import read_points_ply, write_points_ply

    world, poses = crowded_world_and_poses(EGO)
    frame = simulate_frame(world, LidarRig.single(small_sensor()), EGO, poses, np.random.default_rng(1))
    path = tmp_path / "p.ply"
    write_points_ply(path, frame, meta={"scene": "s1", "frame": 3, "ego_pose": list(EGO)})
    rec, meta = read_points_ply(path)
    assert meta["scene"] == "s1" and meta["frame"] == "3" and meta["format"] == "adv3d-lidar-points"
    np.testing.assert_array_equal(np.stack([rec[k] for k in ("x", "y", "z", "intensity")], 1), frame.points)
    np.testing.assert_array_equal(rec["ring"], frame.ring)
    # One actor id ("absent") is not an integer, so labels are actor indices; -1 = background.
    np.testing.assert_array_equal(rec["label"], frame.label)
    # With integer actor ids (scene actors) the label is the id itself.
    int_ids = LidarFrame(frame.points, frame.ring, frame.label, frame.sensor, frame.distance,
                         tuple(100 + i for i in range(len(frame.actor_ids))))
    write_points_ply(path, int_ids)
    rec, _ = read_points_ply(path)
    np.testing.assert_array_equal(rec["label"], np.where(frame.label >= 0, frame.label + 100, -1))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(path.read_bytes().replace(b"comment version 1", b"comment version 9"))
    with pytest.raises(FileFormatError, match="version"):
        read_points_ply(bad)
    bad.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(FileFormatError, match="vertex"):
        read_points_ply(bad)


def test_lidar_render_command(tmp_path, repo_root):
    from adv3d_runner.cli import main
    from adv3d_runner.sensors.pointio import read_points_ply

    scenes = sorted((repo_root / "scenes" / "highway").glob("*.json*"))
    if not scenes:
        pytest.skip("no bundled highway scene")
    out, bev = tmp_path / "pts.ply", tmp_path / "bev.png"
    args = ["-q", "lidar", "render", str(scenes[0]), "--frame", "3", "-o", str(out), "--bev", str(bev),
            "--sensor", "vlp32c", "--library", "none", "--seed", "4"]
    assert main(args) == 0
    rec, meta = read_points_ply(out)
    assert len(rec) > 1000 and meta["frame"] == "3" and bev.stat().st_size > 10_000
    assert (rec["label"] >= 0).any()  # the benchmark scenes have vehicles near the ego
    # Same seed, same file.
    first = out.read_bytes()
    assert main(args) == 0 and out.read_bytes() == first
    assert main(["-q", "lidar", "render", str(scenes[0]), "--frame", "100000", "-o", str(out)]) == 2  # past the scene


def test_scene_with_unknown_lidar_model_names_the_field(repo_root):
    from adv3d_runner.errors import FileFormatError
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sensors.world import rig_from_scene

    scenes = sorted((repo_root / "scenes" / "highway").glob("*.json*"))
    if not scenes:
        pytest.skip("no bundled highway scene")
    scene = load_scene(scenes[0])
    rig = rig_from_scene(scene)
    assert rig.sensors and rig.ego_dimensions == tuple(scene.ego.dimensions)
    scene.ego.sensors[0].model = "hdl-65x"
    with pytest.raises(FileFormatError, match=r"\$\.ego\.sensors\[0\]\.model"):
        rig_from_scene(scene, path=scenes[0])
    assert rig_from_scene(scene, "vlp32c").sensors[0].model.name == "vlp32c"  # an override needs no lookup


def test_count_labels_is_bincount_of_the_actor_labels():
    """The episode's per-actor return count (one compiled pass) against ``np.bincount`` of
    the non-negative labels, and its "fall back" answer for a label past the rows."""
    from adv3d_runner.sensors.kernels import count_labels

    rng = np.random.default_rng(2)
    for n in (1, 5, 31):
        for m in (0, 1, 1000):
            label = np.where(rng.random(m) < 0.3, rng.integers(0, n, m), rng.choice([-1, -3], m)).astype(np.int32)
            got = count_labels(label, n)
            want = np.bincount(label[label >= 0], minlength=n)
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    assert count_labels(np.array([0, 7, -1], np.int32), 5).size == 0


def test_compiled_actor_windows_equal_the_python_windows():
    """kernels.actor_windows (all actors in one call) gives each actor the rays, the nearest
    distance and the out-of-range verdict of ``_Cast.segments`` (the per-actor Python windows),
    for random poses all around the sensor, across the azimuth seam, inside footprints and
    beyond range."""
    from adv3d_runner.sensors import kernels
    from adv3d_runner.sensors.lidar import _ANGLE_PAD, _RADIUS_PAD, _Cast, _segments_to_indices
    from adv3d_runner.sensors.raycast import MeshBVH

    rng = np.random.default_rng(3)
    sensor = MountedLidar(get_model("hdl64", columns=900), (0.4, 0.1, 1.73, 0.0, 0.0, 0.0))
    assert sensor._common_azimuth is not None and sensor._rows_sorted
    bvhs = [MeshBVH(*box_mesh(*size)) for size in ((4.5, 1.9, 1.5), (12.0, 2.5, 3.4), (0.6, 0.6, 0.4))]
    for trial in range(40):
        ego = np.array([EGO[0], EGO[1], rng.uniform(-np.pi, np.pi)])
        cast = _Cast(sensor, ego, None)
        K = 60
        dist = np.concatenate([rng.uniform(0.0, 3.0, 5), rng.uniform(3.0, 130.0, K - 5)])
        ang = rng.uniform(-np.pi, np.pi, K)
        poses = np.stack([cast.sx + dist * np.cos(ang), cast.sy + dist * np.sin(ang), rng.uniform(-4, 4, K)], 1)
        which = rng.integers(0, len(bvhs), K)
        keep, counts, cuts, rays = kernels.actor_windows(
            cast.sx, cast.sy, cast.ego_yaw, cast.reach, poses, np.stack([bvhs[w].window_shape for w in which]),
            sensor._z, sensor.row_elevation_min, sensor.row_elevation_max, sensor._common_azimuth, sensor.columns,
            sensor.n_rays, _RADIUS_PAD, _ANGLE_PAD)
        offsets = np.concatenate([[0], np.cumsum(counts)])
        for k in range(K):
            seg = cast.segments(bvhs[which[k]], poses[k])
            assert keep[k] == (seg is not False)
            if seg is False:
                continue
            expect = np.arange(sensor.n_rays) if seg is None else _segments_to_indices(seg[0], seg[1])
            np.testing.assert_array_equal(rays[offsets[k]:offsets[k + 1]], expect)
            assert cuts[k] == np.float32((0.0 if seg is None else seg[2]) * (1.0 - 1e-5))
