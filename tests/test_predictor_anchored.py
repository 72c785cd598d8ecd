"""The anchored predictor (docs/predictor.md): lane-following anchors, the model file of version 2,
fixed modes, and the training data of every vehicle of a recording."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).parent))
from test_predictor import predict_on, straight_lanes, straight_track  # noqa: E402

from adv3d_runner.autonomy.baselines import LaneFollowingPredictor  # noqa: E402
from adv3d_runner.autonomy.predictor import (CONFIG_NAME, PATH_S, PredictorConfig, anchor_speed,  # noqa: E402
                                             anchor_trajectories, build_net, encode, lane_paths, load_predictor,
                                             save_predictor)
from adv3d_runner.errors import FileFormatError  # noqa: E402
from adv3d_runner.scene.lanemap import LaneMap  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
ACCELS = (0.0, 0.4, -0.4, 1.0, -1.0, -2.0)


def test_anchors_follow_the_lane_at_their_speed_profiles():
    """On a straight lane: the keep-speed anchor is the prior; a braking anchor stops after
    v^2 / 2a and stays; an accelerating one covers v t + a t^2 / 2; all stay on the track's line."""
    lanes, d, nrm = straight_lanes(0.3)
    t, _ = straight_track(d, nrm, 12.0, lateral=0.6)
    lane_map = LaneMap(lanes)
    feats, prior = encode(t, lane_map)
    path = lane_paths(t, lane_map)
    assert path.shape == (1, len(PATH_S), 2)
    speed = anchor_speed(feats)
    assert speed[0] == pytest.approx(12.0, abs=1e-4)
    a = anchor_trajectories(path, speed, (1.0,) * 6, ACCELS)
    assert a.shape == (1, 6, 60, 2)
    assert np.allclose(a[0, 0], prior[0], atol=1e-3)                      # keep speed = the prior
    time = np.arange(1, 61) * 0.1
    assert np.allclose(a[0, 3, :, 0], 12.0 * time + 0.5 * time ** 2, atol=1e-3)
    assert a[0, 5, -1, 0] == pytest.approx(12.0 ** 2 / 4.0, abs=1e-3)      # stopped at 36 m
    assert np.all(np.diff(a[0, :, :, 0], axis=-1) >= -1e-9)               # never backwards
    assert np.allclose(a[0, :, :, 1], 0.0, atol=1e-3)                     # lateral offset kept


def test_anchors_with_the_baselines_speed_factors_are_lane_following():
    """Anchors with the speed factors of LaneFollowingPredictor and no acceleration reproduce
    that baseline (to the 2 m spacing of the lane path)."""
    lanes, d, nrm = straight_lanes(-1.1)
    t, p0 = straight_track(d, nrm, 25.0, lateral=-0.4)
    lane_map = LaneMap(lanes)
    feats, _ = encode(t, lane_map)
    local = anchor_trajectories(lane_paths(t, lane_map), anchor_speed(feats), (1.0, 0.8, 1.15), (0.0, 0.0, 0.0))
    lf = LaneFollowingPredictor()
    lf.reset(lane_map)
    ref = lf.predict(t).trajectories
    from adv3d_runner.autonomy.predictor import to_map_frame
    assert np.abs(to_map_frame(local, np.asarray(t.boxes, float)) - ref).max() < 0.05


def _anchored(tmp_path, fixed=()):
    torch.manual_seed(0)
    cfg = PredictorConfig(num_modes=6, hidden=32, layers=2, residual_scale=0.5, anchor_scales=(1.0,) * 6,
                          anchor_accels=ACCELS)
    net = build_net(cfg)
    save_predictor(net, cfg, tmp_path / "m")
    return net, cfg, load_predictor(tmp_path / "m")


def test_untrained_anchored_model_predicts_its_anchors_and_round_trips(tmp_path):
    """The trajectory head starts at zero: an untrained anchored model is its anchor set; the
    file (version 2) loads back to the same configuration and predictions."""
    net, cfg, p = _anchored(tmp_path)
    assert p.config == cfg and p.config.anchored
    lanes, d, nrm = straight_lanes(0.4)
    t, _ = straight_track(d, nrm, 15.0)
    out = predict_on(p, t, lanes)
    lane_map = LaneMap(lanes)
    feats, _ = encode(t, lane_map)
    from adv3d_runner.autonomy.predictor import to_map_frame
    anchors = anchor_trajectories(lane_paths(t, lane_map), anchor_speed(feats), cfg.anchor_scales, cfg.anchor_accels)
    assert np.abs(out.trajectories - to_map_frame(anchors, np.asarray(t.boxes, float))).max() < 1e-3
    assert np.allclose(out.probabilities.sum(1), 1.0)
    # predict_local on precomputed arrays needs the lane paths
    with pytest.raises(ValueError, match="lane paths"):
        p.predict_local(feats, encode(t, lane_map)[1])


def test_anchored_config_is_checked(tmp_path):
    import json

    _anchored(tmp_path)
    path = tmp_path / "m" / CONFIG_NAME
    doc = json.loads(path.read_text())
    assert doc["version"] == 2
    bad = dict(doc, config=dict(doc["config"], anchor_accels=[0.0, 1.0]))
    path.write_text(json.dumps(bad))
    with pytest.raises(FileFormatError, match="anchor_accels"):
        load_predictor(tmp_path / "m")
    old = dict(doc, version=1)  # a version-1 file has no anchors
    path.write_text(json.dumps(old))
    with pytest.raises(FileFormatError, match="anchor_"):
        load_predictor(tmp_path / "m")


def test_recording_samples_take_every_vehicle_and_the_ego():
    """Every vehicle of the recording, the ego included and beyond the ego's 80 m, recorded
    frames only; deterministic per draw, different between draws."""
    from adv3d_runner.scene import load_scene
    from adv3d_runner.training.predictor_data import ARRAYS, real_scene_samples, recording_samples

    scene = load_scene(REPO / "scenes" / "real" / "USA_US101-5_1_T-1.json.gz")
    a, b, c = recording_samples(scene, 0), recording_samples(scene, 0), recording_samples(scene, 1)
    assert all(np.array_equal(a[k], b[k]) for k in ARRAYS)
    assert not np.array_equal(a["features"], c["features"])
    assert len(a["features"]) > len(real_scene_samples(scene)["features"])
    assert a["future_valid"].sum(axis=1).min() >= 30 and a["path"].shape[1:] == (len(PATH_S), 2)


@pytest.mark.slow
def test_training_command_writes_a_loadable_model_and_is_reproducible(tmp_path):
    """``python -m adv3d_runner.training.predictor_anchored`` (= ``adv3d train predictor``) on a
    little data: the model loads, its report names the train recordings only and holds the curves,
    and the same seed gives the same weights; a second run to the same folder needs --force; the
    fixed modes keep their anchors."""
    import json

    from adv3d_runner.training.predictor_anchored import main

    args = ["--epochs", "1", "--gen-scenes", "1", "--val-scenes", "1", "--draws", "1", "--cache", str(tmp_path / "c"),
            "--val-recording", "5", "--fixed-modes", "0"]
    assert main(["--out", str(tmp_path / "a")] + args) == 0
    assert main(["--out", str(tmp_path / "b")] + args) == 0
    a, b = (tmp_path / "a" / "weights.pt").read_bytes(), (tmp_path / "b" / "weights.pt").read_bytes()
    assert a == b
    assert main(["--out", str(tmp_path / "b")] + args) == 2  # a model is there: refused without --force
    assert main(["--out", str(tmp_path / "b"), "--force"] + args) == 0
    assert (tmp_path / "b" / "weights.pt").read_bytes() == a
    rep = json.loads((tmp_path / "a" / "training_report.json").read_text())
    assert rep["command"].startswith("adv3d train predictor --out ")
    assert rep["data"]["real"]["recordings"] == [1, 2, 3, 8] and rep["data"]["real"]["validation_recording"] == 5
    assert len(rep["curves"]["train_loss"]) == 1 and "validation_recording_5" in rep["held_out"]
    model = load_predictor(tmp_path / "a")
    assert model.config.anchored
    T = model.config.steps
    w = model.net.traj.weight.detach().numpy()
    assert np.all(w[:2 * T] == 0.0) and np.any(w[2 * T:] != 0.0)
