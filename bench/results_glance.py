"""One picture of every kept paper table's headline comparisons (docs/results.md, "At a glance").

    .venv/bin/python bench/results_glance.py [--results docs/results] [--out docs/results/glance.png]

Reads each ``<results>/<folder>/table.json`` (the protocol's tables, as ``bench/paper_tables.py``
wrote them; sub-folders such as ``previous-detector/`` are not tables of the current models) and
draws, for every paired comparison of the **objective** the table holds, the mean per-scene
difference a - b with its 95 % bootstrap interval over scenes, annotated with the scenes where a
is worse for the stack and the permutation p-value. Nothing is recomputed: the values are the
table's own ``comparisons``; the picture only lines them up.

Two panels, because the two stacks' objectives are on other scales (Autonomy-A: detection,
prediction summed over 60 waypoints x 0.1, plan x 0.5; Autonomy-B: occupancy, flow EPE, plan):
a row goes to the panel of the stack that was *evaluated* (a transfer table's shapes come from
the other stack). Writes the PNG and ``glance.json`` (the plotted rows) next to it.
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.errors import ConfigError  # noqa: E402
from adv3d_runner.fileio import atomic_write_bytes, write_json  # noqa: E402

# Reading order of the tables in the picture (the order of docs/results.md's "At a glance").
TABLE_ORDER = ("table1", "table2", "table3", "table4", "table5", "table6", "realism", "transfer")


def table_label(doc: dict, folder: str) -> str:
    """Short name of a kept table: its number or kind, stack, and budget, e.g. ``T1-A b100``."""
    kind = doc["table"]
    name = {"realism": "Realism", "transfer": "Transfer"}.get(kind, "T" + kind.removeprefix("table"))
    stack = doc["autonomy"]
    if kind == "transfer":
        stack = f"{doc['protocol'].get('transfer_from', '?')}->{stack}"
    return f"{name}-{stack} b{doc['protocol']['budget']}"


def glance_rows(results: Path) -> list[dict]:
    """The objective comparisons of every table folder directly under ``results``.

    Returns:
        One dict per comparison, in :data:`TABLE_ORDER` then folder then the table's own order:
        ``folder, label, autonomy`` (the evaluated stack), ``a, b, n`` (scenes), ``mean, lo, hi``
        (objective units of that stack), ``worse`` (scenes where a is worse for the stack),
        ``p`` (two-sided paired permutation p).

    Raises:
        ConfigError: a table.json that is not a paper table, or a comparison without its fields.
    """
    rows = []
    folders = sorted(p.parent for p in Path(results).glob("*/table.json"))
    for folder in folders:
        path = folder / "table.json"
        doc = json.loads(path.read_text())
        if doc.get("format") != "adv3d-paper-table":
            raise ConfigError(f"{path}: format is {doc.get('format')!r}, not 'adv3d-paper-table'")
        label = table_label(doc, folder.name)
        for c in doc.get("comparisons", []):
            if c.get("metric") != "objective":
                continue
            missing = [k for k in ("a", "b", "n", "mean_diff", "ci", "worse_for_stack", "p_permutation") if k not in c]
            if missing:
                raise ConfigError(f"{path}: a comparison lacks {', '.join(missing)}")
            rows.append({"folder": folder.name, "label": label, "table": doc["table"], "autonomy": doc["autonomy"],
                         "a": c["a"], "b": c["b"], "n": int(c["n"]), "mean": float(c["mean_diff"]),
                         "lo": float(c["ci"][0]), "hi": float(c["ci"][1]),
                         "worse": int(c["worse_for_stack"]), "p": float(c["p_permutation"])})
    rank = {t: i for i, t in enumerate(TABLE_ORDER)}
    rows.sort(key=lambda r: (rank.get(r["table"], len(rank)), r["folder"]))  # stable: the table's own order kept
    return rows


def _short(name: str) -> str:
    """Row names shortened for a tick label."""
    return (name.replace("Adv. ", "").replace(" (other stack's shapes)", "*").replace("-loop", "")
            .replace("Adv3D (latent)", "latent").replace("Realistic preset", "preset"))


def draw(rows: list[dict], path: Path) -> None:
    """The forest plot of ``rows`` (from :func:`glance_rows`), one panel per evaluated stack."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stacks = [s for s in ("A", "B") if any(r["autonomy"] == s for r in rows)]
    if not stacks:
        raise ConfigError("no objective comparisons to draw: no kept table found")
    heights = [sum(r["autonomy"] == s for r in rows) for s in stacks]
    fig, axes = plt.subplots(len(stacks), 1, figsize=(8.5, 0.24 * sum(heights) + 1.6 * len(stacks)),
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    for ax, stack in zip(axes[:, 0], stacks):
        mine = [r for r in rows if r["autonomy"] == stack]
        ys = list(range(len(mine)))[::-1]
        for y, r in zip(ys, mine):
            strong = r["p"] <= 0.05
            colour = "tab:red" if strong else ("tab:orange" if r["mean"] > 0 else "tab:blue")
            ax.plot([r["lo"], r["hi"]], [y, y], color=colour, lw=1.6)
            ax.plot(r["mean"], y, "o", color=colour, ms=4)
            ax.annotate(f"{r['worse']}/{r['n']}, p = {r['p']:.2g}", (1.0, y), xycoords=("axes fraction", "data"),
                        xytext=(4, 0), textcoords="offset points", va="center", fontsize=6.5)
        ax.axvline(0.0, color="0.5", lw=0.8)
        ax.set_yticks(ys, [f"{r['label']}: {_short(r['a'])} - {_short(r['b'])}" for r in mine], fontsize=6.5)
        ax.set_ylim(-0.7, len(mine) - 0.3)
        ax.set_xlabel(f"held-out objective difference, Autonomy-{stack}'s objective (higher = worse for the stack)",
                      fontsize=7.5)
        ax.tick_params(axis="x", labelsize=7)
    # a figure title, wrapped to the figure's width: over the axes it was centred right of the long
    # tick labels and ran off the canvas
    fig.suptitle("\n".join(textwrap.wrap(
        "Every kept table's objective comparisons: mean over scenes, 95 % bootstrap CI; red: p <= 0.05, "
        "orange: mean > 0, blue: mean < 0 (scenes where a is worse / scenes, permutation p: with n scenes it "
        "cannot go below 2/2^n; * = the other stack's shapes)", width=int(15 * fig.get_figwidth()))), fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", default=str(ROOT / "docs" / "results"), help="folder of kept tables")
    p.add_argument("--out", default=None, help="PNG to write (default: <results>/glance.png)")
    args = p.parse_args(argv)
    results = Path(args.results)
    out = Path(args.out) if args.out else results / "glance.png"
    try:
        rows = glance_rows(results)
        draw(rows, out)
    except ConfigError as exc:
        print(f"results_glance: {exc}", file=sys.stderr)
        return 2
    write_json(out.with_suffix(".json"), {"format": "adv3d-results-glance", "version": 1,
                                          "command": "python bench/results_glance.py", "rows": rows})
    for r in rows:
        print(f"{r['label']:<16} {r['a']} - {r['b']}: {r['mean']:+.1f} [{r['lo']:.1f}, {r['hi']:.1f}] "
              f"{r['worse']}/{r['n']} p = {r['p']:.3g}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
