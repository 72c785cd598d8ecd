"""Tracker: births, missed detections, deaths, empty frames, crossing objects; interface containers."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.autonomy.interface import Detections, EgoState, Plan, Predictions, Tracks
from adv3d_runner.autonomy.tracker import MultiObjectTracker, TrackerConfig

DT = 0.1


def dets(*centres, yaw=0.0, score=0.9):
    if not centres:
        return Detections()
    c = np.asarray(centres, float).reshape(-1, 2)
    return Detections(np.c_[c, np.full(len(c), 4.5), np.full(len(c), 1.9), np.full(len(c), yaw)], np.full(len(c), score))


def test_birth_needs_min_hits_and_ids_are_stable():
    tr = MultiObjectTracker(TrackerConfig(min_hits=3))
    assert len(tr.update(dets([0, 0]))) == 0
    assert len(tr.update(dets([2, 0]))) == 0
    out = tr.update(dets([4, 0]))
    assert len(out) == 1
    tid = int(out.ids[0])
    for k in range(3, 20):
        out = tr.update(dets([2.0 * k, 0]))
        assert out.ids.tolist() == [tid]
    assert out.velocities[0] == pytest.approx([20.0, 0.0], abs=0.5)  # 2 m per 0.1 s


def test_missed_detections_keep_the_track_then_it_dies():
    cfg = TrackerConfig(min_hits=2, max_misses=3)
    tr = MultiObjectTracker(cfg)
    for k in range(10):
        out = tr.update(dets([25.0 * k * DT, 3.0]))
    tid = int(out.ids[0])
    # three missed frames: the track coasts at its velocity
    for m in range(1, 4):
        out = tr.update(dets())
        assert out.ids.tolist() == [tid] and out.misses[0] == m
        assert out.boxes[0, 0] == pytest.approx(25.0 * (9 + m) * DT, abs=0.5)
    # detection comes back where the object really is: same identity
    out = tr.update(dets([25.0 * 13 * DT, 3.0]))
    assert out.ids.tolist() == [tid] and out.misses[0] == 0
    # now four misses in a row: dead
    for _ in range(4):
        out = tr.update(dets())
    assert len(out) == 0


def test_empty_frames_and_garbage_detections():
    tr = MultiObjectTracker()
    for _ in range(5):
        out = tr.update(Detections())
        assert len(out) == 0 and out.boxes.shape == (0, 5) and out.history.shape[0] == 0
    bad = Detections(np.array([[np.nan, 0, 4, 2, 0], [0, 0, 4, 2, 0]]), np.array([0.9, np.nan]))
    assert len(tr.update(bad)) == 0  # both rows dropped, nothing born
    assert tr.frame == 6


def test_two_crossing_objects_keep_identities():
    tr = MultiObjectTracker()
    ids_a, ids_b = set(), set()
    for k in range(40):
        t = k * DT
        # A drives +x, B drives diagonally across A's path; they pass 1 m apart at k = 20
        a = [20.0 * t, 0.0]
        b = [20.0 * t + 1.0, -10.0 + 5.0 * t]
        order = [a, b] if k % 2 == 0 else [b, a]  # detection order must not matter
        out = tr.update(dets(*order))
        if len(out) == 2:
            for tid, box in zip(out.ids, out.boxes):
                near_a = np.hypot(*(box[:2] - a)) < np.hypot(*(box[:2] - b))
                (ids_a if near_a else ids_b).add(int(tid))
    assert len(ids_a) == 1 and len(ids_b) == 1 and ids_a != ids_b


def test_history_for_the_predictor():
    cfg = TrackerConfig(history=5, min_hits=1)
    tr = MultiObjectTracker(cfg)
    out = None
    for k in range(3):
        out = tr.update(dets([float(k), 0.0]))
    assert out.history.shape == (1, 5, 3)
    assert out.history_valid[0].tolist() == [False, False, True, True, True]
    assert np.all(np.isfinite(out.history))
    assert out.history[0, -1, 0] == pytest.approx(out.boxes[0, 0])
    for k in range(3, 10):
        out = tr.update(dets([float(k), 0.0]))
    assert out.history_valid.all()
    assert np.all(np.diff(out.history[0, :, 0]) > 0)  # oldest first


def test_reset_restarts_ids():
    tr = MultiObjectTracker(TrackerConfig(min_hits=1))
    first = tr.update(dets([0, 0])).ids.tolist()
    tr.reset()
    assert tr.update(dets([50, 50])).ids.tolist() == first


def test_interface_containers_validate_shapes():
    with pytest.raises(ValueError):
        Detections(np.zeros((2, 4)), np.zeros(2))
    with pytest.raises(ValueError):
        Detections(np.zeros((2, 5)), np.zeros(3))
    d = dets([1, 2], [3, 4])
    assert len(d) == 2 and d[1].score == pytest.approx(0.9) and len(Detections.from_list(list(d))) == 2
    with pytest.raises(ValueError):
        Predictions(np.array([1]), np.zeros((2, 3, 60, 2)), np.ones((2, 3)) / 3)
    p = Predictions(np.array([4, 5]), np.zeros((2, 3, 60, 2)), np.ones((2, 3)) / 3)
    assert p.num_modes == 3 and p.horizon == 60
    with pytest.raises(ValueError):
        Plan(np.zeros((5, 3)), np.zeros(4))
    assert EgoState([0, 0, 0], -1.0).speed == 0.0
    assert len(Tracks()) == 0


def test_constant_velocity_predictor_from_tracks():
    from adv3d_runner.autonomy.baselines import ConstantVelocityPredictor
    from adv3d_runner.metrics.prediction import prediction_metrics

    tr = MultiObjectTracker()
    for k in range(15):
        out = tr.update(dets([10.0 + 20.0 * k * DT, 3.5]))
    pred = ConstantVelocityPredictor().predict(out)
    assert pred.trajectories.shape == (1, 3, 60, 2) and pred.probabilities.sum() == pytest.approx(1.0)
    truth = np.c_[10.0 + 20.0 * (14 + np.arange(1, 61)) * DT, np.full(60, 3.5)][None]
    m = prediction_metrics(pred.trajectories, truth)
    assert m.min_ade < 0.5  # the constant-velocity mode is right for a constant-velocity object
    assert m.mean_ade > m.min_ade
    empty = ConstantVelocityPredictor().predict(Tracks())
    assert empty.trajectories.shape == (0, 3, 60, 2)


def test_prior_speed_for_new_tracks():
    tr = MultiObjectTracker(TrackerConfig(min_hits=1))
    out = tr.update(dets([0.0, 0.0], yaw=np.pi / 2), prior_speed=25.0)
    assert out.velocities[0] == pytest.approx([0.0, 25.0], abs=1e-9)
    tr.reset()
    assert tr.update(dets([0.0, 0.0])).velocities[0].tolist() == [0.0, 0.0]


def test_lane_following_predictor_keeps_the_lane():
    from adv3d_runner.autonomy.baselines import LaneFollowingPredictor
    from adv3d_runner.scene.lanemap import LaneMap
    from adv3d_runner.scene.schema import Lane

    R = 200.0
    th = np.linspace(0.0, 1.5, 80)
    lane = Lane(0, np.c_[R * np.sin(th), R * (1 - np.cos(th))], 3.7, speed_limit=30.0)
    far = Lane(1, np.array([[0.0, 500.0], [10.0, 500.0]]), 3.7)
    # a track 0.5 m left of the lane centre at s = 40 m, heading slightly wrong, 20 m/s
    s0 = 40.0
    p = np.array([R * np.sin(s0 / R), R * (1 - np.cos(s0 / R))])
    normal = np.array([-np.sin(s0 / R), np.cos(s0 / R)])
    xy = p + 0.5 * normal
    yaw = s0 / R + 0.03
    tracks = Tracks(np.array([3, 4]), np.array([[*xy, 4.5, 1.9, yaw], [0.0, -40.0, 4.5, 1.9, 0.0]]),
                    np.array([[20 * np.cos(yaw), 20 * np.sin(yaw)], [10.0, 0.0]]), np.ones(2), np.zeros(2, np.int64),
                    np.zeros((2, 1, 3)), np.ones((2, 1), bool))
    lfp = LaneFollowingPredictor()
    lfp.reset(LaneMap([lane, far]))
    pred = lfp.predict(tracks)
    assert pred.trajectories.shape == (2, 3, 60, 2) and np.all(np.isfinite(pred.trajectories))
    radial = np.hypot(pred.trajectories[0, :, :, 0], pred.trajectories[0, :, :, 1] - R)
    assert np.allclose(radial, R - 0.5, atol=0.05)  # stays 0.5 m left of the centre line (inside the curve)
    arc = R * np.arctan2(pred.trajectories[0, 0, -1, 0], R - pred.trajectories[0, 0, -1, 1])
    assert arc == pytest.approx(s0 + 20 * np.cos(0.03) * 6.0, rel=1e-3)  # speed along the heading, along the lane
    # the off-road track falls back to constant velocity
    assert np.allclose(pred.trajectories[1, 0, -1], [60.0, -40.0])


def test_modular_stack_runs_the_chain_in_the_map_frame():
    from adv3d_runner.autonomy.interface import AutonomyStack, SceneContext
    from adv3d_runner.autonomy.modular import ModularStack
    from adv3d_runner.scene.schema import Lane

    class OracleDetector:
        """Sees one car 30 m ahead of the ego whenever there are points."""

        def detect(self, points):
            if len(points) == 0:
                return Detections()
            return Detections(np.array([[30.0, 0.0, 4.5, 1.9, 0.0]]), np.array([0.95]))

    xs = np.linspace(-100.0, 600.0, 71)
    lanes = [Lane(0, np.c_[xs, np.full_like(xs, 10.0)], 3.7, speed_limit=25.0)]
    stack = ModularStack(OracleDetector())
    assert isinstance(stack, AutonomyStack)
    with pytest.raises(RuntimeError, match="reset"):  # no lane map yet
        stack.step(np.ones((10, 4)), EgoState([100.0, 10.0, 0.0], 20.0))
    context = SceneContext.from_lanes(lanes)
    stack.reset(context)
    ego = EgoState([100.0, 10.0, 0.0], 20.0)
    pts = np.ones((10, 4))
    for k in range(3):
        seen_from = ego.pose.copy()
        stack.observe_ground_truth(np.zeros((0, 5)), np.zeros(0, np.int64))  # ignored: not an oracle
        out = stack.step(pts, ego)
        ego = EgoState(out.plan.trajectory[1], out.plan.speed[1], acceleration=float(out.plan.acceleration[0]))
    assert out.detections.boxes[0, :2] == pytest.approx(seen_from[:2] + [30.0, 0.0], abs=1e-6)  # map frame
    assert len(out.tracks) == 1 and out.predictions.trajectories.shape == (1, 3, 60, 2)
    assert set(out.timings) == {"detector", "tracker", "predictor", "planner"}
    assert out.plan.cost_terms["collision"] == 0.0
    empty = stack.step(np.zeros((0, 4)), ego)  # a frame without points
    assert len(empty.detections) == 0 and len(empty.tracks) == 1 and empty.tracks.misses[0] == 1
    stack.reset(context)
    assert len(stack.step(np.zeros((0, 4)), ego).tracks) == 0
