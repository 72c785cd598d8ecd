"""A tampered run bundle is refused before any of it is used (docs/reliability.md, "Journals
verified on resume"; docs/formats.md, "Run bundle"): every journal line's checksum, scene, mode
and index against the run, one record per query, and the point each reused record holds against
what its search asks. Legacy journals (no checksums) still read and resume when they pass the
rest.

Each case is one of the hostile-input corpus: duplicated lines (first, middle, last), an index
of 1e30 or 40 with budget 12, a line from another scene, a pending line with index 99, a
duplicated index carrying cost 1e6, an edited line."""
from __future__ import annotations

import gzip
import json
import re
import shutil
from pathlib import Path

import pytest
from attack_synthetic import SyntheticEvaluator

from adv3d_runner.attack.config import AttackConfig
from adv3d_runner.attack.driver import run_attack
from adv3d_runner.attack.journal import CHECKSUM_RUN_KEY, PENDING_NAME, Journal, read_run, record_checksum
from adv3d_runner.cli import main
from adv3d_runner.errors import ConfigError, FileFormatError

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
CFG = AttackConfig(["synthetic:peak", "synthetic:bowl"], algo="random", budget=12, batch=4, seed=3)


def _run(tmp_path: Path, cfg: AttackConfig = CFG, name: str = "run") -> Path:
    run_attack(cfg, tmp_path / name, evaluator=SyntheticEvaluator, show_progress=False)
    return tmp_path / name


def _rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()]


def _write(path: Path, rows: list[dict], *, sign: bool = True) -> None:
    """Rows as journal lines, each checksum made anew (``sign``: a forger who knows the rule)."""
    out = []
    for r in rows:
        r = dict(r)
        if sign and "sha256" in r:
            r["sha256"] = record_checksum(r)
        out.append(json.dumps(r, separators=(",", ":")) + "\n")
    path.write_text("".join(out))


def _refused(run: Path, match: str, cfg: AttackConfig = CFG) -> None:
    """Both readers refuse it with the same one-line error: the resume and ``adv3d report``;
    and the journal is left as it was (nothing refused is cut away or used)."""
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with pytest.raises(FileFormatError, match=match) as resumed:
        run_attack(cfg, run, evaluator=SyntheticEvaluator, show_progress=False)
    assert "\n" not in str(resumed.value)
    with pytest.raises(FileFormatError, match=match):
        read_run(run)
    after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert after == before


@pytest.mark.parametrize("which", [0, 11, 23])  # first, middle, last line
def test_duplicated_line_is_refused_naming_both_lines(tmp_path, which):
    run = _run(tmp_path)
    path = run / "queries.jsonl"
    rows = _rows(path)
    rows.insert(which + 1, dict(rows[which]))
    _write(path, rows, sign=False)  # an exact copy: its checksum holds
    _refused(run, rf"queries.jsonl: line {which + 2}: \$\.index: expected a query not already in this file "
                  rf"\(line {which + 1} holds query")


def test_duplicated_index_with_a_higher_cost_never_becomes_the_best(tmp_path):
    run = _run(tmp_path)
    path = run / "queries.jsonl"
    summary = json.loads((run / "summary.json").read_text())
    best = summary["scenes"]["synthetic:peak"]["modes"]["closed"]["best_cost"]
    rows = _rows(path)
    forged = dict(rows[5], cost=1e6, components={"synthetic": 1e6})
    rows.insert(6, forged)
    _write(path, rows)  # checksum made anew: the duplicate index is what gives it away
    _refused(run, r"queries.jsonl: line 7: \$\.index: expected a query not already in this file")
    rows = _rows(path)
    del rows[6]
    rows[5]["cost"] = 1e6  # the genuine line edited by hand instead, its checksum left as it was
    _write(path, rows, sign=False)
    _refused(run, r"queries.jsonl: line 6: expected a record whose content matches its sha256")
    assert json.loads((run / "summary.json").read_text())["scenes"]["synthetic:peak"]["modes"]["closed"][
        "best_cost"] == best


@pytest.mark.parametrize("index, match", [
    (40, r"\$\.index: expected a query index in \[0, 11\] \(the run's budget is 12\) \(got 40\)"),
    (10**30, r"\$\.index: expected a query index in \[0, 11\]"),
    (1e30, r"\$\.index: expected an integer"),
    (-1, r"\$\.index: expected an integer >= 0"),
])
def test_index_out_of_the_budget_is_refused(tmp_path, index, match):
    run = _run(tmp_path)
    path = run / "queries.jsonl"
    rows = _rows(path)
    rows[3]["index"] = index
    _write(path, rows)
    _refused(run, "queries.jsonl: line 4: " + match)


def test_line_from_another_scene_or_mode_is_refused(tmp_path):
    run = _run(tmp_path)
    path = run / "queries.jsonl"
    rows = _rows(path)
    original = [dict(r) for r in rows]
    rows[2]["scene"] = "synthetic:ridge"  # not a scene of this run
    _write(path, rows)
    _refused(run, r"queries.jsonl: line 3: \$\.scene: expected one of the run's scenes \(synthetic:peak, "
                  r"synthetic:bowl\) \(got 'synthetic:ridge'\)")
    rows = [dict(r) for r in original]
    rows[2]["mode"] = "open"
    _write(path, rows)
    _refused(run, r"queries.jsonl: line 3: \$\.mode: expected one of the run's modes \(closed\)")
    # a line of the other scene of this run, moved here: unique index, checksum made anew, but
    # the search on this scene asks another point at that index
    rows = [dict(r) for r in original]
    other = next(r for r in rows if r["scene"] == "synthetic:bowl" and r["index"] == 2)
    peak = next(k for k, r in enumerate(rows) if r["scene"] == "synthetic:peak" and r["index"] == 2)
    rows[peak] = {**other, "scene": "synthetic:peak", "unit": [[0.5, 0.5, 0.5, 0.5, 0.5]]}
    _write(path, rows)
    with pytest.raises(ConfigError, match=rf"queries.jsonl: line {peak + 1}: query 2 of synthetic:peak/closed does "
                                          r"not match this run"):
        run_attack(CFG, run, evaluator=SyntheticEvaluator, show_progress=False)


def test_pending_line_with_a_bad_index_is_refused(tmp_path):
    run = _run(tmp_path)
    rows = _rows(run / "queries.jsonl")
    pending = run / PENDING_NAME
    _write(pending, [dict(rows[0], index=99)])
    _refused(run, rf"{PENDING_NAME}: line 1: \$\.index: expected a query index in \[0, 11\] .*\(got 99\)")
    # a pending line that repeats a journal line must be that record (a kill between the move
    # to the journal and the clean-up), not another one
    _write(pending, [dict(rows[0], cost=1e6)])
    _refused(run, rf"{PENDING_NAME}: line 1: expected the record of queries.jsonl line 1")
    _write(pending, [dict(rows[0])], sign=False)  # the same record: accepted, used once
    run_attack(CFG, run, evaluator=SyntheticEvaluator, show_progress=False)
    assert len(read_run(run)[1]) == 24


def test_edited_or_unsigned_line_is_refused(tmp_path):
    run = _run(tmp_path)
    path = run / "queries.jsonl"
    rows = _rows(path)
    assert all(len(r["sha256"]) == 64 for r in rows)
    assert json.loads((run / "run.json").read_text())[CHECKSUM_RUN_KEY] is True
    edited = [dict(r) for r in rows]
    edited[8]["components"] = {"synthetic": 9.0}
    _write(path, edited, sign=False)
    _refused(run, r"queries.jsonl: line 9: expected a record whose content matches its sha256")
    unsigned = [dict(r) for r in rows]
    del unsigned[8]["sha256"]  # the checksum taken off an edited line: this run's lines all have one
    _write(path, unsigned, sign=False)
    _refused(run, r"queries.jsonl: line 9: \$\.sha256: expected the record's checksum")
    path.write_text(re.sub(r'"cost":[^,]+', '"cost":1e400', path.read_text(), count=1))  # JSON reads inf
    with pytest.raises(FileFormatError, match=r"queries.jsonl: line 1: \$\.cost: expected a finite number"):
        read_run(run)


def test_query_never_asked_by_a_search_that_ended_early_is_refused(tmp_path):
    """bruteforce ends after its 50 candidates, before the budget of 60: a record at index 55
    lies inside the budget but was never asked."""
    cfg = AttackConfig(["synthetic:peak"], algo="bruteforce", budget=60, seed=1)
    run = _run(tmp_path, cfg)
    path = run / "queries.jsonl"
    rows = _rows(path)
    assert len(rows) == 50
    _write(path, rows + [dict(rows[-1], index=55)])
    with pytest.raises(ConfigError, match=r"queries.jsonl: line 51: query 55 of synthetic:peak/closed was never "
                                          r"asked: the search ended after 50 queries"):
        run_attack(cfg, run, evaluator=SyntheticEvaluator, show_progress=False)


def test_legacy_journal_without_checksums_reads_and_resumes(tmp_path):
    """A bundle written before checksums (run.json without journal_sha256, lines without
    sha256): read by the report and resumed to the same journal, as long as its lines pass
    every other check."""
    full = _run(tmp_path, name="full")
    run = _run(tmp_path, name="legacy")
    doc = json.loads((run / "run.json").read_text())
    del doc[CHECKSUM_RUN_KEY]
    (run / "run.json").write_text(json.dumps(doc, indent=1))
    rows = _rows(run / "queries.jsonl")
    for r in rows:
        del r["sha256"]
    _write(run / "queries.jsonl", rows[:7], sign=False)  # killed after 7 queries
    assert len(read_run(run)[1]) == 7
    run_attack(CFG, run, evaluator=SyntheticEvaluator, show_progress=False)
    old, new = _rows(run / "queries.jsonl"), _rows(full / "queries.jsonl")
    strip = lambda rs: [{k: v for k, v in r.items() if k not in ("wall_s", "sha256")} for r in rs]  # noqa: E731
    assert strip(old) == strip(new)
    _write(run / "queries.jsonl", [{k: v for k, v in r.items() if k != "sha256"} for r in new[:7]] + [
        {k: v for k, v in new[3].items() if k != "sha256"}], sign=False)  # legacy lines still face the rest
    _refused(run, r"queries.jsonl: line 8: \$\.index: expected a query not already in this file")


def test_kept_run_bundles_still_read(tmp_path):
    """Run folders kept under docs/results (journals from before checksums, gzipped there)."""
    kept = sorted((REPO / "docs" / "results").rglob("queries.jsonl.gz"))
    if not kept:
        pytest.skip("no kept runs")
    for gz in kept[:: max(1, len(kept) // 6)]:
        run = tmp_path / gz.parent.relative_to(REPO)
        run.mkdir(parents=True)
        for f in gz.parent.iterdir():
            if f.is_file() and f.name != gz.name:
                shutil.copy(f, run / f.name)
        (run / "queries.jsonl").write_bytes(gzip.decompress(gz.read_bytes()))
        doc, records, _ = read_run(run)
        assert records and CHECKSUM_RUN_KEY not in doc and all("sha256" not in r for r in records)
        j = Journal(run)
        j.load(run=doc)
        assert len(j.records) == len(records)


def test_cli_resume_of_a_tampered_journal_is_one_error_line(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["-q", "attack", str(SCENE), "--autonomy", "oracle", "--algo", "random", "--seconds", "0.2",
            "--budget", "3", "--out", str(out)]
    assert main(argv) == 0
    path = out / "queries.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    path.write_text(lines[0] + lines[1] + lines[1] + lines[2])
    capsys.readouterr()
    assert main(argv) == 1
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(err) == 1 and err[0].startswith("adv3d: error: ") and "queries.jsonl: line 3: $.index" in err[0]
    assert main(["-q", "report", str(out)]) == 1
    assert path.read_text() == lines[0] + lines[1] + lines[1] + lines[2]
