"""Fuzz figures for docs/reliability.md: the hostile-input cases of ``tests/fuzz_contracts.py``
run on every file contract and the CLI's numeric options, with their outcomes counted.

    .venv/bin/python bench/fuzz.py                 # 300 cases per contract, 2000 command lines
    .venv/bin/python bench/fuzz.py --examples 20   # quick look

Cases are derandomized (hypothesis ``derandomize=True``): the same command gives the same
cases and counts. Outcomes: ``error`` (one line naming the file, and the field where there is
one), ``accepted`` (the file was valid after all, or the change was to a free-form field; the
accepted data passed the contract's checks: exact round trip, finite, in bounds), and the
findings ``crash`` / ``vague`` / ``bad-accept`` (each listed with its case). Also the special
files (device, FIFO, folder, sparse giant, gzip and zip bombs, symlink loop, dangling
symlink) with the time each refusal took. Results: ``bench/results/fuzz.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from fuzz_contracts import CONTRACTS, fuzz_cli, fuzz_contract, run_case, special_files  # noqa: E402

from adv3d_runner.machine import machine_info  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=300, help="cases per file contract")
    ap.add_argument("--cli-examples", type=int, default=2000, help="command lines")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "fuzz.json")
    args = ap.parse_args()
    warnings.simplefilter("ignore")  # commonroad-io and shapely warn about the broken scenarios
    result: dict = {"command": "bench/fuzz.py " + " ".join(sys.argv[1:]), "machine": machine_info("hypothesis", "numpy", "trimesh", "commonroad-io"),
                    "contracts": {}, "findings": []}
    total = Counter()
    for name in [*sorted(CONTRACTS), "cli"]:
        counts, findings, accepted = Counter(), [], []
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="adv3d-fuzz-") as tmp:
            if name == "cli":
                fuzz_cli(args.cli_examples, counts, findings, accepted)
            else:
                fuzz_contract(name, Path(tmp), args.examples, counts, findings, accepted=accepted)
        wall = time.perf_counter() - t0
        result["contracts"][name] = {"cases": sum(counts.values()), **dict(sorted(counts.items())),
                                     "wall_s": round(wall, 1), "accepted_examples": accepted[:12]}
        result["findings"] += findings
        total.update(counts)
        print(f"{name:24s} {dict(sorted(counts.items()))}  {wall:.1f} s", flush=True)
    result["total"] = {"cases": sum(total.values()), **dict(sorted(total.items()))}
    special = {}
    with tempfile.TemporaryDirectory(prefix="adv3d-fuzz-") as tmp:
        from adv3d_runner.scene.schema import load_scene
        from adv3d_runner.validate import read_npz

        for what, path in special_files(Path(tmp)).items():
            load = (lambda p=path: read_npz(p, "points file")) if path.suffix == ".npz" else (lambda p=path: load_scene(p))
            t0 = time.perf_counter()
            outcome = run_case(load, lambda r: None, path, what)
            special[what] = {"outcome": outcome.kind, "message": outcome.message,
                             "ms": round(1000 * (time.perf_counter() - t0), 1)}
            print(f"{what:40s} {outcome.kind}  {special[what]['ms']} ms", flush=True)
    result["special_files"] = special
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["total"]))


if __name__ == "__main__":
    main()
