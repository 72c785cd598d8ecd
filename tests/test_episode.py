"""Episode loop: open vs closed loop, determinism, empty frames, reactive actors, shape
substitution, metrics of a short oracle episode."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.errors import ConfigError
from adv3d_runner.fileio import REPO_ROOT
from adv3d_runner.geometry.boxes import boxes_overlap
from adv3d_runner.geometry.frames import boxes_to_frame
from adv3d_runner.scene import load_scene
from adv3d_runner.sensors.world import LidarWorld, rig_from_scene, world_from_scene
from adv3d_runner.sim.episode import Episode, ShapeOverride, run_episode
from adv3d_runner.sim.evaluate import episode_metrics
from adv3d_runner.autonomy.baselines import LaneFollowingPredictor
from adv3d_runner.autonomy.modular import ModularStack
from adv3d_runner.autonomy.oracle import OracleDetector
from adv3d_runner.autonomy.stacks import make_stack
from adv3d_runner.sim.recorders import STAGES


@pytest.fixture(scope="module")
def free():
    """A free-flow 3-lane scene with box actors and a light rig (fast)."""
    scene = load_scene(REPO_ROOT / "scenes/highway/highway-benchmark-000000.json.gz")
    world = world_from_scene(scene, None)
    rig = rig_from_scene(scene, model="generic-32", columns=512, ray_drop=0.05)
    return scene, world, rig


@pytest.fixture(scope="module")
def dense():
    scene = load_scene(REPO_ROOT / "scenes/highway/highway-benchmark-000015.json.gz")
    return scene, world_from_scene(scene, None), rig_from_scene(scene, model="generic-16", columns=256)


def _box_mesh(L, W, H):
    from adv3d_runner.sensors.world import _box_mesh

    m = _box_mesh((L, W, H))
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def test_open_loop_ego_replays_log_and_closed_loop_follows_plans(free):
    scene, world, rig = free
    op = run_episode(scene, make_stack("oracle"), seconds=1.0, closed_loop=False, world=world, rig=rig)
    cl = run_episode(scene, make_stack("oracle"), seconds=1.0, closed_loop=True, world=world, rig=rig)
    log = scene.ego_poses()[:10]
    np.testing.assert_array_equal(op.ego_poses, log)
    np.testing.assert_array_equal(op.ego_speeds, scene.ego_speeds()[:10])
    # same start; afterwards the closed-loop ego is exactly where its previous plan put it
    np.testing.assert_array_equal(cl.ego_poses[0], log[0])
    for k in range(cl.frames - 1):
        np.testing.assert_allclose(cl.ego_poses[k + 1], cl.outputs[k].plan.trajectory[1], atol=1e-12)
        assert cl.ego_speeds[k + 1] == pytest.approx(cl.outputs[k].plan.speed[1])
    assert not np.allclose(cl.ego_poses, log)  # the planner does not reproduce the log to the mm
    # the replayed actors do not depend on the ego
    np.testing.assert_array_equal(op.actor_poses, cl.actor_poses)
    assert op.frames == cl.frames == 10 and len(cl.outputs) == 10


def test_deterministic_for_a_seed(free):
    scene, world, rig = free
    a = run_episode(scene, make_stack("oracle"), seconds=0.5, world=world, rig=rig, seed=3, record_points=True)
    b = run_episode(scene, make_stack("oracle"), seconds=0.5, world=world, rig=rig, seed=3, record_points=True)
    c = run_episode(scene, make_stack("oracle"), seconds=0.5, world=world, rig=rig, seed=4, record_points=True)
    for pa, pb in zip(a.points, b.points):
        np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(a.ego_poses, b.ego_poses)
    for oa, ob in zip(a.outputs, b.outputs):
        np.testing.assert_array_equal(oa.plan.trajectory, ob.plan.trajectory)
        np.testing.assert_array_equal(oa.detections.boxes, ob.detections.boxes)
    assert any(len(pa) != len(pc) or not np.array_equal(pa, pc) for pa, pc in zip(a.points, c.points))


def test_frames_without_points(free):
    scene, _, rig = free
    empty = LidarWorld(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    r = run_episode(scene, make_stack("oracle"), seconds=0.5, world=empty, rig=rig)
    assert (r.n_points == 0).all() and (r.actor_points == 0).all()
    assert all(len(o.detections) == 0 and len(o.tracks) == 0 for o in r.outputs)
    assert np.isfinite(r.ego_poses).all() and r.ego_speeds[-1] > 0  # still drives on its lane
    m = episode_metrics(r, scene.lanes)
    assert m["detection"]["n_det"] == 0


def test_reactive_actors_start_from_the_log_and_never_on_the_ego(dense):
    scene, world, rig = dense
    r = run_episode(scene, make_stack("oracle"), seconds=2.0, reactive=True, world=world, rig=rig)
    log, valid = scene.all_actor_poses()
    v0 = valid[:, 0]
    np.testing.assert_allclose(r.actor_poses[0, v0], log[v0, 0], atol=1e-6)
    L, W = scene.ego.dimensions[:2]
    ego = np.array([*r.ego_poses[0, :2], L, W, r.ego_poses[0, 2]])
    boxes = r.gt_boxes(0)
    ok = np.isfinite(boxes).all(axis=1)
    assert ok.sum() >= 5
    assert not boxes_overlap(ego[None], boxes[ok]).any()
    # nobody drives into the ego over the episode (IDM keeps its gap behind the ego)
    m = episode_metrics(r, scene.lanes)
    assert not m["collision"]["collided"]
    # the traffic model moved the actors (they do not simply replay the log)
    later = valid[:, 15] & np.isfinite(r.actor_poses[15]).all(axis=1)
    assert np.abs(r.actor_poses[15, later, :2] - log[later, 15, :2]).max() > 0.05
    assert np.isfinite(r.actor_poses[r.frames:]).any()  # traffic continued for prediction ground truth


def test_substituted_mesh_changes_points_and_ground_truth_box(free):
    scene, world, rig = free
    base = run_episode(scene, make_stack("oracle"), seconds=0.3, world=world, rig=rig, lidar_noise=False)
    # the actor with the most returns
    i = int(np.argmax(base.actor_points.sum(axis=0)))
    aid = int(base.actor_ids[i])
    dims = np.array([9.0, 2.6, 3.2])
    v, f = _box_mesh(*dims)
    adv = run_episode(scene, make_stack("oracle"), seconds=0.3, world=world, rig=rig, lidar_noise=False,
                      actor_overrides={aid: ShapeOverride(v, f, dims)})
    assert adv.adversarial[i] and adv.adversarial.sum() == 1
    np.testing.assert_array_equal(adv.actor_dimensions[i], dims)
    assert adv.gt_boxes(0)[i, 2] == 9.0 and adv.gt_boxes(0)[i, 3] == 2.6
    assert adv.actor_points[:, i].sum() > base.actor_points[:, i].sum()  # a bigger body reflects more rays
    # the oracle sees the new box
    det = adv.outputs[0].detections.boxes
    j = np.argmin(np.hypot(*(det[:, :2] - adv.gt_boxes(0)[i, :2]).T))
    assert det[j, 2] == pytest.approx(9.0)
    # the world got its benign mesh back
    again = run_episode(scene, make_stack("oracle"), seconds=0.3, world=world, rig=rig, lidar_noise=False)
    np.testing.assert_array_equal(again.actor_points, base.actor_points)


def test_bad_overrides_and_missing_models(free):
    scene, world, rig = free
    tri = (np.zeros((3, 3)), np.array([[0, 1, 2]]), np.ones(3))
    with pytest.raises(ConfigError):
        run_episode(scene, make_stack("oracle"), seconds=0.1, world=world, rig=rig,
                    actor_overrides={99999: ShapeOverride(*tri)})
    aid = scene.actors[0].id
    with pytest.raises(ConfigError, match="ShapeOverride"):  # the positional tuple is gone
        run_episode(scene, make_stack("oracle"), seconds=0.1, world=world, rig=rig, actor_overrides={aid: tri})
    with pytest.raises(ConfigError):
        make_stack("no-such-stack")  # an unknown stack
    with pytest.raises(ConfigError):
        run_episode(scene, make_stack("oracle"), seconds=30.0, closed_loop=False, world=world, rig=rig)


@pytest.mark.parametrize("bad", [
    dict(faces=np.array([[0, 1, 5]])),                       # face index past the vertices
    dict(faces=np.array([[0, -1, 2]])),                      # negative face index
    dict(dimensions=np.array([4.0, 0.0, 1.5])),              # a zero extent
    dict(dimensions=np.array([4.0, 2.0])),                   # not (3,)
    dict(vertices=np.array([[0.0, 0, 0], [1, 0, 0], [0, np.nan, 0]])),
    dict(vertices=np.zeros((3, 2))),                         # not (V, 3)
])
def test_shape_override_is_checked_once_in_its_constructor(bad):
    good = dict(vertices=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), faces=np.array([[0, 1, 2]]),
                dimensions=np.array([4.0, 2.0, 1.5]))
    ov = ShapeOverride(**good)
    assert ov.vertices.dtype == np.float64 and ov.faces.dtype == np.int64 and ov.dimensions.shape == (3,)
    assert not ov.vertices.flags.writeable  # frozen all the way down: a copy the caller cannot change
    good["vertices"][0, 0] = 7.0
    assert ov.vertices[0, 0] == 0.0
    with pytest.raises(ConfigError):
        ShapeOverride(**{**good, **bad})


class _Counting:
    """A recorder that keeps what the episode hands it."""

    def __init__(self):
        self.frames, self.results = [], []

    def on_frame(self, episode, frame):
        self.frames.append((frame.index, frame.ego.pose.copy(), frame.actor_points.copy(), frame.outputs))

    def on_finish(self, episode, result):
        self.results.append(result)


def test_episode_steps_equal_run_episode_and_recorders_see_every_frame(free):
    scene, world, rig = free
    aid = scene.actors[0].id
    v, f = _box_mesh(6.0, 2.4, 2.0)
    shape = {aid: ShapeOverride(v, f, np.array([6.0, 2.4, 2.0]))}
    plain = run_episode(scene, make_stack("oracle"), seconds=0.4, world=world, rig=rig, seed=5)
    ref = run_episode(scene, make_stack("oracle"), seconds=0.4, world=world, rig=rig, seed=5,
                      actor_overrides=shape, record_points=True)
    rec = _Counting()
    ep = Episode(scene, make_stack("oracle"), seconds=0.4, world=world, rig=rig, seed=5, actor_overrides=shape,
                 recorders=[rec])
    assert ep.frames == 4 and not ep.done
    with pytest.raises(RuntimeError):
        ep.finish()  # not before the last frame
    frames = [ep.step() for _ in range(ep.frames)]
    assert ep.done
    with pytest.raises(RuntimeError):
        ep.step()
    result = ep.finish()
    assert [k for k, *_ in rec.frames] == [0, 1, 2, 3] and rec.results == [result]
    assert [fr.index for fr in frames] == [0, 1, 2, 3]
    np.testing.assert_array_equal(result.ego_poses, ref.ego_poses)
    np.testing.assert_array_equal(result.actor_poses, ref.actor_poses)
    np.testing.assert_array_equal(result.actor_points, ref.actor_points)
    np.testing.assert_array_equal(np.stack([p for _, p, _, _ in rec.frames]), ref.ego_poses)
    np.testing.assert_array_equal(np.stack([c for _, _, c, _ in rec.frames]), ref.actor_points)
    # without a timing or point recorder there are no timings and no points
    assert result.points is None and result.timings == {}
    assert len(ref.points) == 4 and set(ref.timings) == set(STAGES)
    assert all(len(t) == 4 and (t >= 0).all() for t in ref.timings.values())
    assert (ref.timings["total"] > 0).all()
    # stopped early, close() gives the world its benign mesh back; so does finish()
    early = Episode(scene, make_stack("oracle"), seconds=0.4, world=world, rig=rig, seed=5, actor_overrides=shape)
    early.step()
    early.close()
    again = run_episode(scene, make_stack("oracle"), seconds=0.4, world=world, rig=rig, seed=5)
    np.testing.assert_array_equal(again.actor_points, plain.actor_points)
    assert not np.array_equal(plain.actor_points, ref.actor_points)  # the override did change the returns


def test_oracle_detector_needs_points_and_returns():
    det = OracleDetector(min_points=5)
    det.observe_ground_truth(np.array([[10.0, 0, 4.5, 1.9, 0], [20.0, 3, 4.5, 1.9, 0], [np.nan] * 5]),
                             np.array([50, 2, 100]))
    out = det.detect(np.ones((10, 4)))
    assert len(out) == 1 and out.boxes[0, 0] == 10.0 and out.scores[0] == 1.0
    assert len(det.detect(np.zeros((0, 4)))) == 0


class RecordingStack(ModularStack):
    """The oracle stack, recording what the episode loop hands it through the stack interface."""

    def __init__(self):
        super().__init__(OracleDetector(), LaneFollowingPredictor())
        self.calls = []

    def reset(self, context):
        self.calls.append(("reset", context))
        super().reset(context)

    def observe_ground_truth(self, boxes_ego, n_points):
        self.calls.append(("ground_truth", np.array(boxes_ego), np.array(n_points)))
        super().observe_ground_truth(boxes_ego, n_points)

    def step(self, points, ego_state):
        self.calls.append(("step", ego_state.pose.copy()))
        return super().step(points, ego_state)


def test_episode_hands_the_scene_context_once_and_ground_truth_every_frame(free):
    scene, world, rig = free
    stack = RecordingStack()
    r = run_episode(scene, stack, seconds=0.3, world=world, rig=rig)
    assert [c[0] for c in stack.calls] == ["reset"] + ["ground_truth", "step"] * 3
    ctx = stack.calls[0][1]
    assert ctx.scene_id == scene.id and ctx.dt == scene.dt and ctx.lane_map.lanes == tuple(scene.lanes)
    # one lane map for the episode, read by the predictor and the planner
    assert stack.predictor.lane_map is ctx.lane_map and stack.planner.lane_map is ctx.lane_map
    for k, (_, boxes, counts) in enumerate(c for c in stack.calls if c[0] == "ground_truth"):
        assert np.array_equal(counts, r.actor_points[k])  # every actor's returns of that frame
        ok = np.isfinite(r.gt_boxes(k)).all(axis=1)
        assert np.allclose(boxes[ok], boxes_to_frame(r.gt_boxes(k)[ok], r.ego_poses[k]))  # in the ego frame
    assert sum(len(o.detections) for o in r.outputs) > 0  # the oracle detected through the hook


def test_short_oracle_episode_has_sane_metrics(free):
    scene, world, rig = free
    r = run_episode(scene, make_stack("oracle"), seconds=1.5, world=world, rig=rig)
    m = episode_metrics(r, scene.lanes)
    assert m["frames"] == 15
    assert m["detection"]["n_gt"] > 0 and m["detection"]["ap"] > 0.8 and m["detection"]["recall"] > 0.8
    assert m["prediction"]["n"] > 0 and 0 <= m["prediction"]["min_ade"] < 2.0
    assert m["prediction"]["min_ade"] <= m["prediction"]["mean_ade"] < 30
    assert not m["collision"]["collided"] and not m["off_road"]
    speed = scene.ego_speeds()[0]
    assert m["progress_m"] == pytest.approx(speed * 1.4, rel=0.2)
    assert 0 <= m["planning_comfort"]["jerk"] < 5 and 0 <= m["driving_comfort"]["lat"] < 1
    assert m["min_distance"] > 0
    # ground truth in the ROI really is ahead of the ego
    local = boxes_to_frame(r.gt_boxes(0)[np.isfinite(r.gt_boxes(0)).all(axis=1)], r.ego_poses[0])
    assert m["detection"]["n_gt"] <= 15 * int(((local[:, 0] > -5) & (local[:, 0] < 60)).sum())


def test_autonomy_a_stack_or_a_clear_error(free):
    """Autonomy-A is built from the shipped models, or refused with a ConfigError naming them."""
    scene, world, rig = free
    try:
        stack = make_stack("A")
    except ConfigError as exc:
        assert "assets/models" in str(exc) and "--autonomy oracle" in str(exc)
        return
    assert stack.tracker.config.min_score == 0.5
    r = run_episode(scene, stack, seconds=0.5, world=world)
    assert r.frames == 5 and np.isfinite(r.ego_poses).all()
    assert sum(len(o.detections) for o in r.outputs) > 0  # the learned detector sees the cars
