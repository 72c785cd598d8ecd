"""Crash-resume benchmark: kill -9 an attack at random moments, count the finished queries the
kill lost, resume, and compare the resumed journal with an uninterrupted run.

    .venv/bin/python bench/crash_resume.py                    # 40 kills, this tree
    .venv/bin/python bench/crash_resume.py --code OLD_TREE    # the same on another checkout
    .venv/bin/python bench/crash_resume.py --real 5           # + 5 kills of a real `adv3d attack`

The attack (random search, 24 queries asked in batches of 4, 2 worker processes) evaluates a
synthetic objective (``tests/attack_synthetic.py``) that takes 50-250 ms per query, the time
depending on the query, so workers finish out of order. Every evaluation appends a line to a
marker log (fsync) in the worker the moment it has its result: a query is *finished* when its
marker is there. Each run is killed (``SIGKILL`` to the whole process group: driver and workers)
at a seeded uniform moment after its first finished query, within 80 % of the rest of an
uninterrupted run's length; then the bench counts:

* ``lost``: finished queries whose result is in neither ``queries.jsonl`` nor
  ``queries.pending.jsonl`` (the driver had not written it; a result still travelling from the
  worker to the driver counts here too);
* ``redone``: finished queries evaluated a second time by the resume (equal to ``lost``);
* whether the resumed journal equals the uninterrupted one (``strip_times``: everything but
  wall times).

``--real N`` also kills N runs of the real command (``adv3d attack`` on a bundled scene,
oracle perception, 1 s episodes, 8 queries, 2 workers) and compares each resumed journal
with an uninterrupted one. Results: ``bench/results/crash_resume.json`` (or ``--out``).
The machine is shared: times are wall-clock and only set when kills land.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
BUDGET, BATCH, WORKERS, SEED = 24, 4, 2, 7


sys.path.insert(0, str(ROOT / "tests"))
from attack_synthetic import SyntheticEvaluator  # noqa: E402  (the synthetic objective lives with the tests)


class SlowSynthetic(SyntheticEvaluator):
    """The synthetic evaluator, slowed to 50-250 ms per query (by the query's own numbers, so
    the same query always takes the same time), logging each finished evaluation to the file
    named by ``$ADV3D_BENCH_MARKERS`` (workers inherit the environment)."""

    def evaluate(self, query):
        time.sleep(0.05 + 0.2 * float(query.unit[2]))
        try:
            return super().evaluate(query)
        finally:  # a failed query (status invalid / error) has finished too
            _mark(os.environ["ADV3D_BENCH_MARKERS"], query.unit)


def _child(out: str, markers: str) -> None:
    """The attack under test (run in its own process group by the parent)."""
    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.driver import run_attack

    os.environ["ADV3D_BENCH_MARKERS"] = markers
    from adv3d_runner.attack import journal

    if hasattr(journal, "_append"):  # log when the driver writes each record (start, end)
        append = journal._append

        def timed(path, line, log=markers + ".writes"):
            fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                os.write(fd, f"start {time.time()}\n".encode())
                append(path, line)
                os.write(fd, f"end {time.time()}\n".encode())
            finally:
                os.close(fd)

        journal._append = timed
    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=BUDGET, batch=BATCH, seed=SEED)
    run_attack(cfg, out, workers=WORKERS, evaluator=SlowSynthetic, show_progress=False)


def _mark(markers: str, unit) -> None:
    # two times: when the worker had the result, and when its marker was durable (just before
    # the result leaves the worker); an fsync stalled by other jobs' disk writes lies between
    line = json.dumps([[round(float(v), 9) for v in unit], time.time()])
    fd = os.open(markers, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode())
        os.fsync(fd)
        os.write(fd, (json.dumps(["durable", [round(float(v), 9) for v in unit], time.time()]) + "\n").encode())
    finally:
        os.close(fd)


def _writes(path: Path) -> list[tuple[float, float | None]]:
    """(start, end or None) of each journal write the driver made."""
    out: list[tuple[float, float | None]] = []
    if path.exists():
        for line in path.read_text().splitlines():
            kind, t = line.split()
            if kind == "start":
                out.append((float(t), None))
            elif out:
                out[-1] = (out[-1][0], float(t))
    return out


def _key(unit) -> str:
    return json.dumps([round(float(v), 9) for v in np.asarray(unit, dtype=np.float64).reshape(-1)])


def _records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            pass  # a truncated last line (the kill): the resume drops it
    return out


def _strip(records: list[dict]) -> list[dict]:
    out = []
    for r in records:
        r = dict(r)
        r.pop("wall_s", None)
        out.append(r)
    return out


def _wait_for(paths: list[Path], proc: subprocess.Popen, timeout: float = 300) -> float:
    """Seconds until one of ``paths`` holds a byte (the first finished query), or the process
    ended."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout and proc.poll() is None:
        if any(p.exists() and p.stat().st_size for p in paths):
            break
        time.sleep(0.01)
    return time.perf_counter() - t0


def _start(argv: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen(argv, env=env, cwd=ROOT, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)


def _finish(proc: subprocess.Popen, timeout: float = 600) -> None:
    _, err = proc.communicate(timeout=timeout)
    if proc.returncode != 0:
        raise SystemExit(f"attack failed ({proc.returncode}): {err.decode()[-2000:]}")


def synthetic_trials(code: Path, n: int, rng: np.random.Generator, work: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{code}{os.pathsep}{ROOT / 'tests'}", "OMP_NUM_THREADS": "1"}
    me = [sys.executable, str(Path(__file__).resolve()), "--child"]
    ref = work / "reference"
    t0 = time.perf_counter()
    proc = _start(me + [str(ref), str(work / "reference.markers")], env)
    first_s = _wait_for([work / "reference.markers"], proc)
    _finish(proc)
    ref_s = time.perf_counter() - t0
    reference = _strip(_records(ref / "queries.jsonl"))
    assert len(reference) == BUDGET, len(reference)
    write_ms = [1000 * (b - a) for a, b in _writes(work / "reference.markers.writes") if b is not None]
    trials = []
    for k in range(n):
        out, markers = work / f"run{k}", work / f"run{k}.markers"
        # kills land at a uniform moment of the evaluation phase: after the first query finished
        # (process start-up, ~1-2 s, is not interesting), before the end of the run
        delay = float(rng.uniform(0.0, 0.8 * (ref_s - first_s)))  # 0.8: runs end a little sooner than the reference
        proc = _start(me + [str(out), str(markers)], env)
        waited = _wait_for([markers], proc)
        time.sleep(delay)
        kill_at = waited + delay
        t_kill = time.time()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        every = [json.loads(x) for x in markers.read_text().splitlines()] if markers.exists() else []
        lines = [x for x in every if x[0] != "durable"]
        durable_when = {_key(x[1]): x[2] for x in every if x[0] == "durable"}
        finished = [u for u, _ in lines]
        finished_when = {_key(u): t for u, t in lines}
        written = {_key(r["unit"]) for r in _records(out / "queries.jsonl") + _records(out / "queries.pending.jsonl")}
        finished_keys = {_key(u) for u in finished}
        lost = sorted(finished_keys - written)
        journal_keys = {_key(r["unit"]) for r in _records(out / "queries.jsonl")}
        in_journal = len(journal_keys)
        # pending lines already moved to the journal (the pending file is emptied per batch) count once
        in_pending = len({_key(r["unit"]) for r in _records(out / "queries.pending.jsonl")} - journal_keys)
        before = len(finished)
        _finish(_start(me + [str(out), str(markers)], env))  # resume to the end
        after = [x[0] for x in map(json.loads, markers.read_text().splitlines()) if x[0] != "durable"]
        evaluated = [_key(u) for u in after[before:]]
        redone = sorted(set(evaluated) & finished_keys)
        resumed = _strip(_records(out / "queries.jsonl"))
        # how long before the kill each lost query had finished in its worker, and whether the
        # driver was writing (fsync) another record at the kill: a result still on its way to the
        # driver, or queued behind a write, is in flight
        lost_ms = [round(1000 * (t_kill - finished_when[q]), 1) for q in lost]
        # None: the worker's marker was not yet durable at the kill, so its result had not left it
        lost_left_ms = [round(1000 * (t_kill - durable_when[q]), 1) if q in durable_when else None for q in lost]
        writes = _writes(Path(str(markers) + ".writes"))
        busy = bool(writes) and writes[-1][1] is None
        trials.append({"kill_after_s": round(kill_at, 3), "finished_at_kill": len(finished_keys),
                       "lost_finished_ms_before_kill": lost_ms, "lost_left_worker_ms_before_kill": lost_left_ms,
                       "driver_writing_at_kill": busy,
                       "journalled": in_journal, "pending": in_pending, "lost_finished": len(lost),
                       "redone_by_resume": len(redone), "evaluated_by_resume": len(evaluated),
                       "resumed_equals_uninterrupted": resumed == reference})
        print(f"kill {k}: at {kill_at:.2f} s, {len(finished_keys)} finished, {in_journal} journalled + {in_pending} "
              f"only pending, lost {len(lost)} {lost_ms} ms before the kill (left the worker: {lost_left_ms})"
              f"{' (driver writing)' if busy else ''}, "
              f"redone {len(redone)}, equal {resumed == reference}", flush=True)
    all_ms = write_ms + [1000 * (b - a) for k in range(n) for a, b in _writes(work / f"run{k}.markers.writes")
                         if b is not None]
    return {"reference_wall_s": round(ref_s, 2), "reference_first_query_s": round(first_s, 2),
            "journal_write_ms": {"n": len(all_ms), "median": round(float(np.median(all_ms)), 2) if all_ms else None,
                                 "p99": round(float(np.percentile(all_ms, 99)), 1) if all_ms else None,
                                 "max": round(max(all_ms), 1) if all_ms else None},
            "trials": trials,
            "totals": {"kills": n, "finished_at_kill": sum(t["finished_at_kill"] for t in trials),
                       "lost_finished": sum(t["lost_finished"] for t in trials),
                       "redone_by_resume": sum(t["redone_by_resume"] for t in trials),
                       "lost_finished_ms_before_kill_max": max((m for t in trials for m in
                                                                t["lost_finished_ms_before_kill"]), default=None),
                       "lost_after_leaving_worker": sum(m is not None for t in trials
                                                        for m in t["lost_left_worker_ms_before_kill"]),
                       "lost_left_worker_ms_before_kill_max": max((m for t in trials for m in
                                                                   t["lost_left_worker_ms_before_kill"]
                                                                   if m is not None), default=None),
                       "kills_with_a_loss_while_driver_writing": sum(bool(t["lost_finished"]) and
                                                                     t["driver_writing_at_kill"] for t in trials),
                       "resumed_equal": sum(t["resumed_equals_uninterrupted"] for t in trials)}}


def real_trials(code: Path, n: int, rng: np.random.Generator, work: Path) -> dict:
    """Kills of the real command: resumed journals against an uninterrupted one."""
    scene = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "adv3d_runner.cli", "-q", "attack", str(scene), "--algo", "random", "--budget", "8",
           "--seconds", "1", "--autonomy", "oracle", "--workers", "2", "--seed", "3", "--out"]
    if "--batch" in (code / "adv3d_runner" / "attack" / "cli.py").read_text():
        cmd[-1:-1] = ["--batch", "2"]  # batch 2 as the code before --batch had it (= workers)
    t0 = time.perf_counter()
    proc = _start(cmd + [str(work / "real_ref")], env)
    first_s = _wait_for([work / "real_ref" / "queries.jsonl", work / "real_ref" / "queries.pending.jsonl"], proc)
    _finish(proc)
    ref_s = time.perf_counter() - t0
    reference = _strip(_records(work / "real_ref" / "queries.jsonl"))
    trials = []
    for k in range(n):
        out = work / f"real{k}"
        delay = float(rng.uniform(0.0, ref_s - first_s))
        proc = _start(cmd + [str(out)], env)
        kill_at = _wait_for([out / "queries.jsonl", out / "queries.pending.jsonl"], proc) + delay
        time.sleep(delay)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        at_kill = len(_records(out / "queries.jsonl")) + len(_records(out / "queries.pending.jsonl"))
        _finish(_start(cmd + [str(out)], env))
        resumed = _strip(_records(out / "queries.jsonl"))
        trials.append({"kill_after_s": round(kill_at, 2), "journalled_at_kill": at_kill,
                       "resumed_equals_uninterrupted": resumed == reference})
        print(f"real kill {k}: at {kill_at:.1f} s, {at_kill} journalled, equal {resumed == reference}", flush=True)
    return {"reference_wall_s": round(ref_s, 1), "reference_first_query_s": round(first_s, 1), "trials": trials,
            "resumed_equal": sum(t["resumed_equals_uninterrupted"] for t in trials)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", nargs=2, metavar=("OUT", "MARKERS"), help=argparse.SUPPRESS)
    ap.add_argument("--kills", type=int, default=40)
    ap.add_argument("--real", type=int, default=0, help="kills of the real `adv3d attack` command")
    ap.add_argument("--code", type=Path, default=ROOT, help="the tree whose adv3d_runner is tested (default: this one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "crash_resume.json")
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return
    rng = np.random.default_rng(args.seed)
    code = args.code.resolve()
    with tempfile.TemporaryDirectory(prefix="adv3d-crash-") as tmp:
        work = Path(tmp)
        sys.path.insert(0, str(ROOT))
        from adv3d_runner.machine import machine_info

        result = {"command": "bench/crash_resume.py " + " ".join(sys.argv[1:]), "code": str(code),
                  "machine_at_start": machine_info(),
                  "attack": {"algo": "random", "budget": BUDGET, "batch": BATCH, "workers": WORKERS, "seed": SEED,
                             "query_s": "0.05-0.25"},
                  "synthetic": synthetic_trials(code, args.kills, rng, work)}
        if args.real:
            result["real"] = real_trials(code, args.real, rng, work)
        result["load_at_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["synthetic"]["totals"]))


if __name__ == "__main__":
    main()
