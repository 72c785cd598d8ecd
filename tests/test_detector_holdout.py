"""Vehicle hold-out of detector training (docs/detector.md): the default split is deterministic
and stratified by class, training scenes never place a held-out mesh, and AP / recall per
ground-truth group are right on a hand-made set of boxes."""
from __future__ import annotations

import dataclasses
import random

import numpy as np
import pytest

from adv3d_runner.errors import ConfigError
from adv3d_runner.metrics.detection import average_precision, grouped_average_precision
from adv3d_runner.shapes.library import VehicleAsset, VehicleLibrary, library_fingerprint, load_library
from adv3d_runner.training.detector_data import (FrameSet, box_assets, default_holdout, frames_scene,
                                                 resolve_holdout, without_assets)

# The default split of the bundled 38-asset library (docs/detector.md): pinned, so a change of
# the rule or of the library shows here before a model is trained on another split.
BUNDLED_DEFAULT_HOLDOUT = [
    "kaykit-city-builder-bits.stationwagon", "kenney-car-kit.suv", "kenney-car-kit.truck-flat",
    "khronos-cesium-milk-truck.milk-truck", "quaternius-cars.cop", "quaternius-cars.normalcar2",
    "quaternius-cars.sportscar2",
]


def _library(counts: dict[str, int]) -> VehicleLibrary:
    """A hand-made library (records only, no mesh files) with ``counts[class]`` assets."""
    assets = [VehicleAsset(id=f"pack.{cls}-{k}", file=f"{cls}-{k}.glb", vehicle_class=cls, dimensions=(4.5, 1.8, 1.5))
              for cls, n in counts.items() for k in range(n)]
    return VehicleLibrary(root=load_library().root, assets=assets)


def test_default_holdout_is_stratified_by_class():
    lib = _library({"sedan": 12, "suv": 3, "truck": 5, "bus": 2, "van": 1, "pickup": 10})
    held = default_holdout(lib)
    per_class = {c: sum(1 for a in lib.assets if a.id in held and a.vehicle_class == c)
                 for c in ("sedan", "suv", "truck", "bus", "van", "pickup")}
    # min(n - 1, round half up (0.2 n)): 2.4 -> 2, 0.6 -> 1, 1.0 -> 1, 0.4 -> 0, last asset kept, 2.0 -> 2
    assert per_class == {"sedan": 2, "suv": 1, "truck": 1, "bus": 0, "van": 0, "pickup": 2}
    assert held == sorted(held) and len(set(held)) == len(held)


def test_default_holdout_is_deterministic_and_independent_of_order():
    lib = _library({"sedan": 12, "suv": 3, "truck": 4})
    held = default_holdout(lib)
    shuffled = dataclasses.replace(lib, assets=random.Random(3).sample(lib.assets, len(lib.assets)))
    assert default_holdout(shuffled) == held == default_holdout(_library({"sedan": 12, "suv": 3, "truck": 4}))
    # a new asset in one class never changes the split of another class
    grown = _library({"sedan": 12, "suv": 3, "truck": 4})
    grown.assets.append(VehicleAsset(id="pack.truck-new", file="t.glb", vehicle_class="truck", dimensions=(9, 2.5, 3)))
    assert [i for i in default_holdout(grown) if "truck" not in i] == [i for i in held if "truck" not in i]


def test_default_holdout_of_the_bundled_library():
    lib = load_library()
    held = default_holdout(lib)
    assert held == BUNDLED_DEFAULT_HOLDOUT
    assert 0.15 <= len(held) / len(lib.assets) <= 0.25     # "roughly 20 %"
    for cls in {a.vehicle_class for a in lib.assets}:        # every class keeps a mesh for training
        assert any(a.vehicle_class == cls and a.id not in held for a in lib.assets)


def test_resolve_holdout():
    lib = _library({"sedan": 3, "suv": 1})
    assert resolve_holdout(None, lib) == resolve_holdout("none", lib) == []
    assert resolve_holdout("default", lib) == default_holdout(lib)
    assert len(default_holdout(lib)) == 1 and default_holdout(lib)[0].startswith("pack.sedan-")  # 0.6 -> 1; suv kept
    assert resolve_holdout("pack.sedan-2, pack.sedan-0", lib) == ["pack.sedan-0", "pack.sedan-2"]
    with pytest.raises(ConfigError, match="pack.nope"):
        resolve_holdout("pack.sedan-0,pack.nope", lib)
    with pytest.raises(ConfigError, match="suv"):
        resolve_holdout("pack.suv-0", lib)                  # would leave the class without a mesh
    with pytest.raises(ConfigError):
        resolve_holdout("default", None)


def test_training_scenes_never_place_a_held_out_asset():
    lib = load_library()
    held = set(default_holdout(lib))
    train_lib = without_assets(lib, sorted(held))
    assert len(train_lib.assets) == len(lib.assets) - len(held) and not held & set(train_lib.ids())
    assert library_fingerprint(train_lib) != library_fingerprint(lib)   # its frames are cached apart
    drew_held = 0
    for seed in range(100_000, 100_003):                       # training-split scenes
        full = frames_scene(seed, "train", lib)
        train = frames_scene(seed, "train", train_lib)
        assert [a.id for a in full.actors] == [a.id for a in train.actors]
        for a_full, a_train in zip(full.actors, train.actors):
            assert a_train.asset not in held and a_train.asset is not None
            if a_full.asset in held:
                drew_held += 1
                assert lib.get(a_train.asset).vehicle_class == lib.get(a_full.asset).vehicle_class
            else:
                assert a_train.asset == a_full.asset            # rendezvous draw: everyone else keeps it
    assert drew_held > 0   # the full library does place held-out meshes in these scenes


def test_box_assets_follow_the_scene_draw():
    lib = load_library()
    seeds = [900_000, 900_001]
    scenes = {s: frames_scene(s, "train", lib) for s in seeds}
    actors = [(0, scenes[900_000].actors[0].id), (0, scenes[900_000].actors[2].id), (1, scenes[900_001].actors[1].id),
              (1, 999)]                                      # 999: no such actor -> ""
    fs = FrameSet(points=np.zeros((0, 3), np.float32), offsets=np.zeros(3, np.int64),
                  boxes=np.zeros((len(actors), 5)), box_frame=np.array([f for f, _ in actors], np.int64),
                  box_points=np.full(len(actors), 10, np.int64), box_actor=np.array([a for _, a in actors], np.int64),
                  scene_seed=np.array(seeds, np.int64), frame_index=np.zeros(2, np.int64))
    got = box_assets(fs, lib)
    want = [scenes[seeds[f]].actors[[x.id for x in scenes[seeds[f]].actors].index(a)].asset if a != 999 else ""
            for f, a in actors]
    assert got.tolist() == want and all(want[:3])


def _box(x, y=0.0, length=4.0, width=2.0):
    return [x, y, length, width, 0.0]


def _hand_made_frames():
    """Two frames; groups "seen" (A) and "held_out" (B).

    frame 0: A1 at x=10, B1 at x=30. detections: 0.9 on A1 (TP seen), 0.8 on B1 shifted 2.5 m
    (IoU 0.23: FP, attributed to held_out), 0.75 far from every box (background FP), 0.7 on B1
    (TP held_out), 0.4 on A1 again (duplicate: FP attributed to seen).
    frame 1: A2 at x=10, B2 at x=30, B3 at y=20 (missed). detections: 0.95 on B2 (TP held_out),
    0.5 on A2 (TP seen).
    """
    f0 = (np.array([_box(10), _box(30)]), np.array(["seen", "held_out"]),
          np.array([_box(10), _box(32.5), _box(45, 15), _box(30), _box(10.1)]), np.array([0.9, 0.8, 0.75, 0.7, 0.4]))
    f1 = (np.array([_box(10), _box(30), _box(30, 20)]), np.array(["seen", "held_out", "held_out"]),
          np.array([_box(30), _box(10)]), np.array([0.95, 0.5]))
    return [f0, f1]


def test_grouped_average_precision_hand_made():
    r = grouped_average_precision(_hand_made_frames(), ("seen", "held_out"))
    seen, held = r["groups"]["seen"], r["groups"]["held_out"]
    assert r["n_det"] == 7 and r["n_fp_background"] == 1
    # seen: 0.9 TP, 0.5 TP, 0.4 FP (after full recall) -> AP 1; with the background FP (0.75)
    # between the TPs: precision 1/2 at recall 1/2, 2/3 at recall 1 -> 1/2 * 1 + 1/2 * 2/3
    assert (seen["n_gt"], seen["n_tp"], seen["n_fp"]) == (2, 2, 1)
    assert seen["recall"] == 1.0 and seen["ap"] == pytest.approx(1.0)
    assert seen["ap_with_background_fp"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    # held out: 0.95 TP (recall 1/3), 0.8 FP, 0.7 TP (recall 2/3, precision 2/3); B3 missed
    # -> AP 1/3 * 1 + 1/3 * 2/3; with the background FP at 0.75: 1/3 * 1 + 1/3 * 2/4
    assert (held["n_gt"], held["n_tp"], held["n_fp"]) == (3, 2, 1)
    assert held["recall"] == pytest.approx(2 / 3)
    assert held["ap"] == pytest.approx(1 / 3 + 1 / 3 * 2 / 3)
    assert held["ap_with_background_fp"] == pytest.approx(1 / 3 + 1 / 3 * 0.5)


def test_grouped_average_precision_agrees_with_the_overall_metric():
    frames = _hand_made_frames()
    overall = average_precision([(g, d, s) for g, _, d, s in frames])
    one = grouped_average_precision([(g, np.full(len(g), "all"), d, s) for g, _, d, s in frames], ["all"])
    g = one["groups"]["all"]
    # one group holding every box: the background FPs are the only difference between the variants
    assert g["ap_with_background_fp"] == pytest.approx(overall.ap) and g["recall"] == overall.recall
    assert (g["n_gt"], g["n_tp"]) == (overall.n_gt, overall.n_tp)
    two = grouped_average_precision(frames, ("seen", "held_out"))["groups"]
    assert sum(x["n_gt"] for x in two.values()) == overall.n_gt
    assert sum(x["n_tp"] for x in two.values()) == overall.n_tp
    # a group with no box: undefined, not zero
    empty = grouped_average_precision(frames, ("seen", "held_out", "other"))["groups"]["other"]
    assert empty["n_gt"] == 0 and np.isnan(empty["ap"]) and np.isnan(empty["recall"])
    with pytest.raises(ValueError):
        grouped_average_precision([(frames[0][0], np.array(["seen"]), frames[0][2], frames[0][3])], ["seen"])


def test_evaluate_detector_groups_apply_ignore_and_roi():
    pytest.importorskip("torch")
    from adv3d_runner.autonomy.interface import Detections
    from adv3d_runner.training.detector_train import evaluate_detector

    # one frame: A (seen, 40 points), B (held out, 40 points), C (held out, 2 points: ignore box),
    # D (seen, 80 m ahead: outside the ROI)
    boxes = np.array([_box(10), _box(30), _box(20, 10), _box(80)])
    fs = FrameSet(points=np.zeros((0, 3), np.float32), offsets=np.zeros(2, np.int64), boxes=boxes,
                  box_frame=np.zeros(4, np.int64), box_points=np.array([40, 40, 2, 40], np.int64),
                  box_actor=np.arange(4, dtype=np.int64), scene_seed=np.zeros(1, np.int64),
                  frame_index=np.zeros(1, np.int64))
    groups = np.array(["seen", "held_out", "held_out", "seen"])
    dets = [Detections(np.array([_box(10), _box(20, 10), _box(80), _box(45, -15)]), np.array([0.9, 0.8, 0.7, 0.6]))]
    out = evaluate_detector(None, fs, detections=dets, box_groups=groups, groups=("seen", "held_out"))
    # the detection on the ignore box and the one outside the ROI are gone; the 0.6 one is background
    assert (out["n_gt"], out["n_det"], out["n_tp"]) == (2, 2, 1)
    by = out["by_group"]
    assert by["n_fp_background"] == 1
    assert by["groups"]["seen"]["n_gt"] == 1 and by["groups"]["seen"]["recall"] == 1.0
    assert by["groups"]["seen"]["ap"] == 1.0 and by["groups"]["seen"]["ap_with_background_fp"] == 1.0
    assert by["groups"]["held_out"]["n_gt"] == 1 and by["groups"]["held_out"]["recall"] == 0.0
    assert by["groups"]["held_out"]["ap"] == 0.0
    assert "by_group" not in evaluate_detector(None, fs, detections=dets)


def test_train_cli_refuses_an_unknown_holdout_asset(tmp_path, capsys):
    from adv3d_runner.cli import main

    out = tmp_path / "model"
    rc = main(["-q", "train", "detector", "--holdout-assets", "quaternius-cars.nope", "--cache", str(tmp_path / "c"),
               "--out", str(out)])
    assert rc == 2 and "quaternius-cars.nope" in capsys.readouterr().err  # an option the library cannot meet
    assert not out.exists() and not (tmp_path / "c").exists()


@pytest.mark.slow
def test_train_cli_with_holdout_reports_both_groups(tmp_path):
    """A tiny hold-out run: the training frames come from the library without the held-out
    assets (their own cache tag), the held-out frames from the whole library, and the report
    gives AP/recall for vehicles seen and left out (about 40 s)."""
    import json

    pytest.importorskip("torch")
    from adv3d_runner.cli import main

    out, cache = tmp_path / "model", tmp_path / "cache"
    rc = main(["-q", "train", "detector", "--scenes", "2", "--val-scenes", "2", "--frames-per-scene", "2",
               "--epochs", "1", "--resolution", "0.4", "--holdout-assets", "default", "--time-limit", "100000",
               "--cache", str(cache), "--out", str(out)])
    assert rc == 0
    report = json.loads((out / "training_report.json").read_text())
    lib = load_library()
    held = default_holdout(lib)
    h = report["data"]["holdout"]
    assert h["assets"] == held and h["training_library_fingerprint"] == library_fingerprint(without_assets(lib, held))
    assert report["data"]["library_fingerprint"] == library_fingerprint(lib)
    tags = {p.name.split("-lib-")[1] for p in cache.rglob("*.npz")}
    assert len(tags) == 2                                   # training frames and held-out frames apart
    assert report["training"]["epochs_run"] == 1 and report["training"]["stopped_early"] is False
    groups = report["held_out"]["by_group"]["groups"]
    assert set(groups) == {"seen", "held_out"}
    assert groups["seen"]["n_gt"] + groups["held_out"]["n_gt"] == report["held_out"]["n_gt"]
    per_asset = report["held_out_by_vehicle"]["assets"]
    assert {a for a, g in per_asset.items() if g["held_out"]} <= set(held)
    assert sum(g["n_gt"] for g in per_asset.values()) == report["held_out"]["n_gt"]
