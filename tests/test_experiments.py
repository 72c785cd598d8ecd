"""adv3d experiments: the command's registration and rules, and the statistics every table
carries (multiplicity corrections, the detectable difference), on hand-computable cases."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.fileio import REPO_ROOT as REPO
from adv3d_runner.metrics.stats import benjamini_hochberg, holm, paired_mde


def test_holm_by_hand():
    # sorted 0.005, 0.01, 0.03, 0.04 -> 4 x 0.005, 3 x 0.01, 2 x 0.03, max(1 x 0.04, 0.06)
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5]) == pytest.approx([0.5])
    assert holm([0.6, 0.7]) == pytest.approx([1.0, 1.0])              # capped at 1
    # a test that could not run stays NaN and does not count in m
    out = holm([0.01, float("nan"), 0.02])
    assert out[0] == pytest.approx(0.02) and np.isnan(out[1]) and out[2] == pytest.approx(0.02)
    with pytest.raises(ValueError):
        holm([1.5])


def test_benjamini_hochberg_by_hand():
    # m p_(j) / j: 0.02, 0.02, 0.04, 0.04; the running minimum from the top keeps them
    assert benjamini_hochberg([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.02, 0.04, 0.04, 0.02])
    # 3 x 0.04 / 2 = 0.06 > 3 x 0.05 / 3 = 0.05: the step-up takes the smaller
    assert benjamini_hochberg([0.001, 0.04, 0.05]) == pytest.approx([0.003, 0.05, 0.05])
    assert np.isnan(benjamini_hochberg([float("nan")])).all()


def test_paired_mde_by_hand():
    from scipy.stats import t

    # n = 10: (t_{0.975, 9} + t_{0.8, 9}) / sqrt(10) = (2.2622 + 0.8834) / 3.1623 = 0.9947 per unit sd
    assert paired_mde(1.0, 10) == pytest.approx((2.262157 + 0.883404) / np.sqrt(10), rel=1e-5)
    assert paired_mde(2.0, 10) == pytest.approx(2 * paired_mde(1.0, 10))
    # many scenes: the normal form (z_{0.975} + z_{0.8}) sd / sqrt(n) = 2.8016 sd / sqrt(n)
    assert paired_mde(1.0, 10_000) == pytest.approx(2.8016 / 100, rel=2e-3)
    # the exact sign-flip test's smallest two-sided p is 2 / 2^n: 0.0625 at n = 5, so nothing is detectable
    assert paired_mde(1.0, 5) == float("inf") and paired_mde(1.0, 6) == pytest.approx(
        (t.ppf(0.975, 5) + t.ppf(0.8, 5)) / np.sqrt(6))
    assert paired_mde(float("nan"), 10) == float("inf") and paired_mde(0.0, 10) == 0.0


def test_scenes_to_detect_is_the_first_design_whose_mde_reaches_the_difference():
    from adv3d_runner.metrics.stats import scenes_to_detect

    n = scenes_to_detect(43.0, 7.2)
    assert paired_mde(43.0, n) <= 7.2 < paired_mde(43.0, n - 1)
    assert n == scenes_to_detect(43.0, -7.2)                 # the sign does not matter
    assert scenes_to_detect(1.0, 10.0) == 6                  # the exact test's floor
    assert scenes_to_detect(1.0, 0.0) is None and scenes_to_detect(float("nan"), 1.0) is None
    assert scenes_to_detect(100.0, 1e-3) is None              # beyond MAX_PLANNED_SCENES


def test_a_tables_family_is_corrected_and_its_power_stated():
    from adv3d_runner.experiments.tables import correct_family, findings_markdown

    comps = [{"metric": "objective", "n": 8, "p_permutation": 0.01}, {"metric": "AP", "n": 8, "p_permutation": 0.04},
             {"metric": "term det (unweighted)", "n": 8, "p_permutation": 0.001}, {"metric": "ADE", "n": 0,
                                                                                   "p_permutation": 1.0}]
    info = correct_family(comps)
    assert info["m"] == 2                                  # the term breakdown and an empty test left out
    assert comps[0]["p_holm"] == pytest.approx(0.02) and comps[1]["p_holm"] == pytest.approx(0.04)
    assert comps[0]["p_bh"] == pytest.approx(0.02) and comps[1]["p_bh"] == pytest.approx(0.04)
    assert "p_holm" not in comps[2] and comps[3]["p_holm"] is None
    md = "\n".join(findings_markdown({"Original": {"findings": None, "criticality": None},
                                      "Adv.": {"findings": {"stack_induced": 2, "scenario_induced": 1, "pre_existing": 0,
                                                            "no_failure": 0, "shapes": 3, "of": 3},
                                               "criticality": {"ttc": {"mean": 1.25, "scenes": 3}},
                                               "realistic_best_shapes": [1, 3],
                                               "calibrated_realistic_best_shapes": [0, 3]}}))
    assert "| Original | n/a | n/a | n/a | n/a | n/a | n/a | n/a | n/a |" in md
    assert "| Adv. | 2/3 | 1/3 | 0/3 | 0/3 | 1.25 (3 sc.) | n/a | 1/3 | 0/3 |" in md


def test_best_shapes_get_the_calibrated_realism_verdict(tmp_path):
    """``keep_realism`` recomputes a kept run's best shapes' realism reports against the
    calibrated limits (realism.json), once; the table reads it per row."""
    import json
    import shutil

    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.experiments import tables
    from adv3d_runner.shapes.realism import LIMITS

    src = REPO / "docs" / "results" / "shipped" / "table1_A_b20" / "runs" / "bo" / "seed0" / "highway-benchmark-000000"
    run = tmp_path / "runs" / "bo" / "seed0" / src.name
    shutil.copytree(src, run)
    (run / tables.REALISM_FILE).unlink(missing_ok=True)
    summary = json.loads((run / "summary.json").read_text())
    cfg = AttackConfig.from_run_json(json.loads((run / "run.json").read_text()))
    assert tables.keep_realism(summary, cfg, run) == 2                     # open and closed best shapes
    doc = tables.kept_realism(run)
    assert doc["limits"]["jsd"] == pytest.approx(LIMITS.jsd_max)        # the calibrated limits, not the run's
    verdicts = doc["scenes"][src.name]["modes"]
    assert set(verdicts) == {"open", "closed"}
    for v in verdicts.values():
        assert v[0]["actor"] == summary["scenes"][src.name]["targets"][0]
        assert v[0]["realistic"] == (not v[0]["flags"])
    assert tables.keep_realism(summary, cfg, run) == 0                     # kept once
    k = {"scene": src.name, "realism": doc}
    assert tables._calibrated(k, "closed") == verdicts["closed"][0]["realistic"]
    (run / tables.REALISM_FILE).write_text(json.dumps({**doc, "version": 99}))
    with pytest.raises(FileFormatError, match="version"):
        tables.kept_realism(run)


def test_experiments_command_is_registered_light_and_typed():
    """``register`` imports neither numpy nor the driver (``adv3d --help`` stays fast); the
    command's table names and bounds are the driver's and the attack's."""
    code = ("import sys, argparse\nfrom adv3d_runner.experiments import cli\n"
            "p = argparse.ArgumentParser(); cli.register(p.add_subparsers())\n"
            "print(sorted(m for m in ('numpy', 'scipy', 'torch', 'adv3d_runner.experiments.tables') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
    from adv3d_runner.attack.config import MAX_BUDGET, MAX_SECONDS
    from adv3d_runner.experiments import cli, tables

    assert tuple(sorted(tables.TABLES)) == cli.TABLE_NAMES
    assert (cli.ATTACK_MAX_BUDGET, cli.ATTACK_MAX_SECONDS) == (MAX_BUDGET, MAX_SECONDS)


@pytest.mark.parametrize("argv, words", [
    (["experiments", "table1", "--budget", "0"], "argument --budget"),
    (["experiments", "table9"], "argument table"),
    (["experiments", "table1", "--scenes", "0", "--real", "0"], "--scenes/--real"),
    (["experiments", "transfer", "--autonomy", "B", "--source-autonomy", "B"], "--source-autonomy")])
def test_experiments_bad_options_are_one_usage_line(tmp_path, capsys, argv, words):
    from adv3d_runner.cli import main

    argv = [*argv, "--work", str(tmp_path / "w"), "--results", str(tmp_path / "r")]
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("adv3d experiments: error: ") and words in err and err.count("\n") == 1, err
    assert not any(tmp_path.iterdir())


def test_experiments_list_and_table_only_errors(tmp_path, capsys):
    from adv3d_runner.cli import main

    assert main(["experiments", "--list", "--results", str(tmp_path)]) == 0
    assert "table1: Table 1" in capsys.readouterr().out
    assert main(["experiments", "table1", "--table-only", "--results", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("adv3d: error: ") and "no protocol.json" in err and err.count("\n") == 1


@pytest.mark.slow
def test_avoidability_split_is_kept_and_tabled(tmp_path):
    """--avoidability: each kept run gets the oracle reference's held-out records and its
    avoidability.json, and the table's findings count the split. With the oracle as the stack
    under test the reference sees what the stack sees: no failure can be stack-induced."""
    from adv3d_runner.cli import main

    assert main(["experiments", "table1", "--autonomy", "oracle", "--scenes", "1", "--real", "0", "--seeds", "1",
                 "--budget", "1", "--n-initial", "1", "--seconds", "0.3", "--eval-seeds", "1", "--work",
                 str(tmp_path / "w"), "--results", str(tmp_path / "r"), "--avoidability"]) == 0
    folder = tmp_path / "r" / "table1_oracle_b1"
    kept = folder / "runs" / "bo" / "seed0" / "highway-benchmark-000000"
    assert (kept / "avoidability.json").is_file() and (kept / "heldout.oracle.json.gz").is_file()
    import json

    table = json.loads((folder / "table.json").read_text())
    f = table["rows"]["Adv. closed-loop"]["findings"]
    assert f["of"] == 1 and f["shapes"] == 1 and f["stack_induced"] == 0
    assert table["rows"]["Original"]["findings"] is None


def test_realism_table_reports_the_objective_without_the_searched_penalty():
    """The realism preset searches C - W * P; its held-out objective is reported as M0's weights on
    the unweighted terms, so a held-out record that still carries a penalty is not scored lower
    (kept run: three records of highway-benchmark-000015, seed 1, carry P = 0.025)."""
    import gzip
    import json
    from pathlib import Path

    from adv3d_runner.attack.objective import parse_objective, term_split

    folder = Path(__file__).resolve().parents[1] / "docs/results/realism_A_b20"
    table = json.loads((folder / "table.json").read_text())
    assert table["common_objective"] == "M0"
    m0 = parse_objective("M0", "A")
    scene = "highway-benchmark-000015"
    seed_means, raw_means, penalised = [], [], 0
    for seed_dir in sorted((folder / "runs/realistic").glob("seed*")):
        records = json.loads(gzip.open(seed_dir / scene / "heldout.json.gz").read())["evaluations"]
        closed = [r for k, r in records.items() if "|closed|" in k]
        penalised += sum(bool((r.get("components") or {}).get("realism_penalty")) for r in closed)
        seed_means.append(np.mean([sum(t["weighted"] for t in term_split(r["components"], m0).values())
                                   for r in closed]))
        raw_means.append(np.mean([r["cost"] for r in closed]))
    reported = table["rows"]["Realistic preset"]["metrics"]["objective"]["per_scene"][scene]
    assert penalised == 3
    assert reported == pytest.approx(np.mean(seed_means), rel=1e-12)
    assert abs(reported - np.mean(raw_means)) > 1.0  # the searched cost is not what is reported
