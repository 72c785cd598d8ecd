"""Criticality in standard terms by CommonRoad's CriMe (adv3d_runner/sim/criticality.py,
docs/attack.md): a hand-made car-following episode whose measures are known analytically, the server's
shortcuts against plain CriMe, the scenario written for it, the block without CriMe, and the
attack report's criticality table.

CriMe runs in its own environment (``bash examples/crime/install.sh``; docs/attack.md,
"Criticality (CriMe)"): the tests that need it are skipped where it is not installed."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from adv3d_runner.scene.schema import Lane
from adv3d_runner.sim import criticality as cr
from adv3d_runner.sim.episode import EpisodeResult

needs_crime = pytest.mark.skipif(not cr.available(), reason=f"CriMe is not installed ({cr.INSTALL_HINT})")

DT = 0.1
V_EGO, V_LEAD, GAP, LENGTH = 20.0, 10.0, 30.0, 4.5  # m/s, m/s, m bumper to bumper, m


def following(angle: float = 0.0, frames: int = 20) -> EpisodeResult:
    """The ego at 20 m/s 30 m (bumper to bumper) behind a leader at 10 m/s in its lane (actor 7),
    a car beside the leader in the next lane (actor 9), and one behind the ego (actor 11); the
    road runs at ``angle`` rad. No plans: the trajectories end with the episode."""
    t = np.arange(frames + 60) * DT
    d = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-d[1], d[0]])
    ego_s = V_EGO * t[:frames]
    lead_s = LENGTH + GAP + V_LEAD * t

    def poses(s, lateral=0.0):
        return np.c_[s[:, None] * d + lateral * n, np.full(len(s), angle)]

    actors = np.stack([poses(lead_s), poses(lead_s, 3.5), poses(-40.0 + 15.0 * t)], axis=1)
    return EpisodeResult(
        scene_id="following", start_frame=0, dt=DT, closed_loop=True, reactive=False, seed=0,
        actor_ids=np.array([7, 9, 11]), actor_classes=["sedan"] * 3,
        actor_dimensions=np.array([[LENGTH, 1.8, 1.5]] * 3),
        adversarial=np.array([True, False, False]), ego_dimensions=np.array([LENGTH, 1.8, 1.5]),
        ego_poses=poses(ego_s), ego_speeds=np.full(frames, V_EGO), ego_accels=np.zeros(frames), actor_poses=actors,
        n_points=np.zeros(frames, dtype=np.int64), actor_points=np.zeros((frames, 3), dtype=np.int64), outputs=[])


def road(angle: float = 0.0) -> list[Lane]:
    d = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-d[1], d[0]])
    s = np.arange(-100.0, 1001.0, 10.0)[:, None]
    return [Lane(id=1, centerline=s * d, width=np.full(len(s), 3.5), left=2),
            Lane(id=2, centerline=s * d + 3.5 * n, width=np.full(len(s), 3.5), right=1)]


@needs_crime
@pytest.mark.parametrize("degrees", [0.0, 37.0, -140.0])
def test_car_following_matches_the_formulas(degrees):
    """Frame 0: TTC = gap / closing speed = 3 s, DHW = 30 m, THW = gap / v_ego = 1.5 s,
    a_long_req = -(closing speed)^2 / (2 gap) = -1.667 m/s^2, BTN = -a_long_req / 11.5 m/s^2.
    Tolerances: CriMe rounds TTC, DHW and a_long_req to 0.01 and BTN to 1e-4; its THW is the
    first time step at which the ego's front is past the leader's rear, i.e. rounded up to dt.
    The same on a road along +x (CriMe reads a lane orientation of exactly 0 as none) and on
    roads at other headings (CriMe projects speeds with the lane's absolute orientation): the
    scenario is moved rigidly first."""
    angle = math.radians(degrees)
    c = cr.episode_criticality(following(angle), road(angle))
    lead, beside, behind = 0, 1, 2
    closing = V_EGO - V_LEAD
    assert c.pairs["ttc"][0, lead] == pytest.approx(GAP / closing, abs=0.011)
    assert c.pairs["dhw"][0, lead] == pytest.approx(GAP, abs=0.011)
    assert GAP / V_EGO - 1e-9 <= c.pairs["thw"][0, lead] <= GAP / V_EGO + DT + 1e-9
    a_req = -closing**2 / (2 * GAP)
    assert c.pairs["a_long_req"][0, lead] == pytest.approx(a_req, abs=0.006)
    assert c.pairs["btn"][0, lead] == pytest.approx(-a_req / 11.5, abs=1e-3)
    # frame k: the gap is 30 - 10 k dt
    k = 10
    assert c.pairs["ttc"][k, lead] == pytest.approx((GAP - closing * k * DT) / closing, abs=0.011)
    assert c.pairs["dhw"][k, lead] == pytest.approx(GAP - closing * k * DT, abs=0.011)
    # the car in the next lane and the one behind are nobody's leader
    for i in (beside, behind):
        assert np.all(np.isinf(c.pairs["ttc"][:, i])) and np.all(np.isinf(c.pairs["dhw"][:, i]))
        assert np.all(c.pairs["a_long_req"][:, i] == 0.0)
    # closest encounter: the leader, at the end (CriMe's DCE stops one frame before the last)
    assert c.dce[lead, 1] >= 18 and c.dce[lead, 0] == pytest.approx(GAP - closing * c.dce[lead, 1] * DT, abs=0.011)
    assert math.isinf(c.ttc_star) and math.isinf(c.ttb)  # no collision within the episode
    s = c.summary()
    assert s["ttc"] == {"value": pytest.approx(1.1, abs=0.011), "unit": "s", "actor": 7, "frame": 19}
    assert s["dhw"]["actor"] == 7 and s["dhw"]["frame"] == 19 and s["dhw"]["value"] == pytest.approx(11.0, abs=0.011)
    assert s["required_deceleration"]["value"] == pytest.approx(closing**2 / (2 * 11.0), abs=0.006)
    assert s["ttc_star"]["value"] is None and s["ttb"]["value"] is None
    json.dumps(s, allow_nan=False)  # JSON-safe


@needs_crime
def test_server_shortcuts_change_nothing():
    """The server's shortcuts (cached lanelet smoothing, the same-lanelet check asked once, BTN
    from ALongReq, no TTB without a collision) give CriMe's plain values, here with a leader
    that brakes into a collision (TTC*, TTB finite) and cars in the next lane and behind."""
    res = following(frames=30)
    lead = res.actor_poses[:, 0]  # the leader brakes at 6 m/s^2 from 0.5 s: contact at 2.17 s
    t = np.arange(len(lead)) * DT
    tau = np.clip(t - 0.5, 0.0, V_LEAD / 6.0)  # braking time, to a stop
    res.actor_poses[:, 0, 0] = LENGTH + GAP + V_LEAD * np.minimum(t, 0.5) + V_LEAD * tau - 3.0 * tau**2
    fast = cr.episode_criticality(res, road())
    plain = cr.episode_criticality(res, road(), plain=True)
    for key in cr.PAIR:
        np.testing.assert_array_equal(fast.pairs[key], plain.pairs[key], err_msg=key)
    np.testing.assert_array_equal(fast.dce, plain.dce)
    assert fast.ttc_star == plain.ttc_star and fast.ttb == plain.ttb
    assert math.isfinite(fast.ttc_star)  # the ego runs into it within the episode
    assert fast.summary()["ttc"]["value"] < 1.0


@needs_crime
def test_server_survives_a_bad_request(tmp_path):
    crime = cr.server()
    with pytest.raises(cr.CriticalityUnavailable, match="CriMe failed"):
        crime.request({"xml": str(tmp_path / "missing.xml"), "ego_id": 1})
    assert crime.alive()
    assert cr.episode_criticality(following(), road(), crime=crime).summary()["ttc"]["actor"] == 7


def test_scenario_written_for_crime(tmp_path):
    """The CommonRoad file adv3d writes (commonroad-io of adv3d's environment): ids, the rigid
    motion (ego first at the origin, heading HEADING_OFFSET), rectangles of the actors'
    dimensions, speeds from the poses, actors present during the episode only, open lane ends
    extended."""
    from commonroad.common.file_reader import CommonRoadFileReader

    angle = math.radians(37.0)
    res = following(angle)
    res.actor_dimensions[0] = [5.1, 1.36, 1.68]  # a found shape's dimensions
    res.actor_poses[:, 2] = np.nan  # actor 11 never present
    path = tmp_path / "episode.xml"
    ids = cr.write_episode_scenario(res, road(angle), path)
    assert ids.ego == 1 and ids.actors == {0: 2, 1: 3}
    scenario, _ = CommonRoadFileReader(str(path)).open()
    ego = scenario.obstacle_by_id(1)
    np.testing.assert_allclose(ego.initial_state.position, [0.0, 0.0], atol=1e-6)
    assert ego.initial_state.orientation == pytest.approx(cr.HEADING_OFFSET, abs=1e-5)
    lead = scenario.obstacle_by_id(2)
    assert lead.obstacle_shape.length == pytest.approx(5.1) and lead.obstacle_shape.width == pytest.approx(1.36)
    p0 = np.asarray(lead.initial_state.position)
    assert np.hypot(*p0) == pytest.approx(LENGTH + GAP, abs=1e-3)
    assert lead.initial_state.velocity == pytest.approx(V_LEAD, abs=1e-6)
    assert lead.prediction.final_time_step == len(res.ego_poses) - 1
    assert 4 not in [o.obstacle_id for o in scenario.dynamic_obstacles]
    # both lanes run from -100 to 1000 m: extended by EXTEND_ENDS at their end only
    lengths = sorted(float(np.sum(np.hypot(*np.diff(ll.center_vertices, axis=0).T)))
                     for ll in scenario.lanelet_network.lanelets)
    assert lengths == pytest.approx([1100.0 + cr.EXTEND_ENDS] * 2, abs=0.01)


def test_ego_goes_on_along_its_last_plan():
    from types import SimpleNamespace

    from adv3d_runner.autonomy.interface import Plan

    res = following(frames=5)
    last = res.ego_poses[-1]
    traj = np.c_[last[0] + V_EGO * DT * np.arange(4), np.zeros(4), np.zeros(4)]
    res.outputs = [SimpleNamespace(plan=Plan(traj, np.full(4, V_EGO)))] * 5
    poses, speeds = cr._ego_ahead(res, 5)
    assert len(poses) == 8 and np.allclose(poses[5:, 0], last[0] + V_EGO * DT * np.arange(1, 4))
    assert np.allclose(speeds, V_EGO)
    res.outputs = []  # no plans: the episode alone
    assert len(cr._ego_ahead(res, 5)[0]) == 5


def test_block_says_when_crime_is_missing(monkeypatch, tmp_path):
    monkeypatch.setenv(cr.PYTHON_ENV, str(tmp_path / "no-such-python"))
    assert cr.criticality_block(following(), road()) == {"note": cr.NOT_AVAILABLE}
    assert "examples/crime/install.sh" in cr.NOT_AVAILABLE
    monkeypatch.setenv(cr.PYTHON_ENV, "none")
    assert cr.criticality_block(following(), road()) == {"note": "off (ADV3D_CRIME_PYTHON=none)"}


def test_report_table_figures_and_note():
    from adv3d_runner.attack.report import criticality_table

    fig = {"ttc": {"value": 1.1, "unit": "s", "actor": 7, "frame": 19}, "thw": {"value": None, "unit": "s",
           "actor": None, "frame": None}, "ttb": {"value": None, "unit": "s", "frame": 0, "unavoidable": True},
           "ttc_star": {"value": 2.3, "unit": "s", "frame": 0}}
    summary = {"scenes": {"s1": {"original": {"cost": -3.0, "criticality": {"note": cr.NOT_AVAILABLE}},
                                 "modes": {"closed": {"closed_loop_eval": {"cost": 5.0, "criticality": fig}}}},
                          "s2": {"original": {"cost": -1.0}, "modes": {}}}}  # made before the block: no row
    table = criticality_table([("r", {"algo": "bo"}, [], summary)])
    rows = [ln for ln in table.splitlines() if ln.startswith("| ")][1:]
    assert len(rows) == 2
    assert rows[0].startswith("| - | s1 | original | -3 | " + cr.NOT_AVAILABLE)
    cells = [c.strip() for c in rows[1].strip("|").split("|")]
    assert cells[:4] == ["bo", "s1", "best (closed)", "5"]
    assert cells[4] == "1.1 (#7 @19)" and cells[5] == "never" and cells[10] == "2.3" and cells[11] == "unavoidable"
    assert criticality_table([("r", {}, [], {"scenes": {"s2": summary["scenes"]["s2"]}})]) == ""


def test_attack_report_shows_criticality(tmp_path, repo_root, monkeypatch):
    """A tiny real attack (oracle, budget 2, 1 s): summary.json's original and best evaluations
    carry a ``criticality`` block (CriMe's figures where it is installed, else the note) and
    the report shows it beside the objective."""
    scene = repo_root / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not scene.exists():
        pytest.skip("no bundled scenes")
    from adv3d_runner.attack import evaluator
    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.driver import run_attack
    from adv3d_runner.attack.report import write_report

    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    config = AttackConfig([str(scene)], algo="random", budget=2, seconds=1.0, autonomy="oracle", seed=1)
    summary = run_attack(config, tmp_path / "run", show_progress=False)
    entry = summary["scenes"]["highway-benchmark-000000"]
    blocks = [entry["original"]["criticality"], entry["modes"]["closed"]["closed_loop_eval"]["criticality"]]
    on_disk = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert on_disk["scenes"]["highway-benchmark-000000"]["original"]["criticality"] == blocks[0]
    text = write_report([tmp_path / "run"]).read_text()
    assert "### Criticality (CommonRoad CriMe)" in text and "min TTC s" in text
    if cr.available():
        for b in blocks:
            assert "commonroad-crime" in b["tool"] and b["frames"] == 10 and b["ttc"]["unit"] == "s"
        assert "| - | highway-benchmark-000000 | original |" in text
    else:
        assert blocks == [{"note": cr.NOT_AVAILABLE}] * 2 and cr.NOT_AVAILABLE in text
