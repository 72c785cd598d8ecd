"""Sampling planner: each cost term on its own, corridors, and closed-loop hand-made situations
(perfect control: the ego moves to the plan's next pose every 0.1 s)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adv3d_runner.autonomy.interface import EgoState, Predictions, Tracks
from adv3d_runner.autonomy.planner import SamplingPlanner, forecast_from
from adv3d_runner.autonomy.planner import costs
from adv3d_runner.autonomy.planner.scorer import CostWeights, score
from adv3d_runner.metrics.comfort import collisions
from adv3d_runner.scene.corridor import ChainCache, CorridorSet, build_corridor
from adv3d_runner.scene.lanemap import LaneMap
from adv3d_runner.scene.schema import Lane

DT = 0.1
LANE_W = 3.7


def straight_lanes(n_lanes=2, x0=-100.0, x1=600.0, limit=25.0):
    xs = np.linspace(x0, x1, 71)
    lanes = []
    for i in range(n_lanes):
        lanes.append(Lane(i, np.c_[xs, np.full_like(xs, i * LANE_W)], LANE_W,
                          left=i + 1 if i + 1 < n_lanes else None, right=i - 1 if i > 0 else None, speed_limit=limit))
    return lanes


def planner_on(lanes, planner=None):
    """A planner reset onto the lane map of ``lanes`` (a new one unless given)."""
    planner = planner or SamplingPlanner()
    planner.reset(LaneMap(lanes))
    return planner


def actor_inputs(boxes_now, future_xy):
    """Tracks and single-mode predictions from ground truth. boxes_now (N, 5), future_xy (N, 60, 2)."""
    N = len(boxes_now)
    ids = np.arange(N) + 100
    tracks = Tracks(ids, boxes_now, np.zeros((N, 2)), np.ones(N), np.zeros(N, np.int64), np.zeros((N, 1, 3)),
                    np.ones((N, 1), bool))
    return tracks, Predictions(ids, future_xy[:, None], np.ones((N, 1)))


def closed_loop(lanes, ego, actor_fn, seconds, planner=None):
    """Re-plan every step; actor_fn(t) -> (N, 5) boxes. Returns ego boxes (T, 5), actor boxes
    (T, N, 5), speeds (T,), plans."""
    planner = planner_on(lanes, planner)
    ego_boxes, act_boxes, speeds, plans = [], [], [], []
    for k in range(int(round(seconds / DT))):
        t = k * DT
        now = actor_fn(t)
        fut = np.stack([actor_fn(t + (h + 1) * DT)[:, :2] for h in range(60)], axis=1) if len(now) else np.zeros((0, 60, 2))
        tracks, preds = actor_inputs(now, fut)
        plan = planner.plan(ego, preds, tracks)
        ego_boxes.append(ego.box)
        act_boxes.append(now)
        speeds.append(ego.speed)
        plans.append(plan)
        ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]),
                       length=ego.length, width=ego.width, wheelbase=ego.wheelbase, time=t + DT)
    return np.array(ego_boxes), np.array(act_boxes).reshape(len(ego_boxes), -1, 5), np.array(speeds), plans


def idm_only():
    """A planner without the least-jerk candidate (``smooth_follow``), for tests of the IDM
    candidates' own mechanisms."""
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    return SamplingPlanner(PlannerConfig(proposals=replace(PlannerConfig().proposals, smooth_follow=False)))


def stopped_at(*xy):
    boxes = np.array([[x, y, 4.6, 1.9, 0.0] for x, y in xy]).reshape(-1, 5)
    return lambda t: boxes.copy()


# ------------------------------------------------------------------ situations

def test_free_road_makes_progress_towards_the_speed_limit():
    lanes = straight_lanes(1, limit=25.0)
    ego = EgoState([0.0, 0.0, 0.0], 15.0)
    plan = planner_on(lanes).plan(ego)
    assert plan.speed[-1] > 17.0 and np.all(np.diff(plan.speed) >= -1e-9)
    assert plan.cost_terms["collision"] == 0.0
    ego_boxes, _, speeds, _ = closed_loop(lanes, ego, stopped_at(), 12.0)
    assert speeds[-1] > 23.0 and speeds.max() <= 25.0 + 0.05
    assert np.abs(ego_boxes[:, 1]).max() < 0.05  # stays on the lane centre


def test_stopped_car_ahead_brakes_and_does_not_collide():
    lanes = straight_lanes(1)
    ego = EgoState([0.0, 0.0, 0.0], 15.0)
    actor = stopped_at((70.0, 0.0))
    plan = planner_on(lanes).plan(ego, *reversed(actor_inputs(actor(0.0), np.repeat(actor(0.0)[:, None, :2], 60, 1))))
    assert plan.speed[-1] < 15.0  # already slowing down in the first plan
    ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, actor, 14.0)
    rep = collisions(ego_boxes, act_boxes)
    assert not rep.collided
    assert speeds[-1] < 0.3  # came to a stop ...
    assert 0.5 < rep.min_distance < 12.0  # ... behind the car, not far away


def test_blocked_lane_with_free_neighbour_changes_lane():
    lanes = straight_lanes(2)
    ego = EgoState([0.0, 0.0, 0.0], 15.0)
    actor = stopped_at((60.0, 0.0))
    ego_boxes, act_boxes, speeds, plans = closed_loop(lanes, ego, actor, 9.0)
    assert plans[0].label.startswith("left1")
    assert not collisions(ego_boxes, act_boxes).collided
    assert ego_boxes[-1, 0] > 80.0  # drove past the stopped car
    assert abs(ego_boxes[-1, 1] - LANE_W) < 0.3  # now on the left lane's centre
    assert speeds.min() > 10.0  # without braking hard


def test_both_lanes_blocked_brakes_in_lane():
    lanes = straight_lanes(2)
    ego = EgoState([0.0, 0.0, 0.0], 15.0)
    actor = stopped_at((60.0, 0.0), (60.0, LANE_W))
    ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, actor, 12.0)
    assert not collisions(ego_boxes, act_boxes).collided
    assert speeds[-1] < 0.5


def test_follows_a_slower_lead_car_at_a_safe_gap():
    lanes = straight_lanes(1, limit=30.0)
    ego = EgoState([0.0, 0.0, 0.0], 25.0)

    def lead(t):
        return np.array([[40.0 + 15.0 * t, 0.0, 4.6, 1.9, 0.0]])

    ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, lead, 12.0)
    rep = collisions(ego_boxes, act_boxes)
    assert not rep.collided and rep.min_distance > 8.0
    assert speeds[-1] == pytest.approx(15.0, abs=1.5)


def test_curved_road_is_followed_on_the_lane():
    R = 150.0
    th = np.linspace(-0.2, 2.5, 200)
    centre = np.c_[R * np.sin(th), R * (1 - np.cos(th))]
    lanes = [Lane(0, centre, LANE_W, speed_limit=20.0)]
    ego = EgoState([0.0, 0.0, 0.0], 18.0)
    ego_boxes, _, speeds, plans = closed_loop(lanes, ego, stopped_at(), 8.0)
    radial = np.hypot(ego_boxes[:, 0], ego_boxes[:, 1] - R)
    assert np.abs(radial - R).max() < 0.3
    assert all(p.cost_terms["drivable_area"] == 0.0 for p in plans)


def test_no_lane_means_stop():
    plan = planner_on([]).plan(EgoState([0.0, 0.0, 0.0], 10.0))
    assert plan.label == "no-lane/stop" and plan.speed[-1] < 10.0 and np.all(np.isfinite(plan.trajectory))
    far = planner_on(straight_lanes(1)).plan(EgoState([0.0, 500.0, 0.0], 10.0))
    assert far.label == "no-lane/stop"


def test_standing_ego_with_obstacle_stays_put():
    lanes = straight_lanes(1)
    ego = EgoState([0.0, 0.0, 0.0], 0.0)
    ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, stopped_at((8.0, 0.0)), 3.0)
    assert not collisions(ego_boxes, act_boxes).collided
    assert speeds.max() < 1.0 and np.all(np.isfinite(ego_boxes))


# ------------------------------------------------------------------ cost terms one by one

def test_collision_cost_weights_modes_and_time():
    dist = np.full((2, 1, 2, 5), 3.0)
    dist[0, 0, 0, 0] = 0.0   # candidate 0 hits mode 0 now
    dist[1, 0, 1, 4] = 0.0   # candidate 1 hits mode 1 at the horizon end
    probs = np.array([[0.7, 0.3]])
    assert costs.collision_cost(dist, probs).tolist() == pytest.approx([0.7, 0.5 * 0.3])
    assert costs.collision_cost(np.zeros((3, 0, 1, 5)), np.zeros((0, 1))).tolist() == [0, 0, 0]


def test_rear_end_exemption():
    ego = np.zeros((1, 3, 3))
    ego[0, :, 0] = [0.0, 1.0, 2.0]
    act = np.zeros((2, 1, 3, 3))
    act[0, 0, :, 0] = [-6.0, -3.0, 0.5]   # same direction, catching up from behind
    act[1, 0, :, 0] = [8.0, 5.0, 2.5]     # ahead, coming towards the ego
    act[1, 0, :, 2] = math.pi
    fb = costs.from_behind(ego, act)
    assert fb[0, 0, 0].tolist() == [True, True, True] and not fb[0, 1].any()
    dist = np.zeros((1, 2, 1, 3))  # both overlap the ego at every step
    probs = np.ones((2, 1))
    assert costs.collision_cost(dist, probs)[0] == pytest.approx(2.0)
    assert costs.collision_cost(dist, probs, exempt=fb)[0] == pytest.approx(1.0)
    assert costs.buffer_cost(dist, probs, 1.0, exempt=fb)[0] == pytest.approx(1.0)
    # an actor that hits from behind and then "drives through" the ego stays exempt
    through = fb.copy()
    through[0, 0, 0, 2] = False
    assert costs.collision_cost(dist, probs, exempt=through)[0] == pytest.approx(1.0)


def test_buffer_cost():
    dist = np.full((1, 1, 2, 4), 0.5)
    # a constant violation costs its size (the time weights are normalised to mean 1)
    assert costs.buffer_cost(dist, np.array([[0.25, 0.75]]), buffer=1.0)[0] == pytest.approx(0.5)
    dist[..., 2:] = 5.0  # violated only in the first half of the horizon, which weighs more
    w = np.linspace(1.0, 0.5, 4) / np.linspace(1.0, 0.5, 4).mean()
    assert costs.buffer_cost(dist, np.array([[0.25, 0.75]]), buffer=1.0)[0] == pytest.approx(0.5 * w[:2].sum() / 4)


def test_clearance_matches_box_geometry():
    ego = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])  # (B=1, T=2, 3)
    act = np.array([[[[10.0, 0.0, 0.0], [5.5, 0.0, 0.0]]]])  # (N=1, K=1, T=2, 3)
    d = costs.clearance(ego, (4.0, 2.0), act, np.array([[4.0, 2.0]]), max_distance=5.0)
    assert d[0, 0, 0, 0] == np.inf  # too far to compute exactly (circles 10 m apart > 4.47 + 5)
    assert d[0, 0, 0, 1] == pytest.approx(5.5 - 1.0 - 4.0)


def test_headway_cost():
    ego = np.zeros((1, 1, 3))
    v = np.array([[10.0]])  # desired gap 2 + 1.0 * 10 = 12 m
    dims = np.array([[4.0, 2.0]])
    ahead = np.array([[[[4.0 + 6.0, 0.0, 0.0]]]])  # bumper gap 6 m -> shortfall 6 / 12
    assert costs.headway_cost(ego, v, (4.0, 2.0), ahead, dims, np.ones((1, 1)))[0] == pytest.approx(0.5)
    beside = np.array([[[[8.0, LANE_W, 0.0]]]])
    behind = np.array([[[[-8.0, 0.0, 0.0]]]])
    for other in (beside, behind):
        assert costs.headway_cost(ego, v, (4.0, 2.0), other, dims, np.ones((1, 1)))[0] == 0.0


def test_simple_terms():
    assert costs.lane_center_cost(np.array([[0.0, 1.0, 2.0]]))[0] == pytest.approx(1.0)
    assert costs.drivable_area_cost(np.array([[0.0, 0.0, 0.6]]))[0] == pytest.approx(0.2)
    assert costs.speed_limit_cost(np.array([[20.0, 26.0]]), np.array([[25.0, 25.0]]))[0] == pytest.approx(0.5)
    assert costs.progress_cost(np.array([50.0, 150.0, 0.0]), 100.0).tolist() == [0.5, 0.0, 1.0]
    assert costs.jerk_cost(np.array([[1.0, 1.0, 1.0]]), 0.0, 0.1)[0] == pytest.approx(10.0 / 3)
    assert costs.lateral_accel_cost(np.array([[10.0, 10.0]]), np.array([[0.01, -0.01]]))[0] == pytest.approx(1.0)
    assert costs.lane_change_cost(np.array([True, False, False]), np.array([False, False, True])).tolist() == [0, 1, 0]
    same = np.array([True, True, False, True])
    assert costs.offset_change_cost(np.array([0.5, 0.0, -0.5, np.nan]), same, 0.0).tolist() == [0.5, 0.0, 0.0, 0.0]
    assert costs.offset_change_cost(np.array([0.5, 0.0, -0.5]), np.ones(3, bool), 0.5).tolist() == [0.0, 0.5, 1.0]
    assert costs.offset_change_cost(np.array([0.5]), np.array([True]), None).tolist() == [0.0]
    # a change not yet confirmed by the previous plan costs (1 + factor) times as much
    assert costs.offset_change_cost(np.array([0.5, -0.5, 0.0]), np.ones(3, bool), 0.0, 0.5, 4.0).tolist() == [0.5, 2.5, 0.0]
    assert costs.offset_change_cost(np.array([0.5, 0.0]), np.ones(2, bool), 0.0, None, 4.0).tolist() == [2.5, 0.0]


def test_road_geometry_on_a_straight_lane():
    lanes = straight_lanes(1)
    cs = CorridorSet([build_corridor(lanes, 0, np.array([0.0, 0.0]))])
    poses = np.array([[[0.0, 0.0, 0.0], [10.0, 1.5, 0.0]]])
    s_start = np.array([float(cs.project(0, np.array([0.0, 0.0]))[0])])
    dev, exc = costs.road_geometry(poses, np.array([[0.0, 10.0]]), cs, s_start, (4.0, 2.0))
    assert dev[0].tolist() == pytest.approx([0.0, 1.5])
    assert exc[0].tolist() == pytest.approx([0.0, 1.5 + 1.0 - LANE_W / 2])


def _road_geometry_numpy(poses, travelled, corridors, s_start, ego_dims):
    """The numpy definition of ``costs.road_geometry`` (before it was compiled)."""
    L, W = ego_dims
    lx = np.array([L / 2, L / 2, -L / 2, -L / 2])
    ly = np.array([-W / 2, W / 2, W / 2, -W / 2])
    dev = np.full((len(corridors),) + poses.shape[:2], np.inf)
    exc = np.full((len(corridors),) + poses.shape[:2] + (4,), np.inf)
    for ci in range(len(corridors)):
        sc, dc = corridors.project_local(np.full(poses.shape[:2], ci), poses[..., :2], s_start[ci] + travelled)
        dev[ci] = np.abs(dc)
        rel = poses[..., 2] - corridors.heading_on(ci, sc)
        cr, sr = np.cos(rel)[..., None], np.sin(rel)[..., None]
        exc[ci] = corridors.road_excess_on(ci, sc[..., None] + lx * cr - ly * sr, dc[..., None] + lx * sr + ly * cr)
    return dev.min(axis=0), exc.min(axis=0).max(axis=-1)


def test_road_geometry_kernel_is_the_numpy_definition_bit_for_bit(rng):
    a = Lane(0, np.array([[0.0, 0.0], [50.0, 0.0]]), 3.5, successors=[1], left=2, speed_limit=20.0)
    th = np.linspace(0, 1.0, 40)
    b = Lane(1, np.c_[50 + 100 * np.sin(th), 100 * (1 - np.cos(th))], 4.0, speed_limit=15.0)  # a dead end
    c = Lane(2, np.array([[0.0, 3.5], [50.0, 3.5], [200.0, 3.0]]), 3.0, right=0)
    cs = CorridorSet([build_corridor([a, b, c], lid, np.array([10.0, 0.0]), behind=5.0, ahead=150.0)
                      for lid in (0, 2)])
    poses = np.concatenate([rng.uniform([-20, -8, -3], [160, 110, 3], (6, 40, 3))], axis=0)
    poses[0, 5] = np.nan  # NaN propagates like numpy's minimum / maximum
    poses[1, :, 0] += 400.0  # far past the dead end
    travelled = rng.uniform(0, 80, (6, 40))
    s_start = np.array([5.0, 4.0])
    new = costs.road_geometry(poses, travelled, cs, s_start, (4.6, 1.9))
    with np.errstate(invalid="ignore"):
        ref = _road_geometry_numpy(poses, travelled, cs, s_start, (4.6, 1.9))
    for x, y in zip(new, ref):
        assert x.shape == y.shape and x.tobytes() == y.tobytes()
    assert np.isnan(new[0][0, 5]) and np.isnan(new[1][0, 5]) and np.isfinite(new[1][2:]).all()


def test_corridor_cache_gives_the_same_corridors(rng):
    a = Lane(0, np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 0.0]]), 3.5, successors=[1], speed_limit=20.0)
    th = np.linspace(0, 1.0, 40)
    b = Lane(1, np.c_[50 + 100 * np.sin(th), 100 * (1 - np.cos(th))], [4.0] * 40, speed_limit=None)
    lanes = {0: a, 1: b}
    cache = ChainCache()
    for xy, ahead in [((10.0, 0.0), 30.0), ((10.0, 0.5), 200.0), ((-5.0, 1.0), 120.0), ((10.0, 0.0), 30.0)]:
        fresh = build_corridor(lanes, 0, np.array(xy), 20.0, ahead)
        cached = build_corridor(lanes, 0, np.array(xy), 20.0, ahead, cache=cache)
        assert fresh.lane_ids == cached.lane_ids and fresh.ends == cached.ends
        for f in ("points", "width", "speed_limit", "lane_of_point"):
            assert getattr(fresh, f).tobytes() == getattr(cached, f).tobytes()
        assert (fresh.spacing, fresh.s_offset) == (cached.spacing, cached.s_offset)
    assert len(cache._chains) == 2  # (0,) and (0, 1)


def test_scorer_weights_and_breakdown():
    raw = {"collision": np.array([0.0, 1.0]), "progress": np.array([0.5, 0.0]), "jerk": np.array([np.nan, 0.0])}
    w = CostWeights(collision=100.0, progress=10.0, jerk=1.0)
    table = score(raw, w)
    assert table.best == 1  # NaN counts as a huge cost, not as "best"
    assert table.breakdown(1) == {"collision": 100.0, "progress": 0.0, "jerk": 0.0}
    assert table.total[1] == pytest.approx(100.0)
    with pytest.raises(KeyError):
        score({"nonsense": np.zeros(2)})


# ------------------------------------------------------------------ corridors and inputs

def test_corridor_chains_successors_and_local_projection_matches_global(rng):
    a = Lane(0, np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 0.0]]), 3.5, successors=[1], speed_limit=20.0)  # repeated point
    th = np.linspace(0, 1.0, 40)
    b = Lane(1, np.c_[50 + 100 * np.sin(th), 100 * (1 - np.cos(th))], 4.0, speed_limit=15.0)
    cor = build_corridor([a, b], 0, np.array([10.0, 0.0]), behind=5.0, ahead=120.0)
    assert cor.lane_ids == (0, 1) and not cor.ends
    cs = CorridorSet([cor])
    assert cs.limit_at(np.array(0), np.array(5.0)) == 20.0 and cs.limit_at(np.array(0), np.array(100.0)) == 15.0
    xy = cs.pose_at(np.zeros(50, int), np.linspace(0, 110, 50), rng.uniform(-2, 2, 50))[:, :2]
    s_g, d_g = cs.project(0, xy)
    s_l, d_l = cs.project_local(np.zeros(50, int), xy, s_g + rng.uniform(-3, 3, 50))
    assert np.allclose(s_l, s_g, atol=1e-6) and np.allclose(d_l, d_g, atol=1e-6)
    assert LaneMap([a, b]).locate(np.array([60.0, 2.0, 0.2]))[0] == 1


def _curving_corridors() -> CorridorSet:
    """Two corridors: a straight lane into a curve, and its left neighbour that narrows."""
    a = Lane(0, np.array([[0.0, 0.0], [50.0, 0.0]]), 3.5, successors=[1], left=2, speed_limit=20.0)
    th = np.linspace(0, 1.0, 40)
    b = Lane(1, np.c_[50 + 100 * np.sin(th), 100 * (1 - np.cos(th))], 4.0, speed_limit=15.0)
    c = Lane(2, np.array([[0.0, 3.5], [50.0, 3.5], [200.0, 3.0]]), 3.0, right=0)
    return CorridorSet([build_corridor([a, b, c], lid, np.array([10.0, 0.0]), behind=5.0, ahead=150.0)
                        for lid in (0, 2)])


def test_project_near_kernel_is_the_numpy_definition_bit_for_bit(rng):
    cs = _curving_corridors()
    xy = rng.uniform([-30, -20], [180, 120], (7, 11, 2))
    xy[0, 3] = np.nan
    for ci in range(len(cs)):
        for stride in (4, 3):
            got = cs.project_near(ci, xy, stride)
            want = cs.project_near_numpy(ci, xy, stride)
            for x, y in zip(got, want):
                assert x.shape == y.shape == xy.shape[:-1] and x.tobytes() == y.tobytes()


def test_forecast_joins_tracks_and_derives_yaw():
    traj = np.zeros((2, 2, 60, 2))
    traj[0, :, :, 1] = np.arange(1, 61)[None] * 1.0  # moving +y
    traj[1] = 7.0  # standing still
    preds = Predictions(np.array([5, 9]), traj, np.array([[2.0, 2.0], [1.0, 0.0]]))
    tracks = Tracks(np.array([9]), np.array([[7.0, 7.0, 10.0, 2.5, 1.0]]), np.zeros((1, 2)), np.ones(1),
                    np.zeros(1, np.int64), np.zeros((1, 1, 3)), np.ones((1, 1), bool))
    f = forecast_from(preds, tracks, steps=50, dt=0.1)
    assert f.poses.shape == (2, 2, 51, 3)
    assert f.probs[0].tolist() == [0.5, 0.5]
    assert np.allclose(f.poses[0, 0, 1:, 2], math.pi / 2) and np.allclose(f.poses[0, 0, 0, :2], [0.0, 0.0])
    assert f.dims[1].tolist() == [10.0, 2.5] and np.allclose(f.poses[1, :, :, 2], 1.0)  # track yaw held


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3])  # straight, curved, on-ramp, lane drop
def test_benchmark_scenes_with_oracle_perception(repo_root, seed):
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_planner", repo_root / "bench" / "planner.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    path = repo_root / "scenes" / "highway" / f"highway-benchmark-{seed:06d}.json.gz"
    if not path.exists():
        pytest.skip("benchmark scenes not present")
    r = bench.run_scene(path, 5.0, "log")
    assert not r["at_fault"] and r["off_road_m"] == 0.0
    assert r["progress_m"] > 20.0


def test_driving_west_across_the_yaw_wrap():
    xs = np.linspace(600.0, -600.0, 121)  # driving direction -x: heading +-pi
    wiggle = 0.3 * np.sin(xs / 40.0)  # the heading crosses +-pi back and forth
    lanes = [Lane(0, np.c_[xs, wiggle], LANE_W, speed_limit=20.0)]
    ego = EgoState([0.0, 0.0, -math.pi + 0.004], 15.0)
    ego_boxes, _, speeds, plans = closed_loop(lanes, ego, stopped_at(), 4.0)
    assert np.all(np.isfinite(ego_boxes))
    assert ego_boxes[-1, 0] < -55.0  # moved west
    assert np.abs(ego_boxes[:, 1] - 0.3 * np.sin(ego_boxes[:, 0] / 40.0)).max() < 0.3
    assert all(np.all(np.abs(p.trajectory[:, 2]) <= math.pi) for p in plans)
    assert speeds[-1] > 16.0


def test_plan_with_scores_reports_every_term():
    from adv3d_runner.autonomy.planner import PlannerConfig
    from adv3d_runner.autonomy.planner.scorer import OCCUPANCY_TERMS, OPTIONAL_TERMS, TERMS

    planner = planner_on(straight_lanes(3))
    plan, cands, table = planner.plan_with_scores(EgoState([0.0, LANE_W, 0.0], 10.0))  # middle lane
    assert set(plan.cost_terms) == set(TERMS) - set(OCCUPANCY_TERMS) - set(OPTIONAL_TERMS) == set(table.raw)
    with_own = planner_on(straight_lanes(3), SamplingPlanner(PlannerConfig(own_lane_floor=5.0)))
    assert set(with_own.plan(EgoState([0.0, LANE_W, 0.0], 10.0)).cost_terms) == set(TERMS) - set(OCCUPANCY_TERMS)
    # offsets x speeds per lane + the two least-jerk candidates (smooth, smooth-c) + the emergency stop
    assert len(cands) == len(table.total) == 3 * 5 + 2 * 5 + 2 + 1
    assert plan.cost == pytest.approx(sum(plan.cost_terms.values()))
    assert plan.trajectory.shape == (51, 3) and plan.acceleration.shape == (50,)
    assert np.allclose(plan.trajectory[0], [0.0, LANE_W, 0.0]) and plan.speed[0] == 10.0


def test_one_frame_obstacle_does_not_make_the_offset_dither():
    """A-B-A dithering of the in-lane offset: a slightly slower car predicted at the lane's left
    edge for one frame only (as a fresh, noisy track can be) made the planner nudge right for that
    frame and come straight back. An offset change must be preferred on two consecutive plans
    before it is taken; a nudge that stays worthwhile is still taken (one plan later)."""
    lanes = straight_lanes(1, limit=25.0)

    def inputs(present, t):
        if not present:
            return actor_inputs(np.zeros((0, 5)), np.zeros((0, 60, 2)))
        x = 50.0 + 22.0 * t  # 22 m/s, 50 m ahead of the ego's start, overlapping the left edge
        now = np.array([[x, 2.0, 4.6, 1.9, 0.0]])
        return actor_inputs(now, (now[0, :2] + np.c_[22.0 * DT * np.arange(1, 61), np.zeros(60)])[None])

    def offsets(frames_with_car, n=6):
        # the IDM candidates only: with the least-jerk candidate the ego follows that car
        # smoothly at the centre instead of nudging, and there is no offset change to test
        planner, ego, out = planner_on(lanes, idm_only()), EgoState([0.0, 0.0, 0.0], 25.0), []
        for k in range(n):
            tracks, preds = inputs(k in frames_with_car, k * DT)
            plan = planner.plan(ego, preds, tracks)
            out.append(plan.label.split("/")[1])
            ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]),
                           time=(k + 1) * DT)
        return out

    # the car makes a right nudge the cheapest plan (it is then not a leader to follow) ...
    tracks, preds = inputs(True, 0.0)
    assert planner_on(lanes, idm_only()).plan(EgoState([0.0, 0.0, 0.0], 25.0), preds, tracks).label.split("/")[1] == "d-0.5"
    # ... but seen for one frame only while driving on the centre it changes nothing
    assert offsets({2}) == ["d+0.0"] * 6
    # seen for good, the nudge is taken one plan after it first appears, and kept
    assert offsets(set(range(2, 6))) == ["d+0.0"] * 3 + ["d-0.5"] * 3


# ------------------------------------------------------------------ real traffic (docs/autonomy.md)

def test_forecast_heading_ignores_jitter_of_slow_actors():
    """A slow actor's predicted path jitters by centimetres from step to step; its heading must
    not (10-30 degrees step to step made a truck in the next lane overlap the ego)."""
    rng = np.random.default_rng(0)
    t = np.arange(1, 61) * DT
    traj = np.zeros((2, 1, 60, 2))
    traj[0, 0, :, 0] = 3.0 * t + rng.normal(0, 0.04, 60)   # 3 m/s along +x, jittering sideways and back
    traj[0, 0, :, 1] = rng.normal(0, 0.04, 60)
    traj[1, 0] = 50.0 + rng.normal(0, 0.04, (60, 2))       # standing still, jittering
    boxes = np.array([[0.0, 0.0, 14.0, 2.6, 0.0], [50.0, 50.0, 4.6, 1.9, 0.3]])
    tracks = Tracks(np.array([1, 2]), boxes, np.zeros((2, 2)), np.ones(2), np.zeros(2, np.int64),
                    np.zeros((2, 1, 3)), np.ones((2, 1), bool))
    f = forecast_from(Predictions(np.array([1, 2]), traj, np.ones((2, 1))), tracks, steps=50, dt=0.1)
    assert np.degrees(np.abs(f.poses[0, 0, :, 2])).max() < 3.0
    assert np.allclose(f.poses[1, 0, :, 2], 0.3)
    # a plain step-by-step heading of the same path is far off (what the chord is for)
    d = np.diff(traj[0, 0], axis=0)
    assert np.degrees(np.abs(np.arctan2(d[:, 1], d[:, 0]))).max() > 10.0


def _leader_inputs(jitter, rng):
    """A leader 32 m ahead at 15 m/s (near the IDM equilibrium gap), its predicted path jittering by
    ``jitter`` m per step."""
    t = np.arange(1, 61) * DT
    x = 32.0 + 15.0 * t + rng.normal(0.0, jitter, 60)
    return actor_inputs(np.array([[32.0, 0.0, 4.6, 1.9, 0.0]]), np.stack([x, 0 * t], -1)[None])


def test_leader_speed_is_averaged_so_prediction_jitter_does_not_shake_the_ego():
    """Centimetres of jitter in a leader's predicted path, one-step differenced, are +-0.3 m/s of
    leader speed, which the IDM turned into a different first-step acceleration every frame."""
    from adv3d_runner.autonomy.planner import PlannerConfig, ProposalConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, length=4.8, width=1.9)
    spread = {}
    for window in (0.1, 1.5):
        pc = ProposalConfig(leader_speed_window=window, max_jerk=10.0, max_release_jerk=10.0, max_brake_jerk=10.0,
                            accel_deadband=0.0, smooth_follow=False)  # the IDM candidates' mechanism
        firsts = []
        for seed in range(6):
            planner = planner_on(straight_lanes(1), SamplingPlanner(PlannerConfig(proposals=pc)))
            tracks, preds = _leader_inputs(0.03, np.random.default_rng(seed))
            plan = planner.plan(ego, preds, tracks)
            firsts.append(plan.acceleration[0])
        spread[window] = np.ptp(firsts)
    assert spread[0.1] > 0.3 and spread[1.5] < 0.3 * spread[0.1]


def test_firm_braking_builds_up_faster_than_comfortable_changes():
    from adv3d_runner.autonomy.planner import ProposalConfig

    planner = planner_on(straight_lanes(1))
    pc = planner.config.proposals
    assert pc.max_brake_jerk > pc.max_jerk
    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, length=4.8, width=1.9)
    # a standing car 40 m ahead: the IDM asks for more than idm_decel at once (at 30 m only the
    # emergency stop avoids it with the firm-braking limit of 4 m/s^3)
    tracks, preds = actor_inputs(np.array([[40.0, 0.0, 4.6, 1.9, 0.0]]), np.tile([[40.0, 0.0]], (60, 1))[None])
    plan = planner.plan(ego, preds, tracks)
    assert plan.acceleration[0] == pytest.approx(-pc.max_brake_jerk * DT)
    # a slightly slower car far ahead: a comfortable change, at most max_jerk per second
    t = np.arange(1, 61) * DT
    tracks, preds = actor_inputs(np.array([[60.0, 0.0, 4.6, 1.9, 0.0]]), np.stack([60 + 13.0 * t, 0 * t], -1)[None])
    plan = planner.plan(ego, preds, tracks)
    assert abs(plan.acceleration[0]) <= pc.max_jerk * DT + 1e-9
    assert ProposalConfig().max_brake_jerk * DT <= ProposalConfig().max_decel


# ---------------------------------------------------------------- config overrides (tuning runs)
def test_config_overrides_replace_only_the_named_fields():
    from adv3d_runner.autonomy.planner import PlannerConfig

    assert PlannerConfig.from_overrides({}) == PlannerConfig()
    c = PlannerConfig.from_overrides({"proposals": {"max_brake_jerk": 4, "speed_fractions": [0, 0.5, 1]},
                                      "weights": {"jerk": 0.5}, "planner": {"buffer": 2.0}})
    assert c.proposals.max_brake_jerk == 4.0 and isinstance(c.proposals.max_brake_jerk, float)
    assert c.proposals.speed_fractions == (0, 0.5, 1)
    assert c.weights.jerk == 0.5 and c.buffer == 2.0
    assert c.proposals.max_jerk == PlannerConfig().proposals.max_jerk  # the rest untouched


@pytest.mark.parametrize("bad, names", [
    ({"proposal": {}}, "proposal"),
    ({"proposals": {"max_jerks": 1.0}}, "proposals.max_jerks"),
    ({"weights": {"jerk": "high"}}, "weights.jerk"),
    ({"planner": {"exempt_rear_end": 1}}, "planner.exempt_rear_end"),
    ({"planner": {"proposals": {}}}, "planner.proposals"),
    ([1, 2], "expected an object"),
    ({"proposals": {"min_headway": 2.0}}, "min_headway"),
    ({"proposals": {"firm_braking": -1.0}}, "firm_braking"),
    ({"proposals": {"leader_modes": "slowest"}}, "leader_modes"),
])
def test_config_overrides_refuse_unknown_or_mistyped_fields_by_name(bad, names):
    from adv3d_runner.autonomy.planner import PlannerConfig
    from adv3d_runner.errors import ConfigError

    with pytest.raises(ConfigError, match=names.replace(".", r"\.")) as info:
        PlannerConfig.from_overrides(bad, "tune.json")
    assert "tune.json" in str(info.value)


# ------------------------------------------------ real traffic, headings and reversing

def _two_mode_leader(slow_prob):
    """One car 25 m ahead in the ego's lane, two predicted modes: 15 m/s (likely) and 11 m/s."""
    t = np.arange(1, 61) * DT
    now = np.array([[25.0, 0.0, 4.6, 1.9, 0.0]])
    fast, slow = np.stack([25 + 15.0 * t, 0 * t], -1), np.stack([25 + 11.0 * t, 0 * t], -1)
    tracks = Tracks(np.array([7]), now, np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64), np.zeros((1, 1, 3)),
                    np.ones((1, 1), bool))
    preds = Predictions(np.array([7]), np.stack([fast, slow])[None], np.array([[1 - slow_prob, slow_prob]]))
    return tracks, preds


def test_the_idm_follows_an_actors_expected_mode_not_its_slowest():
    """Following the nearest of an actor's modes made the IDM follow a 20 % mode that is slower
    than the likely one, and the step-0 tie picked another mode than step 1: every plan asked
    for a hard brake one step ahead that the next plan took back."""
    from adv3d_runner.autonomy.planner import PlannerConfig, ProposalConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, length=4.8, width=1.9)

    def gaps_and_accel(modes, slow_prob):
        pc = ProposalConfig(leader_modes=modes, idm_coolness=0.0)
        planner = planner_on(straight_lanes(1), SamplingPlanner(PlannerConfig(proposals=pc)))
        tracks, preds = _two_mode_leader(slow_prob)
        plan, cands, table = planner.plan_with_scores(ego, preds, tracks)
        keep = [i for i, lab in enumerate(cands.spec.labels) if lab.endswith("d+0.0/v25.0")][0]
        # the leader's rear bumper along the lane: the ego's arc length plus its gap
        return cands.leader_gap[keep] + cands.s[keep], cands.accel[keep]

    gap_near, acc_near = gaps_and_accel("nearest", 0.2)
    gap_exp, acc_exp = gaps_and_accel("expected", 0.2)
    # the expected leader is where 0.8 x fast + 0.2 x slow puts it: 3.2 m further at 4 s than the slow mode
    t = 4.0
    assert gap_exp[40] - gap_near[40] == pytest.approx(0.8 * (15 - 11) * t, abs=0.05)
    # and the IDM brakes less behind it over the first second
    assert acc_exp[:10].mean() > acc_near[:10].mean() + 0.2
    # a mode below min_mode_prob does not lead at all, and with all probability on the slow mode
    # the expected leader is that mode
    gap_all_slow, _ = gaps_and_accel("expected", 1.0)
    assert gap_all_slow[40] == pytest.approx(gap_near[40], abs=1e-6)
    with pytest.raises(ValueError, match="leader_modes"):
        ProposalConfig(leader_modes="slowest")


def test_acc_model_softens_the_idm_for_a_cut_in_that_is_not_closing():
    """A car that cuts in 8 m ahead but drives faster than the ego: the plain IDM brakes hard (its
    desired gap is far longer), the ACC model (coolness 0.9) brakes about idm_decel at most; for
    a slower car at the same gap both brake firmly."""
    from adv3d_runner.autonomy.planner.proposals import _acc_blend

    v, gap, b, a_max = np.array([14.0]), np.array([8.0]), 2.0, 1.5
    s_star = 3.0 + 14.0 * 1.5 + 14.0 * (14.0 - 16.0) / (2 * np.sqrt(a_max * b))
    a_idm = a_max * (1 - (14.0 / 25.0) ** 4 - (s_star / 8.0) ** 2)
    assert a_idm < -4.0
    faster = _acc_blend(np.array([a_idm]), v, np.array([16.0]), np.array([0.0]), gap, a_max, b, 0.9)[0]
    assert -b - 0.5 < faster < 0.0
    assert _acc_blend(np.array([a_idm]), v, np.array([16.0]), np.array([0.0]), gap, a_max, b, 0.0)[0] == a_idm
    slower = _acc_blend(np.array([-6.0]), v, np.array([8.0]), np.array([0.0]), gap, a_max, b, 0.9)[0]
    assert slower < -b  # closing at 6 m/s on 8 m: firm braking stays
    assert _acc_blend(np.array([1.0]), v, np.array([16.0]), np.array([0.0]), gap, a_max, b, 0.9)[0] == 1.0


def test_emergency_stop_only_when_every_other_candidate_collides():
    """An unlikely mode (8 %) of the car in the next lane swerves in and stops ahead: it touches
    every candidate but the emergency stop, and with its small expected collision the emergency
    stop's -7 m/s^2 scored lowest (in real traffic: a standstill for nothing). It may only be
    chosen when every other candidate expects at least ``emergency_min_collision`` collisions;
    a car standing across the lane close ahead still triggers it."""
    from adv3d_runner.autonomy.planner import PlannerConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, length=4.8, width=1.9)
    t = np.arange(1, 61) * DT
    keeps = np.stack([8 + 15.0 * t, LANE_W + 0 * t], -1)
    x_in = np.minimum(8 + 15.0 * t - 2.5 * t ** 2, 8 + 15.0 ** 2 / 10.0)  # brakes at 5 m/s^2 to a stop
    swerves = np.stack([x_in, np.maximum(LANE_W - 4.0 * t, 0.0)], -1)
    now = np.array([[8.0, LANE_W, 4.6, 1.9, 0.0]])
    tracks = Tracks(np.array([3]), now, np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64), np.zeros((1, 1, 3)),
                    np.ones((1, 1), bool))
    preds = Predictions(np.array([3]), np.stack([keeps, swerves])[None], np.array([[0.92, 0.08]]))
    lanes = straight_lanes(2)
    for gate in (None, 0.5):
        plan, cands, table = planner_on(lanes, SamplingPlanner(PlannerConfig(
            emergency_min_collision=gate))).plan_with_scores(ego, preds, tracks)
        others = ~cands.spec.emergency
        assert 0.0 < table.raw["collision"][others].min() < 0.5
        assert plan.label.endswith("emergency-stop") == (gate is None), plan.label
    # a car standing across the lane 19 m ahead: only the emergency stop stops short of it
    wall = np.array([[22.0, 0.0, 4.6, 1.9, np.pi / 2]])
    tracks, preds = actor_inputs(wall, np.tile([[22.0, 0.0]], (60, 1))[None])
    plan, cands, table = planner_on(straight_lanes(1)).plan_with_scores(ego, preds, tracks)
    assert table.raw["collision"][~cands.spec.emergency].min() >= 0.5
    assert plan.label.endswith("emergency-stop")


def test_an_actor_overlapping_the_ego_now_is_no_collision_to_avoid():
    """A box that already overlaps the ego's footprint (a mislocalised detection beside it) made
    every candidate collide; no plan can undo a present overlap, so it counts in neither the
    collision nor the buffer term."""
    from adv3d_runner.autonomy.planner import PlannerConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 10.0, length=4.8, width=1.9)
    t = np.arange(1, 61) * DT
    ghost = np.array([[1.0, 1.5, 4.6, 1.9, 0.0]])  # 1.5 m left of the ego's centre: overlapping
    tracks, preds = actor_inputs(ghost, np.stack([1 + 10.0 * t, 1.5 + 0 * t], -1)[None])
    on = planner_on(straight_lanes(1)).plan_with_scores(ego, preds, tracks)
    off = planner_on(straight_lanes(1), SamplingPlanner(PlannerConfig(exempt_overlap_now=False))).plan_with_scores(
        ego, preds, tracks)
    assert off[2].raw["collision"].min() > 0.5
    assert on[2].raw["collision"].max() == 0.0 and on[2].raw["buffer"].max() == 0.0


def test_firm_braking_is_released_as_fast_as_it_builds_up():
    from adv3d_runner.autonomy.planner import PlannerConfig, ProposalConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 10.0, acceleration=-6.0, length=4.8, width=1.9)
    for firm in (True, False):
        pc = ProposalConfig(firm_release=firm)
        plan = planner_on(straight_lanes(1), SamplingPlanner(PlannerConfig(proposals=pc))).plan(ego)
        step = plan.acceleration[0] - ego.acceleration
        assert step == pytest.approx((pc.max_brake_jerk if firm else pc.max_release_jerk) * DT)


def test_progress_reference_is_the_best_safe_candidate_within_floor_and_limit():
    d = np.array([2.0, 6.0, 9.0, 40.0])
    safe = np.array([True, True, True, False])  # the longest one collides
    assert costs.progress_reference(d, safe, 125.0, 5.0) == 9.0
    assert costs.progress_reference(d, safe, 8.0, 5.0) == 8.0  # never beyond the speed limit's distance
    assert costs.progress_reference(np.array([1.0, 2.0]), np.array([True, True]), 125.0, 5.0) == 5.0  # the floor
    assert costs.progress_reference(d, np.zeros(4, bool), 125.0, 5.0) == 40.0  # none safe: all count
    # at crawl speed a stop now costs as much as at speed: 1 - 0 / 9 against 1 - 0 / 125
    assert costs.progress_cost(np.array([0.0]), 9.0)[0] == 1.0


def test_quantile_leader_is_the_probability_weighted_quantile_of_the_in_lane_modes():
    from adv3d_runner.autonomy.planner.proposals import _expected_leaders

    # one group, one actor with three modes at 10, 20, 30 m (p 0.2, 0.5, 0.3), all in the lane
    s = np.array([10.0, 20.0, 30.0])[None, :, None]
    ok = np.ones((1, 3, 1), bool)
    probs = np.array([[0.2, 0.5, 0.3]])
    mean, lead = _expected_leaders(s, ok, probs, 0.1)
    assert lead.all() and mean[0, 0, 0] == pytest.approx(0.2 * 10 + 0.5 * 20 + 0.3 * 30)
    assert _expected_leaders(s, ok, probs, 0.1, 0.0)[0][0, 0, 0] == 10.0
    assert _expected_leaders(s, ok, probs, 0.1, 0.5)[0][0, 0, 0] == 20.0
    assert _expected_leaders(s, ok, probs, 0.1, 0.75)[0][0, 0, 0] == 30.0
    # a mode outside the lane does not count; below min_prob of in-lane mass the actor does not lead
    ok_out = np.array([False, True, True])[None, :, None]
    assert _expected_leaders(s, ok_out, probs, 0.1, 0.0)[0][0, 0, 0] == 20.0
    assert not _expected_leaders(s, np.array([True, False, False])[None, :, None], probs, 0.25)[1].any()


def test_acceleration_deadband_holds_through_small_changes_of_the_demand():
    """In steady following the leader's gap and speed jitter from frame to frame; without a
    deadband each plan passed that on to the executed acceleration. Within the band the
    acceleration is held; a real change of the demand (a braking leader) still goes through."""
    from adv3d_runner.autonomy.planner import PlannerConfig, ProposalConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, acceleration=0.0, length=4.8, width=1.9)
    firsts = {}
    for band in (0.0, 0.2):
        pc = ProposalConfig(accel_deadband=band, smooth_follow=False)  # the IDM candidates' mechanism
        out = []
        for gap in (31.0, 32.0, 33.0):  # the leader's distance jittering by a metre
            now = np.array([[gap, 0.0, 4.6, 1.9, 0.0]])
            t = np.arange(1, 61) * DT
            tracks, preds = actor_inputs(now, np.stack([gap + 15.0 * t, 0 * t], -1)[None])
            out.append(planner_on(straight_lanes(1), SamplingPlanner(PlannerConfig(proposals=pc))).plan(
                ego, preds, tracks).acceleration[0])
        firsts[band] = np.array(out)
    assert np.ptp(firsts[0.0]) > 0.01 and np.all(firsts[0.2] == 0.0)
    # a leader braking hard 20 m ahead: the demand leaves the band, braking starts at once
    t = np.arange(1, 61) * DT
    x = 20.0 + np.maximum(15.0 * t - 2.5 * t ** 2, 0.0) * (t < 3) + 22.5 * (t >= 3)
    tracks, preds = actor_inputs(np.array([[20.0, 0.0, 4.6, 1.9, 0.0]]), np.stack([x, 0 * t], -1)[None])
    plan = planner_on(straight_lanes(1), idm_only()).plan(ego, preds, tracks)
    assert plan.acceleration[0] < -0.1


def test_a_car_alongside_leads_only_once_it_is_ahead():
    """A car merging in beside the ego (centre 1 m ahead, 1.6 m to the left: inside the lane
    strip, bumper gap < 0) at the ego's speed. As a leader right away the IDM brakes at
    max_decel for it (real traffic, NGSIM US-101 train recording 5: -3.1 m/s^2 and 21 % of the
    logged progress lost); by default it leads only once its bumper gap is positive, and the
    collision and buffer terms still see it."""
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    lanes = straight_lanes(2)
    ego = EgoState([0.0, 0.0, 0.0], 10.0)
    car = lambda t: np.array([[1.0 + 10.0 * t, 1.6, 4.6, 1.9, 0.0]])  # noqa: E731
    fut = np.stack([car((h + 1) * DT)[:, :2] for h in range(60)], axis=1)
    tracks, preds = actor_inputs(car(0.0), fut)
    default = planner_on(lanes).plan_with_scores(ego, preds, tracks)[1]
    old_cfg = PlannerConfig(proposals=replace(PlannerConfig().proposals, alongside_leads=True))
    old = planner_on(lanes, SamplingPlanner(old_cfg)).plan_with_scores(ego, preds, tracks)[1]
    in_lane = np.array(["lane0/" in lab and "emergency" not in lab and "smooth" not in lab for lab in old.spec.labels])
    assert np.all(old.leader_gap[in_lane, 0] <= 0.0) and np.all(old.accel[in_lane, :5].min(axis=1) < -1.0)
    assert np.all(np.isinf(default.leader_gap[in_lane, 0])) and np.all(default.accel[in_lane, 0] > -0.5)


def test_fixed_acceleration_candidates_reach_their_target_at_the_jerk_limit_and_hold_it():
    """ProposalConfig.accel_targets adds current-lane candidates that move their acceleration to
    a target at the comfortable jerk limit and hold it (off by default)."""
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    cfg = PlannerConfig(proposals=replace(PlannerConfig().proposals, accel_targets=(-1.0, 0.5), accel_deadband=0.0))
    _, cands, _ = planner_on(straight_lanes(1), SamplingPlanner(cfg)).plan_with_scores(EgoState([0.0, 0.0, 0.0], 15.0))
    labels = cands.spec.labels
    assert "lane0/d+0.0/a-1.0" in labels and "lane0/d+0.0/a+0.5" in labels
    brake, accel = cands.accel[labels.index("lane0/d+0.0/a-1.0")], cands.accel[labels.index("lane0/d+0.0/a+0.5")]
    step = cfg.proposals.max_jerk * cfg.proposals.dt
    assert np.allclose(brake[:6], -step * np.arange(1, 7)) and np.allclose(brake[6:], -1.0)
    assert np.allclose(accel[:3], [step, 2 * step, 3 * step]) and np.allclose(accel[3:], 0.5)
    default = planner_on(straight_lanes(1)).plan_with_scores(EgoState([0.0, 0.0, 0.0], 15.0))[1]
    assert not any("/a" in lab.split("/")[-1][:2] for lab in default.spec.labels)


def test_avoidable_later_only_at_speeds_a_later_brake_can_handle():
    dt = 0.1
    t = np.arange(51) * dt
    crawl = np.full((1, 51), 1.8)  # 1.8 m/s: stops in 0.81 m at 2 m/s^2, covers 1.8 m in 1 s
    fast = np.full((1, 51), 15.0)  # 15 m/s: needs 56 m, covers 15 m in 1 s
    speeds = np.concatenate([crawl, fast])
    travelled = speeds * t[None]
    later = costs.avoidable_later(speeds, travelled, dt, reaction=1.0, decel=2.0)
    assert later.shape == (2, 51)
    assert not later[:, :10].any()  # within the reaction time: never
    assert later[0, 10:].all() and not later[1].any()
    assert not costs.avoidable_later(speeds, travelled, dt, reaction=10.0, decel=2.0).any()  # beyond the horizon


def test_contingency_leaves_a_late_collision_with_a_crawling_mode_to_later_plans():
    """At 1.8 m/s, a 15 % mode in which the leader 4 m ahead stops dead makes every candidate
    that keeps following "collide" seconds ahead; with contingency_time the collision term
    leaves that to the later plans (the buffer term still sees it)."""
    from adv3d_runner.autonomy.planner import PlannerConfig

    lanes = straight_lanes(1)
    T = 60
    steps = np.arange(1, T + 1) * DT
    ego_len = 4.5
    lead_x0 = ego_len + 4.0  # 4 m bumper gap
    crawl = np.c_[lead_x0 + 1.8 * steps, np.zeros(T)]
    stop = np.c_[np.full(T, lead_x0), np.zeros(T)]
    traj = np.stack([crawl, stop])[None]  # (1, 2, T, 2)
    preds = Predictions(np.array([1]), traj, np.array([[0.85, 0.15]]))
    tracks = Tracks(np.array([1]), np.array([[lead_x0, 0.0, 4.5, 1.9, 0.0]]), np.array([[1.8, 0.0]]), np.ones(1),
                    np.zeros(1, np.int64), np.zeros((1, 1, 3)), np.ones((1, 1), bool))
    ego = EgoState([0.0, 0.0, 0.0], 1.8, length=ego_len, width=1.9)
    tables = {}
    for name, cfg in (("plain", PlannerConfig()), ("later", PlannerConfig(contingency_time=1.0))):
        plan, cands, table = planner_on(lanes, SamplingPlanner(cfg)).plan_with_scores(ego, preds, tracks)
        follow = [i for i, label in enumerate(cands.spec.labels) if label == "lane0/d+0.0/v25.0"]
        tables[name] = (plan, table.raw["collision"][follow[0]], table.raw["buffer"][follow[0]])
    plan, collision, buffer = tables["plain"]
    assert 0.05 < collision <= 0.15 and plan.label.endswith("/v0.0")  # only the stop target is clean
    _, collision, buffer_later = tables["later"]
    assert collision == 0.0 and buffer_later == buffer > 0.0


def test_own_lane_floor_makes_stopping_cost_at_a_crawl_without_paying_for_lane_changes():
    """A free lane at 1 m/s: against the speed limit a stop loses ~0.1 of the progress term;
    against the best collision-free candidate of the own lane (own_lane_floor) it loses it
    all, while a neighbour lane's candidate that drives as far as the own lane's best gains
    nothing over it."""
    from adv3d_runner.autonomy.planner import PlannerConfig

    ego = EgoState([0.0, 0.0, 0.0], 1.0)
    planner = planner_on(straight_lanes(2), SamplingPlanner(PlannerConfig(own_lane_floor=5.0)))
    _, cands, table = planner.plan_with_scores(ego)
    labels = cands.spec.labels
    stop, go = labels.index("lane0/d+0.0/v0.0"), labels.index("lane0/d+0.0/v25.0")
    left = labels.index("left1/d+0.0/v25.0")
    own = table.raw["own_progress"]
    assert own[stop] > 0.8 and own[go] == 0.0 and own[left] == 0.0
    assert table.raw["progress"][stop] - table.raw["progress"][go] < own[stop] - own[go]


@pytest.mark.parametrize("leader_modes", ["expected", "nearest", "quantile"])
def test_actor_frenet_kernels_are_the_numpy_definition_bit_for_bit(rng, leader_modes):
    import dataclasses

    from adv3d_runner.autonomy.planner.proposals import (ActorForecast, ProposalConfig, _actor_frenet,
                                                         _actor_frenet_numpy)

    cs = _curving_corridors()
    config = dataclasses.replace(ProposalConfig(), leader_modes=leader_modes)

    class Spec:
        def __init__(self, corridor):
            self.corridor = corridor

        def __len__(self):
            return len(self.corridor)

    T, N, K = 50, 7, 4
    for _ in range(5):
        start = rng.uniform([0, -6], [120, 8], (N, 1, 1, 2))
        vel = rng.uniform([5, -1.5], [25, 1.5], (N, K, 1, 2))
        xy = start + vel * (0.1 * np.arange(T + 1))[None, None, :, None]
        poses = np.concatenate([xy, np.zeros((N, K, T + 1, 1))], axis=-1)
        probs = rng.dirichlet(np.ones(K) * 0.5, N)
        dims = np.c_[rng.uniform(3.5, 6.0, N), rng.uniform(1.6, 2.6, N)]
        actors = ActorForecast(poses, dims, probs, np.arange(N))
        corridor = rng.integers(0, 2, 21)
        target_d = rng.choice([-1.0, 0.0, 0.5, 1.0], 21)
        got = _actor_frenet(actors, cs, Spec(corridor), target_d, 1.9, config, T)
        want = _actor_frenet_numpy(actors, cs, Spec(corridor), target_d, 1.9, config, T)
        for x, y in zip(got, want):
            assert x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()
    assert got[0].shape[1] > 0  # some actor-modes lead somewhere


def _relaxing_planner(tau=20.0, min_headway=0.8):
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    cfg = PlannerConfig(proposals=replace(PlannerConfig().proposals, headway_relaxation=tau, min_headway=min_headway))
    return SamplingPlanner(cfg)


def _leader_at(gap, speed, ego_speed=14.0):
    """A car ``gap`` m (bumper to bumper) ahead of an ego at x = 0 in lane 0, driving at ``speed``."""
    car = lambda t: np.array([[gap + 0.5 * (4.6 + 4.6) + speed * t, 0.0, 4.6, 1.9, 0.0]])  # noqa: E731
    fut = np.stack([car((h + 1) * DT)[:, :2] for h in range(60)], axis=1)
    return actor_inputs(car(0.0), fut), EgoState([0.0, 0.0, 0.0], ego_speed, length=4.6, width=1.9)


def test_headway_relaxation_accepts_a_short_gap_that_is_not_closing_and_relaxes_it():
    """Dense real traffic (NGSIM US-101 train recording 8): the ego starts behind a car at
    its own speed of 14 m/s (about 16 m: 1.1 s). With the fixed 1.5 s headway the IDM brakes to open the gap to
    3 m + 21 m; with ``headway_relaxation`` the planner takes the headway it finds, (16 - 3) /
    14 s, and relaxes it back to 1.5 s over ``headway_relaxation`` seconds (one plan per 0.1 s)."""
    lanes = straight_lanes(2)
    (tracks, preds), ego = _leader_at(16.0, 14.0)
    fixed = planner_on(lanes).plan_with_scores(ego, preds, tracks)[1]
    planner = planner_on(lanes, _relaxing_planner(20.0))
    first = planner.plan_with_scores(ego, preds, tracks)[1]
    assert np.array_equal(first.accel, fixed.accel)  # the first plan has seen nothing yet
    found = planner._headway
    assert found == pytest.approx((16.0 - 3.0) / 14.0, abs=0.02)
    second = planner.plan_with_scores(ego, preds, tracks)[1]
    keep = fixed.spec.labels.index("lane0/d+0.0/v25.0")
    assert fixed.accel[keep, :10].min() < -1.0 and second.accel[keep, :10].min() > -0.5
    assert planner._headway == pytest.approx(found)  # the same gap again: found again
    # relaxes by dt x (1.5 - 0.8) / 20 per plan while the headway found is no shorter
    (tracks2, preds2), ego2 = _leader_at(40.0, 14.0)
    planner.plan_with_scores(ego2, preds2, tracks2)
    assert planner._headway == pytest.approx(found + 0.1 * 0.7 / 20.0, abs=1e-9)
    planner.reset(lanes)
    assert planner._headway is None


@pytest.mark.parametrize("gap, speed, why", [(13.0, 12.0, "closing in at 2 m/s"), (8.0, 14.0, "below min_headway")])
def test_headway_relaxation_does_not_accept_a_gap_the_ego_is_closing_or_too_short(gap, speed, why):
    lanes = straight_lanes(2)
    (tracks, preds), ego = _leader_at(gap, speed)
    planner = planner_on(lanes, _relaxing_planner(20.0))
    planner.plan_with_scores(ego, preds, tracks)
    assert planner._headway == pytest.approx(1.5), why


def test_firm_braking_threshold_decides_which_demands_build_up_at_the_brake_jerk():
    """``ProposalConfig.firm_braking``: only braking demanded harder than it builds up at
    ``max_brake_jerk``; by default that is ``idm_decel`` (the shipped planner's rule)."""
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    ego = EgoState(np.array([0.0, 0.0, 0.0]), 15.0, length=4.8, width=1.9)
    tracks, preds = actor_inputs(np.array([[40.0, 0.0, 4.6, 1.9, 0.0]]), np.tile([[40.0, 0.0]], (60, 1))[None])
    first = {}
    for firm in (None, 2.0, 50.0):
        cfg = PlannerConfig(proposals=replace(PlannerConfig().proposals, firm_braking=firm))
        _, cands, _ = planner_on(straight_lanes(1), SamplingPlanner(cfg)).plan_with_scores(ego, preds, tracks)
        first[firm] = cands.accel[cands.spec.labels.index("lane0/d+0.0/v25.0"), 0]
    pc = PlannerConfig().proposals
    assert first[None] == first[2.0] == pytest.approx(-pc.max_brake_jerk * DT)
    assert first[50.0] == pytest.approx(-pc.max_jerk * DT)  # no demand is "firm": the comfortable rate


def test_clearance_kernel_is_the_numpy_definition_bit_for_bit(rng):
    for T_actor in (20, 15):  # the actors' horizon as long as the ego's, and shorter (last pose held)
        ego = np.concatenate([rng.uniform([0, -4], [40, 4], (9, 20, 2)), rng.uniform(-4, 4, (9, 20, 1))], axis=-1)
        act = np.concatenate([rng.uniform([0, -6], [50, 6], (5, 3, T_actor, 2)),
                              rng.uniform(-4, 4, (5, 3, T_actor, 1))], axis=-1)
        act[1, 0, 3] = np.nan
        act[2, 1, :, :2] = ego[0, :T_actor, :2]  # centres on the ego's: overlapping boxes
        dims = np.c_[rng.uniform(3.5, 6.0, 5), rng.uniform(1.6, 2.6, 5)]
        for max_distance in (0.0, 3.0, 40.0):
            got = costs.clearance(ego, (4.6, 1.9), act, dims, max_distance)
            want = costs.clearance_numpy(ego, (4.6, 1.9), act, dims, max_distance)
            assert got.shape == want.shape and got.tobytes() == want.tobytes()
            assert np.isfinite(got).any() and (got == 0.0).any()


def test_yaw_from_motion_equals_its_numpy_version():
    """The compiled chord search against the numpy version it replaced (kept as
    ``_yaw_from_motion_numpy``), bit for bit: moving, standing, jittering and reversing actors,
    several modes, large map coordinates, steps of exactly the chord, non-finite input (the
    fallback) and empty shapes."""
    from adv3d_runner.autonomy.planner.planner import _yaw_from_motion, _yaw_from_motion_numpy

    rng = np.random.default_rng(8)
    for trial in range(80):
        N, K, T = int(rng.integers(1, 9)), int(rng.integers(1, 7)), int(rng.integers(1, 52))
        yaw0 = rng.uniform(-np.pi, np.pi, N)
        speed = rng.choice([0.0, 0.5, 3.0, 30.0], (N, K, 1))
        heading = yaw0[:, None, None] + rng.normal(0, 0.3, (N, K, 1))
        steps = np.stack([np.cos(heading), np.sin(heading)], -1) * speed[..., None] * 0.1
        steps = np.broadcast_to(steps, (N, K, T, 2)) + rng.normal(0, 0.05, (N, K, T, 2)) * (trial % 3)
        if trial % 4 == 0:
            steps = np.round(steps * 4) / 4  # exact multiples: progress ties and steps of the chord
        xy = rng.uniform(-5e3, 5e3, (N, 1, 1, 2)) * (trial % 2) + np.cumsum(steps, axis=2)
        if trial % 9 == 0:
            xy[rng.integers(0, N), 0, rng.integers(0, T), 0] = np.nan
        for chord in (0.25, 1.0, 2.0):
            want = _outcome(_yaw_from_motion_numpy, xy, yaw0, chord)  # NaN: numpy's search may raise
            got = _outcome(_yaw_from_motion, xy, yaw0, chord)
            assert got == want
    for shape in ((0, 3, 5, 2), (2, 0, 5, 2), (2, 3, 0, 2)):
        xy, yaw0 = np.zeros(shape), np.zeros(shape[0])
        assert _yaw_from_motion(xy, yaw0).tobytes() == _yaw_from_motion_numpy(xy, yaw0).tobytes()


def _outcome(f, *args):
    try:
        y = f(*args)
    except IndexError:
        return "IndexError"
    return y.shape, y.tobytes()


# ------------------------------------------------------- least-jerk following (docs/autonomy.md)

def test_smooth_profile_keeps_the_gap_without_a_hard_brake_and_holds_on_a_free_road():
    from adv3d_runner.autonomy.planner.smooth import free_road_speeds, smooth_profile

    k = np.arange(1, 51) * DT
    # free road: a gentle approach towards the IDM's free-road speeds, never faster
    free = smooth_profile(14.0, 0.0, 25.0, np.full(50, np.inf), 3.0, 1.5, DT, 1.5, 7.0)
    idm = free_road_speeds(14.0, 25.0, 1.5, 2.0, DT, 50)
    assert np.all(free >= -1e-9) and np.all(free <= 1.5 + 1e-6) and free.max() > 0.05
    assert np.all(14.0 + np.cumsum(free) * DT <= idm + 1e-9)
    # a car 16 m ahead at the ego's 14 m/s: the IDM's 3 m + 1.5 s gap is 8 m short; the profile
    # opens it over the recovery time at a gentle deceleration instead of braking now
    behind = smooth_profile(14.0, 0.0, 25.0, 16.0 + 14.0 * k, 3.0, 1.5, DT, 1.5, 7.0, recover=8.0)
    assert behind.min() > -1.0 and abs(behind[0]) < 0.2
    v = 14.0 + np.cumsum(behind) * DT
    s = np.cumsum(np.r_[14.0, v[:-1]] * DT + 0.5 * behind * DT * DT)
    assert np.all(16.0 + 14.0 * k - s > 3.0)  # never closer than the jam distance
    # a leader braking at 2 m/s^2 to 8 m/s, 20 m ahead: the ego slows without stopping or touching it
    lead = np.cumsum(np.maximum(14.0 - 2.0 * k, 8.0) * DT)
    brake = smooth_profile(14.0, 0.0, 25.0, 20.0 + lead, 3.0, 1.5, DT, 1.5, 7.0)
    v = 14.0 + np.cumsum(brake) * DT
    s = np.cumsum(np.r_[14.0, v[:-1]] * DT + 0.5 * brake * DT * DT)
    assert brake.min() > -3.0 and v.min() > 5.0 and np.all(20.0 + lead - s > 3.0)


def test_smooth_follow_adds_one_current_lane_candidate_that_plans_its_own_speed():
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    lanes = straight_lanes(2)
    (tracks, preds), ego = _leader_at(16.0, 14.0)
    cfg = PlannerConfig(proposals=replace(PlannerConfig().proposals, smooth_follow=True, smooth_cautious=False))
    cands = planner_on(lanes, SamplingPlanner(cfg)).plan_with_scores(ego, preds, tracks)[1]
    default = planner_on(lanes, idm_only()).plan_with_scores(ego, preds, tracks)[1]
    labels = cands.spec.labels
    assert labels.count("lane0/d+0.0/smooth") == 1 and len(labels) == len(default.spec.labels) + 1
    i, keep = labels.index("lane0/d+0.0/smooth"), labels.index("lane0/d+0.0/v25.0")
    others = [j for j in range(len(labels)) if j != i]
    assert np.array_equal(cands.accel[others], default.accel)  # the other candidates are unchanged
    assert cands.accel[keep, :10].min() < -1.0 and cands.accel[i, :10].min() > -0.6


# ------------------------------------------ stop easing and command resolution (docs/autonomy.md)

def _with(**proposals):
    from dataclasses import replace

    from adv3d_runner.autonomy.planner import PlannerConfig

    return SamplingPlanner(PlannerConfig(proposals=replace(PlannerConfig().proposals, **proposals)))


def test_stop_jerk_eases_the_brake_off_into_standstill():
    """At 14 m/s behind a car stopped 25 m ahead (one lane): without easing, the speed's clamp at
    0 ends the stop at full deceleration within a step (a jerk spike of tens of m/s^3); with
    ``stop_jerk`` the braking fades at about that jerk, and the ego still stops short of the car."""
    ego = EgoState([0.0, 0.0, 0.0], 14.0, length=4.6, width=1.9)
    peaks, gaps = {}, {}
    for j in (0.0, 4.0):
        boxes, act, speeds, plans = closed_loop(straight_lanes(1), ego, stopped_at((29.6, 0.0)), 9.0,
                                                _with(stop_jerk=j))
        acc = np.array([p.acceleration[0] for p in plans])
        assert speeds[-1] < 0.05  # stopped either way
        slow = np.flatnonzero(speeds < 3.0)
        peaks[j] = np.abs(np.diff(acc[slow[0] - 1:])).max() / DT
        gaps[j] = act[-1, 0, 0] - boxes[-1, 0] - 4.6
    assert peaks[0.0] > 10.0 and peaks[4.0] <= 4.0 + 1e-6
    assert gaps[4.0] > 1.0


def test_smooth_resolution_makes_small_input_changes_exact_no_ops():
    """The least-jerk candidate's executed acceleration moves from the present one in whole
    steps of ``smooth_resolution``: a leader a millimetre further away gives the same bits
    (without it, different ones), which is what lets an attack's static-hit cache serve the
    next frame."""
    lanes = straight_lanes(2)
    first = {}
    for res in (0.0, 0.05):
        out = []
        for gap in (20.0, 20.001):
            (tracks, preds), ego = _leader_at(gap, 14.0)
            ego = EgoState([0.0, 0.0, 0.0], 14.0, acceleration=-0.2, length=4.6, width=1.9)
            cands = planner_on(lanes, _with(smooth_resolution=res)).plan_with_scores(ego, preds, tracks)[1]
            out.append(cands.accel[cands.spec.labels.index("lane0/d+0.0/smooth"), 0])
        first[res] = out
    assert first[0.0][0] != first[0.0][1]
    assert first[0.05][0] == first[0.05][1]
    steps = (first[0.05][0] + 0.2) / 0.05
    assert abs(steps - round(steps)) < 1e-9 and abs(first[0.05][0] - first[0.0][0]) <= 0.025 + 1e-12


def test_smooth_speed_weights_add_one_least_jerk_candidate_each():
    """Each extra speed weight is one more least-jerk candidate; a larger weight keeps its
    profile closer to the free-road speeds (here: it brakes less behind a close car)."""
    lanes = straight_lanes(2)
    (tracks, preds), ego = _leader_at(16.0, 14.0)
    cands = planner_on(lanes, _with(smooth_speed_weights=(0.5, 2.0))).plan_with_scores(ego, preds, tracks)[1]
    labels = cands.spec.labels
    base, half, two = (labels.index(f"lane0/d+0.0/{s}") for s in ("smooth", "smooth-s0.5", "smooth-s2"))
    v = {i: 14.0 + np.cumsum(cands.accel[i]) * DT for i in (base, half, two)}
    assert v[base].mean() < v[half].mean() < v[two].mean()
    default = planner_on(lanes).plan_with_scores(ego, preds, tracks)[1]
    assert len(labels) == len(default.spec.labels) + 2
    assert np.array_equal(cands.accel[base], default.accel[default.spec.labels.index("lane0/d+0.0/smooth")])


def test_smooth_resolution_shrinks_with_speed_below_the_reference():
    """``smooth_resolution_speed``: at 1.5 m/s with a 10 m/s reference the step is 0.015 m/s^2
    instead of 0.1, so a crawl's small demands are followed."""
    lanes = straight_lanes(2)
    (tracks, preds), _ = _leader_at(4.0, 1.5, ego_speed=1.5)
    ego = EgoState([0.0, 0.0, 0.0], 1.5, acceleration=0.0, length=4.6, width=1.9)
    first = {}
    for ref in (0.0, 10.0):
        cands = planner_on(lanes, _with(smooth_resolution_speed=ref)).plan_with_scores(ego, preds, tracks)[1]
        first[ref] = cands.accel[cands.spec.labels.index("lane0/d+0.0/smooth"), 0]
    for ref, step in ((0.0, 0.1), (10.0, 0.015)):
        n = first[ref] / step
        assert abs(n - round(n)) < 1e-9, (ref, first[ref])
    assert first[0.0] != first[10.0]


# ------------------------------------------ the cautious least-jerk candidate (docs/autonomy.md)

def _leader_with_a_rare_stop(stop_prob):
    """A car 25 m (bumper to bumper) ahead of an ego at 14 m/s in lane 0, at 14 m/s itself; two
    predicted modes: it keeps its speed (1 - ``stop_prob``) or brakes at 4 m/s^2 to a standstill
    (``stop_prob``, below ``min_mode_prob`` here, so no IDM or ``smooth`` leader follows it)."""
    t = np.arange(1, 61) * DT
    x0 = 25.0 + 4.6
    keep = np.stack([x0 + 14.0 * t, 0 * t], -1)
    stop = np.stack([x0 + np.where(t < 3.5, 14.0 * t - 2.0 * t * t, 24.5), 0 * t], -1)
    now = np.array([[x0, 0.0, 4.6, 1.9, 0.0]])
    tracks = Tracks(np.array([7]), now, np.array([[14.0, 0.0]]), np.ones(1), np.zeros(1, np.int64),
                    np.zeros((1, 1, 3)), np.ones((1, 1), bool))
    preds = Predictions(np.array([7]), np.stack([keep, stop])[None], np.array([[1 - stop_prob, stop_prob]]))
    return tracks, preds, EgoState([0.0, 0.0, 0.0], 14.0, length=4.6, width=1.9)


def test_cautious_smooth_candidate_keeps_clear_of_every_mode_the_collision_term_counts():
    """A 5 % mode of the leader that stops is no IDM or ``smooth`` leader (``min_mode_prob``
    0.1), but the collision term counts it: the ``smooth`` profile behind the expected leader
    runs into it, the ``smooth-c`` profile behind every mode does not, and brakes less than the
    IDM's step-by-step reaction would in its first second. The other candidates are unchanged."""
    lanes = straight_lanes(1)
    tracks, preds, ego = _leader_with_a_rare_stop(0.05)
    plan, cands, table = planner_on(lanes, _with(smooth_cautious=True)).plan_with_scores(ego, preds, tracks)
    _, plain, _ = planner_on(lanes, _with(smooth_cautious=False)).plan_with_scores(ego, preds, tracks)
    labels = cands.spec.labels
    assert labels.count("lane0/d+0.0/smooth-c") == 1 and len(labels) == len(plain.spec.labels) + 1
    smooth, cautious = labels.index("lane0/d+0.0/smooth"), labels.index("lane0/d+0.0/smooth-c")
    assert table.raw["collision"][smooth] > 0.0
    assert table.raw["collision"][cautious] == 0.0
    others = [i for i in range(len(labels)) if i != cautious]
    assert np.array_equal(cands.accel[others], plain.accel)
    # it slows down behind the stopping mode (rear bumper at 25 + 24.5 m), the other does not
    assert cands.speeds[cautious, -1] < 0.5 * cands.speeds[smooth, -1]
    assert cands.s[cautious, -1] - cands.s[cautious, 0] < 25.0 + 24.5
    # without the stopping mode the cautious candidate is the smooth one, bit for bit
    tracks, preds, ego = _leader_with_a_rare_stop(0.0)
    cands = planner_on(lanes, _with(smooth_cautious=True)).plan_with_scores(ego, preds, tracks)[1]
    assert np.array_equal(cands.accel[cautious], cands.accel[smooth])


def test_cautious_smooth_candidate_is_chosen_where_the_smooth_one_collides():
    """Closed loop behind a car whose predictor gives a 5 % stopping mode every frame while it
    keeps 14 m/s: without ``smooth_cautious`` only the IDM candidates are collision-free behind
    that mode, and the ego brakes for it for 1.6 s; with it the least-jerk profile behind
    every mode wins most frames and the ego gives up less speed for a stop that never comes
    (a trade, not a free lunch: its acceleration changes sign twice in these 3 s)."""
    lanes = straight_lanes(1)
    speeds, chosen = {}, {}
    for flag in (False, True):
        planner = planner_on(lanes, _with(smooth_cautious=flag))
        ego, v, labels = EgoState([0.0, 0.0, 0.0], 14.0, length=4.6, width=1.9), [], []
        for k in range(30):
            tracks, preds, _ = _leader_with_a_rare_stop(0.05)
            lead_x = 14.0 * k * DT  # the leader in fact keeps its 14 m/s
            tracks = Tracks(tracks.ids, tracks.boxes + np.r_[lead_x, 0, 0, 0, 0], tracks.velocities, tracks.scores,
                            tracks.misses, tracks.history, tracks.history_valid)
            preds = Predictions(preds.track_ids, preds.trajectories + np.r_[lead_x, 0.0], preds.probabilities)
            plan = planner.plan(ego, preds, tracks)
            labels.append(plan.label)
            ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]),
                           length=4.6, width=1.9, time=(k + 1) * DT)
            v.append(ego.speed)
        speeds[flag], chosen[flag] = np.array(v), labels
    assert not any(lab.endswith("smooth-c") for lab in chosen[False])
    assert sum(lab.endswith("smooth-c") for lab in chosen[True]) >= 15
    assert speeds[True].min() > speeds[False].min() + 0.5
    assert speeds[True][-1] > speeds[False][-1] + 1.0


def test_cautious_smooth_candidate_changes_nothing_behind_single_mode_actors():
    """With one mode per actor (Autonomy-B's lane leaders, oracle forecasts) ``smooth-c`` has the
    ``smooth`` candidate's leader: its profile is reused, never solved again, and the tie goes to
    ``smooth`` (first in order), so every plan is the one without the option."""
    lanes = straight_lanes(2)
    (tracks, preds), ego = _leader_at(12.0, 11.0)
    plans = {}
    for flag in (False, True):
        plan, cands, _ = planner_on(lanes, _with(smooth_cautious=flag)).plan_with_scores(ego, preds, tracks)
        plans[flag] = plan
        if flag:
            labels = cands.spec.labels
            i, j = labels.index("lane0/d+0.0/smooth"), labels.index("lane0/d+0.0/smooth-c")
            assert np.array_equal(cands.accel[i], cands.accel[j])
    assert plans[True].label == plans[False].label
    assert np.array_equal(plans[True].trajectory, plans[False].trajectory)
