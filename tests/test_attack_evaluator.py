"""The typed attack path: AttackConfig <-> run.json, QuerySettings and the run's one shape-space
loader, the QueryEvaluator interface (episode evaluator and the tests' synthetic one),
run_query's failure statuses, and one EpisodeEvaluation shared by the objective and the metrics."""
from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
from attack_synthetic import SyntheticEvaluator

from adv3d_runner.attack.config import AttackConfig, QuerySettings
from adv3d_runner.attack.evaluator import EpisodeEvaluator, Query, QueryEvaluator, QueryResult, run_query
from adv3d_runner.errors import ConfigError, FileFormatError

#: run.json's config keys in their order (docs/formats.md, "Run bundle"): the file contract.
RUN_JSON_KEYS = ["scenes", "algo", "budget", "actors", "mode", "seconds", "seed", "objective", "autonomy",
                 "reactive", "batch", "n_initial", "shape_space", "library", "pred_reduction"]


def test_attack_config_is_frozen_and_round_trips_through_run_json():
    c = AttackConfig(["a.json.gz", "b.json.gz"], algo="random", budget=7, actors=2, mode="both", seconds=1.5,
                     seed=3, objective="M1,beta=2", autonomy="oracle", reactive=True, batch=2, n_initial=4,
                     shape_space="space.npz")
    assert c.scenes == ("a.json.gz", "b.json.gz")  # a list is kept as a tuple
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.seed = 4
    doc = c.run_json()
    assert list(doc) == RUN_JSON_KEYS and doc["scenes"] == ["a.json.gz", "b.json.gz"]
    # what run.json holds besides the config is ignored when reading it back
    assert AttackConfig.from_run_json({**doc, "scene_ids": ["a", "b"], "versions": {}, "workers": 2}) == c
    assert c.modes == ["open", "closed"] and c.with_batch(5).batch == 5 and c.batch == 2
    s = c.settings
    assert s == QuerySettings(autonomy="oracle", actors=2, objective="M1,beta=2", seconds=1.5, seed=3,
                              reactive=True, shape_space="space.npz")
    assert hash(s) == hash(dataclasses.replace(s))  # workers key their scene contexts on it
    assert s.weights.det == 1.0 and s.weights.pred == 0.0 and s.weights.beta == 2.0
    with pytest.raises(FileFormatError, match=r"\$\.scenes"):  # run.json is a file: its errors name the field
        AttackConfig.from_run_json({"algo": "bo"})
    with pytest.raises(FileFormatError, match=r"run.json: \$\.budget"):
        AttackConfig.from_run_json({**doc, "budget": "many"}, "run.json")
    for bad in (dict(mode="sideways"), dict(budget=0), dict(seconds=0.0), dict(batch=0), dict(objective="M9"),
                dict(actors=0), dict(seed=-1), dict(seconds=float("nan")), dict(n_initial=-3), dict(algo="magic"),
                dict(budget=True), dict(autonomy="no-such-stack")):
        with pytest.raises(ConfigError):
            AttackConfig(["a.json.gz"], **bad)


def test_pred_reduction_and_scene_seeds_in_run_json():
    """Runs before the option used the horizon mean: their run.json (no key) reads as "mean", a
    "mean" run writes the run.json it always wrote; the default is Eq. 5's sum and is written."""
    new = AttackConfig(["a.json.gz"])
    assert new.pred_reduction == "sum" and new.run_json()["pred_reduction"] == "sum"
    assert new.settings.weights.pred_reduction == "sum"
    legacy = AttackConfig(["a.json.gz"], pred_reduction="mean")
    assert "pred_reduction" not in legacy.run_json() and "scene_seeds" not in legacy.run_json()
    assert AttackConfig.from_run_json(legacy.run_json()) == legacy
    assert AttackConfig.from_run_json(new.run_json()) == new
    per_scene = AttackConfig(["a.json.gz"], scene_seeds=True)
    assert per_scene.run_json()["scene_seeds"] is True
    assert AttackConfig.from_run_json(per_scene.run_json()) == per_scene
    ranked = AttackConfig(["a.json.gz"], target_rank=2)
    assert ranked.run_json()["target_rank"] == 2 and "target_rank" not in new.run_json()
    assert AttackConfig.from_run_json(ranked.run_json()) == ranked and ranked.settings.target_rank == 2
    for bad in (dict(pred_reduction="max"), dict(scene_seeds=1), dict(target_rank=-1), dict(target_rank=64)):
        with pytest.raises(ConfigError):
            AttackConfig(["a.json.gz"], **bad)


def test_scene_seeds_differ_per_scene_and_stream():
    from adv3d_runner.attack.config import scene_seed

    a, b = "sha256:" + "0" * 64, "sha256:" + "1" * 64
    # fixed value: sha256("7|sha256:00..0|search")[:4] (the derivation is a file contract)
    import hashlib

    assert scene_seed(7, a, "search") == int(hashlib.sha256(f"7|{a}|search".encode()).hexdigest()[:8], 16)
    seeds = {scene_seed(7, d, s) for d in (a, b) for s in ("search", "noise")}
    assert len(seeds) == 4 and all(0 <= x < 2**32 for x in seeds)
    assert scene_seed(8, a, "search") != scene_seed(7, a, "search")
    cfg = AttackConfig(["x"], seed=7)
    assert cfg.search_seed(a) == 7 and cfg.settings.episode_seed(a) == 7  # default: the run seed
    cfg = AttackConfig(["x"], seed=7, scene_seeds=True)
    assert cfg.search_seed(a) == scene_seed(7, a, "search") and cfg.settings.episode_seed(b) == scene_seed(7, b, "noise")
    with pytest.raises(ConfigError):
        scene_seed(-1, a, "search")


def test_one_shape_space_load_per_run_and_process():
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE

    if not DEFAULT_SHAPE_SPACE.exists():
        pytest.skip("no shipped shape space")
    a, b = QuerySettings(), QuerySettings(seed=9, shape_space=str(DEFAULT_SHAPE_SPACE))
    assert a.shape_space_path == DEFAULT_SHAPE_SPACE
    assert a.load_shape_space() is b.load_shape_space()  # the same file is loaded once


def test_shape_space_reloaded_when_its_file_changes(tmp_path):
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE

    if not DEFAULT_SHAPE_SPACE.exists():
        pytest.skip("no shipped shape space")
    path = tmp_path / "space.npz"
    path.write_bytes(DEFAULT_SHAPE_SPACE.read_bytes())
    s = QuerySettings(shape_space=str(path))
    first = s.load_shape_space()
    assert s.load_shape_space() is first
    os.utime(path, ns=(1, 1))  # the file changed (a new modification time): loaded again
    assert s.load_shape_space() is not first
    assert s.load_shape_space().content_hash == first.content_hash


def test_both_evaluators_implement_the_interface():
    for ev in (EpisodeEvaluator(QuerySettings()), SyntheticEvaluator(QuerySettings())):
        assert isinstance(ev, QueryEvaluator)
    assert not isinstance(object(), QueryEvaluator)


class _Fixed:
    """An evaluator whose queries all give one outcome (a QueryResult, or an exception to raise)."""

    def __init__(self, outcome):
        self.outcome = outcome

    def evaluate(self, query):
        if isinstance(self.outcome, Exception):
            raise self.outcome
        return self.outcome


def test_run_query_turns_failures_into_statuses():
    from adv3d_runner.errors import EmptySurfaceError

    q = Query("synthetic:peak", np.full(5, 0.5))
    ok = run_query(_Fixed(QueryResult(cost=1.5, components={"x": 1.5})), q)
    assert ok.status == "ok" and ok.cost == 1.5 and ok.error is None and ok.wall_s > 0
    inv = run_query(_Fixed(EmptySurfaceError("no surface")), q)
    assert inv.status == "invalid" and inv.cost is None and "EmptySurfaceError" in inv.error
    err = run_query(_Fixed(RuntimeError("boom")), q)
    assert err.status == "error" and err.cost is None and "boom" in err.error
    nan = run_query(_Fixed(QueryResult(cost=float("nan"), components={"x": 1.0})), q)
    assert nan.status == "error" and nan.cost is None and "non-finite" in nan.error
    assert nan.components == {"x": 1.0}  # what was measured is kept


def test_synthetic_evaluator_through_run_query():
    ev = SyntheticEvaluator(QuerySettings(actors=1, seed=0))
    assert ev.targets("synthetic:peak") == ([0], 5)
    best = run_query(ev, Query("synthetic:peak", np.array([0.73, 0.21, 0.58, 0.87, 0.34])))
    assert best.status == "ok" and best.cost == pytest.approx(2.0)
    assert run_query(ev, Query("synthetic:peak", np.array([0.99, 0.5, 0.5, 0.5, 0.5]))).status == "invalid"
    assert run_query(ev, Query("synthetic:peak", np.array([0.5, 0.99, 0.5, 0.5, 0.5]))).status == "error"
    assert run_query(ev, Query("synthetic:nope", np.full(5, 0.5))).status == "error"


def test_objective_and_metrics_share_one_episode_evaluation(repo_root):
    """The episode's detection frames and prediction pairs, computed once, give the objective and
    the metrics exactly what each computes on its own."""
    from adv3d_runner.attack.objective import ABLATIONS, episode_objective
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import rig_from_scene, world_from_scene
    from adv3d_runner.sim.episode import run_episode
    from adv3d_runner.sim.evaluate import EpisodeEvaluation, episode_evaluation, episode_metrics
    from adv3d_runner.autonomy.stacks import make_stack

    scene = load_scene(repo_root / "scenes/highway/highway-benchmark-000000.json.gz")
    rig = rig_from_scene(scene, model="generic-32", columns=512)
    r = run_episode(scene, make_stack("oracle"), seconds=1.0, world=world_from_scene(scene, None), rig=rig)
    ev = episode_evaluation(r)
    assert isinstance(ev, EpisodeEvaluation) and len(ev.detection) == len(ev.prediction) == r.frames
    assert sum(len(g) for g, _, _ in ev.detection) > 0 and sum(len(p) for p, _, _ in ev.prediction) > 0
    for w in (ABLATIONS["M0"], ABLATIONS["M1"]):
        assert episode_objective(r, w, ev) == episode_objective(r, w)
    shared, alone = episode_metrics(r, scene.lanes, evaluation=ev), episode_metrics(r, scene.lanes)
    for m in (shared, alone):
        m.pop("ms_per_frame"), m.pop("fps")
    assert shared == alone and shared["detection"]["n_gt"] > 0
    # the shared matchings and plan comforts are made once and equal the per-caller definitions
    from adv3d_runner.attack.objective import detection_terms, planning_terms
    from adv3d_runner.metrics.comfort import planning_comfort
    from adv3d_runner.metrics.detection import evaluate_frames

    assert ev.matches(0.5) is ev.matches(0.5) and len(ev.matches(0.5)) == r.frames
    det = evaluate_frames(*([f[i] for f in ev.detection] for i in range(3)))
    assert shared["detection"]["ap"] == det.ap and shared["detection"]["n_tp"] == det.n_tp
    assert shared["planning_comfort"] == planning_comfort(r.plans(), r.dt).as_dict()
    for thr in (0.5, 0.3):
        a, b = detection_terms(ev.detection, thr, ev.matches(thr)), detection_terms(ev.detection, thr)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert [c.jerk + c.lat for c in ev.plan_comfort] == planning_terms(r.plans(), r.dt).tolist()
    # an evaluation made with another visibility rule is refused, not silently used
    other = episode_evaluation(r, min_gt_points=50)
    with pytest.raises(ValueError):
        episode_metrics(r, scene.lanes, evaluation=other)
    with pytest.raises(ValueError):
        episode_objective(r, ABLATIONS["M0"], other)
    assert episode_metrics(r, scene.lanes, 50, evaluation=other)["detection"]["min_gt_points"] == 50
