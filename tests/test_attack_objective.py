"""Attack objective (paper Eq. 3-5) on hand-made outputs; target selection and decoding."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.attack.objective import (ABLATIONS, ObjectiveWeights, combine, detection_terms, parse_objective,
                                           planning_terms, prediction_terms, term_split)
from adv3d_runner.attack.targets import mesh_dimensions, split_query
from adv3d_runner.errors import ConfigError


def box(x, y, l=4.0, w=2.0, yaw=0.0):
    return [x, y, l, w, yaw]


def test_detection_terms_tp_and_fp():
    gt = np.array([box(10, 0), box(30, 3.5)])
    # det 0: exact match (IoU 1, conf 0.9) -> TP 0.9
    # det 1: shifted 1 m along x on gt 1 -> IoU = 3/5, conf 0.8 -> TP 0.48
    # det 2: nowhere (IoU 0, conf 0.5) -> FP 0.5
    # det 3: duplicate of gt 0 at IoU 1 but lower score -> FP with (1 - 1) * 0.3 = 0
    det = np.array([box(10, 0), box(31, 3.5), box(60, -3.5), box(10, 0)])
    sc = np.array([0.9, 0.8, 0.5, 0.3])
    tp, fp = detection_terms([(gt, det, sc)])
    assert tp[0] == pytest.approx(0.9 + 0.6 * 0.8)
    assert fp[0] == pytest.approx(0.5)
    # empty frame, and a frame with a missed actor (no detections)
    tp2, fp2 = detection_terms([(np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0)), (gt, np.zeros((0, 5)), np.zeros(0))])
    assert tp2.tolist() == [0.0, 0.0] and fp2.tolist() == [0.0, 0.0]


def test_prediction_terms_sum_over_waypoints_and_mean():
    """Eq. 5 sums the displacement over the H waypoints (the default); "mean" averages it."""
    H = 10
    gt = np.zeros((1, H, 2))
    gt[0, :, 0] = np.arange(1, H + 1)
    pred = np.repeat(gt[:, None], 2, axis=1).copy()
    pred[0, 1, :, 1] += 2.0  # mode 1 off by 2 m everywhere, mode 0 exact
    valid = np.ones((1, H), bool)
    frames = [(pred, gt, valid), (np.zeros((0, 2, H, 2)), np.zeros((0, H, 2)), np.zeros((0, H), bool))]
    # sum: (0 + 10 x 2 m) / 2 modes = 10; mean: (0 + 2) / 2 = 1; an empty frame contributes 0
    assert prediction_terms(frames) == pytest.approx([10.0, 0.0])
    assert prediction_terms(frames, "sum") == pytest.approx([10.0, 0.0])
    assert prediction_terms(frames, "mean") == pytest.approx([1.0, 0.0])
    valid[0, 5:] = False  # only valid steps count: 5 waypoints of 2 m in mode 1
    pred[0, 1, 5:, 1] += 100.0
    assert prediction_terms([(pred, gt, valid)])[0] == pytest.approx(5.0)
    assert prediction_terms([(pred, gt, valid)], "mean")[0] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        prediction_terms(frames, "max")


def test_planning_terms_comfort():
    dt = 0.1
    t = np.arange(30) * dt
    straight = np.c_[10 * t, np.zeros_like(t), np.zeros_like(t)]       # constant speed: 0
    R, v = 50.0, 10.0                                                    # circle: a_lat = v^2 / R
    ang = v * t / R
    circle = np.c_[R * np.sin(ang), R * (1 - np.cos(ang)), ang]
    braking = np.c_[10 * t - 0.5 * 4 * np.maximum(t - 1, 0) ** 2, np.zeros_like(t), np.zeros_like(t)]
    out = planning_terms([straight, circle, braking], dt)
    assert out[0] == pytest.approx(0.0, abs=1e-9)
    assert out[1] == pytest.approx(v**2 / R, rel=1e-3)
    assert out[2] > 0.5  # the step in deceleration is a jerk


def test_combine_weights_and_ablations():
    tp, fp = np.array([1.0, 0.5]), np.array([0.0, 0.2])
    pred, plan = np.array([2.0, 4.0]), np.array([0.1, 0.3])
    full = combine(tp, fp, pred, plan)
    assert full.det == pytest.approx(-1.5 + 0.2)
    assert full.total == pytest.approx(-1.3 + 0.1 * 6.0 + 0.5 * 0.4)
    assert combine(tp, fp, pred, plan, ABLATIONS["M1"]).total == pytest.approx(-1.3)
    assert combine(tp, fp, pred, plan, ABLATIONS["M2"]).total == pytest.approx(0.6)
    assert combine(tp, fp, pred, plan, ABLATIONS["M3"]).total == pytest.approx(0.2)
    assert combine(tp, fp, pred, plan, ABLATIONS["M4"]).total == pytest.approx(-1.3 + 0.6)
    assert combine(tp, fp, pred, plan, ABLATIONS["M5"]).total == pytest.approx(-1.3 + 0.2)
    w = ObjectiveWeights(alpha=2.0, beta=3.0)
    assert combine(tp, fp, pred, plan, w).det == pytest.approx(-3.0 + 0.6)
    # a shape that hides the actor (lower TP confidence) must raise the objective
    assert combine(tp * 0.5, fp, pred, plan).total > full.total
    assert not np.isfinite(combine(tp, fp, np.array([np.nan, 1.0]), plan).total)


def test_parse_objective():
    assert parse_objective("M3") == ABLATIONS["M3"]
    assert parse_objective(None) == ABLATIONS["M0"]
    w = parse_objective("M1,beta=2")
    assert w.det == 1 and w.pred == 0 and w.beta == 2
    assert parse_objective("pred=0.2").pred == 0.2
    assert parse_objective("M0").pred_reduction == "sum"  # Eq. 5 as written, by default
    for bad in ("M9", "gamma=1", "pred=x", "det=0,pred=0,plan=0", "alpha=-1", "pred_reduction=mean"):
        with pytest.raises(ConfigError):
            parse_objective(bad)
    with pytest.raises(ConfigError):
        ObjectiveWeights(pred_reduction="max")
    assert ObjectiveWeights(pred_reduction="mean").as_dict()["pred_reduction"] == "mean"


def test_term_split_keeps_weighted_and_unweighted_apart():
    w = ObjectiveWeights()  # det 1, pred 0.1, plan 0.5
    comp = {"det": -12.0, "tp": 13.0, "fp": 1.0, "pred": 300.0, "plan": 4.0, "frames": 50}
    split = term_split(comp, w)
    assert list(split) == ["det", "pred", "plan"]
    assert split["pred"] == {"unweighted": 300.0, "weight": 0.1, "weighted": pytest.approx(30.0)}
    assert split["plan"]["weighted"] == pytest.approx(2.0) and split["det"]["weighted"] == -12.0
    # the weighted terms add up to the objective; the unweighted ones are not summed anywhere
    tp, fp, pred, plan = np.array([13.0]), np.array([1.0]), np.array([300.0]), np.array([4.0])
    assert sum(t["weighted"] for t in split.values()) == pytest.approx(combine(tp, fp, pred, plan, w).total)
    assert term_split(comp, ABLATIONS["M1"])["pred"] == {"unweighted": 300.0, "weight": 0.0, "weighted": 0.0}


def test_split_query_and_dimensions():
    u = np.arange(10) / 10
    assert split_query(u, 2).shape == (2, 5)
    with pytest.raises(ConfigError):
        split_query(u, 3)
    v = np.array([[-2.0, -1.0, 0.0], [2.5, 0.9, 1.5], [0, 0, 0.3]])
    assert mesh_dimensions(v) == pytest.approx([4.5, 1.9, 1.5])


def test_decode_query_dimensions_follow_shape():
    from adv3d_runner.attack.targets import decode_query
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

    if not DEFAULT_SHAPE_SPACE.exists():
        pytest.skip("no shipped shape space")
    space = ShapeSpace.load(DEFAULT_SHAPE_SPACE)
    u = np.full(2 * space.dim, 0.5)
    u[space.k + 1] = 0.0   # actor 0: length scale 0.8
    u[space.dim + space.k + 1] = 1.0  # actor 1: length scale 1.3
    ov, info = decode_query(space, u, [7, 9])
    from adv3d_runner.sim.episode import ShapeOverride

    assert set(ov) == {7, 9} and all(isinstance(o, ShapeOverride) for o in ov.values())
    d7, d9 = ov[7].dimensions, ov[9].dimensions
    assert d9[0] / d7[0] == pytest.approx(1.3 / 0.8, rel=0.05)
    assert info["dimensions"][0] == pytest.approx(list(d7))
    assert np.min(ov[7].vertices[:, 2]) == pytest.approx(0.0, abs=1e-6)
    assert ov[7].faces.dtype == np.int64 and ov[7].faces.max() < len(ov[7].vertices)


def _first_bundled_scene(repo_root):
    import glob

    from adv3d_runner.scene.schema import load_scene

    files = sorted(glob.glob(str(repo_root / "scenes" / "highway" / "*.json.gz")))
    if not files:
        pytest.skip("no bundled scenes")
    return load_scene(files[0])


def test_select_targets_in_front_nearest_first(repo_root):
    from adv3d_runner.attack.targets import select_targets

    scene = _first_bundled_scene(repo_root)
    ids = select_targets(scene, 3)
    ego = scene.ego_poses()[0]
    fwd = np.array([np.cos(ego[2]), np.sin(ego[2])])
    d = []
    for a in ids:
        p = scene.actor_poses(a)[0]
        assert (p[:2] - ego[:2]) @ fwd > 0
        d.append(np.hypot(*(p[:2] - ego[:2])))
    assert d == sorted(d)
    with pytest.raises(ConfigError):
        select_targets(scene, 0)


def test_select_targets_rank_skips_the_closest(repo_root):
    from adv3d_runner.attack.targets import select_targets

    scene = _first_bundled_scene(repo_root)
    three = select_targets(scene, 3)
    assert [select_targets(scene, 1, rank=k)[0] for k in range(3)] == three   # each of the 3 closest alone
    assert select_targets(scene, 2, rank=1) == three[1:]
    n_front = len(select_targets(scene, 64))
    with pytest.raises(ConfigError, match="none of rank"):
        select_targets(scene, 1, rank=n_front)
    with pytest.raises(ConfigError):
        select_targets(scene, 1, rank=-1)
