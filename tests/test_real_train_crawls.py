"""``scenes/real-train-crawls`` (``bench/real_train_crawls.py``): standstill starts made from the
train recordings by playing their queues backwards (docs/benchmark.md)."""
from __future__ import annotations

import gzip
import importlib.util
import math
from pathlib import Path

import numpy as np

from adv3d_runner.geometry.angles import wrap_angle
from adv3d_runner.scene import load_scene
from adv3d_runner.scene.real import load_real_split, recording_of

REPO = Path(__file__).resolve().parents[1]
FOLDER = REPO / "scenes" / "real-train-crawls"


def _script():
    spec = importlib.util.spec_from_file_location("real_train_crawls", REPO / "bench" / "real_train_crawls.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_kept_crawls_are_train_recordings_standstill_starts_and_valid():
    crawls = _script()
    train = set(load_real_split().recordings["train"])
    rows = (FOLDER / "index.csv").read_text().splitlines()
    header, rows = rows[0].split(","), [dict(zip(rows[0].split(","), r.split(","))) for r in rows[1:]]
    files = sorted(FOLDER.glob("*.json.gz"))
    assert header[:3] == ["scene", "source", "first_frame"] and len(rows) == len(files) >= 4
    for row in rows:
        scene = load_scene(FOLDER / f"{row['scene']}.json.gz")  # loading validates the scene
        details = scene.source.details
        assert recording_of(details["benchmark_id"]) in train
        assert scene.id == f"commonroad-{row['scene']}" and details["first_frame"] == int(row["first_frame"])
        info = crawls.standstill_start(scene)
        assert info is not None and info["speed0"] <= crawls.MAX_START_SPEED
        assert info["leader_gap"] <= crawls.MAX_LEADER_GAP and info["logged_progress"] >= crawls.MIN_LOGGED_PROGRESS
        assert str(info["leader"]) == row["leader"] and scene.frames >= 70


def test_rebuild_gives_the_kept_files_byte_for_byte(tmp_path):
    _script().build(tmp_path)
    kept = sorted(p.name for p in FOLDER.iterdir() if p.suffix in (".gz", ".csv"))
    assert sorted(p.name for p in tmp_path.iterdir()) == kept
    for name in kept:
        a, b = (FOLDER / name).read_bytes(), (tmp_path / name).read_bytes()
        if name.endswith(".gz"):  # the gzip header holds a time stamp
            a, b = gzip.decompress(a), gzip.decompress(b)
        assert a == b, name


def test_reversing_twice_gives_the_scene_back_and_a_stop_becomes_a_move_off():
    crawls = _script()
    src = load_scene(REPO / "scenes" / "real-train-egos" / "USA_US101-5_2_T-1.ego523.json.gz")
    rev = crawls.reverse_scene(src, "commonroad-reversed")
    v = np.asarray(src.ego.track.speed)
    assert v[-1] == 0.0 and v[0] > 5.0  # brakes into the queue and stands ...
    assert np.array_equal(np.asarray(rev.ego.track.speed), v[::-1])  # ... reversed: stands, then moves off
    # driving forward along the mirrored lane: heading turned by pi, position moves along it
    e = rev.ego.track
    k = len(v) - 1
    step = np.array([e.x[k] - e.x[k - 5], e.y[k] - e.y[k - 5]])
    assert step @ np.array([math.cos(e.yaw[k]), math.sin(e.yaw[k])]) > 0.0
    back = crawls.reverse_scene(rev, src.id).to_dict()
    orig = src.to_dict()
    for key in ("map", "background", "frames"):
        assert back[key] == orig[key]
    for a, b in zip([orig["ego"]] + orig["actors"], [back["ego"]] + back["actors"]):
        assert a["track"]["start"] == b["track"]["start"] and a["track"]["x"] == b["track"]["x"]
        turn = wrap_angle(np.asarray(a["track"]["yaw"]) - np.asarray(b["track"]["yaw"]))
        assert np.abs(turn).max() <= 1.5e-3  # two turns by pi, each rounded to 1e-3 rad


ROLLING = REPO / "scenes" / "real-train-crawls-rolling"


def test_rolling_starts_are_the_crawls_with_only_the_start_speed_changed(tmp_path):
    """``scenes/real-train-crawls-rolling`` (``--rolling``): every crawl that stands >= 1 s, at
    0.5, 1 and 1.5 m/s at frame 0, nothing else changed; rebuilt byte for byte."""
    crawls = _script()
    rows = (ROLLING / "index.csv").read_text().splitlines()
    rows = [dict(zip(rows[0].split(","), r.split(","))) for r in rows[1:]]
    standing = [r for r in (FOLDER / "index.csv").read_text().splitlines()[1:]
                if float(r.split(",")[-1]) >= crawls.ROLLING_MIN_STANDING]
    assert len(rows) == len(standing) * len(crawls.ROLLING_SPEEDS) >= 9
    for row in rows:
        scene = load_scene(ROLLING / f"{row['scene']}.json.gz")  # loading validates the scene
        crawl = load_scene(FOLDER / f"{row['crawl']}.json.gz")
        a, b = scene.to_dict(), crawl.to_dict()
        assert scene.ego.track.speed[0] == float(row["start_speed"]) > 0.0 == crawl.ego.track.speed[0]
        assert a["ego"]["track"]["speed"][1:] == b["ego"]["track"]["speed"][1:]
        for key in ("x", "y", "yaw"):
            assert a["ego"]["track"][key] == b["ego"]["track"][key]
        assert a["actors"] == b["actors"] and a["map"] == b["map"] and a["frames"] == b["frames"]
        assert scene.source.details["rolling_start_mps"] == float(row["start_speed"])
    crawls.build_rolling(tmp_path)
    kept = sorted(p.name for p in ROLLING.iterdir() if p.suffix in (".gz", ".csv"))
    assert sorted(p.name for p in tmp_path.iterdir()) == kept
    for name in kept:
        x, y = (ROLLING / name).read_bytes(), (tmp_path / name).read_bytes()
        if name.endswith(".gz"):
            x, y = gzip.decompress(x), gzip.decompress(y)
        assert x == y, name
