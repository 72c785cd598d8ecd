"""Journal verification figures for docs/reliability.md ("Journals verified on resume"): the
tampered-journal cases of the hostile-input corpus run against the real command, and every
run folder kept under docs/results read under the same checks.

    .venv/bin/python bench/journal_verify.py          # bench/results/journal_verify.json

1. The run of the corpus: ``adv3d attack highway-benchmark-000000 --autonomy oracle --algo
   random --seconds 1 --budget 12 --workers 2`` (the issue's command). Each case edits a copy
   of its journal (or pending file) as the corpus did, then runs the same command again (the
   resume) and ``adv3d report``, in-process (``adv3d_runner.cli.main``). A case passes when both
   exit 1 with one error line naming the file and the line, and the journal files are left as
   they were (nothing refused is used or cut away). Cases that recompute the line's checksum
   are forgeries by someone who knows the rule: they are caught by the other checks; the one
   caught only by the search (a query point that is not the one asked at its index) is refused
   by the resume, while ``adv3d report``, which asks no search, reads it.
2. Kept runs: each ``docs/results/**/queries.jsonl.gz`` (journals written before checksums)
   with its ``run.json`` and ``summary.json``, read as ``adv3d report`` reads it and verified
   as a resume verifies it (``Journal.load(run=...)``): all must pass.
"""
from __future__ import annotations

import contextlib
import gzip
import io
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.journal import PENDING_NAME, Journal, read_run, record_checksum  # noqa: E402
from adv3d_runner.cli import main as adv3d  # noqa: E402
from adv3d_runner.errors import Adv3dError  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402

SCENE = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
ARGV = ["attack", str(SCENE), "--autonomy", "oracle", "--algo", "random", "--seconds", "1", "--budget", "12",
        "--workers", "2"]


def _rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def _write(path: Path, rows: list[dict], sign: bool) -> None:
    out = []
    for r in rows:
        r = dict(r)
        if sign:
            r["sha256"] = record_checksum(r)
        out.append(json.dumps(r, separators=(",", ":")) + "\n")
    path.write_text("".join(out))


def _cases(rows: list[dict]) -> dict:
    """name -> (file name, rows to write, recompute checksums, line the error must name)."""
    dup = lambda k: rows[:k + 1] + [dict(rows[k])] + rows[k + 1:]  # noqa: E731
    with_index = lambda k, v: [dict(r, index=v) if i == k else r for i, r in enumerate(rows)]  # noqa: E731
    edited = [dict(r, cost=1e6) if i == 4 else r for i, r in enumerate(rows)]
    unsigned = [{k: v for k, v in r.items() if k != "sha256"} if i == 4 else r for i, r in enumerate(rows)]
    point = [dict(r, unit=[[0.5] * len(r["unit"][0])]) if i == 4 else r for i, r in enumerate(rows)]
    return {
        "duplicated first line": ("queries.jsonl", dup(0), False, 2),
        "duplicated middle line": ("queries.jsonl", dup(5), False, 7),
        "duplicated last line": ("queries.jsonl", dup(len(rows) - 1), False, len(rows) + 1),
        "duplicated index carrying cost 1e6 (checksum recomputed)":
            ("queries.jsonl", rows[:6] + [dict(rows[5], cost=1e6)] + rows[6:], True, 7),
        "index 1e30": ("queries.jsonl", with_index(3, 10**30), True, 4),
        "index 40 with budget 12": ("queries.jsonl", with_index(3, 40), True, 4),
        "line from another scene (checksum recomputed)":
            ("queries.jsonl", [dict(r, scene="highway-benchmark-000001") if i == 2 else r for i, r in enumerate(rows)],
             True, 3),
        "another mode (checksum recomputed)":
            ("queries.jsonl", [dict(r, mode="open") if i == 2 else r for i, r in enumerate(rows)], True, 3),
        "pending line with index 99": (PENDING_NAME, [dict(rows[0], index=99)], True, 1),
        "pending line repeating a journal line with another cost": (PENDING_NAME, [dict(rows[0], cost=1e6)], True, 1),
        "cost edited (checksum left)": ("queries.jsonl", edited, False, 5),
        "checksum removed from a line": ("queries.jsonl", unsigned, False, 5),
        "query point edited (checksum recomputed)": ("queries.jsonl", point, True, 5),
    }


def _quiet_call(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = adv3d(["-q", *argv])
        except SystemExit as exc:
            rc = exc.code
    return rc, err.getvalue()


def corpus(work: Path) -> dict:
    ref = work / "reference"
    t0 = time.perf_counter()
    rc, err = _quiet_call(ARGV + ["--out", str(ref)])
    if rc != 0:
        raise SystemExit(f"reference run failed ({rc}): {err}")
    ref_s = time.perf_counter() - t0
    rows = _rows(ref / "queries.jsonl")
    cases = []
    for name, (file, new, sign, line) in _cases(rows).items():
        run = work / f"case{len(cases)}"
        shutil.copytree(ref, run)
        _write(run / file, new, sign)
        journal_files = ("queries.jsonl", PENDING_NAME)
        before = {p: (run / p).read_bytes() for p in journal_files if (run / p).exists()}
        t = time.perf_counter()
        resume_rc, resume_err = _quiet_call(ARGV + ["--out", str(run)])
        resume_s = time.perf_counter() - t
        report_rc, report_err = _quiet_call(["report", str(run)])
        after = {p: (run / p).read_bytes() for p in journal_files if (run / p).exists()}
        msgs = [m.strip() for m in (resume_err, report_err)]
        # every refusal names the file and the line; the forged point is refused by the search
        # itself (the resume), the report has no search to ask and reads the forgery
        named = all(len(m.splitlines()) == 1 and file in m and f"line {line}" in m for m in msgs[:1])
        refused = resume_rc == 1 and named and after == before
        cases.append({"case": name, "file": file, "resume_rc": resume_rc, "report_rc": report_rc,
                      "refused_on_resume": refused, "refused_by_report": report_rc == 1, "resume_s": round(resume_s, 2),
                      "error": msgs[0][:400], "report_error": msgs[1][:400]})
        print(f"{name:60s} resume {resume_rc} report {report_rc} {'ok' if refused else 'FINDING'}: {msgs[0][:140]}",
              flush=True)
    return {"command": "adv3d " + " ".join(a if a != str(SCENE) else SCENE.relative_to(ROOT).as_posix() for a in ARGV),
            "reference_wall_s": round(ref_s, 1), "queries": len(rows), "cases": cases,
            "refused_on_resume": sum(c["refused_on_resume"] for c in cases),
            "refused_by_report": sum(c["refused_by_report"] for c in cases)}


def kept(work: Path) -> dict:
    folders, records, bad = 0, 0, []
    t0 = time.perf_counter()
    for gz in sorted((ROOT / "docs" / "results").rglob("queries.jsonl.gz")):
        run = work / "kept" / str(folders)
        run.mkdir(parents=True)
        for f in gz.parent.iterdir():
            if f.is_file() and f.name != gz.name:
                shutil.copy(f, run / f.name)
        (run / "queries.jsonl").write_bytes(gzip.decompress(gz.read_bytes()))
        try:
            doc, recs, _ = read_run(run)
            Journal(run).load(run=doc)
            records += len(recs)
        except Adv3dError as exc:
            bad.append({"run": gz.parent.relative_to(ROOT).as_posix(), "error": str(exc)[:300]})
        folders += 1
        shutil.rmtree(run)
    wall = time.perf_counter() - t0
    print(f"kept runs: {folders} folders, {records} records, {len(bad)} refused, {wall:.1f} s", flush=True)
    return {"folders": folders, "records": records, "refused": bad, "wall_s": round(wall, 1)}


def main() -> None:
    out = ROOT / "bench" / "results" / "journal_verify.json"
    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix="adv3d-journal-") as tmp:
        result = {"command": "bench/journal_verify.py", "machine": machine_info("numpy"),
                  "corpus": corpus(Path(tmp)), "kept_runs": kept(Path(tmp))}
    result["wall_s"] = round(time.time() - t0, 1)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {out}")


if __name__ == "__main__":
    main()
