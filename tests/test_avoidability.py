"""Avoidability (stack- or scenario-induced failures), failure rates of realistic shapes with
their Clopper-Pearson intervals, and the realistic search region (docs/attack.md, "Avoidability"
and "How often"; docs/realism.md, "The default region"). The episodes are real: 1 s closed-loop
episodes of Autonomy-A and of the oracle stack on a bundled highway scene."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from adv3d_runner.attack.avoidability import (FAILURE_KINDS, SCENARIO_INDUCED, STACK_INDUCED, classify_failures,
                                              episode_failures, finding_of, shape_verdict)
from adv3d_runner.attack.config import AttackConfig, QuerySettings
from adv3d_runner.attack.failure_rate import clopper_pearson, rate_block
from adv3d_runner.errors import ConfigError

SCENE = "scenes/highway/highway-benchmark-000000.json.gz"


def metrics(collided=False, at_fault=False, braking=-1.0, off_road=False, progress=30.0) -> dict:
    return {"collision": {"collided": collided, "at_fault": at_fault}, "hardest_braking_mps2": braking,
            "off_road": off_road, "progress_m": progress}


# ----------------------------------------------------------------------------- rules

def test_episode_failures_follow_the_thresholds():
    orig = metrics(progress=30.0)
    f = episode_failures(metrics(collided=True, at_fault=True, braking=-4.01, off_road=True, progress=23.9), orig)
    assert f == {k: True for k in FAILURE_KINDS}
    f = episode_failures(metrics(collided=True, at_fault=False, braking=-4.0, progress=24.0), orig)
    assert f == {"collision": True, "at_fault_collision": False, "hard_braking": False, "off_road": False,
                 "low_progress": False}
    # figures a record lacks stay unknown, never a pass
    f = episode_failures({"collision": {"collided": False}, "off_road": False, "progress_m": 3.0}, None)
    assert f["hard_braking"] is None and f["low_progress"] is None and f["collision"] is False


def test_classify_and_verdicts():
    s = {k: False for k in FAILURE_KINDS} | {"hard_braking": True, "collision": True}
    r = {k: False for k in FAILURE_KINDS} | {"collision": True, "off_road": True}
    c = classify_failures(s, r)
    assert c["hard_braking"] == STACK_INDUCED and c["collision"] == SCENARIO_INDUCED
    assert c["off_road"] == "reference-only" and c["low_progress"] == "none"
    assert classify_failures({**s, "low_progress": None}, r)["low_progress"] == "unknown"
    none = {k: "none" for k in FAILURE_KINDS}
    # stack-induced on one seed, scenario-induced on another: scenario-induced (the reference can fail there)
    v = shape_verdict([{**none, "hard_braking": STACK_INDUCED}, {**none, "hard_braking": SCENARIO_INDUCED}])
    assert v["hard_braking"]["verdict"] == SCENARIO_INDUCED and v["hard_braking"]["stack_induced"] == 1
    v = shape_verdict([{**none, "hard_braking": STACK_INDUCED}, none], [["hard_braking"], []])
    assert v["hard_braking"]["verdict"] == STACK_INDUCED and v["hard_braking"]["new_stack_induced"] == 0
    assert finding_of(v) == "pre-existing"
    v = shape_verdict([{**none, "hard_braking": STACK_INDUCED}, none], [[], []])
    assert finding_of(v) == STACK_INDUCED
    assert finding_of(shape_verdict([none])) == "no failure"


def test_hardest_braking_of_a_speed_trace():
    from adv3d_runner.sim.evaluate import hardest_braking

    v = np.array([20.0, 20.0, 19.5, 19.0, 18.4, 18.4, 19.0])  # dt 0.1: worst step -0.6 m/s in 0.1 s
    assert hardest_braking(v, 0.1) == pytest.approx(-6.0)
    assert hardest_braking(np.array([10.0, 11.0]), 0.1) == 0.0 and hardest_braking(np.array([3.0]), 0.1) == 0.0


# ----------------------------------------------------------------------------- intervals

@pytest.mark.parametrize("k,n", [(0, 1), (0, 50), (3, 10), (17, 40), (40, 40)])
def test_clopper_pearson_is_scipys_exact_interval(k, n):
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    assert clopper_pearson(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_clopper_pearson_closed_forms_and_coverage():
    assert clopper_pearson(0, 50)[1] == pytest.approx(1 - 0.025 ** (1 / 50))  # k = 0: 1 - (alpha/2)^(1/n)
    assert clopper_pearson(50, 50)[0] == pytest.approx(0.025 ** (1 / 50))
    assert all(math.isnan(x) for x in clopper_pearson(0, 0))
    with pytest.raises(ConfigError):
        clopper_pearson(5, 3)
    # exact coverage >= 95 % for every true rate on a grid (the reason it was chosen)
    from scipy.stats import binom

    n = 20
    bounds = [clopper_pearson(k, n) for k in range(n + 1)]
    for p in np.linspace(0.005, 0.995, 67):
        cover = sum(binom.pmf(k, n, p) for k, (lo, hi) in enumerate(bounds) if lo <= p <= hi)
        assert cover >= 0.95 - 1e-9
    block = rate_block([{k: False for k in FAILURE_KINDS} | {"hard_braking": True}, {k: False for k in FAILURE_KINDS}])
    assert block["hard_braking"]["k"] == 1 and block["hard_braking"]["n"] == 2 and block["any"]["rate"] == 0.5


# ----------------------------------------------------------------------------- realistic region

@pytest.fixture(scope="module")
def scene_path():
    from adv3d_runner.fileio import REPO_ROOT

    p = REPO_ROOT / SCENE
    if not p.exists():
        pytest.skip("no bundled scenes")
    return str(p)


def test_realistic_region_decodes_only_shapes_that_pass(scene_path):
    from adv3d_runner.attack.shape_models import ActorShapes
    from adv3d_runner.attack.targets import select_targets
    from adv3d_runner.scene.schema import load_scene

    settings = QuerySettings(region="realistic")
    scene = load_scene(scene_path)
    shapes = ActorShapes(settings, scene, select_targets(scene, 1), settings.load_shape_space())
    paper = ActorShapes(QuerySettings(), scene, select_targets(scene, 1), settings.load_shape_space())
    rng = np.random.default_rng(3)
    moved = 0
    for _ in range(3):
        u = rng.random(shapes.per_actor)
        (rep,) = shapes.full_reports(u)
        assert rep["realistic"] and rep["projection_t"] in shapes.PROJECTION_STEPS
        assert rep["mahalanobis"] <= shapes.reference.mahalanobis_limit + 1e-9
        overrides, info = shapes.decode_query(u)
        (shape,) = overrides.values()
        assert np.allclose(info["dimensions"][0], rep["dimensions_m"], atol=1e-6)  # the episode's shape is the reported one
        assert shapes.passes(u) == (rep["projection_t"] == 1.0)
        moved += rep["projection_t"] < 1.0
    assert paper.realistic is False and paper.region is None


def test_region_option_defaults_and_refusals():
    import argparse

    from adv3d_runner.attack import cli
    from adv3d_runner.attack.config import REGIONS

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    opts = cli._shape_options(parser.parse_args(["attack", "s.json.gz", "--out", "x"]))
    assert opts["region"] == "realistic"
    opts = cli._shape_options(parser.parse_args(["attack", "s.json.gz", "--out", "x", "--region", "paper"]))
    assert opts["region"] == "paper"
    opts = cli._shape_options(parser.parse_args(["attack", "s.json.gz", "--out", "x", "--algo", "bruteforce"]))
    assert opts["region"] == "paper"
    choices = next(a.choices for a in parser._subparsers._group_actions[0].choices["attack"]._actions
                   if a.dest == "region")
    assert set(choices) == set(REGIONS)
    for bad in (dict(region="realistic", shape_model="vd"), dict(region="realistic", algo="bruteforce"),
                dict(region="box")):
        with pytest.raises(ConfigError):
            AttackConfig(["a.json.gz"], **bad)
    cfg = AttackConfig(["a.json.gz"], region="realistic")
    assert cfg.run_json()["region"] == "realistic" and "region" not in AttackConfig(["a.json.gz"]).run_json()
    assert AttackConfig.from_run_json(AttackConfig(["a.json.gz"]).run_json()).region == "paper"
    assert cfg.settings.region == "realistic"


# ----------------------------------------------------------------------------- real episodes

@pytest.fixture(scope="module")
def run_a(scene_path, tmp_path_factory):
    """Autonomy-A, one query of 1 s in the realistic region, then avoidability on 2 held-out seeds
    (criticality off: CriMe's figures are tested in test_criticality.py)."""
    import os

    from adv3d_runner.cli import main

    out = tmp_path_factory.mktemp("avoid") / "run"
    old = os.environ.get("ADV3D_CRIME_PYTHON")
    os.environ["ADV3D_CRIME_PYTHON"] = "none"
    try:
        assert main(["-q", "attack", scene_path, "--autonomy", "A", "--budget", "1", "--seconds", "1", "--algo",
                     "random", "--out", str(out), "--avoidability", "2"]) == 0
    finally:
        if old is None:
            os.environ.pop("ADV3D_CRIME_PYTHON", None)
        else:
            os.environ["ADV3D_CRIME_PYTHON"] = old
    return out


def test_avoidability_pairs_stack_and_oracle_on_heldout_seeds(run_a):
    from adv3d_runner.attack.avoidability import read_avoidability, reference_store_name
    from adv3d_runner.attack.evaluator import EpisodeEvaluator
    from adv3d_runner.attack.protocol import HeldoutStore, evaluation_seeds, heldout_evaluate, heldout_key
    from adv3d_runner.attack.report import write_report

    doc = read_avoidability(run_a)
    run = json.loads((run_a / "run.json").read_text())
    assert run["region"] == "realistic" and doc["reference"] == "oracle" and doc["stack"] == "A"
    ((sid, sc),) = doc["scenes"].items()
    settings = AttackConfig.from_run_json(run).settings
    seeds = evaluation_seeds(0, EpisodeEvaluator(settings).scene_digest(SCENE), 2)
    assert sc["seeds"] == seeds
    summary = json.loads((run_a / "summary.json").read_text())
    assert summary["scenes"][sid]["modes"]["closed"]["best_index"] == 0
    stack = HeldoutStore(run_a / "heldout.json.gz").evaluations
    oracle = HeldoutStore(run_a / reference_store_name("oracle")).evaluations
    unit = np.asarray(summary["scenes"][sid]["modes"]["closed"]["best_unit"]).reshape(-1).tolist()
    for row, s in zip(sc["modes"]["closed"]["per_seed"], seeds):
        key, okey = heldout_key(sid, "closed", s), heldout_key(sid, "original", s)
        assert stack[key]["unit"] == unit and oracle[key]["unit"] == unit
        want_s = episode_failures(stack[key]["metrics"], stack[okey]["metrics"])
        want_r = episode_failures(oracle[key]["metrics"], oracle[okey]["metrics"])
        assert row["stack"] == want_s and row["reference"] == want_r
        assert row["classes"] == classify_failures(want_s, want_r)
        assert all(v is not None for v in want_s.values())  # hardest braking is in the metrics now
    # the reference episodes are the oracle stack's: the same simulation run again gives them
    s0 = seeds[0]
    again = heldout_evaluate(SCENE, replace(settings, autonomy="oracle"), np.asarray(unit), s0)
    assert again["metrics"]["collision"] == oracle[heldout_key(sid, "closed", s0)]["metrics"]["collision"]
    assert again["cost"] == pytest.approx(oracle[heldout_key(sid, "closed", s0)]["cost"], rel=1e-9)
    text = write_report([run_a], run_a / "r.md").read_text()
    assert "### Avoidability: stack-induced or scenario-induced" in text and sc["modes"]["closed"]["finding"] in text
    from adv3d_runner.attack.avoidability import kind_totals

    totals = kind_totals(doc)
    for kind in FAILURE_KINDS:
        verdict = sc["modes"]["closed"]["kinds"][kind]["verdict"]
        assert totals[kind][STACK_INDUCED] == (verdict == STACK_INDUCED)
        assert totals[kind][SCENARIO_INDUCED] == (verdict == SCENARIO_INDUCED)


def test_reference_equal_to_the_stack_finds_nothing_stack_induced(run_a):
    """Paired seeds: the stack against itself fails or passes together on every seed."""
    from adv3d_runner.attack.avoidability import run_avoidability

    doc = run_avoidability(run_a, eval_seeds=1, reference="A")
    for sc in doc["scenes"].values():
        for m in sc["modes"].values():
            for row in m["per_seed"]:
                assert row["stack"] == row["reference"]
                assert STACK_INDUCED not in row["classes"].values() and "reference-only" not in row["classes"].values()


def test_failure_rate_draws_realistic_shapes_and_counts_failures(run_a):
    from adv3d_runner.attack.evaluator import workspace_for
    from adv3d_runner.attack.failure_rate import format_rate, read_failure_rate, run_failure_rate
    from adv3d_runner.attack.protocol import HeldoutStore
    from adv3d_runner.attack.report import write_report

    doc = run_failure_rate(run_a, samples=2, eval_seeds=1)
    assert read_failure_rate(run_a) == json.loads((run_a / "failure_rate.json").read_text())
    ((sid, sc),) = doc["scenes"].items()
    store = HeldoutStore(run_a / "rate.json.gz").evaluations
    draws = [r for k, r in store.items() if k.split("|")[1].startswith("rate")]
    assert len(draws) == 2 and sc["accepted"] == sum(r["accepted"] for r in draws)
    run = json.loads((run_a / "run.json").read_text())
    ws = workspace_for(SCENE, replace(AttackConfig.from_run_json(run).settings, region="realistic"))
    for r in draws:
        if r["accepted"]:
            assert ws.shapes.passes(np.asarray(r["drawn_unit"]))
    k = sum(bool(r["metrics"]["collision"]["collided"]) for r in draws if r["accepted"])
    assert sc["rates"]["collision"]["k"] == k and sc["rates"]["collision"]["n"] == sc["accepted"]
    lo, hi = clopper_pearson(k, sc["accepted"])
    assert sc["rates"]["collision"]["ci"] == [pytest.approx(lo, abs=1e-6), pytest.approx(hi, abs=1e-6)]
    text = write_report([run_a], run_a / "r2.md").read_text()
    assert "### How often: worst case and failure rate of realistic shapes" in text
    assert format_rate(sc["rates"]["any"]) in text
