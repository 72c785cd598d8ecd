"""Start-up cost of the ``adv3d`` command: what a person waits for before any work.

    .venv/bin/python bench/startup.py [--repeat 5] [--root CHECKOUT [--root CHECKOUT2 ...]] [--only TEXT] [--out FILE]

Runs, ``--repeat`` times each, in subprocesses of this interpreter (``python -m
adv3d_runner.cli``, the code of ``--root``, default this checkout; given several ``--root``, the
runs of each command alternate between them, so that they share the machine's load, and the
file holds each one's figures under ``roots``, the first one's also under ``results``):

* ``adv3d --help`` and ``adv3d SUB --help`` for a fixed set of subcommands;
* ``adv3d simulate highway-benchmark-000000 --seconds 0.1`` with Autonomy-A and with the
  oracle stack (the fixed cost of an episode: imports, scene, world, stack, one frame), after
  one unmeasured run that fills the caches (numba's, the mesh cache);
* ``python -c "import M"`` of the heavy modules (numpy, torch, numba, scipy.optimize, trimesh).

Each figure is the median CPU seconds (user + system of the child, ``os.wait4``) and the median
wall seconds; the machine is shared, so CPU time is the figure to compare. Also records the
heaviest imports of ``simulate`` (``-X importtime``, top level). Writes ``bench/results/
startup.json`` unless ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

HELP = (["--help"], ["simulate", "--help"], ["attack", "--help"], ["shapes", "build", "--help"],
        ["train", "detector", "--help"], ["scenes", "--help"], ["numerics", "--help"])
IMPORTS = ("numpy", "torch", "numba", "scipy.optimize", "trimesh")


def run(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float, int]:
    """(CPU s of the child, wall s, exit code)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_utime + usage.ru_stime, wall, proc.returncode


def measure(cmd: list[str], cwd: Path, env: dict, repeat: int) -> dict:
    return summarize([run(cmd, cwd, env) for _ in range(repeat)], repeat)


def measure_alternating(cmds: list[tuple[list[str], Path, dict]], repeat: int) -> list[dict]:
    """:func:`measure` of each (cmd, cwd, env), their runs alternating."""
    runs: list[list] = [[] for _ in cmds]
    for _ in range(repeat):
        for k, (cmd, cwd, env) in enumerate(cmds):
            runs[k].append(run(cmd, cwd, env))
    return [summarize(r, repeat) for r in runs]


def summarize(runs: list[tuple[float, float, int]], repeat: int) -> dict:
    if any(rc != 0 for _, _, rc in runs):  # e.g. a command the measured checkout does not have
        return {"failed": f"exit {max(rc for _, _, rc in runs)}", "runs": repeat}
    cpu = [c for c, _, _ in runs]
    wall = [w for _, w, _ in runs]
    return {"cpu_s_median": statistics.median(cpu), "cpu_s_min": min(cpu), "cpu_s_max": max(cpu),
            "wall_s_median": statistics.median(wall), "runs": repeat}


def top_imports(cmd: list[str], cwd: Path, env: dict, n: int = 8) -> list[tuple[str, float]]:
    """The ``n`` costliest top-level imports of ``cmd`` (cumulative s, ``-X importtime``)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", *cmd], cwd=cwd, env=env, capture_output=True, text=True)
    out = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, cum, name = line.split("|")
        if not name.startswith("  "):  # top level: one space of indentation
            out.append((name.strip(), int(cum) / 1e6))
    return sorted(out, key=lambda x: -x[1])[:n]


def _commit(root: Path) -> str:
    """The checkout's commit, with ``+changes`` where its tracked files differ from it."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=root).returncode != 0
    return head + ("+changes" if dirty else "")


def main() -> int:
    from adv3d_runner.machine import machine_info

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--root", type=Path, action="append", default=None,
                    help="checkout whose code runs (default this one); repeat to compare checkouts side by side")
    ap.add_argument("--only", default=None, help="measure only the commands whose name holds this text")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "startup.json")
    args = ap.parse_args()
    roots = [r.resolve() for r in (args.root or [ROOT])]
    envs = [{**os.environ, "PYTHONPATH": str(root)} for root in roots]
    py = [sys.executable]
    doc: dict = {"format": "adv3d.bench", "topic": "startup",
                 "command": " ".join([Path(sys.executable).name, "bench/startup.py"] + sys.argv[1:]),
                 "code": str(roots[0]), "commit": _commit(roots[0]),
                 "machine": machine_info("numpy", "torch"),
                 "load_average_at_start": list(os.getloadavg()),
                 "bytecode_cache_written": not os.environ.get("PYTHONDONTWRITEBYTECODE"),
                 "timing": "CPU s (user + system) of each child process, median of --repeat runs; wall s median"}
    results: list[dict] = [{} for _ in roots]

    def record(name: str, cmds: list[list[str]]) -> None:
        if args.only and args.only not in name:
            return
        got = measure_alternating([(cmd, root, env) for cmd, root, env in zip(cmds, roots, envs)], args.repeat)
        for res, r in zip(results, got):
            res[name] = r
        print(f"{name:32s} " + "  ".join(f"{r['cpu_s_median']:6.2f} CPU-s {r['wall_s_median']:6.2f} s"
                                         if "failed" not in r else r["failed"] for r in got), flush=True)

    for words in HELP:
        record("adv3d " + " ".join(words), [[*py, "-m", "adv3d_runner.cli", *words] for _ in roots])
    with tempfile.TemporaryDirectory(prefix="adv3d-startup-") as tmp:
        for stack in ("A", "oracle"):
            cmds = [[*py, "-m", "adv3d_runner.cli", "-q", "simulate",
                     str(root / "scenes" / "highway" / "highway-benchmark-000000.json.gz"), "--seconds", "0.1",
                     "--autonomy", stack, "--out", str(Path(tmp) / f"{stack}{k}")] for k, root in enumerate(roots)]
            if args.only and args.only not in f"adv3d simulate --autonomy {stack}":
                continue
            for cmd, root, env in zip(cmds, roots, envs):
                run(cmd, root, env)  # fills the caches
            record(f"adv3d simulate highway-benchmark-000000 --seconds 0.1 --autonomy {stack}", cmds)
            doc.setdefault("simulate_top_imports_s", {})[stack] = top_imports(cmds[0][1:], roots[0], envs[0])
    for module in IMPORTS:
        record(f"import {module}", [[*py, "-c", f"import {module}"] for _ in roots])
    doc["load_average_at_end"] = list(os.getloadavg())
    doc["results"] = results[0]
    if len(roots) > 1:
        doc["roots"] = [{"code": str(root), "commit": _commit(root), "results": res} for root, res in zip(roots, results)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
