"""Autonomy-B's implicit occupancy model: input, network, files (no pickle), training
(seeded, reproducible), ``--device``, and the stack behind ``make_stack("B")``."""
from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import torch

from adv3d_runner.autonomy.detector import voxelize
from adv3d_runner.autonomy.occupancy import (OccupancyConfig, OccupancyModel, OccupancyNet, bev_input, keep_points,
                                             load_occupancy, save_occupancy, to_current_frame)
from adv3d_runner.errors import ConfigError, FileFormatError

SMALL = dict(x_range=(-8.0, 24.0), y_range=(-8.0, 8.0), channels=(4, 8, 8), features=8, hidden=16)


def _points(rng, n=3000):
    return np.c_[rng.uniform(-30, 90, n), rng.uniform(-30, 30, n), rng.uniform(-0.2, 3.0, n), rng.random(n)]


def test_sweeps_are_voxelised_in_their_own_or_the_current_frame(rng):
    cfg = OccupancyConfig(sweep_frame="map")
    pts = keep_points(_points(rng), cfg)
    assert pts.dtype == np.float32 and pts.shape[1] == 3 and pts[:, 2].min() >= cfg.z_edges[0]
    now, before = np.array([100.0, 50.0, 0.3]), np.array([95.0, 48.0, 0.25])
    grid = bev_input([(pts, now), (pts, before), None], now, cfg)
    per = cfg.channels_per_sweep
    assert grid.shape == (cfg.in_channels, *cfg.grid_shape) and grid.dtype == np.float32
    np.testing.assert_array_equal(grid[:per], voxelize(pts, cfg.voxel_grid))
    np.testing.assert_array_equal(grid[per:2 * per], voxelize(to_current_frame(pts, before, now), cfg.voxel_grid))
    assert not grid[2 * per:].any()  # a missing sweep is zeros
    # the default: every sweep in its own ego frame (the frame moving with the ego)
    own = bev_input([(pts, now), (pts, before), None], now, OccupancyConfig())
    np.testing.assert_array_equal(own[per:2 * per], voxelize(pts, cfg.voxel_grid))
    with pytest.raises(ConfigError):
        OccupancyConfig(sweep_frame="world")
    # to_current_frame is the rigid motion between the two ego frames
    p = np.array([[3.0, -2.0, 1.0]])
    q = to_current_frame(p, before, now)
    c, s = math.cos(before[2]), math.sin(before[2])
    world = before[:2] + [c * 3.0 - s * -2.0, s * 3.0 + c * -2.0]
    c1, s1 = math.cos(now[2]), math.sin(now[2])
    d = world - now[:2]
    np.testing.assert_allclose(q[0, :2], [c1 * d[0] + s1 * d[1], -s1 * d[0] + c1 * d[1]], atol=1e-12)
    assert q[0, 2] == 1.0
    with pytest.raises(ValueError):
        bev_input([None], now, cfg)


def test_training_inputs_are_stored_exactly(rng):
    from adv3d_runner.training.occupancy_data import decode_grid, encode_grid

    cfg = OccupancyConfig()
    pts = keep_points(_points(rng, 40000), cfg)
    now = np.zeros(3)
    grid = bev_input([(pts, now), (pts[::2], now), (pts[::3], now)], now, cfg)
    enc = encode_grid(grid, cfg)
    assert enc.dtype == np.uint8
    np.testing.assert_array_equal(decode_grid(enc, cfg), grid)
    np.testing.assert_array_equal(decode_grid(enc[None], cfg)[0], grid)


def test_network_shapes_and_flow_prior():
    cfg = OccupancyConfig(**SMALL)
    torch.manual_seed(0)
    net = OccupancyNet(cfg).eval()
    x = torch.zeros(2, cfg.in_channels, *cfg.grid_shape)
    z = net.encode(x)
    assert z.shape == (2, cfg.features, cfg.grid_shape[0] // 2, cfg.grid_shape[1] // 2)
    q = torch.tensor([[[0.0, 0.0, 0.0], [30.0, 2.0, 1.5], [500.0, 0.0, 5.0]]]).repeat(2, 1, 1)
    with torch.no_grad():
        net.head[-1].weight.zero_()
        net.head[-1].bias[1:].zero_()
        logit, flow = net.decode(z, q, torch.tensor([20.0, 0.0]))
    assert logit.shape == (2, 3) and flow.shape == (2, 3, 2)
    # a zero residual: the flow is the ego's speed along x (the frame moving with the ego)
    np.testing.assert_allclose(flow[0].numpy(), [[20.0, 0.0]] * 3)
    np.testing.assert_allclose(flow[1].numpy(), 0.0)


def test_field_queries_in_the_map_frame_match_the_ego_frame(rng):
    cfg = OccupancyConfig(**SMALL)
    torch.manual_seed(1)
    model = OccupancyModel(cfg, OccupancyNet(cfg))
    pose = np.array([1000.0, -200.0, 2.0])
    pts = keep_points(_points(rng), cfg)
    field = model.encode([(pts, pose)] * len(cfg.sweep_lags), pose, 25.0)
    local = np.c_[rng.uniform(-5, 20, (50, 2)), rng.uniform(0, 5, 50)]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    xy = pose[:2] + np.c_[c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]]
    o_map, f_map = field.query(xy, local[:, 2])
    o_loc, f_loc = field.query_local(local)
    np.testing.assert_allclose(o_map, o_loc, atol=1e-6)
    np.testing.assert_allclose(f_map, np.c_[c * f_loc[:, 0] - s * f_loc[:, 1], s * f_loc[:, 0] + c * f_loc[:, 1]],
                               atol=1e-4)
    assert np.all((o_map >= 0) & (o_map <= 1))
    assert model.timings["queries"] == 100 and field.horizon == cfg.horizon


def test_save_load_round_trip_and_no_pickle(tmp_path, rng):
    cfg = OccupancyConfig(**SMALL)
    torch.manual_seed(2)
    model = OccupancyModel(cfg, OccupancyNet(cfg))
    save_occupancy(model, tmp_path / "m", {"seed": 2})
    back = load_occupancy(tmp_path / "m")
    assert back.cfg == cfg
    for k, v in model.net.state_dict().items():
        assert torch.equal(v, back.net.state_dict()[k]), k
    # a weights file that needs pickle (an arbitrary object) is refused
    with open(tmp_path / "m" / "occupancy.pt", "wb") as fh:
        pickle.dump({"x": object()}, fh, protocol=2)
    with pytest.raises(FileFormatError, match="weights_only"):
        load_occupancy(tmp_path / "m")
    with pytest.raises(FileFormatError, match="config.json"):
        load_occupancy(tmp_path / "missing")
    (tmp_path / "m" / "config.json").write_text('{"format": "adv3d-occupancy-config", "version": 1, '
                                               '"occupancy": {"resolution": -1}}')
    with pytest.raises(FileFormatError, match=r"\$\.occupancy"):
        load_occupancy(tmp_path / "m")


def _tiny_samples(cfg, n=6, q=64, seed=0):
    """Synthetic samples: a box of points per sample and its ground truth."""
    from adv3d_runner.metrics.occupancy import occupancy_targets
    from adv3d_runner.training.occupancy_data import SampleSet, encode_grid

    rng = np.random.default_rng(seed)
    grids, queries, occ, flow, valid = [], [], [], [], []
    for _ in range(n):
        x, y = rng.uniform(0, 15), rng.uniform(-4, 4)
        car = np.c_[rng.uniform(x - 2, x + 2, 300), rng.uniform(y - 1, y + 1, 300), rng.uniform(0.4, 1.4, 300)]
        grids.append(encode_grid(bev_input([(car, np.zeros(3))] * len(cfg.sweep_lags), np.zeros(3), cfg), cfg))
        qq = np.c_[rng.uniform(-8, 24, q), rng.uniform(-8, 8, q), np.zeros(q)]
        o, f, v = occupancy_targets(qq[:, :2], np.array([[x, y, 4.0, 2.0, 0.0]]), np.array([[x - 5, y, 4.0, 2.0, 0.0]]))
        queries.append(qq)
        occ.append(o)
        flow.append(f)
        valid.append(v)
    return SampleSet(np.stack(grids), np.full(n, 10.0, np.float32), np.stack(queries).astype(np.float32),
                     np.stack(occ), np.stack(flow).astype(np.float32), np.stack(valid), np.zeros(n, np.int64),
                     np.arange(n))


def test_training_is_seeded_and_reproducible():
    from adv3d_runner.training.occupancy_train import evaluate_occupancy, train_occupancy

    cfg = OccupancyConfig(**SMALL)
    data = _tiny_samples(cfg)
    a, ha = train_occupancy(data, data, cfg, epochs=2, batch=3, seed=4, log=lambda s: None)
    b, hb = train_occupancy(data, data, cfg, epochs=2, batch=3, seed=4, log=lambda s: None)
    c, _ = train_occupancy(data, data, cfg, epochs=2, batch=3, seed=5, log=lambda s: None)
    sa, sb, sc = a.net.state_dict(), b.net.state_dict(), c.net.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    assert ha["train_bce"] == hb["train_bce"] and len(ha["epoch"]) == 2
    ev = evaluate_occupancy(a.net, data, cfg)
    assert ev["samples"] == 6 and ev["queries"] == 6 * 64 and ev["epe"] is not None


def test_device_option():
    from adv3d_runner.training.device import device_info, resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert device_info(torch.device("cpu")) == {"device": "cpu"}
    with pytest.raises(ConfigError):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no GPU"):
            resolve_device("cuda")


def test_every_train_command_takes_device():
    import argparse

    from adv3d_runner.training import cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    for model in ("detector", "predictor", "occupancy"):
        assert parser.parse_args(["train", model]).device == "cpu"
        assert parser.parse_args(["train", model, "--device", "auto"]).device == "auto"
        with pytest.raises(SystemExit):
            parser.parse_args(["train", model, "--device", "gpu0"])


@pytest.mark.slow
def test_train_occupancy_cli_quick(tmp_path):
    """`adv3d train occupancy --quick --device auto` writes loadable weights, the report (with
    the device and the times) and the loss plot."""
    import json

    from adv3d_runner.cli import main

    out = tmp_path / "model"
    rc = main(["-q", "train", "occupancy", "--quick", "--scenes", "2", "--val-scenes", "1", "--device", "auto",
               "--cache", str(tmp_path / "cache"), "--out", str(out)])
    assert rc == 0
    for name in ("occupancy.pt", "config.json", "training_report.json", "loss_curves.png"):
        assert (out / name).is_file(), name
    rep = json.loads((out / "training_report.json").read_text())
    assert rep["format"] == "adv3d-occupancy-training-report"
    assert rep["device"]["device"] == ("cuda" if torch.cuda.is_available() else "cpu")
    assert rep["seconds"]["train"] >= 0 and rep["data"]["train_samples"] == 2 * 4
    assert rep["held_out"]["epe"] is not None and len(rep["history"]["epoch"]) == 2
    assert load_occupancy(out).cfg == OccupancyConfig()


def test_make_stack_b_runs_a_short_episode(repo_root):
    """Autonomy-B from the shipped weights: no detections, an occupancy field, occupancy-planned."""
    from adv3d_runner.autonomy.interface import OccupancyField
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sim.episode import run_episode

    if not (repo_root / "assets" / "models" / "occupancy" / "config.json").is_file():
        pytest.skip("no shipped occupancy model")
    scene = load_scene(repo_root / "scenes" / "highway" / "highway-benchmark-000010.json.gz")
    r = run_episode(scene, make_stack("B"), seconds=0.5, library=None)
    assert r.frames == 5
    for o in r.outputs:
        assert len(o.detections) == 0 and len(o.predictions) == 0
        assert isinstance(o.occupancy, OccupancyField)
        assert "occupancy_collision" in o.plan.cost_terms
    assert r.timings["occupancy"].min() > 0 and r.timings["detector"].max() == 0
