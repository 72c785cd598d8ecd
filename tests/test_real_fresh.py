"""The fresh real benchmark part ``scenes/real-fresh/`` (docs/benchmark.md): its kept manifest
and scenes, the split by recording against ``scenes/real/split.json``, and that
``bench/real_fresh.py`` rebuilds the kept scenes from the CommonRoad files."""
from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.scene.real import FRESH_DIR, FRESH_RECORDINGS, load_fresh_part, load_real_split, recording_of
from adv3d_runner.scene.schema import load_scene

REPO = Path(__file__).resolve().parent.parent
SOURCE = REPO.parent / "shared" / "scenarios" / "commonroad-us101"
needs_source = pytest.mark.skipif(not (SOURCE / "USA_US101-15_2_T-1.xml").exists(),
                                  reason="CommonRoad source scenarios (../shared) not present")


def _builder():
    spec = importlib.util.spec_from_file_location("real_fresh", REPO / "bench" / "real_fresh.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_kept_manifest_and_scenes_split_by_recording():
    split = load_real_split()
    fresh = load_fresh_part()
    tuned = set(split.recordings["train"]) | set(split.recordings["benchmark"])
    assert set(fresh.recordings) == set(FRESH_RECORDINGS) and not tuned & set(fresh.recordings)
    assert len(fresh.rows) >= 30
    per_rec = {r: sum(int(row["recording"]) == r for row in fresh.rows) for r in FRESH_RECORDINGS}
    assert min(per_rec.values()) >= 3, per_rec  # several egos per recording
    # every scene file in the folder is in the manifest, and each is what its row says
    assert sorted(p.name for p in FRESH_DIR.glob("*.json.gz")) == sorted(p.name for p in fresh.paths())
    egos = set()
    for row, path in zip(fresh.rows, fresh.paths()):
        scene = load_scene(path)  # validates the whole file
        d = scene.source.details
        assert Path(str(d["file"])).name == row["commonroad_file"]
        assert recording_of(Path(str(d["file"])).stem) == int(row["recording"])
        assert int(d["ego_obstacle_id"]) == int(row["ego_obstacle_id"])
        assert scene.id == f"commonroad-{row['scene']}"
        assert "BSD-3-Clause" in scene.source.licence and "NGSIM" in scene.source.attribution
        v = scene.ego_speeds()[:50]
        assert abs(v.min() - float(row["speed_min_first_5s"])) < 0.011
        assert abs(v.max() - float(row["speed_max_first_5s"])) < 0.011
        egos.add((int(row["recording"]), int(row["ego_obstacle_id"])))
    assert len(egos) == len(fresh.rows)
    # densities: crawls (logged ego below 6 m/s throughout its first 5 s) and free flow (above 15)
    assert any(float(r["speed_max_first_5s"]) < 6.0 for r in fresh.rows)
    assert any(float(r["speed_min_first_5s"]) > 15.0 for r in fresh.rows)


def test_manifest_refuses_a_tuned_recording(tmp_path):
    rows = list(csv.reader((FRESH_DIR / "index.csv").read_text().splitlines()))
    good = rows[1]
    (tmp_path / f"{good[0]}.json.gz").write_bytes((FRESH_DIR / f"{good[0]}.json.gz").read_bytes())
    (tmp_path / "index.csv").write_text("\n".join(",".join(r) for r in rows[:2]) + "\n")
    assert len(load_fresh_part(tmp_path).rows) == 1
    # the same row claimed for a benchmark-part recording (4): refused by name and line
    bad = ["USA_US101-4_1_T-1.ego451", "4", "USA_US101-4_1_T-1.xml"] + good[3:4] + ["451"] + good[5:]
    (tmp_path / "index.csv").write_text("\n".join(",".join(r) for r in (rows[0], bad)) + "\n")
    with pytest.raises(FileFormatError, match=r"index.csv: line 2.recording: expected a fresh recording"):
        load_fresh_part(tmp_path)
    # a fresh recording that split.json puts in its train part
    split = load_real_split()
    moved = type(split)(split.folder, {"train": split.recordings["train"] + (int(good[1]),),
                                       "benchmark": split.recordings["benchmark"]}, split.scenes, split.rule)
    (tmp_path / "index.csv").write_text("\n".join(",".join(r) for r in rows[:2]) + "\n")
    with pytest.raises(FileFormatError, match="outside split.json's train part"):
        load_fresh_part(tmp_path, split=moved)
    (tmp_path / "index.csv").write_text("scene,recording\n")
    with pytest.raises(FileFormatError, match="line 1: expected the header"):
        load_fresh_part(tmp_path)


def test_spread_takes_the_ends_and_evenly_spaced_ranks():
    spread = _builder().spread
    assert spread(3, 5) == [0, 1, 2]
    assert spread(21, 5) == [0, 5, 10, 15, 20]
    assert spread(6, 5) == [0, 1, 2, 4, 5]


def _close(a, b, path="$"):
    """Documents equal up to 1e-9 relative in their numbers (another CPU's last bits)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list) and a and isinstance(a[0], (int, float)) and not isinstance(a[0], bool):
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-9, atol=1e-9, err_msg=path)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-9), path
    else:
        assert a == b, path


@needs_source
def test_build_reproduces_the_kept_scenes(tmp_path):
    """Recording 15 (crawls and 12 m/s traffic) rebuilt: the same egos, manifest rows and scenes."""
    assert _builder().main(["--out", str(tmp_path), "--recordings", "15"]) == 0
    new = load_fresh_part(tmp_path)
    kept = [r for r in load_fresh_part().rows if r["recording"] == "15"]
    assert [r["scene"] for r in new.rows] == [r["scene"] for r in kept] and len(kept) == 5
    for a, b in zip(new.rows, kept):
        assert a["commonroad_sha256"] == b["commonroad_sha256"]
        _close(load_scene(tmp_path / f"{a['scene']}.json.gz").to_dict(),
               load_scene(FRESH_DIR / f"{b['scene']}.json.gz").to_dict())


def test_fine_tuned_predictor_loads_and_saw_train_recordings_only():
    """The fine-tuned predictor kept beside the shipped one loads, predicts finite modes, and its
    report names only scenes of train recordings (docs/benchmark.md)."""
    import json

    from adv3d_runner.autonomy.predictor import load_predictor

    folder = REPO / "assets" / "models" / "predictor-fresh-ft"
    model = load_predictor(folder)
    feats = np.zeros((2, model.config.num_features), np.float32)
    prior = np.zeros((2, model.config.steps, 2), np.float32)
    traj, probs = model.predict_local(feats, prior)
    assert traj.shape == (2, model.config.num_modes, model.config.steps, 2) and np.isfinite(traj).all()
    report = json.loads((folder / "training_report.json").read_text())
    train = set(load_real_split().recordings["train"])
    names = list(report["data"]["real_train_scenes"])
    assert len(names) == 47 and {recording_of(n.split(".")[0]) for n in names} <= train
