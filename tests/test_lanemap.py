"""The scene's lane map: built once, read by the planner, the predictors and the baselines through
``reset``, and kept below the autonomy layer."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.autonomy.baselines import ConstantVelocityPredictor, LaneFollowingPredictor
from adv3d_runner.autonomy.interface import EgoState, SceneContext, Tracks
from adv3d_runner.autonomy.planner import SamplingPlanner
from adv3d_runner.scene import lanes as lanegeo
from adv3d_runner.scene.lanemap import LaneMap
from adv3d_runner.scene.schema import Lane, load_scene

LANE_W = 3.7


def straight(y: float, n_lanes: int = 2) -> list[Lane]:
    """``n_lanes`` parallel lanes along +x, the rightmost at ``y``."""
    xs = np.linspace(-100.0, 600.0, 71)
    return [Lane(i, np.c_[xs, np.full_like(xs, y + i * LANE_W)], LANE_W,
                 left=i + 1 if i + 1 < n_lanes else None, right=i - 1 if i > 0 else None, speed_limit=25.0)
            for i in range(n_lanes)]


def one_track(x: float, y: float, yaw: float = 0.0, speed: float = 20.0) -> Tracks:
    return Tracks(ids=[5], boxes=[[x, y, 4.6, 1.9, yaw]], velocities=[[speed, 0.0]], scores=[0.9], misses=[0],
                  history=np.zeros((1, 1, 3)), history_valid=np.ones((1, 1), bool))


def test_lane_map_holds_every_lane_and_its_geometry():
    lanes = straight(0.0, 3)
    m = LaneMap(lanes)
    assert len(m) == 3 and m.lanes == tuple(lanes) and m.ids.tolist() == [0, 1, 2]
    assert all(m.by_id[i] is lanes[i] for i in range(3)) and len(m.geometry) == 3
    assert m.lane_length(1) == lanegeo.length(lanes[1].centerline) == pytest.approx(700.0)
    lane_id, s, d = m.locate(np.array([50.0, LANE_W + 0.4, 0.1]))
    assert lane_id == 1 and s == pytest.approx(150.0) and d == pytest.approx(0.4)
    assert m.locate(np.array([50.0, 0.0, np.pi]))[0] is None  # heading against every lane
    ids, _, _ = m.locate_many(np.array([[0.0, 0.0, 0.0], [0.0, 2 * LANE_W, 0.0]]))
    assert ids.tolist() == [0, 2]
    empty = LaneMap([])
    assert len(empty) == 0 and empty.locate(np.zeros(3))[0] is None


def test_compiled_locate_is_the_numpy_definition_bit_for_bit():
    """``locate_many``'s compiled pass against ``locate_many_numpy`` (the definition): ids, s
    and d the same bytes for poses on, between, beyond and across real and generated lanes,
    one pose at a time as the planner asks, a degenerate one-point lane included."""
    rng = np.random.default_rng(3)
    scenes = [Path("scenes/highway/highway-benchmark-000010.json.gz"), Path("scenes/real/USA_US101-3_1_T-1.json.gz")]
    maps = [LaneMap.from_scene(load_scene(p)) for p in scenes if p.exists()]
    maps.append(LaneMap(straight(0.0, 3) + [Lane(9, np.array([[40.0, 30.0]]), LANE_W)]))
    for m in maps:
        pts = np.concatenate([np.asarray(lane.centerline, float).reshape(-1, 2) for lane in m.lanes])
        n = 2000
        P = np.c_[pts[rng.integers(len(pts), size=n)] + rng.normal(0.0, 4.0, (n, 2)), rng.uniform(-4.0, 4.0, n)]
        P[:20, :2] = pts.min(axis=0) - rng.uniform(0.0, 80.0, (20, 2))  # off the map
        for got, want in zip(m.locate_many(P), m.locate_many_numpy(P)):
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        for k in range(0, n, 97):
            for got, want in zip(m.locate_many(P[k:k + 1]), m.locate_many_numpy(P[k:k + 1])):
                assert got.tobytes() == want.tobytes()
    # non-finite poses keep numpy's rules
    m = maps[-1]
    bad = np.array([[np.nan, 0.0, 0.0], [1.0, 1.0, np.inf]])
    with np.errstate(invalid="ignore"):
        for got, want in zip(m.locate_many(bad), m.locate_many_numpy(bad)):
            assert got.tobytes() == want.tobytes()


def test_derived_structures_are_built_once_per_map():
    m = LaneMap(straight(0.0))
    idx = m.index(2.0, 220.0)
    assert m.index(2.0, 220.0) is idx and m.index(4.0, 220.0) is not idx
    assert idx.chain_step == 2.0 and m.index(4.0, 220.0).chain_step == 4.0
    cs = m.lane_corridor(0, 800.0)
    assert m.lane_corridor(0, 800.0) is cs and m.lane_corridor(1, 800.0) is not cs
    # the whole lane from its first point, resampled at 2 m
    assert cs.corridors[0].points[0].tolist() == [-100.0, 0.0] and cs.length[0] == pytest.approx(700.0)
    # a map of other lane objects shares nothing with this one
    assert LaneMap(straight(0.0)).index(2.0, 220.0) is not idx


def test_readers_follow_the_map_they_were_reset_with():
    """No reader keeps lanes of its own: after a reset onto a map whose lanes moved 30 m to the
    left (same ids, new objects), predictions and plans follow the new lanes."""
    old, new = LaneMap(straight(0.0)), LaneMap(straight(30.0))
    track = one_track(50.0, 30.3, yaw=0.02)  # on lane 0 of the new map, 0.3 m left of its centre
    lfp = LaneFollowingPredictor()
    lfp.reset(old)
    off_old = lfp.predict(track).trajectories[0, 0, -1]
    lfp.reset(new)
    on_new = lfp.predict(track).trajectories[0, 0, -1]
    assert on_new[1] == pytest.approx(30.3, abs=1e-9)  # kept its lateral offset in the new lane
    assert off_old[1] > 32.0  # off every old lane: straight along its heading, drifting left
    planner = SamplingPlanner()
    planner.reset(old)
    assert planner.plan(EgoState([0.0, 30.0, 0.0], 20.0)).label == "no-lane/stop"  # 30 m off the old lanes
    planner.reset(new)
    plan = planner.plan(EgoState([0.0, 30.0, 0.0], 20.0))
    assert plan.label.startswith("lane0") and abs(plan.trajectory[-1, 1] - 30.0) < 0.6


def test_readers_need_a_map_first():
    for reader, call in ((SamplingPlanner(), lambda r: r.plan(EgoState([0.0, 0.0, 0.0], 10.0))),
                         (LaneFollowingPredictor(), lambda r: r.predict(one_track(0.0, 0.0)))):
        with pytest.raises(RuntimeError, match="reset"):
            call(reader)
    # constant velocity reads no lanes: reset is accepted and changes nothing
    cv = ConstantVelocityPredictor()
    before = cv.predict(one_track(0.0, 0.0)).trajectories
    cv.reset(LaneMap(straight(5.0)))
    assert np.array_equal(cv.predict(one_track(0.0, 0.0)).trajectories, before)


def test_scene_context_from_a_scene():
    from adv3d_runner.scene.generate import generate_scene

    scene = generate_scene(100_002, "train")
    ctx = SceneContext.from_scene(scene)
    assert ctx.scene_id == scene.id and ctx.dt == scene.dt
    assert ctx.lane_map.lanes == tuple(scene.lanes) and len(ctx.lane_map) == len(scene.lanes)
    assert SceneContext.from_lanes(scene.lanes).lane_map.lanes == tuple(scene.lanes)


def _modules_after_import(*modules: str) -> set[str]:
    code = ("import sys\n" + "".join(f"import {m}\n" for m in modules) +
            "print('\\n'.join(sorted(k for k in sys.modules if k.startswith('adv3d_runner'))))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent).stdout
    return set(out.split())


def test_layers_of_the_lane_map_and_the_training_package():
    """The lane map sits in the scene layer (no autonomy, sim or attack below it), and the runtime
    stack, the simulator and the attack never import the training package."""
    loaded = _modules_after_import("adv3d_runner.scene.lanemap")
    assert not {m for m in loaded if m.split(".")[1:2] in (["autonomy"], ["sim"], ["attack"], ["training"])}, loaded
    runtime = ("adv3d_runner.autonomy.stacks", "adv3d_runner.autonomy.modular", "adv3d_runner.autonomy.detector",
               "adv3d_runner.autonomy.predictor", "adv3d_runner.autonomy.oracle", "adv3d_runner.sim.episode",
               "adv3d_runner.sim.cli", "adv3d_runner.attack.driver")
    loaded = _modules_after_import(*runtime)
    assert set(runtime) <= loaded and not {m for m in loaded if m.startswith("adv3d_runner.training")}, loaded


def test_border_ends_are_the_lanes_that_stop_where_the_map_stops():
    xs = np.linspace(0.0, 600.0, 61)
    # three lanes to the map's edge at x = 600; the right one drops at x = 300 (a lane drop)
    lanes = [Lane(0, np.c_[xs[:31], np.full(31, 0.0)], 3.7, left=1),
             Lane(1, np.c_[xs, np.full(61, 3.7)], 3.7, left=2, right=0),
             Lane(2, np.c_[xs, np.full(61, 7.4)], 3.7, right=1)]
    m = LaneMap(lanes)
    assert m.border_ends() == frozenset({1, 2})
    assert m.border_ends() is m.border_ends()  # kept
    # a lane with a successor never ends; an oncoming lane going on does not make an end a drop
    lanes = [Lane(0, np.c_[xs[:31], np.zeros(31)], 3.7, successors=[1]), Lane(1, np.c_[xs[30:], np.zeros(31)], 3.7),
             Lane(2, np.c_[xs[::-1], np.full(61, -3.7)], 3.7)]
    assert LaneMap(lanes).border_ends() == frozenset({1, 2})
