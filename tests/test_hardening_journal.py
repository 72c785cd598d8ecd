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


# ------------------------------------------------------------------ one exit-code rule

def _cli(capsys, *argv) -> tuple[int, str]:
    try:
        rc = main(["-q", *map(str, argv)])
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def _one_line(err: str) -> str:
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


_A = ["attack", str(SCENE), "--autonomy", "oracle", "--seconds", "0.2", "--budget", "1", "--out", "unused-run"]


@pytest.mark.parametrize("argv, option", [
    # a value wrong by itself: refused by its argument type
    (_A + ["--shape-model", "vd", "--vd-bound", "1e9"], "--vd-bound"),
    (_A + ["--shape-model", "vd", "--vd-bound", "-1"], "--vd-bound"),
    (_A + ["--shape-model", "vd", "--vd-bound", "nan"], "--vd-bound"),
    (_A + ["--shape-model", "vd", "--vd-lattice", "abc"], "--vd-lattice"),
    (_A + ["--shape-model", "vd", "--vd-lattice", "1,3,3"], "--vd-lattice"),
    (_A + ["--max-mahalanobis", "-1"], "--max-mahalanobis"),
    (_A + ["--max-mahalanobis", "nan"], "--max-mahalanobis"),
    (_A + ["--realism-weight", "-1"], "--realism-weight"),
    (_A + ["--realism-weight", "inf"], "--realism-weight"),
    (_A + ["--objective", "M9"], "--objective"),
    (_A + ["--objective", "pred=abc"], "--objective"),
    (_A + ["--objective", "pred=nan"], "--objective"),
    (["shapes", "build", "--method", "bogus"], "--method"),
    (["shapes", "realism", "--u", "0.5,0.5,0.5,0.5,0.5", "--class", "bogus"], "--class"),
    (["shapes", "decode", "--u", "0.5,0.5,0.5,0.5,0.5", "-o", "x.txt"], "-o"),
    (["lidar", "render", str(SCENE), "-o", "p.ply", "--sensor", "bogus"], "--sensor"),
    (["train", "detector", "--scenes", "99999999"], "--scenes"),
    (["train", "occupancy", "--scenes", "99999999"], "--scenes"),
    (["train", "predictor", "--real-weight", "0"], "--real-weight"),
    (["blender", "render", "--what", "shapes", "--u", "abc", "--out", "x.png"], "--u"),
    (["blender", "render", "--what", "shapes", "--size", "abc", "--out", "x.png"], "--size"),
    (["assets", "import", "x.obj", "--class", "Bad Class"], "--class"),
    (["assets", "import", "x.obj", "--class", "sedan", "--id", "a" * 300], "--id"),
    # a value wrong for the other options or for the files it names: UsageError
    (_A + ["--vd-bound", "0.5"], "--vd-bound"),
    (_A + ["--shape-model", "vd", "--algo", "grid"], "--algo grid"),
    (_A + ["--shape-model", "vd", "--max-mahalanobis", "2"], "--max-mahalanobis"),
    (["shapes", "decode", "--u", "0.5,0.5", "-o", "x.glb"], "--u"),
    (["lidar", "render", str(SCENE), "-o", "p.ply", "--frame", "999999"], "--frame"),
    (["simulate", str(SCENE), "--start-frame", "999999", "--out", "unused-out"], "--start-frame"),
    (["scenes", "generate", "--out", "unused-out", "--seed", "4294967295", "--count", "5"], "--seed"),
    (["train", "detector", "--holdout-assets", "no.such.asset"], "--holdout-assets"),
    (["train", "predictor", "--seed", "1"], "--seed"),
    (["blender", "render", "--what", "sweep", "--dim", "99", "--out", "x.png"], "--dim"),
    (["assets", "import", "x.obj", "--class", "sedan", "--up", "+z", "--forward", "+z"], "--up"),
])
def test_bad_option_values_are_one_usage_line_and_exit_2(tmp_path, monkeypatch, capsys, argv, option):
    monkeypatch.chdir(tmp_path)
    rc, err = _cli(capsys, *argv)
    line = _one_line(err)
    cmd = " ".join(w for w in argv[:2] if not w.startswith("-") and "/" not in w)
    assert rc == 2 and line.startswith(f"adv3d {cmd}: error: ") and option in line, line
    assert line.endswith("--help)") and not list(tmp_path.iterdir())  # nothing written


def test_commonroad_seconds_shorter_than_a_frame_is_a_usage_error(tmp_path, capsys):
    from fuzz_contracts import commonroad_xml

    xml = tmp_path / "s.xml"
    xml.write_text(commonroad_xml())
    rc, err = _cli(capsys, "scenes", "import-commonroad", xml, "--out", tmp_path / "s.json", "--seconds", "0.01")
    assert rc == 2 and "--seconds must be at least one frame" in _one_line(err)
    rc, err = _cli(capsys, "scenes", "import-commonroad", xml, "--out", tmp_path / "s.json", "--ego", "999")
    assert rc == 2 and "--ego 999: no such dynamic obstacle" in _one_line(err)
    assert not (tmp_path / "s.json").exists()


def test_resume_notes_are_printed_with_quiet(tmp_path, capsys, monkeypatch):
    """A resume under other versions (planner, weights, code) changes what the run's results
    mean: the note is printed even with -q."""
    from adv3d_runner import progress

    run = _run(tmp_path)
    doc = json.loads((run / "run.json").read_text())
    doc["versions"] = {**doc["versions"], "planner": "0000000000000000", "models": {"detector": "sha256:old"}}
    (run / "run.json").write_text(json.dumps(doc))
    monkeypatch.setattr(progress, "_QUIET", True)
    capsys.readouterr()
    run_attack(CFG, run, evaluator=SyntheticEvaluator, show_progress=False)
    said = capsys.readouterr().out
    assert "other versions" in said and "planner: 0000000000000000 ->" in said and "models: {'detector'" in said


# ------------------------------------------------------------------ silent accepts that were

@pytest.mark.parametrize("where, value, match", [
    ("actor", [-4.5, 1.8, 1.5], r"\$\.actors\[0\]\.dimensions\[0\]: expected a positive size in m"),
    ("actor", [4.5, 1.8, 1.4e9], r"\$\.actors\[0\]\.dimensions\[2\]: expected a positive size in m \(at most 100\)"),
    ("ego", [0.0, 0.0, 0.0], r"\$\.ego\.dimensions\[0\]: expected a positive size in m"),
])
def test_replay_with_impossible_dimensions_is_refused(tmp_path, where, value, match):
    from fuzz_contracts import _make_replay

    from adv3d_runner.fileio import read_json, write_json
    from adv3d_runner.sim.replay import load_replay

    path = _make_replay(tmp_path)
    doc = read_json(path)
    (doc["actors"][0] if where == "actor" else doc["ego"])["dimensions"] = value
    write_json(path, doc)
    with pytest.raises(FileFormatError, match=match):
        load_replay(path)


def test_lane_whose_centre_line_is_one_repeated_point_is_refused(tmp_path, capsys):
    from fuzz_contracts import SIGN_OBJ, small_scene_doc

    from adv3d_runner.fileio import write_json
    from adv3d_runner.scene.schema import load_scene

    doc = small_scene_doc()
    (tmp_path / "sign.obj").write_text(SIGN_OBJ)
    lane = doc["map"]["lanes"][1]
    lane["centerline"] = [list(lane["centerline"][0])] * len(lane["centerline"])
    write_json(tmp_path / "s.json", doc)
    with pytest.raises(FileFormatError, match=r"\$\.map\.lanes\[1\]\.centerline: expected at least two distinct points"):
        load_scene(tmp_path / "s.json")
    rc, err = _cli(capsys, "simulate", tmp_path / "s.json", "--autonomy", "oracle", "--seconds", "0.2",
                   "--out", tmp_path / "out")
    assert rc == 1 and "centerline" in _one_line(err) and not (tmp_path / "out").exists()


# ------------------------------------------------------------------ tracebacks that were

def test_output_below_a_file_is_one_error_line(tmp_path, capsys):
    (tmp_path / "FILE").write_text("mine")
    for out in ("FILE/x.glb", "FILE/a/b/x.glb"):
        rc, err = _cli(capsys, "shapes", "decode", "--u", "0.5,0.5,0.5,0.5,0.5", "-o", tmp_path / out)
        assert rc == 1 and "FILE is a file, not a folder" in _one_line(err)
    assert (tmp_path / "FILE").read_text() == "mine"


def test_names_too_long_for_the_file_system_leave_nothing_behind(tmp_path, capsys):
    from adv3d_runner.fileio import atomic_path

    with pytest.raises(ConfigError, match="cannot write this file"):
        with atomic_path(tmp_path / "new" / "deeper" / ("x" * 300 + ".glb")):
            pass
    assert not (tmp_path / "new").exists()  # the folders made for it are gone again
    src = tmp_path / "src"
    src.mkdir()
    (src / "car.obj").write_text("v 0 0 0\nv 4 0 0\nv 0 2 0\nv 0 0 1.5\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    (src / ("c" * 200 + ".obj")).write_text((src / "car.obj").read_text())
    (src / "License.txt").write_text("CC0 1.0 creativecommons.org/publicdomain/zero/1.0/")
    lib = tmp_path / "lib" / "library.json"
    cases = [(["--id", "a" * 300], 2, "--id"), (["--source-pack", "p" * 300], 1, "source pack"),
             ([], 1, "asset id")]
    for extra, code, said in cases:
        path = src / ("c" * 200 + ".obj") if not extra else src / "car.obj"
        rc, err = _cli(capsys, "assets", "import", path, "--class", "sedan", "--library", lib, *extra)
        assert rc == code and said in _one_line(err)
    assert not (tmp_path / "lib").exists()


def test_run_lock_that_is_a_folder_is_one_error_line(tmp_path, capsys):
    run = _run(tmp_path)
    lock = run / ".adv3d-run.lock"
    lock.unlink()
    lock.mkdir()
    with pytest.raises(ConfigError, match=r"\.adv3d-run\.lock: cannot open the run's lock file .*plain file"):
        run_attack(CFG, run, evaluator=SyntheticEvaluator, show_progress=False)
    rc, err = _cli(capsys, "attack", SCENE, "--autonomy", "oracle", "--seconds", "0.2", "--budget", "1",
                   "--out", tmp_path / "other")
    assert rc == 0
    (tmp_path / "other" / ".adv3d-run.lock").unlink()
    (tmp_path / "other" / ".adv3d-run.lock").mkdir()
    rc, err = _cli(capsys, "attack", SCENE, "--autonomy", "oracle", "--seconds", "0.2", "--budget", "1",
                   "--out", tmp_path / "other")
    assert rc == 1 and "lock file" in _one_line(err)
