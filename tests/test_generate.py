"""Highway generator: determinism, ahead-vehicle guarantee, split separation, bundled scenes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.cli import main
from adv3d_runner.errors import ConfigError
from adv3d_runner.scene.generate import (LAYOUTS, check_split, generate_scene, generate_scenes,
                                         vehicles_ahead)
from adv3d_runner.scene.schema import load_scene, save_scene

REPO = Path(__file__).resolve().parent.parent
BUNDLED = sorted((REPO / "scenes" / "highway").glob("*.json.gz"))


def test_same_seed_same_bytes(tmp_path):
    a = generate_scene(3, layout="onramp", density="light")
    b = generate_scene(3, layout="onramp", density="light")
    save_scene(a, tmp_path / "a.json.gz")
    save_scene(b, tmp_path / "b.json.gz")
    assert (tmp_path / "a.json.gz").read_bytes() == (tmp_path / "b.json.gz").read_bytes()
    c = generate_scene(4, layout="onramp", density="light")
    assert not np.array_equal(c.ego_poses(), a.ego_poses())


@pytest.mark.parametrize("layout", LAYOUTS)
def test_layouts_have_vehicle_ahead_and_sane_tracks(layout):
    scene = generate_scene(11, layout=layout, density="moderate")
    assert scene.frames == 200 and scene.dt == pytest.approx(0.1)
    assert vehicles_ahead(scene), "no vehicle ahead within 50 m in the first 5 s"
    assert scene.source.details["layout"] == layout
    speeds = scene.ego_speeds()
    assert np.all(speeds >= 0) and np.isfinite(scene.ego_poses()).all()
    # the ego never jumps: displacement per frame bounded by its speed
    step = np.hypot(*np.diff(scene.ego_poses()[:, :2], axis=0).T)
    assert step.max() < 5.0
    scene.validate()


def test_free_flow_is_faster_than_congestion():
    free = generate_scene(0, layout="straight", density="free")
    jam = generate_scene(0, layout="straight", density="congested")
    assert free.ego_speeds().mean() > jam.ego_speeds().mean() + 5.0
    assert len(jam.actors) > len(free.actors)


def test_splits_are_separate(tmp_path):
    check_split("benchmark", 0)
    check_split("train", 100_000)
    with pytest.raises(ConfigError):
        check_split("train", 5)
    with pytest.raises(ConfigError):
        check_split("benchmark", 100_000)
    with pytest.raises(ConfigError):
        generate_scenes(REPO / "scenes" / "highway" / "sub", 1, 100_000, split="train")
    # same seed number in another namespace is a different scene (and a different id)
    a = generate_scene(100_000, split="train", layout="straight", density="light")
    assert a.id.startswith("highway-train-")


def test_cli_generate_info_validate(tmp_path, capsys):
    assert main(["-q", "scenes", "generate", "--out", str(tmp_path), "--count", "1", "--seed", "7"]) == 0
    files = list(tmp_path.glob("*.json.gz"))
    assert len(files) == 1
    assert main(["scenes", "validate", str(tmp_path)]) == 0
    assert main(["scenes", "info", str(files[0])]) == 0
    out = capsys.readouterr().out
    assert "highway-benchmark-000007" in out and "ahead_50m_5s=" in out
    files[0].write_text("{}")
    assert main(["scenes", "validate", str(tmp_path)]) == 1
    # --seed outside the split's range: the command line cannot run as given (exit 2)
    assert main(["scenes", "generate", "--out", str(tmp_path), "--split", "train", "--seed", "1"]) == 2


def test_bundled_benchmark_loads_and_has_targets():
    assert len(BUNDLED) >= 100
    layouts, densities = set(), set()
    for path in BUNDLED:
        scene = load_scene(path)
        assert vehicles_ahead(scene), path.name
        assert path.stat().st_size < 150_000, path.name
        layouts.add(scene.source.details["layout"])
        densities.add(scene.source.details["density"])
        assert scene.source.details["split"] == "benchmark"
    assert layouts == set(LAYOUTS) and len(densities) == 5
