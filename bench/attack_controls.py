"""What in the best adversarial shape hurts the stack: its size, its form, or being a decoded shape?

    .venv/bin/python bench/attack_controls.py [RUN ...] [--mode closed] [--scenes N] [--out FILE]

For every scene of the given attack runs (default ``runs/bo100``) with a best shape in ``--mode``,
evaluates in closed loop (same scene, seconds, seed, autonomy and objective as the run):

* ``mean``: the shape space's mean shape (latents 0) at nominal size (scales 1, 1): the effect of
  swapping the actor's library asset for a decoded SDF shape at all;
* ``size only``: mean form, the best shape's width and length scales;
* ``form only``: the best shape's latents at nominal size;
* ``best``: the best shape itself (a re-simulation: it must reproduce the run's own closed-loop
  evaluation exactly, which this script checks).

Prints per variant the paired change against the original scene (mean ± std over scenes) and
writes ``bench/results/attack_controls.json``. About 4 episodes per scene, ~15 s per scene.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.config import AttackConfig  # noqa: E402
from adv3d_runner.attack.evaluator import SceneWorkspace  # noqa: E402
from adv3d_runner.attack.journal import read_run  # noqa: E402
from adv3d_runner.fileio import atomic_write_text  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402

VARIANTS = ("mean", "size only", "form only", "best")
METRICS = (("objective", None, 1.0), ("AP %", ("detection", "ap"), 100.0), ("recall %", ("detection", "recall"), 100.0),
           ("minADE m", ("prediction", "min_ade"), 1.0), ("meanADE m", ("prediction", "mean_ade"), 1.0),
           ("drive jerk", ("driving_comfort", "jerk"), 1.0))


def variant_units(space, best: np.ndarray) -> dict[str, np.ndarray]:
    """(m, K+2) best unit vectors -> the four variants, same shape each."""
    k = space.k
    neutral = space.latent_to_unit(np.zeros(k), (1.0, 1.0))
    out = {"mean": np.tile(neutral, (len(best), 1)), "best": best.copy()}
    out["size only"] = out["mean"].copy()
    out["size only"][:, k:] = best[:, k:]
    out["form only"] = best.copy()
    out["form only"][:, k:] = neutral[k:]
    return out


def metric(record: dict, path: tuple[str, str] | None, scale: float) -> float:
    if path is None:
        return float(record["cost"])
    value = record["metrics"].get(path[0], {}).get(path[1])
    return float(value) * scale if isinstance(value, (int, float)) else float("nan")


def evaluate_run(run_dir: Path, mode: str, limit: int | None = None) -> list[dict]:
    run, _, summary = read_run(run_dir)
    settings = AttackConfig.from_run_json(run).settings
    rows = []
    for ref, sid in list(zip(run["scenes"], run["scene_ids"]))[:limit]:
        entry = summary.get("scenes", {}).get(sid, {})
        m = entry.get("modes", {}).get(mode)
        if not m or "best_unit" not in m or "original" not in entry:
            print(f"  {sid}: no {mode} result in {run_dir}, skipped")
            continue
        t0 = time.perf_counter()
        ctx = SceneWorkspace(str(ROOT / ref) if not Path(ref).is_absolute() else ref, settings)
        best = np.asarray(m["best_unit"], dtype=np.float64).reshape(len(entry["targets"]), -1)
        row = {"scene": sid, "run": str(run_dir), "original": entry["original"],
               "recorded_best": m["closed_loop_eval"], "units": {}, "variants": {}}
        for name, units in variant_units(ctx.space, best).items():
            record, _ = ctx.evaluate(units.reshape(-1), closed_loop=True)
            row["units"][name] = units.tolist()
            row["variants"][name] = {"cost": record.cost, "metrics": record.metrics, "dimensions": record.dimensions}
        row["best_reproduced"] = bool(np.isclose(row["variants"]["best"]["cost"], m["closed_loop_eval"]["cost"],
                                                 rtol=0, atol=1e-9))
        rows.append(row)
        print(f"  {sid}: " + ", ".join(f"{n} {row['variants'][n]['cost']:.1f}" for n in VARIANTS)
              + f" (original {entry['original']['cost']:.1f}; best reproduced: {row['best_reproduced']}; "
              f"{time.perf_counter() - t0:.0f} s)")
    return rows


def paired_table(rows: list[dict]) -> list[dict]:
    table = []
    for name in VARIANTS:
        cells = {"variant": name}
        for label, path, scale in METRICS:
            d = np.array([metric(r["variants"][name], path, scale) - metric(r["original"], path, scale) for r in rows])
            d = d[np.isfinite(d)]
            cells[label] = {"mean": float(d.mean()), "std": float(d.std()), "n": int(len(d))} if len(d) else None
        table.append(cells)
    return table


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", default=["runs/bo100"], help="attack run folders (default runs/bo100)")
    parser.add_argument("--mode", default="closed", choices=("closed", "open"), help="whose best shapes (default closed)")
    parser.add_argument("--scenes", type=int, default=None, help="only the first N scenes of each run")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "attack_controls.json"))
    args = parser.parse_args()
    info = machine_info("numpy", "embreex", "torch")
    rows = []
    for run_dir in args.runs:
        print(f"{run_dir} [{args.mode}]")
        rows += evaluate_run(Path(run_dir), args.mode, args.scenes)
    if not rows:
        print("no scenes with results", file=sys.stderr)
        return 1
    table = paired_table(rows)
    print(f"\nPaired change against the original, closed loop, {len(rows)} scenes (mean ± std)")
    print(f"{'variant':<11}" + "".join(f"{label:>18}" for label, _, _ in METRICS))
    for cells in table:
        print(f"{cells['variant']:<11}" + "".join(
            f"{cells[label]['mean']:>+10.3g} ± {cells[label]['std']:<5.2g}" if cells[label] else f"{'-':>18}"
            for label, _, _ in METRICS))
    print(f"best shape reproduced exactly on {sum(r['best_reproduced'] for r in rows)}/{len(rows)} scenes")
    doc = {"format": "adv3d-bench", "topic": "attack_controls",
           "command": "python bench/attack_controls.py " + " ".join(sys.argv[1:]), "machine": info,
           "mode": args.mode, "table": table, "scenes": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
