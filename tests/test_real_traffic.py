"""The real-traffic benchmark (docs/scenes.md, docs/autonomy.md): every bundled real scene validated, the split by
recording, the importer's ego rank, real training samples, traffic statistics and the
generator's us101 profile."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.errors import ConfigError, FileFormatError
from adv3d_runner.scene.real import PARTS, load_real_split, recording_of
from adv3d_runner.scene.schema import load_scene, save_scene, scene_equal

REPO = Path(__file__).resolve().parent.parent
REAL = REPO / "scenes" / "real"
SOURCE = REPO.parent / "shared" / "scenarios" / "commonroad-us101"
needs_source = pytest.mark.skipif(not (SOURCE / "USA_US101-4_3_T-1.xml").exists(),
                                  reason="CommonRoad source scenarios not present")


def test_every_real_scene_is_valid_and_in_exactly_one_part():
    split = load_real_split()
    files = sorted(p.name for p in REAL.glob("*.json.gz"))
    listed = sorted(f"{n}.json.gz" for part in PARTS for n in split.scenes[part])
    assert files == listed and len(files) == 21  # every shared CommonRoad file, once
    assert not set(split.recordings["train"]) & set(split.recordings["benchmark"])
    for part in PARTS:
        for path in split.paths(part):
            scene = load_scene(path)  # validates the whole file
            details = scene.source.details
            assert recording_of(details["benchmark_id"]) in split.recordings[part]
            assert scene.frames == 100 and np.isfinite(scene.ego_poses()).all()
            assert "BSD-3-Clause" in scene.source.licence and "NGSIM" in scene.source.attribution
    # variants of a recording are different scenes: their egos differ
    egos = {}
    for part in PARTS:
        for path in split.paths(part):
            d = load_scene(path).source.details
            key = (recording_of(d["benchmark_id"]), d["recorded_frames"], d["ego_obstacle_id"])
            assert key not in egos, f"{path.name} repeats {egos.get(key)}"
            egos[key] = path.name


def test_extra_train_egos_are_other_cars_of_the_train_recordings_only():
    """``scenes/real-train-egos`` (``bench/real_train_egos.py``): tuning scenes with other recorded
    cars as the ego; none from a benchmark recording, none repeating an ego of ``scenes/real``."""
    split = load_real_split()
    taken = set()
    for part in PARTS:
        for path in split.paths(part):
            d = load_scene(path).source.details
            taken.add((recording_of(d["benchmark_id"]), d["ego_obstacle_id"]))
    folder = REPO / "scenes" / "real-train-egos"
    files = sorted(folder.glob("*.json.gz"))
    index = (folder / "index.csv").read_text().splitlines()[1:]
    assert len(files) == len(index) == 33
    seen = set()
    for path in files:
        scene = load_scene(path)
        d = scene.source.details
        key = (recording_of(d["benchmark_id"]), d["ego_obstacle_id"])
        assert key[0] in split.recordings["train"] and key not in taken and key not in seen
        seen.add(key)
        assert scene.id == f"commonroad-{path.name[:-len('.json.gz')]}" and scene.frames == 100
        assert "BSD-3-Clause" in scene.source.licence


def _write_split(tmp_path, doc):
    for part in PARTS:
        for name in doc["scenes"][part]:
            (tmp_path / f"{name}.json.gz").write_bytes(b"")
    path = tmp_path / "split.json"
    path.write_text(json.dumps(doc))
    return path


def test_split_file_is_checked(tmp_path):
    good = {"format": "adv3d-real-split", "version": 1,
            "recordings": {"train": [1, 2], "benchmark": [4]},
            "scenes": {"train": ["USA_US101-1_1_T-1", "USA_US101-2_1_T-1"], "benchmark": ["USA_US101-4_1_T-1"]}}
    split = load_real_split(_write_split(tmp_path, good))
    assert split.recordings == {"train": (1, 2), "benchmark": (4,)}
    assert [p.name for p in split.paths("benchmark")] == ["USA_US101-4_1_T-1.json.gz"]
    bad = json.loads(json.dumps(good))
    bad["recordings"]["benchmark"] = [4, 2]  # a recording in both parts
    with pytest.raises(FileFormatError, match=r"split.json.*\$\.recordings\.benchmark\[1\]"):
        load_real_split(_write_split(tmp_path, bad))
    bad = json.loads(json.dumps(good))
    bad["scenes"]["benchmark"] = ["USA_US101-2_2_T-1"]  # a train recording's variant in the benchmark
    with pytest.raises(FileFormatError, match=r"\$\.scenes\.benchmark\[0\]"):
        load_real_split(_write_split(tmp_path, bad))
    bad = json.loads(json.dumps(good))
    path = _write_split(tmp_path, bad)
    (tmp_path / "USA_US101-4_1_T-1.json.gz").unlink()
    with pytest.raises(FileFormatError, match="file USA_US101-4_1_T-1.json.gz"):
        load_real_split(path)
    assert recording_of("USA_US101-9_4_T-1") == 9
    with pytest.raises(ValueError):
        recording_of("highway-benchmark-000001")


def test_scenes_validate_skips_the_split_manifest(capsys):
    from adv3d_runner.cli import main

    assert main(["scenes", "validate", str(REAL)]) == 0
    assert "21 of 21 scene file(s) valid" in capsys.readouterr().out


@needs_source
def test_ego_rank_gives_variants_their_own_ego(tmp_path):
    from adv3d_runner.cli import main
    from adv3d_runner.scene.commonroad import import_commonroad

    first = import_commonroad(SOURCE / "USA_US101-4_3_T-1.xml", seconds=10, extend=True)
    other = load_scene(REAL / "USA_US101-4_1_T-1.json.gz")  # another variant: same traffic, same ego rule
    assert np.allclose(first.ego_poses(), other.ego_poses()) and first.actor_ids == other.actor_ids
    out = tmp_path / "x.json.gz"
    assert main(["-q", "scenes", "import-commonroad", str(SOURCE / "USA_US101-4_3_T-1.xml"), "--out", str(out),
                 "--seconds", "10", "--extend", "--ego-rank", "1"]) == 0
    second = load_scene(out)
    shipped = load_scene(REAL / "USA_US101-4_3_T-1.json.gz")  # also records its meshes (docs/library.md)
    assert scene_equal(second, replace(shipped, actors=[replace(a, asset=None) for a in shipped.actors]))
    assert second.source.details["ego_obstacle_id"] != first.source.details["ego_obstacle_id"]
    assert first.source.details["ego_obstacle_id"] in second.actor_ids  # the rank-0 car is now an actor
    with pytest.raises(ConfigError, match="only 2 car"):
        import_commonroad(SOURCE / "USA_US101-1_1_T-1.xml", seconds=10, extend=True, ego_rank=2)
    with pytest.raises(ConfigError):
        import_commonroad(SOURCE / "USA_US101-1_1_T-1.xml", ego_id=489, ego_rank=1)


def test_real_training_samples_use_recorded_frames_only():
    from adv3d_runner.training.predictor_data import ARRAYS, real_scene_samples

    short = load_scene(REAL / "USA_US101-3_3_T-1.json.gz")  # 3.2 s recorded, the rest extrapolated
    assert len(real_scene_samples(short)["features"]) == 0  # never 3 s of recorded future
    scene = load_scene(REAL / "USA_US101-5_1_T-1.json.gz")
    a, b = real_scene_samples(scene), real_scene_samples(scene)
    assert len(a["features"]) > 100 and all(np.array_equal(a[k], b[k]) for k in ARRAYS)
    assert np.all(a["seed"] < 0)  # never a generator seed
    assert a["future_valid"].sum(axis=1).min() >= 30


def test_traffic_statistics():
    from adv3d_runner.scene.traffic_stats import _count_lane_changes, compare, ks_distance, traffic_samples

    assert ks_distance(np.arange(10.0), np.arange(10.0)) == 0.0
    assert ks_distance(np.zeros(5), np.ones(7)) == 1.0
    assert ks_distance(np.array([0.0, 1.0]), np.array([1.0, 1.0])) == 0.5
    pairs = {(1, 2), (2, 1)}
    ids = np.array([1, 1, 2, 1, 2, 2, 2, 2, 2, 2, 1, -1])
    # the flicker at frame 2 does not count; the change at frame 4 (then 6 frames in lane 2) does
    assert np.flatnonzero(_count_lane_changes(ids, pairs, hold=5)).tolist() == [4]
    scene = load_scene(REAL / "USA_US101-2_1_T-1.json.gz")
    s = traffic_samples(scene)
    assert len(s["speed"]) == int(np.sum(s["vehicle_seconds"]) / 0.1)
    assert np.all(s["headway"] >= 0) and 0.3 < np.median(s["headway"]) < 4.0
    assert compare(s, s) == {"speed": 0.0, "headway": 0.0, "lane_changes": 0.0}


def test_us101_profile_is_its_own_seed_space_and_leaves_default_unchanged(tmp_path):
    from adv3d_runner.scene.generate import PROFILES, generate_scene, generate_scenes

    bundled = load_scene(REPO / "scenes" / "highway" / "highway-benchmark-000003.json.gz")
    d = bundled.source.details
    # the shipped scene also records its actors' meshes (docs/library.md); the generator leaves them open
    bundled = replace(bundled, actors=[replace(a, asset=None) for a in bundled.actors])
    assert scene_equal(generate_scene(3, "benchmark", d["layout"], d["density"], profile="default"), bundled)
    a = generate_scene(3, "benchmark", profile="us101")
    assert a.id == "highway-us101-benchmark-000003" and a.source.details["profile"] == "us101"
    assert d["lanes"] != 5 or not np.allclose(a.ego_poses()[:5], bundled.ego_poses()[:5])
    main_lanes = a.source.details["lanes"] - (a.source.details["layout"] == "onramp")
    assert main_lanes == 5 and a.source.details["layout"] in PROFILES["us101"].layouts
    save_scene(a, tmp_path / "a.json.gz")
    save_scene(generate_scene(3, "benchmark", profile="us101"), tmp_path / "b.json.gz")
    assert (tmp_path / "a.json.gz").read_bytes() == (tmp_path / "b.json.gz").read_bytes()
    with pytest.raises(ConfigError, match="density"):
        generate_scene(3, "benchmark", density="dense", profile="us101")
    with pytest.raises(ConfigError, match="benchmark folder"):
        generate_scenes(REPO / "scenes" / "highway", 1, 0, profile="us101")
    with pytest.raises(ConfigError, match="profile"):
        generate_scene(3, profile="nope")
