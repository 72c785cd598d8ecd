"""Report sections on hand-made run data: paired deltas against the original, head to head at
equal budget. (The full ``adv3d report`` path is exercised in test_attack_driver.)"""
from __future__ import annotations

import numpy as np

from adv3d_runner.attack.report import head_to_head, paired_deltas


def _metrics(ap: float, min_ade: float, jerk: float) -> dict:
    return {"detection": {"ap": ap, "recall": ap}, "prediction": {"min_ade": min_ade, "mean_ade": 2 * min_ade},
            "planning_comfort": {"lat": 0.0, "jerk": jerk}, "driving_comfort": {"lat": 0.0, "jerk": jerk}}


def _summary(rows: dict[str, tuple[tuple, tuple | None]], mode: str = "closed") -> dict:
    """scene -> ((cost, ap, ade, jerk) of the original, same for the attack's best shape or None)."""
    scenes = {}
    for sid, (orig, adv) in rows.items():
        entry = {"original": {"cost": orig[0], "metrics": _metrics(*orig[1:])}, "modes": {mode: {}}}
        if adv is not None:
            entry["modes"][mode]["closed_loop_eval"] = {"cost": adv[0], "metrics": _metrics(*adv[1:])}
        scenes[sid] = entry
    return {"scenes": scenes}


def _records(curves: dict[str, list[float]], mode: str = "closed") -> list[dict]:
    return [{"scene": sid, "mode": mode, "index": i, "cost": c, "status": "ok" if np.isfinite(c) else "error"}
            for sid, costs in curves.items() for i, c in enumerate(costs)]


def _row(table: str, name: str) -> list[str]:
    line = next(ln for ln in table.splitlines() if ln.startswith(f"| {name} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_paired_deltas_per_scene_mean_spread_and_worse_count():
    summary = _summary({"s1": ((-50, 1.0, 0.2, 0.3), (-30, 0.5, 0.4, 0.3)),
                        "s2": ((-40, 0.9, 0.3, 0.5), (-36, 0.9, 0.2, 0.7)),
                        "s3": ((-60, 1.0, 0.1, 0.1), None)})           # no evaluation: not paired
    table = paired_deltas([("r", {"algo": "bo"}, [], summary)])
    cells = _row(table, "Adv. closed-loop (bo)")
    assert cells[1] == "2"                                                   # scenes
    assert cells[2] == "+12 ± 8 (2/2)"                                       # objective +20, +4
    assert cells[3] == "-25 ± 25 (1/2)"                                      # AP in %: -50, 0 -> lower is worse
    assert cells[5] == "+0.05 ± 0.15 (1/2)"                                  # minADE +0.2, -0.1
    assert cells[8] == "+0.1 ± 0.1 (1/2)"                                    # plan jerk 0, +0.2


def test_objective_split_unweighted_and_weighted_apart():
    from adv3d_runner.attack.report import objective_label, objective_split

    def comp(det, pred, plan):
        return {"det": det, "tp": -det, "fp": 0.0, "pred": pred, "plan": plan, "frames": 50}

    summary = {"scenes": {
        "s1": {"original": {"cost": 0, "metrics": {}, "components": comp(-20.0, 100.0, 2.0)},
               "modes": {"closed": {"closed_loop_eval": {"cost": 0, "metrics": {}, "components": comp(-10.0, 160.0, 4.0)}}}},
        "s2": {"original": {"cost": 0, "metrics": {}, "components": comp(-30.0, 200.0, 1.0)},
               "modes": {"closed": {"closed_loop_eval": {"cost": 0, "metrics": {}, "components": comp(-24.0, 220.0, 1.0)}}}}}}
    run = {"scenes": ["s1", "s2"], "algo": "bo", "objective": "M0", "pred_reduction": "sum"}
    table = objective_split([("r", run, [], summary)])
    cells = _row(table, "Adv. closed-loop (bo; M0, pred sum)")
    assert cells[1] == "2"
    assert cells[2:5] == ["8 ± 2", "1", "8 ± 2"]          # det +10, +6; weight 1
    assert cells[5:8] == ["40 ± 20", "0.1", "4 ± 2"]      # pred +60, +20; weight 0.1 (sum form)
    assert cells[8:11] == ["1 ± 1", "0.5", "0.5 ± 0.5"]   # plan +2, 0; weight 0.5
    # a run.json without the key predates it: the horizon mean
    assert objective_label({"objective": "M0"}) == "M0, pred mean"


def test_paired_deltas_empty_without_originals():
    assert paired_deltas([("r", {"algo": "bo"}, [], {"scenes": {"s": {"modes": {}}}})]) == ""


def test_head_to_head_wins_ties_losses_and_budgets():
    bo = _records({"s1": [0, 5, 9, 9], "s2": [1, 1, 4, 4], "s3": [2, 2, 2, 2]})
    rnd = _records({"s1": [0, 1, 2, 3], "s2": [1, 3, 3, 6], "s3": [2, 2, 2, 2]})
    table = head_to_head([("a", {"algo": "bo"}, bo, {}), ("b", {"algo": "random"}, rnd, {})], budgets=(2,))
    rows = [ln for ln in table.splitlines() if ln.startswith("| bo vs random")]
    assert len(rows) == 2                                     # budget 2 and the common length 4
    at2 = [c.strip() for c in rows[0].strip("|").split("|")]
    assert at2[1:4] == ["2", "3", "+0.667 ± 2.5"]             # d = 5-1, 1-3, 2-2
    assert at2[4] == "1 / 1 / 1"
    at4 = [c.strip() for c in rows[1].strip("|").split("|")]
    assert at4[3:5] == ["+1.33 ± 3.4", "1 / 1 / 1"]           # d = 9-3, 4-6, 0
    assert at4[5] != "-"                                      # Wilcoxon on the two non-zero differences


def test_head_to_head_failed_queries_and_unshared_modes():
    bo = _records({"s1": [np.nan, 3.0], "s2": [np.nan, np.nan]})
    rnd = _records({"s1": [1.0, 1.0], "s2": [0.0, 0.5]})
    other_mode = _records({"s1": [9.0, 9.0]}, mode="open")
    table = head_to_head([("a", {"algo": "bo"}, bo, {}), ("b", {"algo": "random"}, rnd, {}),
                          ("c", {"algo": "grid"}, other_mode, {})], budgets=())
    rows = [ln for ln in table.splitlines() if ln.startswith("| ")][1:]
    assert len(rows) == 1 and "bo vs random [closed]" in rows[0]   # grid searched another mode
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[2] == "1"                                    # s2: BO never succeeded -> -inf, dropped
    assert cells[3] == "+2"


def test_shape_sheet_grid_of_rows_and_columns(tmp_path):
    import matplotlib.image as mpimg
    import trimesh

    from adv3d_runner.attack.report import render_shape_sheet

    small = trimesh.creation.box(extents=(3.0, 1.4, 1.0))
    big = trimesh.creation.box(extents=(5.0, 2.0, 1.6))
    cells = {("s1", "bo closed"): (small.vertices, small.faces, "small"),
             ("s1", "random closed"): (big.vertices, big.faces, "big"),
             ("s2", "bo closed"): (big.vertices, big.faces, "big")}
    png = tmp_path / "sheet.png"
    render_shape_sheet(cells, png)
    img = mpimg.imread(png)
    assert img.shape[1] > img.shape[0]                   # 2 columns x 2 rows of 2.6 x 1.9 in cells
    orange = (img[..., 0] > 0.3) & (img[..., 2] < 0.5 * img[..., 0])
    h, w = img.shape[:2]
    quadrants = [orange[:h // 2, :w // 2], orange[:h // 2, w // 2:], orange[h // 2:, :w // 2], orange[h // 2:, w // 2:]]
    filled = [q.mean() for q in quadrants]
    assert filled[3] < 0.001 < min(filled[:3])            # no shape in the empty cell (s2, random)
    assert filled[0] < filled[1]                          # one scale: the small box covers fewer pixels


def test_results_doc_tables_match_the_kept_run_summaries(repo_root):
    """docs/results.md quotes Table 1 and the paired changes of the benchmark runs; the run
    summaries kept in docs/results/ must still produce exactly those rows (with the JSD of the
    best shapes, recomputed from their unit vectors: the runs predate the realism figures)."""
    import json

    from adv3d_runner.attack.report import attach_realism, table1

    runs = []
    for name in ("bo100", "random100", "bruteforce"):
        folder = repo_root / "docs" / "results" / name
        runs.append((f"runs/{name}", json.loads((folder / "run.json").read_text()), [],
                     json.loads((folder / "summary.json").read_text())))
    attach_realism(runs)
    doc = (repo_root / "docs" / "results.md").read_text() + (repo_root / "docs" / "archive.md").read_text()
    rows = [ln for ln in (table1(runs) + paired_deltas(runs)).splitlines() if ln.startswith(("| Original", "| Adv."))]
    assert len(rows) == 5 + 4
    for row in rows:
        assert row in doc, row


def test_results_doc_autonomy_b_tables_match_the_kept_run_summary(repo_root):
    """docs/results.md quotes Table 1's lower block (Autonomy-B) and its paired changes; the
    run summary kept in docs/results/bo50-B must still produce exactly those rows."""
    import json

    from adv3d_runner.attack.report import COLUMNS_B, attach_realism, table1

    folder = repo_root / "docs" / "results" / "bo50-B"
    runs = [("runs/bo50-B", json.loads((folder / "run.json").read_text()), [],
             json.loads((folder / "summary.json").read_text()))]
    attach_realism(runs)
    doc = (repo_root / "docs" / "results.md").read_text() + (repo_root / "docs" / "archive.md").read_text()
    rows = [ln for ln in (table1(runs, COLUMNS_B) + paired_deltas(runs, COLUMNS_B)).splitlines()
            if ln.startswith(("| Original", "| Adv."))]
    assert len(rows) == 3 + 2
    for row in rows:
        assert row in doc, row
