"""``adv3d export`` (docs/export.md): a found failure as CommonRoad, OpenSCENARIO and glb files,
re-imported with ``scenes import-commonroad --manifest`` and re-simulated within the tolerance of
docs/export.md; bad input ends in one line and leaves nothing behind."""
from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("scenariogeneration")

from adv3d_runner.cli import main  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "real" / "USA_US101-3_5_T-1.json.gz"
SCENE_ID = "commonroad-USA_US101-3_5_T-1"
SECONDS = 3.0
#: reproduction tolerance (docs/export.md): same collision, hardest braking and minimum distance within
BRAKING_TOL = 0.5   # m/s^2
DISTANCE_TOL = 0.5  # m


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A tiny attack: oracle stack, 2 random queries of the paper's box, 3 s, on a real US-101 scene
    whose best shape makes the oracle brake hard (about -4.3 m/s^2)."""
    out = tmp_path_factory.mktemp("attack") / "run"
    assert main(["-q", "attack", str(SCENE), "--autonomy", "oracle", "--budget", "2", "--seconds", f"{SECONDS:g}",
                 "--algo", "random", "--region", "paper", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def exported(run_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "failure"
    assert main(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(out)]) == 0
    return out


def _braking(replay_path: Path) -> float:
    from adv3d_runner.attack.export import hardest_braking
    from adv3d_runner.sim.replay import load_replay

    replay = load_replay(replay_path, points=False)
    return hardest_braking(replay.ego_speeds, replay.dt)


def test_export_writes_every_file(exported, run_dir):
    from commonroad.common.file_reader import CommonRoadFileReader

    from adv3d_runner.shapes.library import load_asset_mesh, load_library
    from adv3d_runner.shapes.mesh_io import mesh_dimensions, read_library_mesh
    from adv3d_runner.sim.replay import load_replay

    m = json.loads((exported / "export.json").read_text())
    assert m["format"] == "adv3d-export" and m["source"]["scene"] == SCENE_ID and m["source"]["mode"] == "closed"
    summary = json.loads((run_dir / "summary.json").read_text())
    best = summary["scenes"][SCENE_ID]["modes"]["closed"]
    assert m["source"]["best_index"] == best["best_index"] and m["source"]["cost"] == best["best_cost"]
    assert m["stack"]["name"] == "oracle" and m["stack"]["version"]
    run = json.loads((run_dir / "run.json").read_text())
    assert m["stack"] == run["versions"]["stack"]
    metrics = best["closed_loop_eval"]["metrics"]
    f = m["failure"]
    assert f["collision"] == metrics["collision"]["collided"] and f["min_distance_m"] == metrics["min_distance"]
    assert f["hard_braking"] == (f["hardest_braking_mps2"] < -4.0)
    replay = load_replay(run_dir / best["files"]["replay"], points=False)
    assert f["hardest_braking_mps2"] == pytest.approx(_braking(run_dir / best["files"]["replay"]), abs=1e-4)

    # the shape: the attack's glb, byte for byte, with its dimensions
    (target,) = summary["scenes"][SCENE_ID]["targets"]
    shape = m["files"]["shapes"][0]
    assert shape["actor"] == target
    assert (exported / shape["file"]).read_bytes() == (run_dir / best["files"]["meshes"][str(target)]).read_bytes()
    dims = mesh_dimensions(read_library_mesh(exported / shape["file"]))
    assert np.allclose(dims, shape["dimensions_m"], atol=1e-4)
    library = load_library(exported / "library" / "library.json")
    found = library.get(shape["asset"])
    assert np.allclose(found.dimensions, dims, atol=1e-4)
    assert np.allclose(mesh_dimensions(load_asset_mesh(library, found.id)), dims, atol=1e-4)
    for asset in library.assets:  # every mesh and licence file is there
        assert library.path_of(asset).is_file() and (library.root / asset.licence["file"]).is_file()

    # CommonRoad: dt 0.1, every vehicle, the attacked one with the shape's footprint, the ego's
    # closed-loop trajectory under its id, the planning problem from its first state
    scenario, problems = CommonRoadFileReader(str(exported / "scenario.xml")).open()
    assert scenario.dt == pytest.approx(0.1)
    obstacles = {o.obstacle_id: o for o in scenario.dynamic_obstacles}
    present = [a.id for a in replay.actors if np.isfinite(a.poses[:, 0]).any()]
    assert set(obstacles) == {m["ids"]["ego"], *present}
    attacked = obstacles[target].obstacle_shape
    target_dims = next(a for a in replay.actors if a.id == target).dimensions
    assert (attacked.length, attacked.width) == pytest.approx(tuple(target_dims[:2]), abs=1e-4)
    ego = obstacles[m["ids"]["ego"]]
    states = [ego.initial_state] + list(ego.prediction.trajectory.state_list)
    xy = np.array([s.position for s in states])
    assert len(states) == replay.n_frames and np.abs(xy - replay.ego_poses[:, :2]).max() < 1e-3
    (problem,) = problems.planning_problem_dict.values()
    assert np.allclose(problem.initial_state.position, replay.ego_poses[0, :2], atol=1e-3)
    assert problem.initial_state.velocity == pytest.approx(replay.ego_speeds[0], abs=1e-3)
    from adv3d_runner.scene import load_scene

    # the acceleration the stack started from: the scene log's, not the closed loop's first step
    assert problem.initial_state.acceleration == pytest.approx(load_scene(SCENE).ego_accelerations()[0], abs=1e-3)

    # OpenSCENARIO: every vehicle follows its trajectory (absolute times, T vertices for the ego),
    # the attacked one with the found glb as model3d; the road file is there
    root = ET.parse(exported / "scenario.xosc").getroot()
    assert root.find("RoadNetwork/LogicFile").get("filepath") == "road.xodr" and (exported / "road.xodr").is_file()
    vehicles = {o.get("name"): o.find("Vehicle") for o in root.iter("ScenarioObject")}
    assert set(vehicles) == {"ego", *(f"actor{a}" for a in present)}
    assert vehicles[f"actor{target}"].get("model3d") == shape["file"]
    box = vehicles[f"actor{target}"].find("BoundingBox/Dimensions")
    assert float(box.get("length")) == pytest.approx(dims[0], abs=1e-3)
    assert float(box.get("height")) == pytest.approx(dims[2], abs=1e-3)
    ego_traj = next(t for t in root.iter("Trajectory") if t.get("name") == "ego_trajectory")
    times = [float(v.get("time")) for v in ego_traj.iter("Vertex")]
    assert times == pytest.approx(list(np.arange(replay.n_frames) * 0.1))
    from scenariogeneration import xosc

    assert len(xosc.ParseOpenScenario(str(exported / "scenario.xosc")).entities.scenario_objects) == len(vehicles)


def test_reimport_and_simulate_reproduce_the_failure(exported, capsys):
    """The manifest's replay commands: import the CommonRoad file with the manifest, simulate with
    the same stack and the export's library (the found shape as the attacked actor's asset)."""
    from adv3d_runner.scene import load_scene

    m = json.loads((exported / "export.json").read_text())
    scene_file = exported / "replay" / "scene.json.gz"
    assert main(["-q", "scenes", "import-commonroad", str(exported / "scenario.xml"), "--manifest",
                 str(exported / "export.json"), "--out", str(scene_file)]) == 0
    scene = load_scene(scene_file)
    assert scene.source.details["ego_obstacle_id"] == m["ids"]["ego"]
    shape = m["files"]["shapes"][0]
    actor = next(a for a in scene.actors if a.id == shape["actor"])
    assert actor.asset == shape["asset"] and np.allclose(actor.dimensions, shape["dimensions_m"], atol=2e-3)
    assert scene.frames == m["source"]["frames"]
    assert main(["-q", "simulate", str(scene_file), "--autonomy", m["source"]["autonomy"], "--seconds", f"{SECONDS:g}",
                 "--seed", str(m["source"]["seed"]), "--library", str(exported / "library" / "library.json"),
                 "--out", str(exported / "replay")]) == 0
    got = json.loads((exported / "replay" / "metrics.json").read_text())
    braking = _braking(exported / "replay" / "replay.json.gz")
    f = m["failure"]
    with capsys.disabled():  # the figures docs/export.md states
        print(f"\nexport reproduction: collision {f['collision']} -> {got['collision']['collided']}, min distance "
              f"{f['min_distance_m']:.3f} -> {got['min_distance']:.3f} m, hardest braking "
              f"{f['hardest_braking_mps2']:.2f} -> {braking:.2f} m/s^2, progress {f['progress_m']:.2f} -> "
              f"{got['progress_m']:.2f} m")
    assert got["collision"]["collided"] == f["collision"]
    assert got["collision"]["at_fault"] == f["at_fault"]
    assert abs(got["min_distance"] - f["min_distance_m"]) <= DISTANCE_TOL
    assert abs(braking - f["hardest_braking_mps2"]) <= BRAKING_TOL
    assert f["hard_braking"]  # the scene was chosen for a hard-braking failure


def test_reimport_without_manifest_takes_the_named_ego(exported, tmp_path):
    from adv3d_runner.scene.commonroad import import_commonroad

    m = json.loads((exported / "export.json").read_text())
    scene = import_commonroad(exported / "scenario.xml", ego_id=m["ids"]["ego"])
    assert m["ids"]["ego"] not in [a.id for a in scene.actors]
    assert scene.frames == m["source"]["frames"]
    # the same ego as with the manifest, from the planning problem's initial state on
    from commonroad.common.file_reader import CommonRoadFileReader

    _, problems = CommonRoadFileReader(str(exported / "scenario.xml")).open()
    (problem,) = problems.planning_problem_dict.values()
    assert np.allclose(scene.ego_poses()[0, :2], problem.initial_state.position, atol=0.01)


def test_export_again_replaces_an_earlier_export(run_dir, exported, tmp_path):
    out = tmp_path / "again"
    assert main(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(out)]) == 0
    first = json.loads((out / "export.json").read_text())
    (out / "replay").mkdir()
    assert main(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(out)]) == 0
    second = json.loads((out / "export.json").read_text())
    assert first == second and not (out / "replay").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]  # no temporary folder left
    assert (out / "shapes").exists() and (out / "library" / "library.json").is_file()


def _fails(argv: list[str], capsys, code: int, words: str) -> str:
    assert main(argv) == code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    return err


def test_bad_input_one_line_nothing_written(run_dir, tmp_path, capsys):
    out = tmp_path / "x"
    # an unknown scene: a usage error (exit 2)
    _fails(["-q", "export", str(run_dir), "--scene", "nope", "--out", str(out)], capsys, 2, "no such scene")
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--mode", "open", "--out", str(out)], capsys, 2,
           "--mode open")
    # --out is a file, or a folder of something else: usage errors, untouched
    (tmp_path / "file").write_text("mine")
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(tmp_path / "file")], capsys, 2,
           "is a file")
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(tmp_path / "file" / "sub")], capsys, 2,
           "is a file")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(mine)], capsys, 2, "not an adv3d export")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    # not a run folder; a run whose best shape is gone (exit 1)
    _fails(["-q", "export", str(tmp_path), "--scene", SCENE_ID, "--out", str(out)], capsys, 1, "not an attack run")
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    shutil.rmtree(broken / "scenes")
    _fails(["-q", "export", str(broken), "--scene", SCENE_ID, "--out", str(out)], capsys, 1, "missing")
    summary = json.loads((broken / "summary.json").read_text())
    del summary["scenes"][SCENE_ID]["modes"]["closed"]["files"]
    (broken / "summary.json").write_text(json.dumps(summary))
    _fails(["-q", "export", str(broken), "--scene", SCENE_ID, "--out", str(out)], capsys, 1, "no best-shape files")
    # a scene file that is not the attacked one
    other = REPO / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--scene-file", str(other), "--out", str(out)],
           capsys, 1, "not the scene")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "file", "mine"]


def test_failure_while_writing_leaves_nothing(run_dir, tmp_path, monkeypatch, capsys):
    from adv3d_runner.errors import ConfigError
    from adv3d_runner.scene import openscenario

    def broken(*args, **kwargs):
        raise ConfigError("disk full (simulated)")

    monkeypatch.setattr(openscenario, "write_openscenario", broken)
    out = tmp_path / "deep" / "er" / "x"
    _fails(["-q", "export", str(run_dir), "--scene", SCENE_ID, "--out", str(out)], capsys, 1, "disk full")
    assert list(tmp_path.iterdir()) == []  # not even the folders above --out


def test_gaps_and_late_actors_round_trip(tmp_path):
    """Writers on a synthetic episode: an actor that enters late and one with a gap come back
    from CommonRoad where they were (the gap interpolated); OpenSCENARIO hides the late one until
    it enters."""
    from adv3d_runner.scene.commonroad import import_commonroad
    from adv3d_runner.scene.commonroad_export import Vehicle, write_commonroad
    from adv3d_runner.scene.openscenario import write_opendrive, write_openscenario
    from adv3d_runner.scene.schema import Lane

    T, dt = 20, 0.1
    lanes = [Lane(id=0, centerline=np.array([[0.0, 0.0], [200.0, 0.0]]), width=np.array([3.5, 3.5]), left=1,
                  speed_limit=30.0),
             Lane(id=1, centerline=np.array([[0.0, 3.5], [100.0, 3.6], [200.0, 4.0]]), width=np.array([3.5, 3.6, 3.7]),
                  right=0)]
    t = np.arange(T) * dt
    ego = Vehicle(5, "sedan", (4.8, 1.9, 1.5), np.c_[10 + 20 * t, np.zeros(T), np.zeros(T)], np.full(T, 20.0))
    late = np.c_[40 + 18 * t, np.full(T, 3.5), np.zeros(T)]
    late[:6] = np.nan
    gap = np.c_[30 + 19 * t, np.zeros(T), np.zeros(T)]
    gap[8:11] = np.nan
    actors = [Vehicle(0, "truck", (9.0, 2.5, 3.5), late, np.full(T, 18.0)),
              Vehicle(1, "suv", (4.9, 2.0, 1.8), gap, np.full(T, 19.0))]
    ids = write_commonroad(tmp_path / "s.xml", lanes, ego, actors, dt, name="synthetic", author="t", affiliation="t",
                           source="t")
    assert ids.gaps_filled == [1] and set(ids.lanelets.values()).isdisjoint({0, 1, 5})
    scene = import_commonroad(tmp_path / "s.xml", ego_id=5)
    assert [lane.speed_limit for lane in scene.lanes] == [30.0, None]
    assert np.allclose(scene.lanes[1].width, [3.5, 3.6, 3.7], atol=1e-3)
    assert np.allclose(scene.lanes[1].centerline, lanes[1].centerline, atol=1e-3)
    assert scene.lanes[0].left == ids.lanelets[1]
    a0, a1 = (next(a for a in scene.actors if a.id == i) for i in (0, 1))
    assert a0.track.start == 6 and a0.cls == "truck"
    assert np.allclose(scene.actor_poses(0)[6:, :2], late[6:, :2], atol=0.01)
    assert np.allclose(scene.actor_poses(1)[:, 0], 30 + 19 * t, atol=0.01)  # the gap interpolated
    write_opendrive(tmp_path / "road.xodr", lanes, "synthetic")
    write_openscenario(tmp_path / "s.xosc", ego, actors, dt, name="synthetic", author="t", description="t",
                       wheelbase=2.85, road_file="road.xodr")
    root = ET.parse(tmp_path / "s.xosc").getroot()
    visibility = list(root.iter("VisibilityAction"))  # hidden in Init, shown at 0.55 s
    assert [v.get("graphics") for v in visibility] == ["false", "true"]
    late_traj = next(tr for tr in root.iter("Trajectory") if tr.get("name") == "actor0_trajectory")
    assert float(next(late_traj.iter("Vertex")).get("time")) == pytest.approx(0.6)
    gap_traj = next(tr for tr in root.iter("Trajectory") if tr.get("name") == "actor1_trajectory")
    assert len(list(gap_traj.iter("Vertex"))) == T - 3
    roads = ET.parse(tmp_path / "road.xodr").getroot().findall("road")
    assert [r.get("id") for r in roads] == ["0", "1"]
