"""The IDM's jam distance while the ego moves off behind a queue's leader
(``ProposalConfig.moveoff_gap``, ``proposals.moveoff_jam_gap``; docs/autonomy.md)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from adv3d_runner.autonomy.interface import EgoState
from adv3d_runner.autonomy.planner import PlannerConfig, SamplingPlanner
from adv3d_runner.autonomy.planner.proposals import moveoff_jam_gap
from adv3d_runner.metrics.comfort import collisions

from test_planner import DT, actor_inputs, closed_loop, planner_on, straight_lanes


def _planner(gap: float) -> SamplingPlanner:
    base = PlannerConfig()
    return SamplingPlanner(replace(base, proposals=replace(base.proposals, moveoff_gap=gap)))


def test_jam_gap_falls_only_while_the_ego_is_slow_and_the_leader_pulls_away():
    s0, low, v_ref, dv = 3.0, 2.0, 3.0, 1.0
    assert moveoff_jam_gap(s0, 0.0, 2.0, low, v_ref, dv) == pytest.approx(2.0)  # standing, leader rolls
    assert moveoff_jam_gap(s0, 0.0, 0.5, low, v_ref, dv) == pytest.approx(2.5)  # half the speed lead: half
    assert moveoff_jam_gap(s0, 1.5, 3.0, low, v_ref, dv) == pytest.approx(2.5)  # half way to v_ref: half
    assert moveoff_jam_gap(s0, 0.0, 0.0, low, v_ref, dv) == s0  # the leader stands: unchanged
    assert moveoff_jam_gap(s0, 2.0, 1.0, low, v_ref, dv) == s0  # closing in (a stop): unchanged
    assert moveoff_jam_gap(s0, 3.0, 8.0, low, v_ref, dv) == s0  # at moveoff_speed: unchanged
    assert moveoff_jam_gap(s0, 0.0, 2.0, 0.0, v_ref, dv) == s0  # off
    assert moveoff_jam_gap(s0, 0.0, 2.0, 3.5, v_ref, dv) == s0  # above the jam distance: off
    # continuous where the rule starts and ends
    assert moveoff_jam_gap(s0, 3.0 - 1e-9, 8.0, low, v_ref, dv) == pytest.approx(s0, abs=1e-6)
    assert moveoff_jam_gap(s0, 1.0, 1.0 + 1e-9, low, v_ref, dv) == pytest.approx(s0, abs=1e-6)


def _rolling_leader(x0: float, start: float, accel: float):
    """A car standing at ``x0`` that moves off at ``start`` s with ``accel`` m/s^2 up to 3 m/s."""
    def boxes(t: float) -> np.ndarray:
        tau = max(t - start, 0.0)
        t_top = 3.0 / accel
        x = x0 + (0.5 * accel * tau ** 2 if tau < t_top else 0.5 * accel * t_top ** 2 + 3.0 * (tau - t_top))
        return np.array([[x, 0.0, 4.6, 1.9, 0.0]])
    return boxes


def _first_move(speeds: np.ndarray, threshold: float = 0.3) -> float:
    moving = np.flatnonzero(speeds > threshold)
    return float(moving[0]) * DT if len(moving) else np.inf


def test_standing_ego_moves_off_with_a_rolling_leader_instead_of_waiting_for_the_jam_gap():
    """Standing 2.5 m (bumper to bumper) behind a car that rolls off at 1 m/s^2 after 0.5 s: the
    plain IDM (s0 = 3 m) holds the ego until the leader has opened the gap past 3 m; with the
    move-off jam distance it rolls off about a second earlier, drives further in 5 s, and keeps
    more than 1.5 m to the leader."""
    lanes = straight_lanes(1)
    ego = EgoState([0.0, 0.0, 0.0], 0.0, length=4.8, width=1.9)
    leader = _rolling_leader(0.5 * 4.8 + 2.5 + 0.5 * 4.6, 0.5, 1.0)
    runs = {}
    for gap in (0.0, 2.0):
        ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, leader, 5.0, planner=_planner(gap))
        rep = collisions(ego_boxes, act_boxes)
        assert not rep.collided
        runs[gap] = (_first_move(speeds), float(ego_boxes[-1, 0] - ego_boxes[0, 0]), rep.min_distance)
    (t_off, dist_off, _), (t_on, dist_on, clear_on) = runs[0.0], runs[2.0]
    assert t_on <= t_off - 0.5, runs
    assert dist_on >= dist_off + 1.0, runs
    assert clear_on > 1.5, runs


def test_behind_a_standing_car_the_plans_are_unchanged():
    """The leader stands (a queue not yet moving) or the ego closes in on it (a stop): the jam
    distance is the IDM's, and every candidate's acceleration is the same with the rule on."""
    lanes = straight_lanes(1)
    for speed, x_lead in ((0.0, 7.3), (4.0, 20.0)):
        ego = EgoState([0.0, 0.0, 0.0], speed, length=4.8, width=1.9)
        now = np.array([[x_lead, 0.0, 4.6, 1.9, 0.0]])
        tracks, preds = actor_inputs(now, np.repeat(now[:, None, :2], 60, axis=1))
        a_off = planner_on(lanes, _planner(0.0)).plan_with_scores(ego, preds, tracks)[1].accel
        a_on = planner_on(lanes, _planner(2.0)).plan_with_scores(ego, preds, tracks)[1].accel
        assert np.array_equal(a_off, a_on)


def test_config_refuses_a_negative_moveoff_gap():
    from adv3d_runner.autonomy.planner import ProposalConfig

    with pytest.raises(ValueError, match="moveoff_gap"):
        ProposalConfig(moveoff_gap=-1.0)
    with pytest.raises(ValueError, match="moveoff_speed"):
        ProposalConfig(moveoff_speed=0.0)


def test_the_rule_switched_off_is_left_out_of_the_planner_fingerprint():
    """Off (``moveoff_gap`` 0), the plans are those of the planner before the rule (the jam
    distance is ``idm_gap`` exactly), so its fields are not hashed: kept runs stay valid. On, they
    are."""
    import dataclasses

    from adv3d_runner.autonomy.planner import ProposalConfig
    from adv3d_runner.autonomy.planner.proposals import fingerprint_fields

    off = fingerprint_fields(dataclasses.asdict(ProposalConfig(moveoff_gap=0.0)))
    on = fingerprint_fields(dataclasses.asdict(ProposalConfig(moveoff_gap=2.0)))
    assert not {"moveoff_gap", "moveoff_speed", "moveoff_dv"} & set(off)
    assert on["moveoff_gap"] == 2.0 and on["moveoff_speed"] == ProposalConfig().moveoff_speed
    assert set(on) - set(off) == {"moveoff_gap", "moveoff_speed", "moveoff_dv"}


def _moveoff_planner(**fields) -> SamplingPlanner:
    base = PlannerConfig()
    return SamplingPlanner(replace(base, proposals=replace(base.proposals, moveoff_gap=2.0, **fields)))


def test_an_ego_that_stopped_closer_than_the_moveoff_gap_moves_off_with_moveoff_stand():
    """Stopped 1.5 m (bumper to bumper) behind a car that rolls off at 1 m/s^2 after 0.3 s (an
    ego that rolled into the queue stops closer than ``moveoff_gap``): with the lower jam distance
    at most 0.9 of the gap now (``moveoff_stand``) it starts rolling at least 0.5 s earlier and
    drives further in 4 s than with ``moveoff_gap`` alone (which holds it until the gap has grown
    past 2 m), and keeps more than 1 m to the leader."""
    lanes = straight_lanes(1)
    ego = EgoState([0.0, 0.0, 0.0], 0.0, length=4.8, width=1.9)
    leader = _rolling_leader(0.5 * 4.8 + 1.5 + 0.5 * 4.6, 0.3, 1.0)
    runs = {}
    for stand in (0.0, 0.9):
        ego_boxes, act_boxes, speeds, _ = closed_loop(lanes, ego, leader, 4.0,
                                                      planner=_moveoff_planner(moveoff_stand=stand))
        rep = collisions(ego_boxes, act_boxes)
        assert not rep.collided
        runs[stand] = (_first_move(speeds, 0.01), float(ego_boxes[-1, 0] - ego_boxes[0, 0]), rep.min_distance)
    (t_plain, dist_plain, _), (t_stand, dist_stand, clear) = runs[0.0], runs[0.9]
    assert t_stand <= t_plain - 0.5, runs
    assert dist_stand > dist_plain + 0.05, runs
    assert clear > 1.0, runs


def test_moveoff_start_only_leaves_a_slow_follow_behind_a_slower_leader_unchanged():
    """An ego at 2.5 m/s 6 m behind a leader at 1.5 m/s (slowing behind a slower car, below
    ``moveoff_speed``): the rule does not hold now, but the rollouts that slow below the leader's
    speed later apply it in their later steps, which changes the candidates; with
    ``moveoff_start_only`` every candidate is the one without the rule."""
    lanes = straight_lanes(1)
    ego = EgoState([0.0, 0.0, 0.0], 2.5, length=4.8, width=1.9)
    x_lead = 0.5 * 4.8 + 6.0 + 0.5 * 4.6
    now = np.array([[x_lead, 0.0, 4.6, 1.9, 0.0]])
    future = np.stack([np.c_[x_lead + 1.5 * DT * np.arange(1, 61), np.zeros(60)]])
    tracks, preds = actor_inputs(now, future)

    def accel(planner):
        return planner_on(lanes, planner).plan_with_scores(ego, preds, tracks)[1].accel

    off = accel(_planner(0.0))
    assert not np.array_equal(accel(_moveoff_planner()), off)
    assert np.array_equal(accel(_moveoff_planner(moveoff_start_only=True)), off)


def test_the_moveoff_refinements_switched_off_are_left_out_of_the_fingerprint():
    import dataclasses

    from adv3d_runner.autonomy.planner import ProposalConfig
    from adv3d_runner.autonomy.planner.proposals import fingerprint_fields

    plain = fingerprint_fields(dataclasses.asdict(ProposalConfig(moveoff_gap=2.0)))
    assert not {"moveoff_stand", "moveoff_start_only"} & set(plain)
    both = fingerprint_fields(dataclasses.asdict(ProposalConfig(moveoff_gap=2.0, moveoff_stand=0.9,
                                                                moveoff_start_only=True)))
    assert both["moveoff_stand"] == 0.9 and both["moveoff_start_only"] is True
    off = fingerprint_fields(dataclasses.asdict(ProposalConfig(moveoff_stand=0.9, moveoff_start_only=True)))
    assert not {"moveoff_gap", "moveoff_stand", "moveoff_start_only"} & set(off)
    with pytest.raises(ValueError, match="moveoff_stand"):
        ProposalConfig(moveoff_stand=1.0)
