"""Metrics against hand-computed cases: rotated-box IoU, AP/recall, ADE, comfort, collisions."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adv3d_runner.geometry import boxes as bx
from adv3d_runner.geometry import frames as fr
from adv3d_runner.metrics import comfort as cf
from adv3d_runner.metrics import detection as det
from adv3d_runner.metrics import prediction as pred


def box(x, y, l, w, yaw=0.0):
    return np.array([[x, y, l, w, yaw]], dtype=float)


# ------------------------------------------------------------------ reference clipping

def _clip_ref(subject, clip):
    """Sutherland-Hodgman in plain Python (slow reference) for convex CCW polygons."""
    out = [tuple(p) for p in subject]
    for i in range(len(clip)):
        a, b = clip[i], clip[(i + 1) % len(clip)]
        inp, out = out, []
        if not inp:
            break

        def inside(p):
            return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= 0

        def inter(p, q):
            x1, y1, x2, y2 = *p, *q
            x3, y3, x4, y4 = *a, *b
            den = (x1 - x2) * (y3 - y4) - (y1 - y2) * (x3 - x4)
            t = ((x1 - x3) * (y3 - y4) - (y1 - y3) * (x3 - x4)) / den
            return (x1 + t * (x2 - x1), y1 + t * (y2 - y1))

        for j in range(len(inp)):
            p, q = inp[j], inp[(j + 1) % len(inp)]
            if inside(q):
                if not inside(p):
                    out.append(inter(p, q))
                out.append(q)
            elif inside(p):
                out.append(inter(p, q))
    if len(out) < 3:
        return 0.0
    return abs(float(bx.polygon_area(np.array(out))))


# ------------------------------------------------------------------ boxes

def test_corners_ccw_and_area():
    c = bx.box_corners(box(1, 2, 4, 2, 0.3))[0]
    assert bx.polygon_area(c) == pytest.approx(8.0)  # positive: counter-clockwise
    assert np.allclose(c.mean(axis=0), [1, 2])
    assert bx.box_areas(box(0, 0, -1, 2))[0] == 0.0


@pytest.mark.parametrize("b, expected", [
    (box(0, 0, 2, 2), 1.0),                                   # identical
    (box(1, 0, 2, 2), 2.0 / 6.0),                             # half overlap: 2 / (4 + 4 - 2)
    (box(2, 0, 2, 2), 0.0),                                   # touching edges
    (box(2, 2, 2, 2), 0.0),                                   # touching corners
    (box(0, 0, 1, 1), 0.25),                                  # nested
    (box(0, 0, 1, 1, 0.7), 0.25),                             # nested, rotated
    (box(0, 0, 2, 2, math.pi / 4), (8 * (math.sqrt(2) - 1)) / (8 - 8 * (math.sqrt(2) - 1))),  # 45 deg octagon
    (box(0, 0, 2, 2, math.pi / 2), 1.0),                      # a square rotated by 90 deg is itself
    (box(0, 0, 0, 2), 0.0),                                   # zero length
    (box(0, 0, 0, 0), 0.0),                                   # a point
    (box(np.nan, 0, 2, 2), 0.0),                              # garbage
])
def test_iou_hand_cases(b, expected):
    a = box(0, 0, 2, 2)
    assert bx.iou_pairwise(a, b)[0, 0] == pytest.approx(expected, abs=1e-12)
    assert bx.iou_pairwise(b, a)[0, 0] == pytest.approx(expected, abs=1e-12)
    assert bx.iou_paired(a, b)[0] == pytest.approx(expected, abs=1e-12)


def test_iou_zero_area_pair_and_empty_inputs():
    z = box(0, 0, 0, 0)
    assert bx.iou_pairwise(z, z)[0, 0] == 0.0
    assert bx.iou_pairwise(np.zeros((0, 5)), box(0, 0, 1, 1)).shape == (0, 1)
    assert bx.iou_pairwise(box(0, 0, 1, 1), np.zeros((0, 5))).shape == (1, 0)


def test_iou_large_coordinates_keep_precision():
    off = np.array([[4.5e5, -3.2e5, 0, 0, 0]])
    a, b = box(0, 0, 4, 2, 0.2), box(0.7, 0.3, 4.5, 1.8, -0.4)
    assert bx.iou_pairwise(a + off, b + off)[0, 0] == pytest.approx(bx.iou_pairwise(a, b)[0, 0], abs=1e-9)


def test_iou_random_against_reference(rng):
    A = np.c_[rng.uniform(-2, 2, (60, 2)), rng.uniform(0.2, 4, (60, 2)), rng.uniform(-4, 4, 60)]
    B = np.c_[rng.uniform(-2, 2, (50, 2)), rng.uniform(0.2, 4, (50, 2)), rng.uniform(-4, 4, 50)]
    inter = bx.intersection_area_pairwise(A, B)
    ca, cb = bx.box_corners(A), bx.box_corners(B)
    for i, j in zip(rng.integers(0, 60, 150), rng.integers(0, 50, 150)):
        assert inter[i, j] == pytest.approx(_clip_ref(ca[i], cb[j]), abs=1e-9)
    iou = bx.iou_pairwise(A, B)
    assert np.all(np.isfinite(iou)) and iou.min() >= 0 and iou.max() <= 1
    assert np.allclose(iou, bx.iou_pairwise(B, A).T)
    assert (iou > 0).sum() > 100  # the sample really exercises overlapping pairs


def test_box_distance_and_overlap():
    a = box(0, 0, 2, 2)
    assert bx.box_distance(a, box(5, 0, 2, 2))[0] == pytest.approx(3.0)
    # 45-deg square at (3, 3), half diagonal sqrt(2): its nearest edge lies on x + y = 6 - sqrt(2),
    # the nearest point of the unit square is its corner (1, 1)
    d = bx.box_distance(a, box(3, 3, 2, 2, math.pi / 4))[0]
    assert d == pytest.approx((3 + 3 - math.sqrt(2) - 2) / math.sqrt(2), abs=1e-9)
    assert bx.box_distance(a, box(2, 0, 2, 2))[0] == 0.0  # touching
    assert not bx.boxes_overlap(a, box(2, 0, 2, 2))[0]
    assert bx.boxes_overlap(a, box(1.9, 0, 2, 2))[0]
    assert bx.box_distance(a, box(0.5, 0, 1, 1))[0] == 0.0  # nested
    assert bx.box_distance(a, box(np.nan, 0, 1, 1))[0] == np.inf


def test_frame_round_trip(rng):
    b = np.c_[rng.uniform(-50, 50, (10, 2)), rng.uniform(1, 5, (10, 2)), rng.uniform(-3, 3, 10)]
    pose = np.array([12.0, -7.0, 2.5])
    back = fr.boxes_from_frame(fr.boxes_to_frame(b, pose), pose)
    assert np.allclose(back[:, :4], b[:, :4])
    assert np.allclose(np.cos(back[:, 4] - b[:, 4]), 1.0)


# ------------------------------------------------------------------ detection

def _ap_example():
    """Two frames, 3 GT boxes, 5 detections: scores .9 TP, .8 FP, .7 TP, .6 TP (IoU 0.6), .5 FP (dup)."""
    gt1 = np.array([[0, 0, 4, 2, 0], [20, 0, 4, 2, 0]], float)
    det1 = np.array([[0, 0, 4, 2, 0], [40, 5, 4, 2, 0], [21, 0, 4, 2, 0]], float)  # last: IoU 6/10
    sc1 = np.array([0.9, 0.8, 0.6])
    gt2 = np.array([[10, 3, 4, 2, 0]], float)
    det2 = np.array([[10, 3, 4, 2, 0], [10, 3, 4, 2, 0]], float)
    sc2 = np.array([0.7, 0.5])
    return [(gt1, det1, sc1), (gt2, det2, sc2)]


def test_ap_hand_worked():
    # sorted: TP FP TP TP FP -> precision 1 .5 .667 .75 .6, recall 1/3 1/3 2/3 1 1
    # envelope: 1 on (0, 1/3], .75 on (1/3, 1]  ->  AP = 1/3 + 2/3 * .75 = 0.8333
    m = det.average_precision(_ap_example())
    assert m.ap == pytest.approx(1 / 3 + 2 / 3 * 0.75)
    assert m.recall == 1.0 and m.n_gt == 3 and m.n_det == 5 and m.n_tp == 3


def test_ap_edge_cases():
    g = np.array([[0, 0, 4, 2, 0]], float)
    perfect = det.average_precision([(g, g, np.array([0.3]))])
    assert perfect.ap == pytest.approx(1.0) and perfect.recall == 1.0
    none = det.average_precision([(g, np.zeros((0, 5)), np.zeros(0))])
    assert none.ap == 0.0 and none.recall == 0.0
    empty = det.average_precision([(np.zeros((0, 5)), g, np.array([0.9]))])
    assert math.isnan(empty.ap) and empty.n_gt == 0
    # a zero-area detection on top of a GT box is a false positive, not a crash
    z = det.average_precision([(g, np.array([[0, 0, 0, 0, 0]], float), np.array([0.9]))])
    assert z.ap == 0.0


def test_matching_prefers_high_score_and_best_iou():
    gt = np.array([[0, 0, 4, 2, 0]], float)
    dets = np.array([[0.5, 0, 4, 2, 0], [0, 0, 4, 2, 0]], float)
    m = det.match_frame(gt, dets, np.array([0.9, 0.4]))
    assert m.tp.tolist() == [True, False]  # the higher score wins even with a lower IoU
    assert m.iou[1] == pytest.approx(1.0)  # the duplicate keeps its best IoU for the FP term


def test_tp_fp_terms_hand_worked():
    gt1, det1, sc1 = _ap_example()[0]
    assert det.true_positive_term(gt1, det1, sc1) == pytest.approx(0.9 * 1.0 + 0.6 * 0.6)
    assert det.false_positive_term(gt1, det1, sc1) == pytest.approx(0.8 * 1.0)
    assert det.detection_loss(gt1, det1, sc1, alpha=2.0, beta=0.5) == pytest.approx(-2 * 1.26 + 0.5 * 0.8)
    gt2, det2, sc2 = _ap_example()[1]
    assert det.false_positive_term(gt2, det2, sc2) == pytest.approx(0.0)  # duplicate: IoU 1 -> (1 - 1) x .5


def test_roi_in_ego_frame():
    ego = np.array([100.0, 50.0, math.pi / 2])  # facing +y
    b = np.array([[100, 60, 4, 2, 0], [100, 120, 4, 2, 0], [100, 45, 4, 2, 0], [130, 60, 4, 2, 0]], float)
    assert det.roi_mask(b, ego).tolist() == [True, False, False, True]
    assert det.roi_mask(b, ego, lateral=20).tolist() == [True, False, False, False]
    m = det.evaluate_frames([b], [b[:1]], [np.array([0.9])], ego_poses=[ego])
    assert m.n_gt == 2 and m.recall == pytest.approx(0.5)


# ------------------------------------------------------------------ prediction

def test_ade_fde_by_hand():
    gt = np.zeros((1, 4, 2))
    gt[0, :, 0] = [1, 2, 3, 4]
    p = np.zeros((1, 2, 4, 2))
    p[0, 0] = gt[0] + [0, 1]            # 1 m off at every step
    p[0, 1] = gt[0]
    p[0, 1, 3] = [4, 3]                 # only the last step off by 3 m
    valid = np.array([[True, True, True, False]])  # last step unknown
    ade, fde = pred.displacement_errors(p, gt, valid)
    assert ade[0].tolist() == pytest.approx([1.0, 0.0])
    assert fde[0].tolist() == pytest.approx([1.0, 0.0])  # FDE at the last *valid* step
    ade_all, fde_all = pred.displacement_errors(p, gt)
    assert ade_all[0].tolist() == pytest.approx([1.0, 0.75]) and fde_all[0].tolist() == pytest.approx([1.0, 3.0])
    m = pred.prediction_metrics(p, gt)
    assert m.min_ade == pytest.approx(0.75) and m.mean_ade == pytest.approx(0.875) and m.min_fde == pytest.approx(1.0)
    assert pred.prediction_loss(p, gt, reduction="sum") == pytest.approx((4 + 3) / 2)


def test_ade_invalid_actor_and_horizon_mismatch():
    p = np.zeros((2, 3, 60, 2))
    gt = np.ones((2, 30, 2))  # the episode ended after 3 s
    valid = np.ones((2, 30), bool)
    valid[1] = False
    m = pred.prediction_metrics(p, gt, valid)
    assert m.n_actors == 1 and m.min_ade == pytest.approx(math.sqrt(2))
    assert np.isnan(pred.min_ade(p, gt, valid)[1])
    none = pred.prediction_metrics(p, gt, np.zeros((2, 30), bool))
    assert none.n_actors == 0 and math.isnan(none.min_ade)
    assert pred.prediction_loss(p, gt, np.zeros((2, 30), bool)) == 0.0


# ------------------------------------------------------------------ comfort

def _circle(v, radius, T=60, dt=0.1, with_yaw=True):
    t = np.arange(T) * dt
    th = v * t / radius
    xy = np.c_[radius * np.sin(th), radius * (1 - np.cos(th))]
    return np.c_[xy, th] if with_yaw else xy


@pytest.mark.parametrize("with_yaw", [True, False])
def test_constant_curvature_lateral_acceleration(with_yaw):
    v, radius = 12.0, 40.0
    c = cf.trajectory_comfort(_circle(v, radius, with_yaw=with_yaw))
    assert c.lat == pytest.approx(v * v / radius, rel=2e-3)  # v^2 kappa
    assert c.jerk == pytest.approx(0.0, abs=1e-2)
    # large map coordinates do not change it
    off = _circle(v, radius, with_yaw=with_yaw)
    off[:, :2] += [6.1e5, -4.3e6]
    assert cf.trajectory_comfort(off).lat == pytest.approx(c.lat, rel=1e-6)


def test_jerk_of_linear_acceleration_ramp():
    dt, j = 0.1, 0.8
    t = np.arange(50) * dt
    x = 10 * t + j * t ** 3 / 6  # a = j t
    prof = cf.kinematic_profiles(np.c_[x, np.zeros_like(x), np.zeros_like(x)], dt)
    assert len(prof["jerk"]) == 47 and np.allclose(prof["jerk"], j, atol=1e-6)
    assert np.allclose(prof["lat_accel"], 0.0)


def test_comfort_degenerate_inputs():
    assert cf.trajectory_comfort(np.zeros((1, 3))).lat == 0.0
    assert cf.trajectory_comfort(np.zeros((2, 2))).jerk == 0.0
    still = cf.trajectory_comfort(np.zeros((20, 2)))  # standing: heading undefined, no NaN
    assert still.lat == 0.0 and still.jerk == 0.0
    plans = [_circle(10, 50), _circle(10, 100)]
    pc = cf.planning_comfort(plans)
    assert pc.lat == pytest.approx(0.5 * (2.0 + 1.0), rel=2e-3)
    c0 = cf.trajectory_comfort(plans[0])
    assert cf.plan_comfort_cost(plans[0]) == pytest.approx(c0.lat + c0.jerk) and c0.lat > 1.9


def test_collisions_and_min_distance():
    T = 30
    ego = np.c_[np.arange(T) * 1.0, np.zeros(T), np.full(T, 4.0), np.full(T, 2.0), np.zeros(T)]
    actors = np.zeros((T, 2, 5))
    actors[:, 0] = [20.0, 0.0, 4.0, 2.0, 0.0]   # stopped in the path: ego front reaches 18 at t=16
    actors[:, 1] = [10.0, 5.0, 4.0, 2.0, 0.0]   # beside the road: 3 m lateral gap
    valid = np.ones((T, 2), bool)
    rep = cf.collisions(ego, actors, valid)
    assert rep.collided and rep.first_frame == 17 and rep.actors == [0]
    assert rep.min_distance == 0.0
    assert rep.min_distance_per_frame[0] == pytest.approx(math.hypot(6, 3))  # 16 m to actor 0, corner-corner to 1
    valid[:, 0] = False
    rep2 = cf.collisions(ego, actors, valid)
    assert not rep2.collided and rep2.first_frame == -1 and rep2.min_distance == pytest.approx(3.0)
    assert cf.min_distance(ego, actors[:, :0]) == np.inf


def test_match_tracks_to_ground_truth():
    gt = np.array([[0, 0, 4, 2, 0], [10, 0, 4, 2, 0], [np.nan, 0, 4, 2, 0]], float)
    tracks = np.array([[10.5, 0.2, 4, 2, 0], [50, 50, 4, 2, 0], [0.4, 0, 4, 2, 0], [9.0, 0, 4, 2, 0]], float)
    # track 3 is also near GT 1 but further than track 0: one-to-one keeps the closer pair
    assert pred.match_to_ground_truth(tracks, gt).tolist() == [1, -1, 0, -1]
    assert pred.match_to_ground_truth(np.zeros((0, 5)), gt).shape == (0,)


def test_iou_symmetries_far_from_the_origin(rng):
    A = np.c_[rng.uniform(-1e5, 1e5, (500, 2)), rng.uniform(0.1, 20, (500, 2)), rng.uniform(-10, 10, 500)]
    assert np.allclose(bx.iou_paired(A, A), 1.0, atol=1e-8)
    flipped = A.copy()
    flipped[:, 4] += math.pi  # a box turned by 180 deg covers the same footprint
    assert np.allclose(bx.iou_paired(A, flipped), 1.0, atol=1e-8)
    swapped = A.copy()
    swapped[:, 4] += math.pi / 2
    swapped[:, [2, 3]] = A[:, [3, 2]]  # so does one turned by 90 deg with length and width swapped
    assert np.allclose(bx.iou_paired(A, swapped), 1.0, atol=1e-8)
    ahead = A.copy()  # nose to tail: shifted by its length along its heading
    ahead[:, 0] += A[:, 2] * np.cos(A[:, 4])
    ahead[:, 1] += A[:, 2] * np.sin(A[:, 4])
    assert np.allclose(bx.iou_paired(A, ahead), 0.0, atol=1e-8)
    thin = A.copy()
    thin[:, 3] = 1e-12
    assert np.all(np.isfinite(bx.iou_pairwise(A[:40], thin[:40])))


def test_detection_frame_terms_are_the_two_terms_from_one_matching(rng):
    from adv3d_runner.metrics.detection import detection_frame_terms, false_positive_term, true_positive_term

    gt = np.c_[rng.uniform(0, 30, (6, 2)), np.full((6, 1), 4.5), np.full((6, 1), 1.9), rng.uniform(-1, 1, 6)]
    det = gt[[0, 1, 1, 3]] + np.c_[rng.normal(0, 0.4, (4, 2)), np.zeros((4, 3))]
    scores = np.array([0.9, 0.8, 0.5, np.nan])  # a duplicate (false positive); NaN scores count 0
    tp, fp = detection_frame_terms(gt, det, scores)
    assert (tp, fp) == (true_positive_term(gt, det, scores), false_positive_term(gt, det, scores))
    assert tp > 0 and fp > 0


def test_match_frame_equals_its_numpy_loop():
    """The compiled greedy matching against the numpy loop it replaced (kept as
    ``match_frame_numpy``): same true positives, matches and IoUs, bit for bit, with ties in
    scores and IoU, overlapping ground truth, degenerate and non-finite boxes."""
    rng = np.random.default_rng(5)
    for trial in range(300):
        g, d = int(rng.integers(0, 6)), int(rng.integers(0, 9))
        gt = np.c_[rng.normal(0, 4, (g, 2)), rng.uniform(0.5, 5, (g, 2)), rng.normal(0, 1, g)]
        dets = np.c_[rng.normal(0, 4, (d, 2)), rng.uniform(0.5, 5, (d, 2)), rng.normal(0, 1, d)]
        if d and g and trial % 3 == 0:  # detections on top of ground truth, some exactly
            dets[: min(d, g)] = gt[: min(d, g)] + rng.normal(0, 0.3 * (trial % 2), (min(d, g), 5))
        if d and trial % 7 == 0:
            dets[rng.integers(0, d), rng.integers(0, 5)] = np.nan
        if g and trial % 11 == 0:
            gt[rng.integers(0, g), 2] = 0.0
        scores = np.round(rng.random(d), 1)
        for thr in (0.0, 0.1, 0.5):
            a = det.match_frame(gt, dets, scores, thr)
            b = det.match_frame_numpy(gt, dets, scores, thr)
            assert a.n_gt == b.n_gt
            for x, y in ((a.tp, b.tp), (a.matched_gt, b.matched_gt), (a.iou, b.iou)):
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
