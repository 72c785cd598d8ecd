"""bench/paper_tables.py: the campaign driver on a tiny configuration (one scene, one seed,
budget 2, 0.3 s episodes): run, resume without new work, rebuild the table from the kept files,
refuse to grow a table with other protocol values; and the paper's numbers against its tex."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

REPO = Path(__file__).resolve().parent.parent
TEX = Path("/work/shared/seed/adv3d_paper.tex")


def _driver():
    return load_bench("paper_tables")


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"(?<![\w.])\d+(?:\.\d+)?", text)]


def _subsequence(needle: list[float], hay: list[float]) -> bool:
    it = iter(hay)
    return all(any(abs(h - n) < 1e-9 for h in it) for n in needle)


@pytest.mark.skipif(not TEX.exists(), reason="the paper's tex is not on this machine")
def test_paper_numbers_are_the_papers():
    doc = json.loads((REPO / "bench" / "paper_numbers.json").read_text())
    lines = TEX.read_text().splitlines()
    for name, table in doc["tables"].items():
        assert f"\\label{{{table['label']}}}" in TEX.read_text(), name
        for row, values in table["rows"].items():
            want = [v for v in values if v is not None]
            assert any(_subsequence(want, _numbers(ln)) for ln in lines if "&" in ln), (name, row)


def test_driver_smoke_run_resume_and_rebuild(tmp_path, capsys):
    mod = _driver()

    args = ["table1", "--scenes", "1", "--real", "0", "--seeds", "1", "--budget", "2", "--n-initial", "2",
            "--seconds", "0.3", "--eval-seeds", "1", "--work", str(tmp_path / "work"), "--results", str(tmp_path / "res")]
    assert mod.main(args) == 0
    folder = tmp_path / "res" / "table1_A_b2"
    kept = folder / "runs" / "bo" / "seed0" / "highway-benchmark-000000"
    assert sorted(p.name for p in kept.iterdir()) == ["heldout.json.gz", "queries.jsonl.gz", "realism.json", "run.json",
                                                      "summary.json"]
    run = json.loads((kept / "run.json").read_text())
    assert run["scene_seeds"] is True and run["pred_reduction"] == "sum" and run["mode"] == "both"
    table = json.loads((folder / "table.json").read_text())
    assert list(table["rows"]) == ["Original", "Adv. open-loop", "Adv. closed-loop"]
    assert table["protocol"]["scenes"][0]["density"] == "free" and table["protocol"]["seeds"] == [0]
    row = table["rows"]["Adv. closed-loop"]
    assert row["n_scenes"] == 1 and row["terms"]["pred"]["weight"] == 0.1
    assert row["objective_form"]["pred_reduction"] == "sum"
    held = {c["metric"]: c for c in table["comparisons"] if c["a"] == "Adv. closed-loop" and c["b"] == "Original"}
    assert held["objective"]["n"] == 1
    # the held-out seed is not the search's: the evaluation differs from the search's closed-loop one
    summary = json.loads((kept / "summary.json").read_text())
    m = summary["scenes"]["highway-benchmark-000000"]["modes"]["closed"]
    from adv3d_runner.fileio import read_json

    evals = read_json(kept / "heldout.json.gz")["evaluations"]
    assert all(r["seed"] not in (m["search_seed"], m["noise_seed"]) for r in evals.values())
    assert len(evals) == 3                                   # original, open best, closed best on 1 seed
    assert (folder / "table.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"   # the table's picture
    md = (folder / "table.md").read_text()
    assert "*paper: Adv. closed-loop*" in md and "prediction term **sum**" in md
    before = (folder / "table.json").read_text()
    # a second run resumes: no query, no held-out evaluation is made again
    assert mod.main(args) == 0
    inv = json.loads((folder / "compute.json").read_text())["invocations"]
    assert len(inv) == 2 and inv[1]["queries"] == 0 and inv[1]["heldout_evaluations"] == 0
    assert inv[0]["cpu_s"] > 0 and inv[0]["cpu_model"]
    # the table is rebuilt from the kept files alone, the same (the compute total aside)
    assert mod.main(["table1", "--table-only", "--budget", "2", "--results", str(tmp_path / "res")]) == 0
    a, b = json.loads(before), json.loads((folder / "table.json").read_text())
    a.pop("compute"), b.pop("compute")
    assert a == b
    # transfer: the kept best shapes evaluated with another stack on the same held-out seeds
    assert mod.main(["transfer", "--autonomy", "oracle", "--source-autonomy", "A", "--budget", "2",
                     "--results", str(tmp_path / "res")]) == 0
    moved = json.loads((tmp_path / "res" / "transfer_oracle_b2" / "table.json").read_text())
    assert moved["protocol"]["transfer_from"] == "A" and moved["rows"]["Original"]["n_scenes"] == 1
    # its versions are the evaluating stack's; the shapes' stack is named apart
    assert "detector" not in moved["protocol"]["versions"].get("models", {})
    assert moved["protocol"]["source_versions"]["models"]["detector"] == table["versions"]["models"]["detector"]
    tk = tmp_path / "res" / "transfer_oracle_b2" / "runs" / "shapes" / "seed0" / "highway-benchmark-000000"
    assert sorted(read_json(tk / "heldout.json.gz")["evaluations"]) == sorted(evals)   # same keys, same seeds
    # growing the table with other weights (a retrained detector) is refused
    proto_path = folder / "protocol.json"
    proto = json.loads(proto_path.read_text())
    assert proto["versions"]["models"]["detector"]
    proto_path.write_text(json.dumps({**proto, "versions": {**proto["versions"], "models": {"detector": "0" * 16}}}))
    capsys.readouterr()
    assert mod.main(args) == 1   # one line, exit code 1, as adv3d's errors
    err = capsys.readouterr().err
    assert err.startswith("paper_tables.py: error: ") and "model weights" in err and err.count("\n") == 1
    proto_path.write_text(json.dumps(proto))
    # growing the table with other protocol values is refused (another budget is another folder)
    assert mod.main([*args[:11], "--seconds", "0.4", *args[13:]]) == 1
    assert "seconds" in capsys.readouterr().err


def test_shards_split_the_units_and_merge_their_compute(tmp_path):
    """--shard I/N: N processes side by side run disjoint units (seed, setting, scene), each
    with its own compute file; together they make the table one process makes."""
    mod = _driver()
    from adv3d_runner.errors import ConfigError

    common = ["table4", "--scenes", "1", "--real", "0", "--seeds", "1", "--budget", "1", "--n-initial", "1",
              "--seconds", "0.2", "--eval-seeds", "1", "--work", str(tmp_path / "work")]
    folder = tmp_path / "res" / "table4_A_b1"
    for i in range(3):   # 4 units (m = 1, 2, 3, 5) over 3 shards: 2, 1 and 1 of them
        assert mod.main([*common, "--results", str(tmp_path / "res"), "--shard", f"{i}/3"]) == 0
    assert not (folder / "table.json").exists()          # a shard never builds the table
    shards = sorted(folder.glob("compute-shard*.json"))
    assert [p.name[:17] for p in shards] == ["compute-shard0of3", "compute-shard1of3", "compute-shard2of3"]
    runs = sorted(p.parent.parent.parent.name for p in (folder / "runs").glob("*/seed0/*/run.json"))
    assert runs == ["m1", "m2", "m3", "m5"]
    merged = mod.load_compute(folder)
    assert len(merged["invocations"]) == 3
    assert merged["cpu_s_total"] == pytest.approx(sum(e["cpu_s"] for e in merged["invocations"]), abs=0.2)
    assert merged["invocations"][0]["environment"]["numpy"]
    assert mod.main(["table4", "--table-only", "--budget", "1", "--results", str(tmp_path / "res")]) == 0
    sharded = json.loads((folder / "table.json").read_text())
    assert sharded["compute"]["invocations"] == 3
    # the same table from one process: the same rows, bit for bit
    assert mod.main([*common, "--results", str(tmp_path / "one"), "--work", str(tmp_path / "work1")]) == 0
    single = json.loads((tmp_path / "one" / "table4_A_b1" / "table.json").read_text())
    assert sharded["rows"] == single["rows"]
    # a finished unit is taken from its kept files, not searched again: neither where its work
    # folder is gone, nor where its journal would not replay here (made on another machine, whose
    # libraries propose other points); the kept files stay, and the table grows by a seed beside it
    import shutil

    kept_before = {p: p.read_bytes() for p in (folder / "runs").rglob("*") if p.is_file()}
    journals = sorted((tmp_path / "work").rglob("queries.jsonl"))
    assert len(journals) == 4
    shutil.rmtree(journals[0].parent)
    for path in journals[1:]:
        recs = [json.loads(line) for line in path.read_text().splitlines()]
        path.write_text("".join(json.dumps({**r, "unit": (0.5 * np.asarray(r["unit"])).tolist()}) + "\n" for r in recs))
    assert mod.main([*common[:6], "2", *common[7:], "--results", str(tmp_path / "res"), "--shard", "0/1"]) == 0
    assert all(p.read_bytes() == b for p, b in kept_before.items())
    assert sorted(p.parent.parent.name for p in (folder / "runs").glob("m1/seed*/*/run.json")) == ["seed0", "seed1"]
    # every scene's units spread over the shards, also where the shard count divides the scenes'
    settings, scenes = [f"M{m}-r{r}" for m in range(6) for r in range(3)], list("abcdef")
    units = mod.campaign_units(range(2), settings, scenes)
    assert sorted(units) == sorted((s, m, sc) for s in range(2) for m in settings for sc in scenes)
    assert [u[0] for u in units] == sorted(u[0] for u in units)       # seed by seed
    for i in range(2):
        mine = units[i::2]
        assert all(sum(u[2] == sc for u in mine) == 18 for sc in scenes)
    for bad in ("3/3", "x/2", "1"):
        with pytest.raises(ConfigError, match="--shard"):
            mod.parse_shard(bad)


def test_each_search_row_is_pictured_against_its_own_original():
    mod = _driver()
    t6, t1 = mod.TABLES["table6"], mod.TABLES["table1"]
    assert mod.baseline_row(t6, "Adv. closed-loop (reactive)") == "Original (reactive)"
    assert mod.baseline_row(t6, "Adv. open-loop (replayed)") == "Original (replayed)"
    assert mod.baseline_row(t6, "Original (reactive)") is None
    assert mod.baseline_row(t1, "Adv. closed-loop") == "Original"
    assert mod.baseline_row(mod.TABLES["table2"], "M3 open-loop") == "Original"


def test_tables_listed_with_what_they_need(capsys):
    mod = _driver()
    assert mod.main(["--list"]) == 0
    out = capsys.readouterr().out
    specs, _, kept = out.partition("\n\n")  # the tables, then the kept folders of docs/results
    for name in ("table1", "table2", "table3", "table4", "table5", "table6", "realism", "transfer"):
        assert specs.count(f"{name}:") == 1
    assert all(line.endswith("; runs") for line in specs.strip().splitlines())  # every table has its entry
    assert "table1_A: run seeds 0, 1, 2 x 8 scenes reported" in kept


@pytest.mark.parametrize("folder, table, autonomy, with_tests", [
    ("table1_A_b20", "table1", "A", True), ("table1_B_b20", "table1", "B", True),
    ("transfer_A_b20", "transfer", "A", False), ("transfer_B_b20", "transfer", "B", False),
    ("table3_A_b20", "table3", "A", False), ("table6_A_b20", "table6", "A", False),
    ("table4_A_b20", "table4", "A", False), ("realism_A_b20", "realism", "A", False),
    ("table5_A_b20", "table5", "A", False), ("table2_A_b20", "table2", "A", False),
    ("table1_A", "table1", "A", False), ("transfer_B", "transfer", "B", False),
    ("table1_B", "table1", "B", False), ("transfer_A", "transfer", "A", False)])
def test_results_doc_quotes_the_kept_tables(folder, table, autonomy, with_tests):
    """docs/results.md and the archive quote the protocol's tables; each table rebuilt from its kept files in
    docs/results/<folder> must give exactly the rows the doc shows (main table and paired
    tests)."""
    path = REPO / "docs" / "results" / folder
    if not (path / "protocol.json").exists():
        pytest.skip(f"{folder} has not been run")
    import shutil
    import tempfile

    mod = _driver()
    budget = json.loads((path / "protocol.json").read_text())["budget"]
    with tempfile.TemporaryDirectory() as tmp:  # rebuild from a copy: the kept files stay untouched
        shutil.copytree(path, Path(tmp) / folder)
        assert mod.main([table, "--autonomy", autonomy, "--table-only", "--budget", str(budget), "--results", tmp]) == 0
        rebuilt = (Path(tmp) / folder / "table.md").read_text()
    assert rebuilt == (path / "table.md").read_text()  # the kept table is what its files give
    # the current page and the archive (the older stack's tables live there)
    doc = (REPO / "docs" / "results.md").read_text() + (REPO / "docs" / "archive.md").read_text()
    names = list(json.loads((path / "table.json").read_text())["rows"])
    lines = rebuilt.splitlines()
    if any(ln.startswith("Findings (") for ln in lines):   # the findings table (new columns) is not quoted
        start = next(i for i, ln in enumerate(lines) if ln.startswith("Findings ("))
        end = next(i for i, ln in enumerate(lines) if ln.startswith("n/a: not in the kept runs"))
        lines = lines[:start] + lines[end:]
    first_cells = [ln.split("|")[1].strip() if ln.startswith("|") else "" for ln in lines]
    rows = [ln for ln, cell in zip(lines, first_cells)  # the main rows, the paired tests if quoted
            if cell in names or cell.startswith("*paper") or (with_tests and cell.split(" - ")[0] in names)]
    assert len(rows) >= 3
    for row in rows:
        assert row in doc, row
    if (path / "budget_effect.json").exists():   # the budget comparison the doc quotes, recomputed
        be = load_bench("budget_effect")
        kept = json.loads((path / "budget_effect.json").read_text())
        md = be.markdown(be.compare(REPO / kept["a"], REPO / kept["b"]))
        assert md == (path / "budget_effect.md").read_text()
        quoted = [ln for ln in md.splitlines() if ln.startswith("| Adv.") and "| objective |" in ln]
        assert quoted and all(ln in doc for ln in quoted)


def test_worst_case_rows_pick_by_search_seed_and_common_objective():
    """Table 2's rows: per scene the group's attack with the highest search-seed objective, its
    held-out records; the objective column recomputed with M0's weights from the terms."""
    mod = _driver()
    spec = mod.TABLES["table2"]

    def kept(setting, seed, search_cost, held_cost, det):
        rec = {"seed": 9, "cost": held_cost, "components": {"det": det, "pred": 100.0, "plan": 2.0}, "metrics": {}}
        summary = {"scenes": {"s": {"ref": "s.json", "original": {"cost": 0.0},
                                    "modes": {"closed": {"closed_loop_eval": {"cost": search_cost}}}}}}
        return {"setting": setting, "seed": seed, "scene": "s", "run": {}, "summary": summary,
                "heldout": {"s|closed|9": rec, "s|original|9": {**rec, "cost": 0.0}}}

    rows = mod.collect(spec, [kept("M1-r0", 0, 5.0, 1.0, -3.0), kept("M1-r1", 0, 7.0, 2.0, -4.0),
                              kept("M1-r2", 1, 6.0, 9.0, -5.0)])
    (e,) = rows["M1 closed-loop"]
    assert e["picked"] == {"setting": "M1-r1", "seed": 0} and e["candidates"] == 3
    assert e["heldout"][0]["cost"] == 2.0            # the held-out value of the pick, not the largest one
    assert rows["M2 closed-loop"] == []


def test_planner_parameters_are_part_of_a_runs_versions(monkeypatch):
    """A retuned planner changes every closed-loop result: its parameters are fingerprinted in
    the versions a table refuses to mix."""
    import dataclasses

    from adv3d_runner.attack import evaluator
    from adv3d_runner.autonomy.planner import planner as planner_mod

    before = evaluator.planner_fingerprint()
    assert before == evaluator.planner_fingerprint() and len(before) == 16
    tuned = dataclasses.make_dataclass("PlannerConfig", [("min_gap", float, 2.5)], bases=(planner_mod.PlannerConfig,),
                                       frozen=True)
    monkeypatch.setattr(planner_mod, "PlannerConfig", tuned)
    assert evaluator.planner_fingerprint() != before


def test_table5_runs_every_searcher_with_its_compute(tmp_path):
    """Table 5 on one scene, one seed, budget 2 (oracle stack, 0.3 s episodes): every algorithm,
    scikit-optimize's GP included, runs on the protocol, and the table gets its compute column
    (queries per search from the kept journals: the paper's grid 243 and random 500 for BO's 100
    scale to 5 and 10 here; brute force spends one query per library vehicle)."""
    pytest.importorskip("skopt")
    mod = _driver()
    args = ["table5", "--autonomy", "oracle", "--scenes", "1", "--real", "0", "--seeds", "1", "--budget", "2",
            "--n-initial", "2", "--seconds", "0.3", "--eval-seeds", "1", "--work", str(tmp_path / "work"),
            "--results", str(tmp_path / "res")]
    assert mod.main(args) == 0
    folder = tmp_path / "res" / "table5_oracle_b2"
    run = json.loads((folder / "runs" / "skopt" / "seed0" / "highway-benchmark-000000" / "run.json").read_text())
    assert run["algo"] == "skopt" and run["n_initial"] == 2 and run["budget"] == 2
    table = json.loads((folder / "table.json").read_text())
    rows = table["rows"]
    assert list(rows) == ["Original", "GS", "RS", "BS", "BO", "Brute-Force", "BO (scikit-optimize)"]
    queries = {name: rows[name]["search_compute"]["queries_mean"] for name in rows if name != "Original"}
    from adv3d_runner.attack.config import QuerySettings

    n_vehicles = len(QuerySettings().load_shape_space().asset_ids)
    assert queries == {"GS": 5, "RS": 10, "BS": 2, "BO": 2, "Brute-Force": n_vehicles, "BO (scikit-optimize)": 2}
    assert all(rows[n]["search_compute"]["query_wall_s_mean"] > 0 for n in queries)
    assert "search_compute" not in rows["Original"]
    assert any(c["a"] == "BO" and c["b"] == "BO (scikit-optimize)" for c in table["comparisons"])
    md = (folder / "table.md").read_text()
    assert "| queries / search | episode min / search |" in md and "| BO (scikit-optimize) | 1 | 1 |" in md


def test_budget_effect_pairs_two_budgets_on_shared_runs(tmp_path):
    """bench/budget_effect.py: two budgets of one table compared on their shared scenes and run
    seeds; the originals must agree exactly, else the comparison is refused."""
    be = load_bench("budget_effect")
    from adv3d_runner.errors import ConfigError

    mod = _driver()
    common = ["table1", "--scenes", "1", "--real", "0", "--budget", "{b}", "--n-initial", "1", "--seconds", "0.2",
              "--eval-seeds", "1", "--work", str(tmp_path / "work{b}"), "--results", str(tmp_path / "res")]
    for budget, seeds in ((1, "2"), (3, "1")):   # the small budget has a run seed the large one lacks
        assert mod.main([a.format(b=budget) for a in common] + ["--seeds", seeds]) == 0
    a, b = tmp_path / "res" / "table1_A_b3", tmp_path / "res" / "table1_A_b1"
    assert be.main([str(a), str(b)]) == 0
    res = json.loads((a / "budget_effect.json").read_text())
    assert res["run_seeds"] == [0] and res["budget_a"] == 3 and res["budget_b"] == 1
    assert list(res["rows"]) == ["Adv. open-loop", "Adv. closed-loop"]
    obj = res["rows"]["Adv. closed-loop"]["objective"]
    # the difference is that of the two folders' own held-out records for run seed 0
    from adv3d_runner.fileio import read_json

    def closed(folder):
        ev = read_json(folder / "runs" / "bo" / "seed0" / "highway-benchmark-000000" / "heldout.json.gz")["evaluations"]
        return np.mean([r["cost"] for k, r in ev.items() if k.split("|")[1] == "closed"])

    assert obj["n"] == 1 and obj["mean_diff"] == pytest.approx(closed(a) - closed(b))
    assert "| Adv. closed-loop | objective |" in (a / "budget_effect.md").read_text()
    # another stack's (or machine's) originals: refused, naming the scene
    held = b / "runs" / "bo" / "seed0" / "highway-benchmark-000000" / "heldout.json.gz"
    doc = read_json(held)
    for key, rec in doc["evaluations"].items():
        if key.split("|")[1] == "original":
            rec["cost"] += 1.0
    from adv3d_runner.fileio import write_json

    write_json(held, doc)
    with pytest.raises(ConfigError, match="highway-benchmark-000000 run seed 0: the originals differ"):
        be.compare(a, b)
    assert be.main([str(a), str(tmp_path)]) == 2     # not a table folder: a clear error, exit 2


def test_a_table_reports_only_whole_blocks_of_seeds_and_scenes():
    """A table growing over several sittings keeps finished searches of a half-done seed (or
    scene) in its folder, but reports only the largest block of run seeds 0..j x scenes finished
    for every setting, held-out evaluations included."""
    mod = _driver()

    def kept(seed, scene, setting, n_held=2):
        summary = {"scenes": {scene: {"ref": f"{scene}.json", "original": {},
                                      "modes": {"closed": {"best_unit": [0.5]}}}}}
        held = {f"{scene}|{what}|{s}": {} for what in ("original", "closed") for s in range(n_held)}
        return {"seed": seed, "scene": scene, "setting": setting, "summary": summary, "heldout": held}

    full = [kept(s, c, t) for s in (0, 1) for c in ("a", "b", "c") for t in ("x", "y")]
    assert mod.complete_block(full, ["x", "y"], [0, 1, 2], ["a", "b", "c"], 2) == ([0, 1], ["a", "b", "c"])
    # seed 2 half done: reported as before
    growing_seed = full + [kept(2, "a", "x"), kept(2, "a", "y"), kept(2, "b", "x")]
    assert mod.complete_block(growing_seed, ["x", "y"], [0, 1, 2], ["a", "b", "c"], 2) == ([0, 1], ["a", "b", "c"])
    # a fourth scene finished on seed 0 only: the 2 seeds x 3 scenes stay (6 cells against 4)
    growing_scene = full + [kept(0, "d", "x"), kept(0, "d", "y")]
    assert mod.complete_block(growing_scene, ["x", "y"], [0, 1], ["a", "b", "c", "d"], 2) == ([0, 1], ["a", "b", "c"])
    # seed 1 finished on two of three scenes: more cells (4 against 3), but the table reported
    # seed 0 on all three before, and it does not drop a scene while it grows
    half = [k for k in full if not (k["seed"] == 1 and k["scene"] == "c")]
    assert mod.complete_block(half, ["x", "y"], [0, 1], ["a", "b", "c"], 2) == ([0, 1], ["a", "b"])
    assert mod.complete_block(half, ["x", "y"], [0, 1], ["a", "b", "c"], 2, ([0], ["a", "b", "c"])) == ([0], ["a", "b", "c"])
    # a search whose held-out evaluations are not all stored is not finished
    short = [k if (k["seed"], k["scene"], k["setting"]) != (1, "b", "y") else kept(1, "b", "y", n_held=1) for k in full]
    assert mod.complete_block(short, ["x", "y"], [0, 1], ["a", "b", "c"], 2) == ([0, 1], ["a", "c"])
    # a skipped scene (too few actors) needs no held-out evaluation
    skipped = {"seed": 0, "scene": "e", "setting": "x", "summary": {"scenes": {"e": {"skipped": "1 actor"}}}, "heldout": {}}
    assert mod.unit_complete(skipped, 3)
    # the header says what is kept beyond the block, and nothing for a whole table
    assert mod.growth_words([0], [0], None) == ""
    words = mod.growth_words([0], [0, 1, 2], {"1": {"kept_searches": 7, "searches": 108}})
    assert words == (" (of 0, 1, 2: the table is growing; kept beyond it until their run seed is finished on "
                     "its scenes: run seed 1, 7 of 108 searches)")


def test_list_names_each_kept_tables_block_and_what_grows_beyond_it(tmp_path):
    """``--list`` says, per kept table folder, the block its last build reports and the
    searches kept beyond it, so a campaign spread over sittings can be picked up."""
    mod = _driver()
    folder = tmp_path / "table2_A_b20"
    folder.mkdir()
    row = {"seeds": [0], "metrics": {"objective": {"per_scene": {"s1": 1.0, "s2": 2.0}}}}
    (folder / "table.json").write_text(json.dumps({
        "rows": {"Original": row}, "protocol": {"seeds": [0, 1, 2], "scenes": [{}, {}], "budget": 20},
        "growing": {"1": {"kept_searches": 7, "searches": 36}}}))
    text = mod.list_tables(tmp_path)
    assert ("table2_A_b20: run seeds 0 x 2 scenes reported (protocol: seeds 0, 1, 2, 2 scenes, budget 20); "
            "run seed 1: 7 of 36 searches kept") in text
    assert "table2: Table 2" in text


# ------------------------------------------------------------------ the command line's rules

@pytest.mark.parametrize("bad, option", [
    (["--scenes", "-1"], "--scenes"), (["--real", "-5"], "--real"), (["--budget", "0"], "--budget"),
    (["--budget", "-5"], "--budget"), (["--seconds", "-1"], "--seconds"), (["--seconds", "nan"], "--seconds"),
    (["--n-initial", "-1"], "--n-initial"), (["--batch", "0"], "--batch"), (["--shard", "3/2"], "--shard"),
    (["--shard", "abc"], "--shard"), (["--shard", "0/0"], "--shard"), (["--autonomy", "Z"], "--autonomy"),
    (["--eval-seeds", "-1"], "--eval-seeds"), (["--seeds", "-1"], "--seeds"), (["--seeds", "0"], "--seeds"),
    (["--workers", "0"], "--workers"), (["--budget", "99999999999999999999"], "--budget"),
    (["--seeds", "1001"], "--seeds"), (["--scenes", "0", "--real", "0"], "--scenes/--real"),
    (["--scenes", "5000"], "--scenes/--real"), (["--source-autonomy", "Q"], "--source-autonomy"),
    (["--results", "{file}"], "--results"), (["--work", "{file}/sub"], "--work"), (["--fresh", "-1"], "--fresh"),
    (["--fresh", "999"], "--scenes/--real/--fresh"), (["--region", "box"], "--region"),
    (["--realism-verdicts"], "--realism-verdicts")])
def test_a_bad_option_is_one_usage_line_and_exit_2_before_anything_runs(tmp_path, capsys, bad, option):
    """Every bad value of bench/paper_tables.py is refused by its argparse type (the CLI's
    adv3d_runner.argtypes) with one usage line naming the option, exit code 2, before any attack
    runs or anything is written (docs/reliability.md)."""
    mod = _driver()
    (tmp_path / "file").write_text("the user's file")
    bad = [b.format(file=tmp_path / "file") for b in bad]
    base = {"--scenes": "1", "--real": "0", "--seeds": "1", "--budget": "1", "--n-initial": "1", "--seconds": "0.2",
            "--eval-seeds": "1", "--work": str(tmp_path / "work"), "--results": str(tmp_path / "res")}
    for flag in bad[::2]:
        base.pop(flag, None)
    argv = ["table1", "--autonomy", "oracle"] if "--autonomy" not in bad else ["table1"]
    argv += [w for kv in base.items() for w in kv] + bad
    with pytest.raises(SystemExit) as exc:
        mod.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("paper_tables.py: error: ") and option in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "work").exists() and not (tmp_path / "res").exists()
    assert (tmp_path / "file").read_text() == "the user's file"


def test_the_driver_runs_from_any_folder(tmp_path):
    """Started from another folder (here the test's own), scene paths are still the
    repository's, and --work / --results are taken relative to that folder."""
    import subprocess
    import sys

    cmd = [sys.executable, str(REPO / "bench" / "paper_tables.py"), "table1", "--autonomy", "oracle", "--scenes", "1",
           "--real", "0", "--seeds", "1", "--budget", "1", "--n-initial", "1", "--seconds", "0.2", "--eval-seeds", "1",
           "--work", "work", "--results", "res"]
    out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    table = json.loads((tmp_path / "res" / "table1_oracle_b1" / "table.json").read_text())
    assert table["rows"]["Adv. closed-loop"]["n_scenes"] == 1
    assert (tmp_path / "work" / "table1_oracle_b1" / "bo" / "seed0").is_dir()
    run = json.loads((tmp_path / "res" / "table1_oracle_b1" / "runs" / "bo" / "seed0" / "highway-benchmark-000000"
                      / "run.json").read_text())
    assert run["scenes"] == ["scenes/highway/highway-benchmark-000000.json.gz"]   # kept relative to the repository


@pytest.fixture(scope="module")
def kept_table(tmp_path_factory):
    """A tiny kept table (oracle stack, one scene, one seed, budget 1), made once."""
    mod = _driver()
    root = tmp_path_factory.mktemp("kept")
    argv = ["table1", "--autonomy", "oracle", "--scenes", "1", "--real", "0", "--seeds", "1", "--budget", "1",
            "--n-initial", "1", "--seconds", "0.2", "--eval-seeds", "1", "--work", str(root / "work"),
            "--results", str(root / "res")]
    assert mod.main(argv) == 0
    return root / "res" / "table1_oracle_b1"


def _damage(folder: Path, what: str) -> Path:
    """Damage one kept file of a table folder's only run; returns the file named in the error."""
    import gzip

    run = folder / "runs" / "bo" / "seed0" / "highway-benchmark-000000"
    summary = run / "summary.json"
    doc = json.loads(summary.read_text())
    entry = doc["scenes"]["highway-benchmark-000000"]
    if what == "garbled summary":
        summary.write_bytes(summary.read_bytes()[:200] + b"\x00garbage")
    elif what == "empty summary":
        summary.write_text("{}")
    elif what == "summary without its scene":
        summary.write_text(json.dumps({**doc, "scenes": {}}))
    elif what == "summary without a mode":
        entry["modes"].pop("open")
        summary.write_text(json.dumps(doc))
    elif what == "summary missing":
        summary.unlink()
    elif what == "run.json missing":
        (run / "run.json").unlink()
        return run / "run.json"
    elif what == "run.json garbled":
        (run / "run.json").write_text('{"format": "adv3d.attack_run", "version": 2, "scenes": [], "budget": -1}')
        return run / "run.json"
    elif what == "heldout missing":
        (run / "heldout.json.gz").unlink()
        return run / "heldout.json.gz"
    elif what == "heldout garbled":
        held = json.loads(gzip.decompress((run / "heldout.json.gz").read_bytes()))
        key = next(iter(held["evaluations"]))
        held["evaluations"]["no-bars"] = held["evaluations"].pop(key)
        (run / "heldout.json.gz").write_bytes(gzip.compress(json.dumps(held).encode()))
        return run / "heldout.json.gz"
    elif what == "protocol garbled":
        (folder / "protocol.json").write_text('{"scenes": [{"path": "../../etc/passwd"}], "seeds": [0]}')
        return folder / "protocol.json"
    elif what == "bad seed folder":
        (folder / "runs" / "bo" / "seedX" / "s").mkdir(parents=True)
        return folder / "runs" / "bo" / "seedX"
    return summary


@pytest.mark.parametrize("what", ["garbled summary", "empty summary", "summary without its scene",
                                  "summary without a mode", "summary missing", "run.json missing", "run.json garbled",
                                  "heldout missing", "heldout garbled", "protocol garbled", "bad seed folder"])
def test_table_only_refuses_a_damaged_kept_folder_naming_the_file(kept_table, tmp_path, capsys, what):
    """--table-only over a kept folder with a garbled or incomplete file: one line naming the
    file, exit code 1, and the table as it was (never rebuilt with fewer scenes)."""
    import shutil

    mod = _driver()
    folder = tmp_path / kept_table.name
    shutil.copytree(kept_table, folder)
    before = {p: (folder / p).read_bytes() for p in ("table.md", "table.json")}
    named = _damage(folder, what)
    capsys.readouterr()
    assert mod.main(["table1", "--autonomy", "oracle", "--budget", "1", "--table-only", "--results", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("paper_tables.py: error: ") and str(named) in err, err
    assert {p: (folder / p).read_bytes() for p in before} == before
    # the undamaged folder rebuilds
    assert mod.main(["table1", "--autonomy", "oracle", "--budget", "1", "--table-only", "--results",
                     str(kept_table.parent)]) == 0


def test_table_only_needs_a_table_folder(tmp_path, capsys):
    mod = _driver()
    assert mod.main(["table1", "--budget", "1", "--table-only", "--results", str(tmp_path)]) == 1
    assert "no protocol.json" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_table_whose_search_does_not_fit_in_memory_is_refused_before_anything_is_written(tmp_path, capsys):
    """A budget whose BO matrices pass the memory budget (docs/reliability.md, "Memory"): one
    line naming --budget, exit code 1, before the protocol or any run folder is written."""
    mod = _driver()
    assert mod.main(["table1", "--autonomy", "oracle", "--scenes", "1", "--real", "0", "--budget", "20000",
                     "--work", str(tmp_path / "work"), "--results", str(tmp_path / "res")]) == 1
    err = capsys.readouterr().err
    assert "--budget 20000" in err and "GiB" in err and err.count("\n") == 1
    assert not any(tmp_path.iterdir())


def test_a_plugin_stack_gets_a_safe_table_folder_and_tables_record_the_stack():
    """Any stack of docs/stacks.md can make a table: a spec that is not a plain name becomes a
    safe folder name with a digest; the stack (name, version, fingerprint) is among the
    versions a table is never grown across."""
    pt = _driver()
    assert pt.stack_folder("A") == "A" and pt.stack_folder("my-stack") == "my-stack"
    odd = pt.stack_folder("exec:/opt/venv/bin/python /srv/stack server.py")
    assert "/" not in odd and " " not in odd and odd != pt.stack_folder("exec:/opt/venv/bin/python other.py")
    assert "stack" in pt.VERSION_KEYS
    assert pt.model_versions("oracle")["stack"]["name"] == "oracle"


def test_a_realistic_region_table_on_fresh_scenes_has_its_own_folder(tmp_path, capsys):
    """``--region realistic`` searches where the realism report passes and keeps the table in
    ``<table>_<stack>[_b<budget>]_realistic`` (another protocol than the paper's box);
    ``--fresh`` takes scenes of the fresh real part, labelled so in the table."""
    mod = _driver()
    args = ["table1", "--autonomy", "oracle", "--region", "realistic", "--scenes", "0", "--real", "0", "--fresh", "1",
            "--seeds", "1", "--budget", "2", "--n-initial", "2", "--seconds", "0.3", "--eval-seeds", "1",
            "--work", str(tmp_path / "work"), "--results", str(tmp_path / "res")]
    assert mod.main(args) == 0
    folder = tmp_path / "res" / "table1_oracle_b2_realistic"
    proto = json.loads((folder / "protocol.json").read_text())
    assert proto["region"] == "realistic" and proto["scenes"][0]["part"] == "real-fresh"
    assert "fresh:" in proto["scene_rule"]
    run = next(folder.glob("runs/bo/seed0/*/run.json"))
    assert json.loads(run.read_text())["region"] == "realistic"
    # every best shape's calibrated realism verdict is kept beside the run; in the realistic
    # region every shape the search simulated passed it
    cal = json.loads((run.parent / "realism.json").read_text())["scenes"]
    assert all(a["realistic"] for s in cal.values() for m in s["modes"].values() for a in m)
    assert json.loads((folder / "table.json").read_text())["rows"]["Adv. closed-loop"][
        "calibrated_realistic_best_shapes"] == [1, 1]
    assert "fresh real (recording 10) 1" in (folder / "table.md").read_text()
    assert not (tmp_path / "res" / "table1_oracle_b2").exists()
    # a protocol.json without the key is the paper's box: growing it with the realistic region is refused
    proto.pop("region")
    (folder / "protocol.json").write_text(json.dumps(proto))
    capsys.readouterr()
    assert mod.main(args) == 1 and "region" in capsys.readouterr().err
