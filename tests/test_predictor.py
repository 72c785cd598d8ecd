"""Learned predictor: shipped weights, shapes, map-frame geometry, degenerate inputs, data
determinism, and the shipped model against constant velocity on held-out training-split scenes."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from adv3d_runner.autonomy.baselines import ConstantVelocityPredictor  # noqa: E402
from adv3d_runner.autonomy.interface import Tracks  # noqa: E402
from adv3d_runner.autonomy.predictor import (CONFIG_NAME, DEFAULT_MODEL_DIR, NUM_FEATURES, WEIGHTS_NAME,  # noqa: E402
                                             PredictorConfig, agent_features, build_net, lane_index,
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
    rc = main(["-q", "train", "predictor", "--quick", "--scenes", "1", "--val-scenes", "1", "--epochs", "1",
               "--seed", "100011", "--cache", str(tmp_path / "cache"), "--out", str(out)])
    assert rc == 0
    for name in ("weights.pt", "config.json", "training_report.json", "loss_curves.png"):
        assert (out / name).is_file(), name
    import json

    rep = json.loads((out / "training_report.json").read_text())
    assert rep["format"] == "adv3d-predictor-training-report"
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
