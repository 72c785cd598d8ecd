"""Occupancy and flow metrics (ImplicitO / Waymo occupancy-flow) on hand-made cases with known
answers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adv3d_runner.metrics.occupancy import (OccupancySample, flow_epe, flow_grounded, frame_terms, occupancy_ap,
                                            occupancy_metrics, occupancy_targets, points_in_boxes, soft_iou)


def test_points_in_boxes_rotated_and_overlapping():
    boxes = np.array([[0.0, 0.0, 4.0, 2.0, 0.0],            # x in [-2, 2], y in [-1, 1]
                      [10.0, 0.0, 4.0, 2.0, math.pi / 2],   # rotated: x in [9, 11], y in [-2, 2]
                      [1.5, 0.0, 2.0, 2.0, 0.0],            # overlaps the first one
                      [np.nan] * 5])
    pts = np.array([[0.0, 0.0], [-1.9, 0.9], [2.1, 0.0], [10.0, 1.9], [11.5, 0.0], [1.8, 0.0], [2.0, 1.0]])
    # (1.8, 0): in boxes 0 and 2, box 2's centre is nearer; (2, 1): on the corner of both (closed)
    assert points_in_boxes(pts, boxes).tolist() == [0, 0, 2, 1, -1, 2, 2]
    assert points_in_boxes(pts, np.zeros((0, 5))).tolist() == [-1] * len(pts)


def test_targets_translating_box_flow_is_its_velocity():
    now = np.array([[10.0, 2.0, 4.0, 2.0, 0.0]])
    before = np.array([[7.0, 2.5, 4.0, 2.0, 0.0]])  # 3 m and -0.5 m in 0.5 s
    occ, flow, valid = occupancy_targets(np.array([[10.0, 2.0], [11.5, 2.8], [20.0, 0.0]]), now, before, lag=0.5)
    assert occ.tolist() == [True, True, False] and valid.tolist() == [True, True, False]
    np.testing.assert_allclose(flow[:2], [[6.0, -1.0], [6.0, -1.0]])
    np.testing.assert_array_equal(flow[2], [0.0, 0.0])


def test_targets_rotating_box_moves_each_body_point():
    # a box turned by 90 degrees about its centre in 1 s: its front tip (2, 0) was at (0, -2)
    now = np.array([[0.0, 0.0, 4.0, 1.0, 0.0]])
    before = np.array([[0.0, 0.0, 4.0, 1.0, -math.pi / 2]])
    occ, flow, valid = occupancy_targets(np.array([[2.0, 0.0], [0.0, 0.0]]), now, before, lag=1.0)
    np.testing.assert_allclose(flow, [[2.0, 2.0], [0.0, 0.0]], atol=1e-12)
    assert valid.all()
    # an actor absent lag s earlier: occupied, flow unknown
    occ, flow, valid = occupancy_targets(np.array([[0.0, 0.0]]), now, np.full((1, 5), np.nan))
    assert occ.tolist() == [True] and valid.tolist() == [False]
    assert occupancy_targets(np.array([[0.0, 0.0]]), now, None)[2].tolist() == [False]


def test_soft_iou_known_values():
    o = np.array([1, 1, 0, 0], bool)
    assert soft_iou(o, np.array([1.0, 0.5, 0.5, 0.0])) == pytest.approx(1.5 / 2.5)
    assert soft_iou(o, o.astype(float)) == 1.0
    assert soft_iou(o, np.zeros(4)) == 0.0
    assert soft_iou(np.zeros(3, bool), np.zeros(3)) == 0.0            # empty: 0 (Waymo)
    assert soft_iou(np.zeros(3, bool), np.full(3, 0.4)) == 0.0


def test_average_precision_known_values():
    o = np.array([1, 0, 1, 0], bool)
    # ranks: TP (P 1, R .5), FP, TP (P 2/3, R 1): AP = .5 x 1 + .5 x 2/3
    assert occupancy_ap(o, np.array([0.9, 0.8, 0.7, 0.1])) == pytest.approx(0.5 + 1 / 3)
    assert occupancy_ap(o, np.array([0.9, 0.1, 0.8, 0.2])) == pytest.approx(1.0)
    # tied scores are one threshold: everything at once, precision 1/2
    assert occupancy_ap(np.array([1, 0], bool), np.array([0.5, 0.5])) == pytest.approx(0.5)
    assert math.isnan(occupancy_ap(np.zeros(3, bool), np.ones(3)))
    # the order of the query points does not matter
    rng = np.random.default_rng(0)
    oo, pp = rng.random(200) < 0.3, rng.random(200)
    perm = rng.permutation(200)
    assert occupancy_ap(oo, pp) == pytest.approx(occupancy_ap(oo[perm], pp[perm]))


def test_flow_epe_and_flow_grounded():
    ft = np.array([[3.0, 4.0], [1.0, 0.0], [9.0, 9.0]])
    fp = np.zeros((3, 2))
    assert flow_epe(ft, fp, np.array([True, True, False])) == pytest.approx(3.0)
    assert math.isnan(flow_epe(ft, fp, np.zeros(3, bool)))
    # a box at (0, 0) 0.5 s ago; the query (5, 0) traced back with 10 m/s lands in it, with 2 m/s not
    before = np.array([[0.0, 0.0, 4.0, 2.0, 0.0]])
    pts = np.array([[5.0, 0.0], [5.0, 0.0]])
    g = flow_grounded(np.array([0.8, 0.8]), np.array([[10.0, 0.0], [2.0, 0.0]]), pts, before, lag=0.5)
    np.testing.assert_allclose(g, [0.8, 0.0])


def _sample(t, occ, pred, flow_true=None, flow_pred=None, grounded=None):
    n = len(occ)
    z = np.zeros((n, 2))
    return OccupancySample(t, np.asarray(occ, bool), np.asarray(pred, float),
                           z if flow_true is None else np.asarray(flow_true, float),
                           z if flow_pred is None else np.asarray(flow_pred, float), np.asarray(occ, bool),
                           None if grounded is None else np.asarray(grounded, float))


def test_pooled_metrics_per_time_then_mean():
    # t = 0: perfect; t = 1 over two frames: AP 0.5 + 1/3 (pooled), Soft-IoU 1/3
    s = [_sample(0.0, [1, 0], [1.0, 0.0], [[2.0, 0.0], [0, 0]], [[2.0, 0.0], [0, 0]], grounded=[1.0, 0.0]),
         _sample(1.0, [1, 0], [0.9, 0.8], [[4.0, 0.0], [0, 0]], [[1.0, 0.0], [0, 0]]),
         _sample(1.0, [1, 0], [0.7, 0.1])]
    m = occupancy_metrics(s)
    assert m["times"] == [0.0, 1.0] and m["n_queries"] == 6 and m["n_occupied"] == 3
    assert m["per_time"]["1"]["ap"] == pytest.approx(0.5 + 1 / 3)
    assert m["map"] == pytest.approx((1.0 + 0.5 + 1 / 3) / 2)
    iou1 = (0.9 + 0.7) / (0.9 + 0.8 + 0.7 + 0.1 + 2 - 0.9 - 0.7)
    assert m["soft_iou"] == pytest.approx((1.0 + iou1) / 2)
    assert m["epe"] == pytest.approx((0.0 + 3.0 + 0.0) / 3)  # three occupied points with a known flow
    # flow-grounded: only the slice that has it (t = 0)
    assert m["flow_grounded_map"] == 1.0 and m["flow_grounded_soft_iou"] == 1.0
    assert occupancy_metrics([])["map"] is None


def test_frame_terms_are_the_objective_terms():
    s = [_sample(0.0, [1, 1, 0, 0], [1.0, 0.5, 0.5, 0.0], [[3.0, 4.0], [1.0, 0.0], [0, 0], [0, 0]])]
    iou, epe = frame_terms(s)
    assert iou == pytest.approx(0.6) and epe == pytest.approx(3.0)
    assert frame_terms([]) == (0.0, 0.0)
    assert frame_terms([_sample(0.0, [0, 0], [0.2, 0.1])]) == (0.0, 0.0)
