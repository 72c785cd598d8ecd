"""Learned predictor: shipped weights, shapes, map-frame geometry, degenerate inputs, data
determinism, and the shipped model against constant velocity on held-out training-split scenes."""
from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from adv3d_runner.autonomy.baselines import ConstantVelocityPredictor  # noqa: E402
from adv3d_runner.autonomy.interface import Tracks  # noqa: E402
from adv3d_runner.autonomy.predictor import (CONFIG_NAME, DEFAULT_MODEL_DIR, NUM_FEATURES, WEIGHTS_NAME,  # noqa: E402
                                             PredictorConfig, agent_features, build_net, encode, lane_index,
                                             load_predictor, save_predictor)
from adv3d_runner.errors import FileFormatError  # noqa: E402
from adv3d_runner.scene.lanemap import LaneMap  # noqa: E402

HAS_MODEL = (DEFAULT_MODEL_DIR / WEIGHTS_NAME).is_file()
needs_model = pytest.mark.skipif(not HAS_MODEL, reason="no shipped predictor (run `adv3d train predictor`)")


@pytest.fixture(scope="module")
def model():
    return load_predictor()


def predict_on(model, tracks, lanes):
    """``model`` reset onto the lane map of ``lanes``, then its predictions for ``tracks``."""
    model.reset(LaneMap(lanes))
    return model.predict(tracks)


def straight_lanes(heading: float, origin=(1000.0, -500.0), width: float = 3.7, length: float = 600.0):
    """Three parallel straight lanes (right, middle, left) along ``heading``."""
    d = np.array([np.cos(heading), np.sin(heading)])
    nrm = np.array([-d[1], d[0]])
    s = np.linspace(-100.0, length, 71)
    lanes = []
    for k, off in enumerate((-width, 0.0, width)):
        pts = np.asarray(origin) + s[:, None] * d + off * nrm
        lanes.append(SimpleNamespace(id=k + 1, centerline=pts, width=np.full(len(pts), width),
                                     left=k + 2 if k < 2 else None, right=k if k > 0 else None,
                                     successors=[], speed_limit=31.3))
    return lanes, d, nrm


def straight_track(lanes_dir, nrm, speed: float, lateral: float = 0.0, origin=(1000.0, -500.0), n_hist: int = 10):
    """One track driving along the lanes at ``speed``, its history consistent with it."""
    heading = float(np.arctan2(lanes_dir[1], lanes_dir[0]))
    p0 = np.asarray(origin) + 50.0 * lanes_dir + lateral * nrm
    k = np.arange(-9, 1) * 0.1
    hist = np.c_[p0 + (speed * k)[:, None] * lanes_dir, np.full(10, heading)]
    valid = np.zeros(10, bool)
    valid[10 - n_hist:] = True
    return Tracks(ids=[7], boxes=[[*p0, 4.6, 1.9, heading]], velocities=[speed * lanes_dir], scores=[0.9],
                  misses=[0], history=hist[None], history_valid=valid[None]), p0


@needs_model
def test_weights_load_weights_only():
    state = torch.load(DEFAULT_MODEL_DIR / WEIGHTS_NAME, map_location="cpu", weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in state.values())
    p = load_predictor()
    assert p.num_modes >= 3
    assert p.config.steps == 60


@needs_model
@pytest.mark.parametrize("heading", [0.0, 0.7, -2.5])
def test_straight_lane_constant_speed_is_predicted_along_the_lane(model, heading):
    lanes, d, nrm = straight_lanes(heading)
    tracks, p0 = straight_track(d, nrm, speed=25.0)
    out = predict_on(model, tracks, lanes)
    assert out.trajectories.shape == (1, model.num_modes, 60, 2)
    assert out.probabilities.shape == (1, model.num_modes)
    assert out.track_ids.tolist() == [7]
    truth = p0 + (25.0 * np.arange(1, 61) * 0.1)[:, None] * d
    fde = np.linalg.norm(out.trajectories[0, :, -1] - truth[-1], axis=-1)
    assert fde.min() < 2.0, fde
    # the most probable mode stays ahead in the lane (not reversed or in the next lane)
    best = out.trajectories[0, np.argmax(out.probabilities[0])]
    along = (best - p0) @ d
    across = (best - p0) @ nrm
    assert along[-1] > 100.0 and np.abs(across).max() < 2.5


@needs_model
def test_probabilities_sum_to_one_and_batch_equals_single(model):
    lanes, d, nrm = straight_lanes(0.3)
    t1, _ = straight_track(d, nrm, 20.0)
    t2, _ = straight_track(d, nrm, 30.0, lateral=3.7)
    both = Tracks(ids=[1, 2], boxes=np.r_[t1.boxes, t2.boxes + [[10.0, 0, 0, 0, 0]]],
                  velocities=np.r_[t1.velocities, t2.velocities], scores=[0.9, 0.9], misses=[0, 0],
                  history=np.r_[t1.history, t2.history], history_valid=np.r_[t1.history_valid, t2.history_valid])
    out = predict_on(model, both, lanes)
    assert np.allclose(out.probabilities.sum(axis=1), 1.0)
    assert np.all(out.probabilities >= 0)
    assert np.all(np.isfinite(out.trajectories))
    single = predict_on(model, t1, lanes)
    assert single.trajectories.shape[0] == 1
    assert np.all(np.isfinite(single.trajectories))


@needs_model
def test_empty_tracks_give_empty_predictions(model):
    lanes, _, _ = straight_lanes(0.0)
    for ln in (lanes, []):
        out = predict_on(model, Tracks(), ln)
        assert len(out) == 0
        assert out.trajectories.shape == (0, model.num_modes, 60, 2)
        assert out.probabilities.shape == (0, model.num_modes)


@needs_model
def test_short_invalid_history_and_no_lanes(model):
    lanes, d, nrm = straight_lanes(1.2)
    tracks, p0 = straight_track(d, nrm, 22.0, n_hist=1)
    tracks.history[0, :9] = np.nan  # garbage where the history is flagged invalid
    out = predict_on(model, tracks, lanes)
    assert np.all(np.isfinite(out.trajectories)) and np.allclose(out.probabilities.sum(1), 1.0)
    # no map at all: still finite, and the best mode still goes roughly straight ahead
    out2 = predict_on(model, tracks, [])
    assert np.all(np.isfinite(out2.trajectories))
    truth = p0 + 22.0 * 6.0 * d
    assert np.linalg.norm(out2.trajectories[0, :, -1] - truth, axis=-1).min() < 15.0
    # a history array shorter than the model's (H = 3) is accepted too
    short = Tracks(ids=[3], boxes=tracks.boxes, velocities=tracks.velocities, scores=[0.5], misses=[2],
                   history=tracks.history[:, -3:], history_valid=np.ones((1, 3), bool))
    assert np.all(np.isfinite(predict_on(model, short, lanes).trajectories))


@needs_model
def test_non_finite_track_does_not_spoil_the_others(model):
    lanes, d, nrm = straight_lanes(0.0)
    t, _ = straight_track(d, nrm, 25.0)
    bad = Tracks(ids=[1, 2], boxes=np.r_[t.boxes, [[np.nan, 0, 4, 2, 0]]], velocities=np.r_[t.velocities, [[np.nan, 0]]],
                 scores=[0.9, 0.9], misses=[0, 0], history=np.r_[t.history, t.history],
                 history_valid=np.r_[t.history_valid, t.history_valid])
    out = predict_on(model, bad, lanes)
    ref = predict_on(model, t, lanes)
    assert np.allclose(out.trajectories[0], ref.trajectories[0], atol=1e-4)
    assert np.allclose(out.probabilities.sum(1), 1.0)


def test_save_load_roundtrip_and_bad_files(tmp_path):
    torch.manual_seed(0)
    cfg = PredictorConfig(num_modes=3, hidden=32, layers=2)
    net = build_net(cfg)
    save_predictor(net, cfg, tmp_path / "m")
    p = load_predictor(tmp_path / "m")
    lanes, d, nrm = straight_lanes(0.4)
    t, _ = straight_track(d, nrm, 20.0)
    a = predict_on(p, t, lanes)
    with torch.inference_mode():
        from adv3d_runner.autonomy.predictor import encode, no_reversing, to_map_frame
        f, prior = encode(t, LaneMap(lanes))
        traj, _ = net.eval()(torch.from_numpy(f), torch.from_numpy(prior))
    assert np.allclose(a.trajectories, to_map_frame(no_reversing(traj.numpy().astype(float)), t.boxes), atol=1e-4)
    with pytest.raises(FileFormatError):
        load_predictor(tmp_path / "missing")
    (tmp_path / "m" / WEIGHTS_NAME).write_bytes(b"not a torch file")
    with pytest.raises(FileFormatError):
        load_predictor(tmp_path / "m")
    (tmp_path / "m" / CONFIG_NAME).write_text('{"format": "something-else", "version": 1}')
    with pytest.raises(FileFormatError, match="format"):
        load_predictor(tmp_path / "m")


def test_features_shape_and_lane_index_matches_planner_locate():
    from adv3d_runner.scene.generate import generate_scene

    scene = generate_scene(100_002, "train")  # on-ramp layout
    poses, valid = scene.all_actor_poses()
    P = poses[valid[:, 40], 40]
    lane_map = LaneMap.from_scene(scene)
    idx = lane_index(lane_map)
    assert lane_index(lane_map) is idx  # built once per map, shared by every reader
    row, (s, dd, _, _, _) = idx.locate(P)
    ids, s_ref, d_ref = lane_map.locate_many(P)
    assert np.array_equal(np.where(row >= 0, idx.ids[np.maximum(row, 0)], -1), ids)
    ok = row >= 0
    assert np.allclose(s[ok, row[ok]], s_ref[ok]) and np.allclose(dd[ok, row[ok]], d_ref[ok])
    n = len(P)
    tr = Tracks(ids=np.arange(n), boxes=np.c_[P[:, :2], np.full(n, 4.5), np.full(n, 1.8), P[:, 2]],
                velocities=np.zeros((n, 2)), scores=np.ones(n), misses=np.zeros(n),
                history=np.repeat(P[:, None], 10, 1), history_valid=np.ones((n, 10), bool))
    f = agent_features(tr, lane_map)
    assert f.shape == (n, NUM_FEATURES) and f.dtype == np.float32 and np.all(np.isfinite(f))


def test_data_generation_is_deterministic():
    from adv3d_runner.training.predictor_data import ARRAYS, scene_samples

    a = scene_samples(100_003)
    b = scene_samples(100_003)
    assert len(a["features"]) > 50
    for k in ARRAYS:
        assert np.array_equal(a[k], b[k]), k
    assert np.all(a["future_valid"].sum(1) >= 30)
    assert np.all(np.isfinite(a["features"])) and np.all(np.isfinite(a["prior"]))


def test_cache_roundtrip(tmp_path):
    from adv3d_runner.training.predictor_data import ARRAYS, load_samples, save_samples, scene_samples

    a = scene_samples(100_007)
    save_samples(tmp_path / "x.npz", a)
    b = load_samples(tmp_path / "x.npz")
    for k in ARRAYS:
        assert np.array_equal(a[k], b[k]) and a[k].dtype == b[k].dtype


@needs_model
def test_shipped_model_beats_constant_velocity_on_held_out_scenes(model):
    """End to end in the map frame: noisy detections -> tracker -> predict, on training-split
    scenes whose seeds were used neither for training nor for the training report."""
    from adv3d_runner.training.predictor_data import tracked_evaluation_frames
    from adv3d_runner.metrics.prediction import prediction_metrics
    from adv3d_runner.scene.generate import generate_scene

    cv = ConstantVelocityPredictor()
    learned_p, cv_p, gts, vals = [], [], [], []
    for seed in (900_000_001, 900_000_006):
        scene = generate_scene(seed, "train")
        model.reset(LaneMap.from_scene(scene))
        for _, tracks, rows, future, future_valid in tracked_evaluation_frames(
                scene, np.random.default_rng(seed), frames=range(140), every=10):
            learned_p.append(model.predict(tracks).trajectories[rows])
            cv_p.append(cv.predict(tracks).trajectories[rows])
            gts.append(future)
            vals.append(future_valid)
    gt, val = np.concatenate(gts), np.concatenate(vals)
    ml = prediction_metrics(np.concatenate(learned_p), gt, val)
    mc = prediction_metrics(np.concatenate(cv_p), gt, val)
    assert ml.n_actors > 50
    assert ml.min_ade < mc.min_ade, (ml, mc)
    assert ml.min_ade < 0.8 * mc.min_ade, (ml, mc)  # a clear margin, not a tie


@pytest.mark.slow
def test_train_cli_quick(tmp_path):
    from adv3d_runner.cli import main

    out = tmp_path / "model"
    rc = main(["-q", "train", "predictor", "--model", "free", "--quick", "--scenes", "1", "--val-scenes", "1", "--epochs", "1",
               "--seed", "100011", "--cache", str(tmp_path / "cache"), "--out", str(out)])
    assert rc == 0
    for name in ("weights.pt", "config.json", "training_report.json", "loss_curves.png"):
        assert (out / name).is_file(), name
    import json

    rep = json.loads((out / "training_report.json").read_text())
    assert rep["format"] == "adv3d-predictor-training-report"
    assert rep["training"]["device"] == {"device": "cpu"} and rep["training"]["seconds"] >= 0
    models = rep["held_out"]["all"]["models"]
    assert {"constant_velocity", "lane_following", "learned_top3"} <= set(models)
    assert load_predictor(out).num_modes == 6
    # the cache is reused on a second run (same data, no regeneration needed)
    assert any((tmp_path / "cache").rglob("*.npz"))


def test_no_reversing_keeps_forward_progress():
    from adv3d_runner.autonomy.predictor import no_reversing

    local = np.zeros((1, 2, 5, 2))
    local[0, 0, :, 0] = [0.5, 0.3, 1.0, 0.8, 2.0]     # jitters backwards
    local[0, 1, :, 0] = [-0.2, -0.5, -1.0, -2.0, -3.0]  # rolls back
    local[..., 1] = 0.1
    out = no_reversing(local)
    assert out[0, 0, :, 0].tolist() == [0.5, 0.5, 1.0, 1.0, 2.0]
    assert out[0, 1, :, 0].tolist() == [0.0] * 5
    assert np.all(out[..., 1] == 0.1) and local[0, 1, 0, 0] == -0.2  # lateral kept, input untouched


# ------------------------------------------------------------- the compiled encode: same bits
# ``encode`` and ``LearnedPredictor.predict`` run as compiled loops around a few numpy calls. Here
# is the plain numpy formulation they replaced (kept verbatim as the reference: every feature,
# prior and trajectory must be bit for bit the same on real tracker output and on degenerate
# tracks, on this machine's numpy and torch).
def _ref_rot(xy, c, s):
    shape = (-1,) + (1,) * (xy.ndim - 2)
    c = c.reshape(shape)
    s = s.reshape(shape)
    return np.stack([c * xy[..., 0] + s * xy[..., 1], -s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def _ref_project_all(index, xy):
    q = np.asarray(xy, np.float64).reshape(-1, 2)
    rows = np.arange(len(index.ids))
    rx = q[:, 0, None, None] - index.seg_a[None, ..., 0]
    ry = q[:, 1, None, None] - index.seg_a[None, ..., 1]
    t = rx * index.seg_u[None, ..., 0] + ry * index.seg_u[None, ..., 1]
    tc = np.clip(t, index._lo[None], index._hi[None])
    dist2 = rx * rx + ry * ry + tc * (tc - 2.0 * t)
    dist2[:, ~index.seg_ok] = np.inf
    best = np.argmin(dist2, axis=2)
    take = lambda a: np.take_along_axis(a, best[..., None], axis=2)[..., 0]  # noqa: E731
    tb = take(tc)
    u = index.seg_u[rows[None, :], best]
    r = np.stack([take(rx), take(ry)], axis=-1)
    s = index.seg_s[rows[None, :], best] + tb
    d = u[..., 0] * r[..., 1] - u[..., 1] * r[..., 0]
    head = np.arctan2(u[..., 1], u[..., 0])
    seg_len = index.seg_len[rows[None, :], best]
    frac = np.clip(tb / np.maximum(seg_len, 1e-9), 0.0, 1.0)
    width = index.seg_w0[rows[None, :], best] * (1 - frac) + index.seg_w1[rows[None, :], best] * frac
    beyond = np.maximum(np.maximum(-s, s - index.length[None]), 0.0)
    return s, d, head, width, beyond


def _ref_locate(index, poses):
    from adv3d_runner.geometry.angles import wrap_angle

    P = np.asarray(poses, np.float64).reshape(-1, 3)
    n = len(P)
    proj = _ref_project_all(index, P[:, :2])
    s, d, head, width, beyond = proj
    herr = np.abs(wrap_angle(P[:, 2:3] - head))
    inside = (np.abs(d) <= 0.5 * width) & (beyond == 0.0)
    key = np.where(inside, 0.0, 1e6) + np.abs(d) + beyond
    key = np.where(herr <= np.pi / 2, key, np.inf)
    row = np.argmin(key, axis=1)
    row = np.where(np.isfinite(key[np.arange(n), row]), row, -1)
    return row.astype(np.int64), proj


def _ref_sample(index, rows, s):
    rows = np.asarray(rows, np.int64)
    ok_row = rows >= 0
    r = np.where(ok_row, rows, 0)
    cmax = index.chain.shape[1]
    u = s / index.chain_step
    with np.errstate(invalid="ignore"):
        i = np.clip(np.floor(u).astype(np.int64), 0, cmax - 2)
    f = u - i
    a = index.chain[r[:, None], i]
    b = index.chain[r[:, None], i + 1]
    pts = a + f[..., None] * (b - a)
    clen = index.chain_len[r][:, None]
    last = np.maximum(np.round(clen / index.chain_step).astype(np.int64), 1)
    past = s > clen
    if np.any(past):
        pa = index.chain[r[:, None], last - 1]
        pb = index.chain[r[:, None], last]
        seg = pb - pa
        seg_n = seg / np.maximum(np.linalg.norm(seg, axis=-1, keepdims=True), 1e-9)
        ext = pb + (s - clen)[..., None] * seg_n
        pts = np.where(past[..., None], np.broadcast_to(ext, pts.shape), pts)
    valid = ok_row[:, None] & ~(past & index.dead_end[r][:, None])
    return pts, valid


def _ref_encode(tracks, lane_map, steps=60, dt=0.1):
    from adv3d_runner.autonomy.predictor import (_LANE_F, HISTORY, LANE_OFFSETS, NEIGHBOUR_RANGE, NEIGHBOURS,
                                                 OFF_LANE, sanitize_tracks)

    n = len(tracks)
    if n == 0:
        return np.zeros((0, NUM_FEATURES), np.float32), np.zeros((0, steps, 2), np.float32)
    boxes, vel, hist, hv, ok = sanitize_tracks(tracks)
    x0, y0, yaw = boxes[:, 0], boxes[:, 1], boxes[:, 4]
    c, s = np.cos(yaw), np.sin(yaw)
    origin = boxes[:, None, :2]
    speed_h = np.maximum(vel[:, 0] * c + vel[:, 1] * s, 0.0)
    t = np.arange(1, steps + 1) * dt
    prior = np.zeros((n, steps, 2))
    prior[..., 0] = speed_h[:, None] * t[None]
    hxy = _ref_rot(hist[..., :2] - origin, c, s)
    dyaw = hist[..., 2] - yaw[:, None]
    hist_f = np.concatenate([hxy / 10.0, np.cos(dyaw)[..., None], np.sin(dyaw)[..., None], hv[..., None]], axis=-1)
    hist_f = np.where(hv[..., None], hist_f, 0.0).reshape(n, -1)
    v_loc = _ref_rot(vel[:, None, :], c, s)[:, 0]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    misses = np.asarray(tracks.misses, np.float64).reshape(n)
    agent_f = np.stack([v_loc[:, 0] / 10.0, v_loc[:, 1] / 10.0, speed / 10.0, boxes[:, 2] / 10.0,
                        boxes[:, 3] / 2.0, np.clip(misses, 0, 10) / 3.0, hv.sum(1) / HISTORY,
                        ok.astype(np.float64)], axis=1)
    lane_f = np.zeros((n, 3, _LANE_F))
    if len(lane_map):
        index = lane_index(lane_map)
        poses = np.stack([x0, y0, yaw], axis=1)
        row, (ps, pd, _, pw, _) = _ref_locate(index, poses)
        row = np.where(ok, row, -1)
        ii = np.arange(n)
        rows = np.stack([row, np.where(row >= 0, index.left[np.maximum(row, 0)], -1),
                         np.where(row >= 0, index.right[np.maximum(row, 0)], -1)], axis=1)
        for j in range(3):
            rj = rows[:, j]
            has = rj >= 0
            rs = np.maximum(rj, 0)
            s_on = ps[ii, rs]
            pts, valid = _ref_sample(index, rj, s_on[:, None] + LANE_OFFSETS[None])
            loc = _ref_rot(pts - origin, c, s)
            loc = np.where(valid[..., None], loc, 0.0)
            blk = np.concatenate([loc[..., 0:1] / 50.0, loc[..., 1:2] / 10.0, valid[..., None]], axis=-1)
            lane_f[:, j, 0] = has
            lane_f[:, j, 1:1 + 3 * len(LANE_OFFSETS)] = blk.reshape(n, -1)
            lane_f[:, j, -3] = np.where(has, pw[ii, rs] / 4.0, 0.0)
            lane_f[:, j, -2] = np.where(has, np.clip(pd[ii, rs], -20, 20) / 4.0, 0.0)
            lane_f[:, j, -1] = np.where(has, index.limit[rs] / 30.0, 0.0)
        rs = np.maximum(row, 0)
        d0 = pd[ii, rs]
        bound = (row >= 0) & (np.abs(d0) - 0.5 * pw[ii, rs] <= OFF_LANE)
        if np.any(bound):
            b = np.flatnonzero(bound)
            st = ps[b, rs[b]][:, None] + speed_h[b, None] * t[None]
            p0, _ = _ref_sample(index, row[b], st)
            p1, _ = _ref_sample(index, row[b], st + 1.0)
            tan = p1 - p0
            tan /= np.maximum(np.linalg.norm(tan, axis=-1, keepdims=True), 1e-9)
            path = p0 + d0[b, None, None] * np.stack([-tan[..., 1], tan[..., 0]], axis=-1)
            prior[b] = _ref_rot(path - origin[b], c[b], s[b])
    lane_f = lane_f.reshape(n, -1)
    neigh_f = np.zeros((n, NEIGHBOURS, 5))
    if n > 1:
        rel = boxes[None, :, :2] - boxes[:, None, :2]
        dist = np.hypot(rel[..., 0], rel[..., 1])
        bad = ~(ok[:, None] & ok[None, :]) | np.eye(n, dtype=bool) | (dist > NEIGHBOUR_RANGE)
        dist = np.where(bad, np.inf, dist)
        k = min(NEIGHBOURS, n - 1)
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        dsel = np.take_along_axis(dist, order, axis=1)
        valid = np.isfinite(dsel)
        rp = _ref_rot(np.take_along_axis(rel, order[..., None], axis=1), c, s)
        rv = _ref_rot(vel[order] - vel[:, None, :], c, s)
        blk = np.concatenate([rp[..., 0:1] / 50.0, rp[..., 1:2] / 10.0, rv / 10.0, valid[..., None]], axis=-1)
        neigh_f[:, :k] = np.where(valid[..., None], blk, 0.0)
    neigh_f = neigh_f.reshape(n, -1)
    out = np.concatenate([hist_f, agent_f, lane_f, neigh_f], axis=1)
    prior = np.where(ok[:, None, None], prior, 0.0)
    return (np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32),
            np.nan_to_num(prior).astype(np.float32))


def _ref_predict(model, tracks, lane_map):
    """``LearnedPredictor.predict`` as it was: the module's forward, numpy post-processing."""
    from adv3d_runner.autonomy.predictor import no_reversing, to_map_frame

    n = len(tracks)
    feats, prior = _ref_encode(tracks, lane_map, model.config.steps, model.config.dt)
    path = None
    if model.config.anchored:  # the anchors' lane paths (the compiled kernel; tested in test_predictor_anchored)
        from adv3d_runner.autonomy.predictor import lane_paths
        path = lane_paths(tracks, lane_map)
    local, probs = model.predict_local(feats, prior, path)
    local = no_reversing(local)
    boxes = np.asarray(tracks.boxes, np.float64).reshape(n, 5)
    traj = to_map_frame(local, np.nan_to_num(boxes))
    bad = ~np.all(np.isfinite(boxes), axis=1)
    if np.any(bad):
        traj[bad] = np.nan
    probs = probs / probs.sum(axis=1, keepdims=True)
    return traj, probs


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _tracker_frames(path, frames: int, seed: int):
    """Tracks of a bundled scene as the tracker gives them from noisy detections (the first
    ``frames`` frames), with the scene's lane map."""
    from adv3d_runner.autonomy.interface import Detections
    from adv3d_runner.autonomy.tracker import MultiObjectTracker
    from adv3d_runner.scene.schema import load_scene

    scene = load_scene(path)
    lane_map = LaneMap.from_scene(scene)
    poses, valid = scene.all_actor_poses()
    dims = scene.actor_dimensions()
    ego = scene.ego_poses()
    speed = scene.ego_speeds()
    rng = np.random.default_rng(seed)
    tracker = MultiObjectTracker()
    for f in range(min(frames, scene.frames)):
        vis = np.flatnonzero(valid[:, f] & (np.hypot(poses[:, f, 0] - ego[f, 0], poses[:, f, 1] - ego[f, 1]) <= 80.0))
        det = np.c_[poses[vis, f, :2], dims[vis, :2], poses[vis, f, 2]]
        det[:, :2] += rng.normal(0.0, 0.15, (len(vis), 2))
        det[:, 4] += rng.normal(0.0, 0.03, len(vis))
        det = det[rng.random(len(vis)) > 0.1]
        yield tracker.update(Detections(det, np.full(len(det), 0.9)), prior_speed=float(speed[f])), lane_map


def _degenerate(tracks, rng):
    """Variants of real tracks: what the numpy formulation handles through its masks and casts."""
    import copy

    n = len(tracks)
    out = []
    k = int(rng.integers(0, n))
    t = copy.deepcopy(tracks)
    t.velocities[k] = [np.nan, 1.0]
    t.velocities[(k + 1) % n] = [np.inf, -np.inf]
    t.boxes[(k + 2) % n, int(rng.integers(0, 5))] = np.nan
    t.history[k, -3:, 0] = np.nan
    t.history_valid[(k + 1) % n, :4] = False
    out.append(t)
    t = copy.deepcopy(tracks)                               # off the lanes, against them, missed
    t.boxes[:, :2] += rng.normal(0.0, 30.0, (n, 2))
    t.boxes[:, 4] += rng.normal(0.0, 1.5, n)
    t.misses[:] = rng.integers(0, 20, n)
    out.append(t)
    t = copy.deepcopy(tracks)                               # standing, headings with negative zeros
    t.velocities[:] = 0.0
    t.velocities[::2] = -0.0
    t.boxes[:, 4] = rng.choice([np.pi, -np.pi / 2, 3.0, -0.0, -2.0, 1.0], n)
    out.append(t)
    t = copy.deepcopy(tracks)                               # all at one place: neighbour ties
    t.boxes[:, :2] = t.boxes[0, :2]
    t.velocities[:, 0] = -3.0 * np.abs(t.velocities[:, 0])
    out.append(t)
    t = copy.deepcopy(tracks)                               # behind the lane starts, past their ends
    t.boxes[:, 0] += rng.choice([-400.0, 5000.0], n)
    out.append(t)
    t = copy.deepcopy(tracks)                               # overflowing values
    t.velocities[k] = [1.7e308, 1.7e308]
    t.velocities[(k + 1) % n] = [1e200, -1e300]
    t.boxes[(k + 2) % n, :2] = [1e300, -1e300]
    t.boxes[(k + 3) % n, 2:4] = [1e39, -5.0]
    t.history[(k + 4) % n, -2:, :2] = 1e305
    out.append(t)
    t = copy.deepcopy(tracks)                               # short and no history
    t.history, t.history_valid = t.history[:, -3:].copy(), t.history_valid[:, -3:].copy()
    out.append(t)
    out.append(Tracks(ids=tracks.ids, boxes=tracks.boxes, velocities=tracks.velocities, scores=tracks.scores,
                      misses=tracks.misses, history=np.zeros((n, 0, 3)), history_valid=np.zeros((n, 0), bool)))
    return out


def _bundled_scenes():
    from adv3d_runner.fileio import REPO_ROOT

    paths = [REPO_ROOT / "scenes/highway/highway-benchmark-000010.json.gz",
             REPO_ROOT / "scenes/highway/highway-benchmark-000003.json.gz"]
    paths += sorted((REPO_ROOT / "scenes/real").glob("*.json.gz"))[:1]
    return [p for p in paths if p.is_file()]


@needs_model
def test_encode_and_predict_are_bit_identical_to_the_numpy_formulation(model):
    rng = np.random.default_rng(0)
    scenes = _bundled_scenes()
    assert scenes
    checked = 0
    empty = LaneMap([])
    for si, path in enumerate(scenes):
        for f, (tracks, lane_map) in enumerate(_tracker_frames(path, 30, si)):
            cases = [(tracks, lane_map)]
            if len(tracks) and f % 3 == 0:
                cases += [(tracks, empty)] + [(t, lane_map) for t in _degenerate(tracks, rng)]
            for t, lm in cases:
                model.reset(lm)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # the overflowing cases
                    ref_f, ref_p = _ref_encode(t, lm)
                    f, p = encode(t, lm)
                    assert _same(f, ref_f) and _same(p, ref_p), (path.name, len(t))
                    if len(t):
                        ref_traj, ref_probs = _ref_predict(model, t, lm)
                        out = model.predict(t)
                        assert _same(out.trajectories, ref_traj) and _same(out.probabilities, ref_probs), path.name
                        assert _same(out.track_ids, t.ids)
                checked += 1
    assert checked > 150
    # predict runs the network as functional calls; the module's own forward gives the same bits
    assert model._functional() is not None and not any(model._functional()[0])
    model._plan_net, model._plan = model.net, None
    try:
        for t, lm in list(_tracker_frames(scenes[0], 8, 9))[2:]:
            model.reset(lm)
            ref_traj, ref_probs = _ref_predict(model, t, lm)
            out = model.predict(t)
            assert _same(out.trajectories, ref_traj) and _same(out.probabilities, ref_probs)
    finally:
        model._plan_net = None


def test_kernel_helpers_are_numpys_operations():
    from adv3d_runner.autonomy.predictor import (_CAST, _chain_point, _floor_index, _locate_one, _np_clip, _np_max,
                                                 _np_wrap)
    from adv3d_runner.geometry.angles import wrap_angle
    from adv3d_runner.scene.generate import generate_scene

    rng = np.random.default_rng(1)
    special = np.array([0.0, -0.0, 1e-9, -1e-9, 1.0, -1.0, 20.0, -20.0, np.pi, -np.pi, 2 * np.pi, 1e300, -1e300,
                        np.inf, -np.inf, np.nan, 5e-324, 9.3e18, -9.3e18])
    x = np.concatenate([special, rng.normal(0.0, 10.0, 3000), rng.normal(0.0, 1e4, 1000)])
    bits = lambda a: np.asarray(a, np.float64).view(np.int64)  # noqa: E731
    for b in (0.0, 1e-9):
        assert np.array_equal(bits([_np_max(v, b) for v in x]), bits(np.maximum(x, b)))
    pairs = rng.choice(x, (2000, 2))
    assert np.array_equal(bits([_np_max(a, b) for a, b in pairs]), bits(np.maximum(pairs[:, 0], pairs[:, 1])))
    for lo, hi in ((0.0, 1.0), (-20.0, 20.0), (0.0, 10.0), (-np.inf, 3.5), (0.0, np.inf)):
        assert np.array_equal(bits([_np_clip(v, lo, hi) for v in x]), bits(np.clip(x, lo, hi)))
    with np.errstate(invalid="ignore"):
        assert np.array_equal(bits([_np_wrap(v) for v in x]), bits(wrap_angle(x)))
    u = np.concatenate([x, x / 2.0])
    with np.errstate(invalid="ignore"):
        ref = np.clip(np.floor(u).astype(np.int64), 0, 110)
    assert [_floor_index(v, 110, _CAST) for v in u] == ref.tolist()
    # one pose / one chain point at a time, float64 bits against the numpy formulation
    lane_map = LaneMap.from_scene(generate_scene(100_002, "train"))  # on-ramp: merges, dead ends
    idx = lane_index(lane_map)
    lo, hi = np.min(idx.seg_a.reshape(-1, 2), 0) - 50.0, np.max(idx.seg_a.reshape(-1, 2), 0) + 50.0
    P = np.c_[rng.uniform(lo, hi, (400, 2)), rng.uniform(-np.pi, np.pi, 400)]
    row, (s, d, _, w, _) = _ref_locate(idx, P)
    new_row, new_proj = idx.locate(P)  # the index's own numpy queries (precomputed headings)
    assert _same(new_row, row) and all(_same(a, b) for a, b in zip(new_proj, _ref_project_all(idx, P[:, :2])))
    L = len(idx)
    for i, p in enumerate(P):
        ls, ld, lw = np.zeros(L), np.zeros(L), np.zeros(L)
        r = _locate_one(p[0], p[1], p[2], idx.seg_a, idx.seg_u, idx.seg_head, idx.seg_len, idx.seg_s, idx.seg_w0,
                        idx.seg_w1, idx.n_seg, idx._lo, idx._hi, idx.length, ls, ld, lw)
        assert r == row[i] and _same(ls, s[i]) and _same(ld, d[i]) and _same(lw, w[i])
    rows = rng.integers(-1, L, 50)
    sv = np.concatenate([rng.uniform(-50.0, idx.chain_len.max() + 100.0, (50, 40)),
                         rng.choice(special, (50, 10))], axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        pts, valid = _ref_sample(idx, rows, sv)
        new_pts, new_valid = idx.sample(rows, sv)  # (precomputed extrapolation)
    assert _same(new_pts, pts) and _same(new_valid, valid)
    for i in range(len(rows)):
        for m in range(sv.shape[1]):
            px, py, dead = _chain_point(idx.chain, idx.chain_len, idx.dead_end, idx.ext_from, idx.ext_dir,
                                        idx.chain_step, _CAST, max(rows[i], 0), sv[i, m])
            assert _same(np.array([px, py]), pts[i, m]) and (rows[i] >= 0 and not dead) == valid[i, m]



def test_functional_forward_is_the_modules_forward():
    from adv3d_runner.autonomy.predictor import LearnedPredictor

    torch.manual_seed(0)
    cfg = PredictorConfig(num_modes=3, hidden=32, layers=2)
    net = build_net(cfg).eval()
    pred = LearnedPredictor(net, cfg)
    rng = np.random.default_rng(2)
    feats = rng.normal(size=(7, NUM_FEATURES)).astype(np.float32)
    prior = rng.normal(size=(7, cfg.steps, 2)).astype(np.float32)
    assert pred._functional() is not None
    traj, probs = pred._forward(feats, prior)
    with torch.inference_mode():
        t_ref, logits = net(torch.from_numpy(feats), torch.from_numpy(prior))
        p_ref = torch.softmax(logits, dim=-1)
    assert _same(traj, t_ref.numpy()) and _same(probs, p_ref.numpy())
    # with a hook registered (on any of its modules, or globally) the net is called as a module
    for register in (net.body[0].register_forward_hook, torch.nn.modules.module.register_module_forward_hook):
        handle = register(lambda m, i, o: o * 2.0 if isinstance(o, torch.Tensor) else None)
        traj, _ = pred._forward(feats, prior)
        with torch.inference_mode():
            hooked = net(torch.from_numpy(feats), torch.from_numpy(prior))[0].numpy()
        assert _same(traj, hooked) and not _same(traj, t_ref.numpy())
        handle.remove()
    assert _same(pred._forward(feats, prior)[0], t_ref.numpy())
