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

from adv3d_runner.attack.evaluator import EpisodeEvaluator  # noqa: E402


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


def _time_writes(markers: str) -> None:
    """Log every journal write this process makes (``journal._append``: the driver's journal and
    pending lines, and a worker's own pending lines) to ``MARKERS.writes.<pid>``: its start, and
    its end with the file and the record's unit vector, so the bench knows when each query
    became durable."""
    from adv3d_runner.attack import journal

    if not hasattr(journal, "_append") or getattr(journal._append, "_bench_timed", False):
        return
    append = journal._append
    log = f"{markers}.writes.{os.getpid()}"

    def timed(path, line):
        fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, f"start {time.time()}\n".encode())
            append(path, line)
            try:
                key = _key(json.loads(line)["unit"]).replace(" ", "")
            except (ValueError, KeyError, TypeError):
                key = "-"
            os.write(fd, f"end {time.time()} {Path(path).name} {key}\n".encode())
        finally:
            os.close(fd)

    timed._bench_timed = True
    journal._append = timed


if __name__ == "__mp_main__" and os.environ.get("ADV3D_BENCH_MARKERS"):
    _time_writes(os.environ["ADV3D_BENCH_MARKERS"])  # a spawned worker: its own journal writes too


def _child(out: str, markers: str) -> None:
    """The attack under test (run in its own process group by the parent)."""
    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.driver import run_attack

    os.environ["ADV3D_BENCH_MARKERS"] = markers
    _time_writes(markers)
    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=BUDGET, batch=BATCH, seed=SEED)
    run_attack(cfg, out, workers=WORKERS, evaluator=SlowSynthetic, show_progress=False)


class MarkedEpisode(EpisodeEvaluator):
    """The production episode evaluator, logging each finished evaluation like
    :class:`SlowSynthetic` (the real command's workers run it: ``_real_child``)."""

    def evaluate(self, query):
        try:
            return super().evaluate(query)
        finally:
            _mark(os.environ["ADV3D_BENCH_MARKERS"], query.unit)


def _real_child(out: str, markers: str, argv: str) -> None:
    """``adv3d ARGV --out OUT`` (the real command's code path: ``adv3d_runner.cli.main``) with
    the episode evaluator marking each finished query."""
    from adv3d_runner import cli
    from adv3d_runner.attack import driver

    os.environ["ADV3D_BENCH_MARKERS"] = markers
    _time_writes(markers)
    driver.run_attack.__kwdefaults__["evaluator"] = MarkedEpisode
    raise SystemExit(cli.main(json.loads(argv) + ["--out", out]))


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


def _writes(markers: Path) -> dict:
    """The journal writes of every process of a run (``_time_writes``' logs): their durations
    (ms), whether one had started and not ended (a kill during a write), and per query (unit
    key) the moment its first line was durable (the end of the write: after the fsync)."""
    ms: list[float] = []
    busy = False
    durable: dict[str, float] = {}
    for log in sorted(markers.parent.glob(markers.name + ".writes.*")):
        start = None
        for line in log.read_text().splitlines():
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "start":
                start = float(parts[1])
            elif parts[0] == "end":
                t = float(parts[1])
                if start is not None:
                    ms.append(1000 * (t - start))
                start = None
                if len(parts) >= 4 and parts[3] != "-":
                    durable[parts[3]] = min(t, durable.get(parts[3], t))
        busy = busy or start is not None
    return {"ms": ms, "busy": busy, "durable": durable}


def _key(unit) -> str:
    return json.dumps([round(float(v), 9) for v in np.asarray(unit, dtype=np.float64).reshape(-1)],
                      separators=(",", ":"))


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
        m = r.get("metrics")
        if isinstance(m, dict):  # the episode's own timings (strip_times)
            r["metrics"] = {k: v for k, v in m.items() if k not in ("ms_per_frame", "fps")}
        out.append(r)
    return out


def _markers(path: Path) -> tuple[list[tuple[str, float]], dict[str, float]]:
    """The finished queries a marker log names, in order ((unit key, when the worker had the
    result)), and when each marker was durable (its result about to leave the worker)."""
    every = [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []
    finished = [(_key(x[0]), x[1]) for x in every if x[0] != "durable"]
    left = {_key(x[1]): x[2] for x in every if x[0] == "durable"}
    return finished, left


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


def _finish(proc: subprocess.Popen, timeout: float = 900) -> None:
    _, err = proc.communicate(timeout=timeout)
    if proc.returncode != 0:
        raise SystemExit(f"attack failed ({proc.returncode}): {err.decode()[-2000:]}")


def _trials(child: list[str], env: dict, n: int, rng: np.random.Generator, work: Path, prefix: str,
            budget: int, label: str, window: str = "run") -> dict:
    """An uninterrupted run of ``child OUT MARKERS``, then ``n`` runs killed (``SIGKILL`` to the
    process group) at a seeded uniform moment after their first finished query: within 80 % of
    the rest of the uninterrupted run (``window="run"``), or, for the real command, whose best
    shape's closed-loop evaluation takes a good part of a run, until the uninterrupted run's
    last query finished (``"queries"``: every kill lands while queries are evaluated); each
    resumed to the end.

    Per kill: the queries finished at the kill (their worker had the result: a marker), those
    durable then (a journal or pending line written and fsynced: ``_time_writes``), those
    *lost* (in neither file after the kill), split into lost after being durable (a write the
    kill undid: must never happen) and lost in flight (the worker had the result, no line was
    durable yet), those the resume evaluated again, and whether the resumed journal equals the
    uninterrupted one (everything but wall times)."""
    ref = work / f"{prefix}reference"
    ref_markers = work / f"{prefix}reference.markers"
    t0, t0_wall = time.perf_counter(), time.time()
    proc = _start(child + [str(ref), str(ref_markers)], env)
    first_s = _wait_for([ref_markers], proc)
    _finish(proc)
    ref_s = time.perf_counter() - t0
    last_s = max(t for _, t in _markers(ref_markers)[0]) - t0_wall  # the last query finished
    span = 0.8 * (ref_s - first_s) if window == "run" else max(0.0, last_s - first_s)
    reference = _strip(_records(ref / "queries.jsonl"))
    assert len(reference) == budget, (len(reference), budget)
    ref_finished, ref_left = _markers(ref_markers)
    ref_writes = _writes(ref_markers)
    # how long a finished query waits until it is durable, in the uninterrupted run
    to_durable = [1000 * (ref_writes["durable"][k] - t) for k, t in ref_finished if k in ref_writes["durable"]]
    write_ms = list(ref_writes["ms"])
    trials = []
    for k in range(n):
        out, markers = work / f"{prefix}run{k}", work / f"{prefix}run{k}.markers"
        # kills land at a uniform moment of the evaluation phase: after the first query finished
        # (process start-up is not interesting), before the end of the run
        delay = float(rng.uniform(0.0, span))  # "run": 0.8, as runs end a little sooner than the reference
        proc = _start(child + [str(out), str(markers)], env)
        waited = _wait_for([markers], proc)
        time.sleep(delay)
        kill_at = waited + delay
        t_kill = time.time()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        finished, left = _markers(markers)
        writes = _writes(markers)
        write_ms += writes["ms"]
        finished_when = dict(finished)
        finished_keys = set(finished_when)
        durable = {q for q in finished_keys if writes["durable"].get(q, np.inf) <= t_kill}
        journal_keys = {_key(r["unit"]) for r in _records(out / "queries.jsonl")}
        pending_keys = {_key(r["unit"]) for r in _records(out / "queries.pending.jsonl")}
        lost = sorted(finished_keys - journal_keys - pending_keys)
        lost_durable = [q for q in lost if q in durable]
        in_flight = [q for q in lost if q not in durable]
        before = len(finished)
        _finish(_start(child + [str(out), str(markers)], env))  # resume to the end
        evaluated = [q for q, _ in _markers(markers)[0][before:]]
        redone = sorted(set(evaluated) & finished_keys)
        resumed = _strip(_records(out / "queries.jsonl"))
        lost_ms = [round(1000 * (t_kill - finished_when[q]), 1) for q in in_flight]
        # None: the worker's marker was not yet durable at the kill, so its result had not left it
        left_ms = [round(1000 * (t_kill - left[q]), 1) if q in left else None for q in in_flight]
        trials.append({"kill_after_s": round(kill_at, 3), "finished_at_kill": len(finished_keys),
                       "durable_at_kill": len(durable), "journalled": len(journal_keys),
                       # pending lines already moved to the journal count once
                       "pending": len(pending_keys - journal_keys),
                       "lost_finished": len(lost_durable), "lost_in_flight": len(in_flight),
                       "in_flight_ms_before_kill": lost_ms, "in_flight_left_worker_ms_before_kill": left_ms,
                       "driver_or_worker_writing_at_kill": writes["busy"],
                       "redone_by_resume": len(redone),
                       "redone_durable_by_resume": len(set(evaluated) & durable),
                       "evaluated_by_resume": len(evaluated),
                       "resumed_equals_uninterrupted": resumed == reference})
        print(f"{label} kill {k}: at {kill_at:.2f} s, {len(finished_keys)} finished ({len(durable)} durable), "
              f"{len(journal_keys)} journalled + {len(pending_keys - journal_keys)} only pending, lost "
              f"{len(lost_durable)} durable + {len(in_flight)} in flight {lost_ms} ms before the kill (left the "
              f"worker: {left_ms}){' (writing)' if writes['busy'] else ''}, redone {len(redone)}, equal "
              f"{resumed == reference}", flush=True)

    def stat(xs: list[float]) -> dict:
        return {"n": len(xs), "median": round(float(np.median(xs)), 2) if xs else None,
                "p99": round(float(np.percentile(xs, 99)), 1) if xs else None,
                "max": round(max(xs), 1) if xs else None}

    return {"reference_wall_s": round(ref_s, 2), "reference_first_query_s": round(first_s, 2),
            "reference_last_query_s": round(last_s, 2), "kill_window": window, "kill_window_s": round(span, 2),
            "journal_write_ms": stat(write_ms), "finished_to_durable_ms_uninterrupted": stat(to_durable),
            "trials": trials,
            "totals": {"kills": n, "kills_before_the_last_query": sum(t["finished_at_kill"] < budget for t in trials),
                       "finished_at_kill": sum(t["finished_at_kill"] for t in trials),
                       "durable_at_kill": sum(t["durable_at_kill"] for t in trials),
                       "lost_finished": sum(t["lost_finished"] for t in trials),
                       "lost_in_flight": sum(t["lost_in_flight"] for t in trials),
                       "in_flight_ms_before_kill_max": max((m for t in trials for m in t["in_flight_ms_before_kill"]),
                                                           default=None),
                       "in_flight_after_leaving_worker": sum(m is not None for t in trials
                                                             for m in t["in_flight_left_worker_ms_before_kill"]),
                       "redone_by_resume": sum(t["redone_by_resume"] for t in trials),
                       "redone_durable_by_resume": sum(t["redone_durable_by_resume"] for t in trials),
                       "resumed_equal": sum(t["resumed_equals_uninterrupted"] for t in trials)}}


def synthetic_trials(code: Path, n: int, rng: np.random.Generator, work: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{code}{os.pathsep}{ROOT / 'tests'}", "OMP_NUM_THREADS": "1"}
    me = [sys.executable, str(Path(__file__).resolve()), "--child"]
    return _trials(me, env, n, rng, work, "", BUDGET, "synthetic")


#: The real command's crash test: Autonomy-A on a bundled scene, 2 s episodes, 6 queries asked in
#: batches of 2 on 2 worker processes.
REAL_SCENE = "scenes/highway/highway-benchmark-000000.json.gz"
REAL_ARGS = {"autonomy": "A", "budget": 6, "seconds": 2, "workers": 2, "batch": 2, "seed": 3}


def real_trials(code: Path, n: int, rng: np.random.Generator, work: Path) -> dict:
    """Kills of the real command (``adv3d attack``, its evaluator marking finished queries)."""
    env = {**os.environ, "PYTHONPATH": f"{code}{os.pathsep}{ROOT / 'tests'}", "OMP_NUM_THREADS": "1"}
    argv = ["-q", "attack", str(ROOT / REAL_SCENE)] + [w for k, v in REAL_ARGS.items() for w in (f"--{k}", str(v))]
    me = [sys.executable, str(Path(__file__).resolve()), "--real-child", json.dumps(argv)]
    return {"command": "adv3d " + " ".join(argv) + " --out OUT",
            **_trials(me, env, n, rng, work, "real-", REAL_ARGS["budget"], "real", window="queries")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", nargs=2, metavar=("OUT", "MARKERS"), help=argparse.SUPPRESS)
    ap.add_argument("--real-child", nargs=3, metavar=("ARGV", "OUT", "MARKERS"), help=argparse.SUPPRESS)
    ap.add_argument("--kills", type=int, default=40, help="kills of the synthetic attack (0: none)")
    ap.add_argument("--real", type=int, default=0, help="kills of the real `adv3d attack` command")
    ap.add_argument("--code", type=Path, default=ROOT, help="the tree whose adv3d_runner is tested (default: this one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "crash_resume.json")
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return
    if args.real_child:
        argv, out, markers = args.real_child
        _real_child(out, markers, argv)
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
                  }
        if args.kills:
            result["synthetic"] = synthetic_trials(code, args.kills, rng, work)
        if args.real:
            result["real"] = real_trials(code, args.real, rng, work)
        result["load_at_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for part in ("synthetic", "real"):
        if part in result:
            print(part, json.dumps(result[part]["totals"]))


if __name__ == "__main__":
    main()
