"""Autonomy-B through the evaluation, the objective and the report: a real episode whose
outputs carry a hand-made (perfect or empty) occupancy field gives the known metrics and
objective terms; B's presets; the report's Table 1 lower block."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.attack.objective import (ABLATIONS, ABLATIONS_B, LAMBDA_PLAN, combine_occupancy,
                                           episode_objective, parse_objective)
from adv3d_runner.metrics.occupancy import FLOW_LAG, occupancy_targets


class TruthField:
    """The ground truth of frame k of an episode as an occupancy field (a perfect model)."""

    horizon = 5.0

    def __init__(self, result, k: int, scale: float = 1.0):
        self.result, self.k, self.scale = result, k, scale
        self.pose = result.ego_poses[k]

    def query(self, xy, t):
        r = self.result
        xy = np.asarray(xy, float).reshape(-1, 2)
        t = np.broadcast_to(np.asarray(t, float), (len(xy),))
        occ, flow = np.zeros(len(xy)), np.zeros((len(xy), 2))
        lag = int(round(FLOW_LAG / r.dt))
        for s in np.unique(np.rint(t / r.dt).astype(int)):
            m = np.rint(t / r.dt).astype(int) == s
            j = self.k + s
            before = r.gt_boxes(j - lag) if j - lag >= 0 else None
            o, f, _ = occupancy_targets(xy[m], r.gt_boxes(j), before)
            occ[m], flow[m] = o * self.scale, f
        return occ, flow


@pytest.fixture(scope="module")
def episode():
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.fileio import REPO_ROOT
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sim.episode import run_episode

    scene = load_scene(REPO_ROOT / "scenes" / "highway" / "highway-benchmark-000010.json.gz")
    return scene, run_episode(scene, make_stack("oracle"), seconds=0.8, library=None)


def _with_fields(result, scale):
    import copy

    r = copy.copy(result)
    r.outputs = [copy.copy(o) for o in result.outputs]
    for k, o in enumerate(r.outputs):
        o.occupancy = TruthField(r, k, scale)
    return r


def test_perfect_occupancy_scores_perfectly(episode):
    from adv3d_runner.sim.evaluate import episode_evaluation, episode_metrics

    scene, result = episode
    r = _with_fields(result, 1.0)
    ev = episode_evaluation(r)
    assert ev.instance_free and len(ev.occupancy) == r.frames
    assert [s.time for s in ev.occupancy[0]] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    # frames 0-4 have no ground truth 0.5 s before t = 0: no flow-grounded slice there
    assert ev.occupancy[0][0].grounded is None and ev.occupancy[0][1].grounded is not None
    assert ev.occupancy[6][0].grounded is not None
    m = episode_metrics(r, scene.lanes, evaluation=ev)
    assert m["detection"] is None and m["prediction"] is None
    o = m["occupancy"]
    assert o["n_occupied"] > 100 and o["n_flow"] > 0
    assert o["map"] == pytest.approx(1.0) and o["soft_iou"] == pytest.approx(1.0)
    assert o["epe"] == pytest.approx(0.0, abs=1e-9)
    assert o["flow_grounded_map"] > 0.95 and o["flow_grounded_soft_iou"] > 0.95  # rigid motion, exact flow
    # Autonomy-B's objective: l_det = -1 per frame with occupancy, l_pred = 0
    obj = episode_objective(r, parse_objective("M0", "B"), ev)
    assert obj.components()["soft_iou"] == pytest.approx(r.frames)
    assert obj.det == pytest.approx(-r.frames) and obj.pred == pytest.approx(0.0, abs=1e-9)
    assert obj.total == pytest.approx(-r.frames + LAMBDA_PLAN * obj.plan)
    assert set(obj.components()) == {"det", "soft_iou", "pred", "plan", "frames"}


def test_an_empty_prediction_is_the_worst_detection_term(episode):
    from adv3d_runner.sim.evaluate import episode_evaluation, episode_metrics

    scene, result = episode
    r = _with_fields(result, 0.0)
    ev = episode_evaluation(r)
    m = episode_metrics(r, scene.lanes, evaluation=ev)["occupancy"]
    assert m["soft_iou"] == 0.0
    obj = episode_objective(r, parse_objective("M1", "B"), ev)
    assert obj.total == 0.0 and obj.soft_iou == 0.0


def test_instance_based_episodes_keep_their_metrics(episode):
    from adv3d_runner.sim.evaluate import episode_evaluation, episode_metrics

    scene, result = episode
    ev = episode_evaluation(result)
    assert not ev.instance_free
    m = episode_metrics(result, scene.lanes, evaluation=ev)
    assert "occupancy" not in m and m["detection"]["ap"] is not None
    assert set(episode_objective(result, evaluation=ev).components()) == {"det", "tp", "fp", "pred", "plan", "frames"}


def test_b_presets_and_terms():
    assert ABLATIONS_B["M0"].pred == 1.0 and ABLATIONS_B["M0"].plan == 0.5 and ABLATIONS_B["M0"].det == 1.0
    assert ABLATIONS["M0"].pred == 0.1
    for name in ABLATIONS:
        a, b = ABLATIONS[name], ABLATIONS_B[name]
        assert (a.det > 0, a.pred > 0, a.plan > 0) == (b.det > 0, b.pred > 0, b.plan > 0)
    assert parse_objective("M2", "B").pred == 1.0 and parse_objective("M2", "A").pred == 0.1
    assert parse_objective("M4,pred=0.3", "B").pred == 0.3
    v = combine_occupancy(np.array([0.5, 0.25]), np.array([2.0, 1.0]), np.array([0.2, 0.4]))
    assert v.det == -0.75 and v.pred == 3.0 and v.total == pytest.approx(-0.75 + 3.0 + 0.5 * 0.6)
    assert v.tp is None and v.fp is None


def test_attack_config_uses_the_stacks_presets():
    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.errors import ConfigError

    assert AttackConfig(["s.json"], autonomy="B").settings.weights.pred == 1.0
    assert AttackConfig(["s.json"], autonomy="A").settings.weights.pred == 0.1
    with pytest.raises(ConfigError, match="autonomy"):
        AttackConfig(["s.json"], autonomy="no-such-stack")


def test_report_has_the_lower_block_for_b_runs():
    from adv3d_runner.attack.report import COLUMNS, COLUMNS_B, is_instance_free, paired_deltas, table1

    def metrics(m, iou):
        return {"detection": None, "prediction": None,
                "occupancy": {"map": m, "soft_iou": iou, "flow_grounded_map": m, "flow_grounded_soft_iou": iou,
                              "epe": 1.5},
                "planning_comfort": {"lat": 0.1, "jerk": 0.2}, "driving_comfort": {"lat": 0.1, "jerk": 0.3}}

    summary = {"scenes": {"s1": {"original": {"cost": -10.0, "metrics": metrics(0.8, 0.5)},
                                 "modes": {"closed": {"closed_loop_eval": {"cost": -5.0, "metrics": metrics(0.7, 0.4)}}}}}}
    runs = [("r", {"algo": "bo", "autonomy": "B"}, [], summary)]
    assert is_instance_free(runs[0][1]) and not is_instance_free({"autonomy": "A"})
    table = table1(runs, COLUMNS_B)
    assert "Occ. mAP" in table and "Flow-gr. Soft-IoU" in table and "| Original | 1 | -10 | 80 | 50 | 80 | 50 | 1.5 |" in table
    deltas = paired_deltas(runs, COLUMNS_B)
    assert "-10 (1/1)" in deltas  # mAP 80 -> 70 %: lower is worse
    assert "| Original | 1 | -10 | - | - |" in table1(runs, COLUMNS)  # A's columns have nothing to show
