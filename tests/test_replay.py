"""Replay file: exact round trip, named errors for malformed fields, the simulate command."""
from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.fileio import REPO_ROOT, read_json, write_json
from adv3d_runner.sim.replay import (Replay, ReplayActor, ReplayFrame, load_replay, points_path, replay_equal,
                                     replay_from_dict, replay_to_dict, save_replay)


def _replay(rng, T=4, with_points=True) -> Replay:
    actors = []
    for i, aid in enumerate((3, 7, 12)):
        poses = np.c_[rng.uniform(-500, 500, (T, 2)), rng.uniform(-np.pi, np.pi, T)]
        poses[i % T] = np.nan  # absent in one frame
        actors.append(ReplayActor(aid, "sedan", rng.uniform(1, 5, 3), poses, adversarial=(i == 0),
                                  mesh="adv_3.ply" if i == 0 else None))
    frames = []
    for k in range(T):
        d, m, p = k % 3, (k + 1) % 3, k % 2 * 2
        frames.append(ReplayFrame(rng.normal(0, 50, (d, 5)), rng.random(d), np.arange(m) + 10 * k,
                                  rng.normal(0, 50, (m, 5)), rng.normal(0, 5, (m, 2)), np.arange(p),
                                  rng.normal(0, 50, (p, 3, 60, 2)), rng.dirichlet(np.ones(3), p),
                                  rng.normal(0, 50, (51, 3)), rng.uniform(0, 30, 51), f"lane{k}", float(k) * 1.23456789))
    points = None
    if with_points:
        points = []
        for k in range(T):
            n = 0 if k == 1 else 200  # one frame without points
            points.append(np.c_[rng.uniform(-120, 120, (n, 3)), rng.random(n), rng.integers(-1, 3, n)].astype(np.float32))
    return Replay("scene-x", 0.1, [4.8, 1.9, 1.55], np.c_[rng.normal(0, 100, (T, 2)), rng.uniform(-3, 3, T)],
                  rng.uniform(0, 30, T), actors, frames, start_frame=2, closed_loop=False, reactive=True, seed=5,
                  autonomy="oracle", scene_file="scenes/x.json.gz", points=points, metadata={"cost": 1.5})


@pytest.mark.parametrize("name", ["r.json", "r.json.gz"])
def test_round_trip_is_exact(tmp_path, rng, name):
    rp = _replay(rng)
    path = save_replay(rp, tmp_path / name)
    assert points_path(path).exists()
    back = load_replay(path)
    assert replay_equal(rp, back)
    assert back.actors[0].adversarial and back.actors[0].mesh == "adv_3.ply"
    assert np.isnan(back.actors[1].poses[1]).all() and len(back.points[1]) == 0
    # and again: load -> save -> load gives the same document
    save_replay(back, tmp_path / ("again_" + name))
    assert replay_equal(back, load_replay(tmp_path / ("again_" + name)))
    assert replay_to_dict(back, "x") == replay_to_dict(load_replay(tmp_path / ("again_" + name)), "x")
    # without points
    assert load_replay(path, points=False).points is None


def test_quantisation_is_small(rng):
    rp = _replay(rng, with_points=False)
    raw = np.array([1.23456789, -2.0000004, 3.14159265])
    f = ReplayFrame(np.zeros((0, 5)), [], [], np.zeros((0, 5)), np.zeros((0, 2)), [], np.zeros((0, 3, 60, 2)),
                    np.zeros((0, 3)), np.c_[raw, raw, raw], raw, "", 0.0)
    assert np.abs(f.plan - raw[:, None]).max() < 6e-4
    assert replay_equal(rp, replay_from_dict(json.loads(json.dumps(replay_to_dict(rp)))))


def _doc(rng):
    return replay_to_dict(_replay(rng, with_points=False))


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(format="adv3d-scene"), "$.format"),
    (lambda d: d.update(version=3), "$.version"),
    (lambda d: d["scene"].pop("id"), "$.scene.id"),
    (lambda d: d.update(frames=-1), "$.frames"),
    (lambda d: d["ego"].update(speed=[1.0, 2.0]), "$.ego.speed"),
    (lambda d: d["ego"]["poses"].__setitem__(2, None), "$.ego.poses[2]"),
    (lambda d: d["actors"][1]["poses"].__setitem__(0, [1.0, "a", 2.0]), "$.actors[1].poses[0]"),
    (lambda d: d["actors"][2].update(id=3), "$.actors[2].id"),
    (lambda d: d["actors"][0].update(dimensions=[1.0, 2.0]), "$.actors[0].dimensions"),
    (lambda d: d["outputs"].pop(), "$.outputs"),
    (lambda d: d["outputs"][2]["detections"].update(scores=[0.5, 0.5, 0.5, 0.5]), "$.outputs[2].detections.scores"),
    (lambda d: d["outputs"][1]["tracks"].update(boxes=[[1, 2, 3]]), "$.outputs[1].tracks.boxes"),
    (lambda d: d["outputs"][1]["predictions"].update(trajectories=[[[[0.0, 0.0]]]]), "$.outputs[1].predictions.trajectories"),
    (lambda d: d["outputs"][0]["plan"].update(speed=[1.0]), "$.outputs[0].plan.speed"),
    (lambda d: d["outputs"][0]["plan"]["trajectory"][3].__setitem__(1, None), "$.outputs[0].plan.trajectory[3][1]"),
    (lambda d: d.update(metadata=[1]), "$.metadata"),
])
def test_malformed_fields_are_named(tmp_path, rng, mutate, field):
    doc = _doc(rng)
    mutate(doc)
    path = tmp_path / "bad.json"
    write_json(path, doc)
    with pytest.raises(FileFormatError) as err:
        load_replay(path)
    assert err.value.field == field, str(err.value)
    assert str(path) in str(err.value)


def test_bad_points_file(tmp_path, rng):
    path = save_replay(_replay(rng), tmp_path / "r.json.gz")
    pp = points_path(path)
    with np.load(pp, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    bad = dict(data, label=np.full_like(data["label"], 7))
    np.savez(pp, **bad)
    with pytest.raises(FileFormatError) as err:
        load_replay(path)
    assert err.value.field == "$.label"
    np.savez(pp, **dict(data, offsets=data["offsets"][:-1]))
    with pytest.raises(FileFormatError) as err:
        load_replay(path)
    assert err.value.field == "$.offsets"
    np.savez(pp, **dict(data, label=np.array([{"a": 1}], dtype=object)))  # needs pickle: refused
    with pytest.raises(FileFormatError):
        load_replay(path)
    pp.unlink()
    with pytest.raises(FileFormatError):
        load_replay(path)
    assert load_replay(path, points=False).points is None


def test_not_json(tmp_path):
    p = tmp_path / "r.json.gz"
    p.write_bytes(gzip.compress(b"{not json"))
    with pytest.raises(FileFormatError):
        load_replay(p)


def test_simulate_command_writes_metrics_and_replay(tmp_path):
    from adv3d_runner.cli import main

    out = tmp_path / "sim"
    rc = main(["--quiet", "simulate", str(REPO_ROOT / "scenes/highway/highway-benchmark-000001.json.gz"),
               "--seconds", "0.5", "--autonomy", "oracle", "--library", "none", "--points", "--out", str(out)])
    assert rc == 0
    m = read_json(out / "metrics.json")
    assert m["format"] == "adv3d-episode-metrics" and m["frames"] == 5 and m["autonomy"] == "oracle"
    rp = load_replay(out / "replay.json.gz")
    assert rp.n_frames == 5 and len(rp.points) == 5 and all(len(p) > 1000 for p in rp.points)
    assert rp.points_in_map(0).shape == (len(rp.points[0]), 3)
    assert np.isfinite(rp.frames[-1].plan).all() and len(rp.frames[-1].plan) > 10
    # the replay's ego is the episode's: progress in metrics = path length of the poses
    path = float(np.sum(np.hypot(*np.diff(rp.ego_poses[:, :2], axis=0).T)))
    assert path == pytest.approx(m["progress_m"], abs=0.01)


def test_simulate_autonomy_b_writes_occupancy_metrics_and_maps(tmp_path):
    """``adv3d simulate --autonomy B`` with the shipped occupancy model: the metrics have the
    occupancy block instead of detection and prediction, the replay (version 2) a heat map per
    frame."""
    from adv3d_runner.cli import main

    if not (REPO_ROOT / "assets" / "models" / "occupancy" / "config.json").is_file():
        pytest.skip("no shipped occupancy model")
    out = tmp_path / "simB"
    assert main(["--quiet", "simulate", str(REPO_ROOT / "scenes/highway/highway-benchmark-000001.json.gz"),
                 "--seconds", "0.3", "--autonomy", "B", "--library", "none", "--out", str(out)]) == 0
    m = read_json(out / "metrics.json")
    assert m["autonomy"] == "B" and m["detection"] is None and m["prediction"] is None
    assert set(m["occupancy"]) >= {"map", "soft_iou", "flow_grounded_map", "flow_grounded_soft_iou", "epe"}
    assert m["ms_per_frame"]["occupancy"] > 0 and m["ms_per_frame"]["detector"] == 0
    assert read_json(out / "replay.json.gz")["version"] == 2
    rp = load_replay(out / "replay.json.gz")
    assert all(f.occupancy is not None and f.occupancy.values.shape == (4, 80, 32) for f in rp.frames)


def test_docs_example_loads(tmp_path):
    text = (REPO_ROOT / "docs" / "formats.md").read_text()
    section = text.split("## Replay", 1)[1].split("\n## ", 1)[0]
    doc = json.loads(section.split("```json", 1)[1].split("```", 1)[0])
    path = tmp_path / "replay.json"
    write_json(path, doc)
    rp = load_replay(path, points=False)
    assert rp.n_frames == 2 and rp.actors[0].adversarial and np.isnan(rp.actors[0].poses[1]).all()
    assert rp.frames[1].pred_trajectories.shape == (1, 3, 2, 2)


# ------------------------------------------------------------------ occupancy maps (version 2)

class _Field:
    """A hand-made occupancy field: one 4 x 2 m box at (10, 0) moving at 5 m/s along +x."""

    horizon = 5.0
    pose = np.zeros(3)

    def query(self, xy, t):
        xy = np.asarray(xy, float).reshape(-1, 2)
        t = np.broadcast_to(np.asarray(t, float), (len(xy),))
        inside = (np.abs(xy[:, 0] - 10.0 - 5.0 * t) <= 2.0) & (np.abs(xy[:, 1]) <= 1.0)
        return np.where(inside, 0.9, 0.02), np.tile([5.0, 0.0], (len(xy), 1))


def test_occupancy_map_samples_the_field_on_a_moving_grid():
    from adv3d_runner.sim.replay import occupancy_map

    m = occupancy_map(_Field(), np.array([10.0, 0.0]), 0.0, 5.0, times=(0.0, 2.0), cell=0.5, size=(8.0, 4.0))
    assert m.values.shape == (2, 16, 8) and m.values.dtype == np.uint8
    np.testing.assert_allclose(m.poses[:, :2], [[10.0, 0.0], [20.0, 0.0]])  # carried at 5 m/s
    for k in range(2):  # the box sits in the middle of each grid: 4 x 2 m = 8 x 4 cells of 0.9
        assert (m.values[k] == 230).sum() == 8 * 4 and (m.values[k] == 5).sum() == 16 * 8 - 32
        c = m.cell_centres(k)[m.values[k] == 230]
        np.testing.assert_allclose(c.mean(axis=0), m.poses[k, :2], atol=1e-9)


def _with_maps(rp):
    from adv3d_runner.sim.replay import OccupancyMap

    rng = np.random.default_rng(1)
    for k, f in enumerate(rp.frames):
        if k != 1:  # one frame without a map
            f.occupancy = OccupancyMap([0.0, 1.5], rng.normal(0, 50, (2, 3)), 0.5, rng.integers(0, 256, (2, 6, 4)))
    return rp


def test_occupancy_maps_round_trip_as_version_2(tmp_path, rng):
    rp = _with_maps(_replay(rng))
    path = save_replay(rp, tmp_path / "r.json.gz")
    doc = read_json(path)
    assert doc["version"] == 2 and doc["outputs"][1]["occupancy"] is None
    assert doc["outputs"][0]["occupancy"]["shape"] == [6, 4]
    back = load_replay(path)
    assert replay_equal(rp, back) and back.frames[1].occupancy is None
    assert np.array_equal(back.frames[2].occupancy.values, rp.frames[2].occupancy.values)
    # a replay without maps stays version 1, byte for byte as before
    assert replay_to_dict(_replay(np.random.default_rng(0)))["version"] == 1
    other = _with_maps(_replay(np.random.default_rng(0)))
    other.frames[0].occupancy.values = other.frames[0].occupancy.values.copy()
    other.frames[0].occupancy.values[0, 0, 0] ^= 1
    assert not replay_equal(_with_maps(_replay(np.random.default_rng(0))), other)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(version=1), "$.outputs[0].occupancy"),
    (lambda d: d["outputs"][0]["occupancy"].update(values=[[[300]]]), "$.outputs[0].occupancy.values"),
    (lambda d: d["outputs"][0]["occupancy"]["values"][1][2].__setitem__(3, 0.5), "$.outputs[0].occupancy.values"),
    (lambda d: d["outputs"][0]["occupancy"].update(shape=[6]), "$.outputs[0].occupancy.shape"),
    (lambda d: d["outputs"][2]["occupancy"].update(poses=[[1.0, 2.0, 3.0]]), "$.outputs[2].occupancy.poses"),
    (lambda d: d["outputs"][2]["occupancy"].update(cell=0), "$.outputs[2].occupancy.cell"),
    (lambda d: d["outputs"][2]["occupancy"].pop("times"), "$.outputs[2].occupancy.times"),
])
def test_malformed_occupancy_maps_are_named(tmp_path, rng, mutate, field):
    doc = replay_to_dict(_with_maps(_replay(rng, with_points=False)))
    mutate(doc)
    path = tmp_path / "bad.json"
    write_json(path, doc)
    with pytest.raises(FileFormatError) as err:
        load_replay(path)
    assert err.value.field == field, str(err.value)
