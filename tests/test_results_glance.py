"""bench/results_glance.py: the "At a glance" picture lines up the kept tables' own comparisons."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import load_bench

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "docs" / "results"


def _glance():
    return load_bench("results_glance")


def test_rows_are_the_tables_objective_comparisons():
    """Every objective comparison of every kept table appears once, with the table's values."""
    mod = _glance()
    rows = mod.glance_rows(RESULTS)
    expected = []
    for path in sorted(RESULTS.glob("*/table.json")):
        doc = json.loads(path.read_text())
        expected += [(path.parent.name, c["a"], c["b"], c["mean_diff"], tuple(c["ci"]), c["p_permutation"])
                     for c in doc["comparisons"] if c["metric"] == "objective"]
    got = [(r["folder"], r["a"], r["b"], r["mean"], (r["lo"], r["hi"]), r["p"]) for r in rows]
    assert sorted(got) == sorted(expected) and len(got) >= 10
    # Table 1 first, transfer last; a transfer row is drawn on the evaluated stack's panel
    assert rows[0]["table"] == "table1" and rows[-1]["table"] == "transfer"
    t = next(r for r in rows if r["folder"] == "transfer_B_b20")
    assert t["autonomy"] == "B" and t["label"] == "Transfer-A->B b20"


def test_shipped_glance_is_current():
    """docs/results/glance.json (what glance.png shows) equals what the kept tables give now:
    rerun ``python bench/results_glance.py`` after a table is rebuilt."""
    shipped = json.loads((RESULTS / "glance.json").read_text())
    assert shipped["rows"] == _glance().glance_rows(RESULTS)
    assert (RESULTS / "glance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_picture_written_and_bad_table_named(tmp_path, capsys):
    mod = _glance()
    for folder in ("table1_A", "transfer_B"):
        shutil.copytree(RESULTS / folder, tmp_path / folder, ignore=shutil.ignore_patterns("runs"))
    assert mod.main(["--results", str(tmp_path)]) == 0
    assert (tmp_path / "glance.png").stat().st_size > 10_000
    rows = json.loads((tmp_path / "glance.json").read_text())["rows"]
    assert {r["autonomy"] for r in rows} == {"A", "B"} and len(rows) == 6

    bad = tmp_path / "table1_A" / "table.json"
    doc = json.loads(bad.read_text())
    del doc["comparisons"][0]["ci"]
    bad.write_text(json.dumps(doc))
    assert mod.main(["--results", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "ci" in err
    doc["format"] = "something else"
    bad.write_text(json.dumps(doc))
    with pytest.raises(mod.ConfigError, match="format"):
        mod.glance_rows(tmp_path)
