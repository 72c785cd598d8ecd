"""CommonRoad import and the bundled real scenes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.errors import ConfigError, FileFormatError
from adv3d_runner.scene.commonroad import import_commonroad
from adv3d_runner.scene.generate import vehicles_ahead
from adv3d_runner.scene.schema import load_scene, save_scene, scene_equal

REPO = Path(__file__).resolve().parent.parent
REAL = REPO / "scenes" / "real"
SOURCE = REPO.parent / "shared" / "scenarios" / "commonroad-us101"
XML_33 = SOURCE / "USA_US101-3_3_T-1.xml"
needs_source = pytest.mark.skipif(not XML_33.exists(), reason="CommonRoad source scenarios not present")


@pytest.mark.parametrize("name", ["USA_US101-3_3_T-1", "USA_US101-4_1_T-1"])
def test_bundled_real_scenes_load_with_attribution(name):
    scene = load_scene(REAL / f"{name}.json.gz")
    assert scene.source.kind == "commonroad"
    assert "BSD-3-Clause" in scene.source.licence
    for who in ("NGSIM", "FHWA", "Technical University of Munich", "OpenStreetMap"):
        assert who in scene.source.attribution
    assert scene.frames == 100 and len(scene.actors) > 5 and len(scene.lanes) > 5
    assert vehicles_ahead(scene)
    assert np.isfinite(scene.ego_poses()).all()
    assert "Redistribution and use" in (REAL / "LICENSE.txt").read_text()


def test_real_scene_synthetic_frames_are_marked():
    short = load_scene(REAL / "USA_US101-3_3_T-1.json.gz")
    recorded = short.source.details["recorded_frames"]
    assert recorded < short.frames
    assert short.ego.track.synthetic[recorded:].all() and not short.ego.track.synthetic[:recorded].any()
    for actor in short.actors:
        syn = short.actor_synthetic(actor.id)
        assert not syn[:recorded].any()
    assert any(short.actor_synthetic(a.id)[recorded:].any() for a in short.actors)
    full = load_scene(REAL / "USA_US101-4_1_T-1.json.gz")
    assert not full.ego.track.synthetic.any()
    assert not any(a.track.synthetic.any() for a in full.actors)


@needs_source
def test_import_refuses_short_recording_without_extend(tmp_path):
    with pytest.raises(ConfigError, match="--extend"):
        import_commonroad(XML_33, seconds=10.0)
    scene = import_commonroad(XML_33)  # default: the recording's own length
    assert scene.frames == scene.source.details["recorded_frames"]
    assert not scene.ego.track.synthetic.any()


@needs_source
def test_import_matches_bundled_file_and_round_trips(tmp_path):
    scene = import_commonroad(XML_33, seconds=10.0, extend=True)
    save_scene(scene, tmp_path / "a.json.gz")
    # the bundled file also records the actors' meshes (docs/scenes.md, "Actor meshes")
    bundled = load_scene(REAL / "USA_US101-3_3_T-1.json.gz")
    assert all(a.asset is not None for a in bundled.actors)
    for actor in bundled.actors:
        actor.asset = None
    assert scene_equal(load_scene(tmp_path / "a.json.gz"), bundled)
    # lanes: neighbours are symmetric and every lane has a positive width
    by_id = {lane.id: lane for lane in scene.lanes}
    for lane in scene.lanes:
        assert np.all(lane.width > 0)
        if lane.left is not None:
            assert by_id[lane.left].right == lane.id
    # the ego is a recorded car, not among the actors
    assert scene.source.details["ego_obstacle_id"] not in scene.actor_ids


@needs_source
def test_extended_vehicles_do_not_overlap():
    scene = import_commonroad(XML_33, seconds=10.0, extend=True)
    poses, valid = scene.all_actor_poses()
    for f in range(scene.source.details["recorded_frames"], scene.frames, 5):
        idx = np.flatnonzero(valid[:, f])
        p = poses[idx, f, :2]
        dist = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
        np.fill_diagonal(dist, np.inf)
        assert dist.min() > 3.0


@needs_source
def test_user_ego_choice(tmp_path):
    with pytest.raises(ConfigError):
        import_commonroad(XML_33, ego_id=123456)
    scene = import_commonroad(XML_33, ego_id=363)
    assert scene.source.details["ego_obstacle_id"] == 363


def test_bad_xml_names_file(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<commonRoad><lanelet")
    with pytest.raises(FileFormatError, match="broken.xml"):
        import_commonroad(bad)


@needs_source
def test_cli_import(tmp_path, capsys):
    from adv3d_runner.cli import main
    out = tmp_path / "real" / "x.json.gz"
    # the recording is shorter than --seconds: the command line cannot run as given (exit 2)
    assert main(["scenes", "import-commonroad", str(XML_33), "--out", str(out), "--seconds", "5"]) == 2
    assert "--extend" in capsys.readouterr().err and not out.exists()
    assert main(["-q", "scenes", "import-commonroad", str(XML_33), "--out", str(out), "--seconds", "5", "--extend"]) == 0
    scene = load_scene(out)
    assert scene.frames == 50 and scene.ego.track.synthetic[-1]
