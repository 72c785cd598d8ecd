"""Does a larger search budget find stronger shapes? Two kept folders of the same table (say
``table1_A_b100`` and ``table1_A_b20``), compared row by row on the scenes and run seeds they
share, with the protocol's held-out evaluations and paired statistics.

    .venv/bin/python bench/budget_effect.py docs/results/table1_A_b100 docs/results/table1_A_b20

Both folders hold the same held-out seeds for a scene and run seed (they derive from the run
seed and the scene alone), so the ``Original`` row must agree exactly: the script checks it and
stops otherwise. Per row and metric it reports the per-scene mean of each folder (over the
shared run seeds and their evaluation seeds) and the paired difference a - b over scenes: mean,
95 % bootstrap interval, scenes where a is worse for the stack, and the permutation p-value.

Writes ``budget_effect.json`` and ``budget_effect.md`` into the first folder and prints the
markdown.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.attack.protocol import LOWER_IS_WORSE, metric_value, metrics_for, scene_means  # noqa: E402
from adv3d_runner.errors import ConfigError  # noqa: E402
from adv3d_runner.fileio import atomic_write_text, write_json  # noqa: E402
from adv3d_runner.metrics.stats import paired_summary  # noqa: E402


def _driver():
    """bench/paper_tables.py as a module (it is a script, not a package member)."""
    spec = importlib.util.spec_from_file_location("paper_tables", ROOT / "bench" / "paper_tables.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("paper_tables", mod)
    spec.loader.exec_module(mod)
    return mod


def _table_of(folder: Path) -> tuple[str, int, str]:
    """(table name, budget, autonomy) of a kept folder, from its protocol.json."""
    path = folder / "protocol.json"
    if not path.exists():
        raise ConfigError(f"{path}: no protocol.json (is {folder} a kept table folder?)")
    proto = json.loads(path.read_text())
    for field in ("table", "budget", "autonomy"):
        if field not in proto:
            raise ConfigError(f"{path}: field {field!r} is missing")
    return proto["table"], int(proto["budget"]), proto["autonomy"]


def row_values(rows: dict, name: str, seeds: set[int], metric: str) -> dict[str, float]:
    """Per scene the mean of ``metric`` over the held-out records of the run seeds ``seeds``."""
    return scene_means(((e["scene"], r) for e in rows.get(name, []) if e["seed"] in seeds for r in e["heldout"]),
                       lambda r: metric_value(r, metric))


def compare(a: Path, b: Path) -> dict:
    """Row by row, metric by metric: folder ``a`` against folder ``b`` on their shared scenes and
    run seeds (see the module docstring)."""
    mod = _driver()
    (table_a, budget_a, auto_a), (table_b, budget_b, auto_b) = _table_of(a), _table_of(b)
    if (table_a, auto_a) != (table_b, auto_b):
        raise ConfigError(f"{a} holds {table_a} for {auto_a}, {b} {table_b} for {auto_b}: compare two folders "
                          f"of one table and stack")
    spec = mod.TABLES[table_a]
    rows_a, rows_b = mod.collect(spec, mod.load_kept(a)), mod.collect(spec, mod.load_kept(b))
    runs_a = {(e["scene"], e["seed"]) for es in rows_a.values() for e in es}
    runs_b = {(e["scene"], e["seed"]) for es in rows_b.values() for e in es}
    shared = runs_a & runs_b
    if not shared:
        raise ConfigError(f"{a} and {b} share no scene and run seed")
    seeds = {s for _, s in shared}
    scenes = sorted({sc for sc, _ in shared})
    # the originals are the same episodes on the same held-out seeds: they must agree exactly
    for sc, s in sorted(shared):
        ka = {r["seed"]: r["cost"] for e in rows_a.get("Original", []) if (e["scene"], e["seed"]) == (sc, s)
              for r in e["heldout"]}
        kb = {r["seed"]: r["cost"] for e in rows_b.get("Original", []) if (e["scene"], e["seed"]) == (sc, s)
              for r in e["heldout"]}
        if ka != kb:
            raise ConfigError(f"{sc} run seed {s}: the originals differ between {a} and {b} (another stack, "
                              f"other held-out seeds or another machine): the two budgets do not compare")
    out = {"a": str(a), "b": str(b), "table": table_a, "budget_a": budget_a, "budget_b": budget_b,
           "scenes": scenes, "run_seeds": sorted(seeds), "rows": {}}
    for name in spec.rows:
        if name == "Original" or not rows_a.get(name) or not rows_b.get(name):
            continue
        out["rows"][name] = {}
        for metric in metrics_for(auto_a):
            va, vb = row_values(rows_a, name, seeds, metric), row_values(rows_b, name, seeds, metric)
            pa = [va.get(sc, np.nan) for sc in scenes]
            pb = [vb.get(sc, np.nan) for sc in scenes]
            s = paired_summary(pa, pb)
            worse = s["less"] if metric in LOWER_IS_WORSE else s["greater"]
            out["rows"][name][metric] = {"a_mean": float(np.nanmean(pa)), "b_mean": float(np.nanmean(pb)),
                                         "mean_diff": s["mean_diff"], "ci": s["ci"], "n": s["n"],
                                         "a_worse_for_stack": int(worse), "p_permutation": s["p_permutation"]}
    return out


def markdown(res: dict) -> str:
    """The comparison as a markdown table."""
    ba, bb = res["budget_a"], res["budget_b"]
    lines = [f"Budget {ba} against budget {bb} ({res['table']}; {len(res['scenes'])} scenes, run seeds "
             f"{', '.join(map(str, res['run_seeds']))}; held-out closed-loop evaluations, per scene the mean over "
             f"the shared run seeds and their evaluation seeds; Original agrees exactly).", "",
             f"| row | metric | budget {bb} | budget {ba} | Δ = {ba} - {bb} [95 % CI] | scenes where {ba} is worse "
             f"for the stack | p (permutation) |", "|---|---|---:|---:|---:|---:|---:|"]
    for name, metrics in res["rows"].items():
        for metric, m in metrics.items():
            lines.append(f"| {name} | {metric} | {m['b_mean']:.4g} | {m['a_mean']:.4g} | {m['mean_diff']:.3g} "
                         f"[{m['ci'][0]:.3g}, {m['ci'][1]:.3g}] | {m['a_worse_for_stack']}/{m['n']} | "
                         f"{m['p_permutation']:.3g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="kept table folder, e.g. docs/results/table1_A_b100")
    p.add_argument("b", type=Path, help="the same table at another budget, e.g. docs/results/table1_A_b20")
    args = p.parse_args(argv)
    try:
        res = compare(args.a, args.b)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    md = markdown(res)
    write_json(args.a / "budget_effect.json", res)
    atomic_write_text(args.a / "budget_effect.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
