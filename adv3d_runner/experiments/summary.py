"""docs/results.md's generated parts, from the kept tables alone: each finding's verdict with
its evidence (:func:`verdicts_markdown`) and the compute of every kept table with the
campaign's projected cost (:func:`compute_markdown`); :func:`fill_blocks` writes them between
``<!-- BEGIN generated: NAME -->`` and ``<!-- END generated: NAME -->`` markers, and a test
checks that the page holds what the kept files give (``adv3d experiments --docs``).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from .tables import TABLES, TableSpec, load_compute

#: Significance level of the verdicts (two-sided, after Holm's correction across the table).
ALPHA = 0.05


@dataclass(frozen=True)
class Finding:
    """A claim of the paper checked on a kept table: ``a`` is worse for the stack than ``b`` in
    ``metric`` (higher objective, lower AP ...), compared over scenes."""

    claim: str
    folder: str
    a: str
    b: str
    metric: str = "objective"


FINDINGS = (
    Finding("Table 1, B: closed-loop shapes beat open-loop ones", "shipped/table1_B_realistic", "Adv. closed-loop",
            "Adv. open-loop"),
    Finding("Table 1, B: the closed-loop attack hurts the stack", "shipped/table1_B_realistic", "Adv. closed-loop",
            "Original"),
    Finding("Table 1, B: the open-loop attack hurts the stack", "shipped/table1_B_realistic", "Adv. open-loop",
            "Original"),
    Finding("Table 1, B: the closed-loop attack lowers occupancy mAP", "shipped/table1_B_realistic",
            "Adv. closed-loop", "Original", "Occupancy mAP"),
    Finding("Table 1, A: closed-loop shapes beat open-loop ones", "shipped/table1_A_b20", "Adv. closed-loop",
            "Adv. open-loop"),
    Finding("Table 1, A: the closed-loop attack hurts the stack", "shipped/table1_A_b20", "Adv. closed-loop",
            "Original"),
    Finding("Table 1, A: closed-loop shapes beat open-loop ones", "table1_A_b20", "Adv. closed-loop", "Adv. open-loop"),
    Finding("Table 1, A: closed-loop shapes beat open-loop ones", "table1_A", "Adv. closed-loop", "Adv. open-loop"),
    Finding("Table 1, A: the closed-loop attack hurts the stack", "table1_A_b20", "Adv. closed-loop", "Original"),
    Finding("Table 1, A: the closed-loop attack hurts the stack", "table1_A", "Adv. closed-loop", "Original"),
    Finding("Table 1, A: the closed-loop attack lowers AP", "table1_A_b20", "Adv. closed-loop", "Original", "AP"),
    Finding("Table 1, A: the closed-loop attack lowers AP", "table1_A", "Adv. closed-loop", "Original", "AP"),
    Finding("Table 1, B: closed-loop shapes beat open-loop ones", "table1_B_b20", "Adv. closed-loop", "Adv. open-loop"),
    Finding("Table 1, B: closed-loop shapes beat open-loop ones", "table1_B", "Adv. closed-loop", "Adv. open-loop"),
    Finding("Table 1, B: the closed-loop attack hurts the stack", "table1_B_b20", "Adv. closed-loop", "Original"),
    Finding("Table 1, B: the closed-loop attack hurts the stack", "table1_B", "Adv. closed-loop", "Original"),
    Finding("Table 2: M0 in closed loop beats M0 in open loop", "table2_A_b20", "M0 closed-loop", "M0 open-loop"),
    Finding("Table 2: M0 beats the detection-only M1", "table2_A_b20", "M0 closed-loop", "M1 closed-loop"),
    Finding("Table 3: the latent attack as strong as VD 0.5 m", "table3_A_b20", "Adv3D (latent)", "VD 0.5 m"),
    Finding("Table 3: the latent attack hurts the stack", "table3_A_b20", "Adv3D (latent)", "Original"),
    Finding("Table 4: m = 5 actors hurt more than m = 1", "table4_A_b20", "m = 5", "m = 1"),
    Finding("Table 5: BO beats random search", "table5_A_b20", "BO", "RS"),
    Finding("Table 5: BO beats brute force over the library", "table5_A_b20", "BO", "Brute-Force"),
    Finding("Table 6: with reactive actors closed loop beats open loop", "table6_A_b20", "Adv. closed-loop (reactive)",
            "Adv. open-loop (reactive)"),
    Finding("Realism preset: the unconstrained attack is stronger", "realism_A_b20", "Unconstrained", "Realistic preset"),
    Finding("Transfer: A's closed-loop shapes hurt B", "transfer_B", "Adv. closed-loop (other stack's shapes)", "Original"),
    Finding("Transfer: B's closed-loop shapes hurt A", "transfer_A", "Adv. closed-loop (other stack's shapes)", "Original"),
)


def _fmt(x: float | None, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


def _table(root: Path, folder: str) -> dict | None:
    path = root / folder / "table.json"
    return json.loads(path.read_text()) if path.is_file() else None


def comparison(doc: dict, a: str, b: str, metric: str) -> dict | None:
    """A kept table's paired comparison a - b in ``metric`` (None when it has none)."""
    return next((c for c in doc.get("comparisons", []) if (c["a"], c["b"], c["metric"]) == (a, b, metric)), None)


def verdict(c: dict, lower_is_worse: bool) -> str:
    """A finding's verdict from its comparison: ``supported`` (Holm p <= 0.05 in the claimed
    direction), ``not after correction`` (p <= 0.05 alone), ``underpowered`` (the design
    detects no difference), ``opposite`` (significant the other way) or ``not shown``."""
    worse = (c["mean_diff"] < 0) if lower_is_worse else (c["mean_diff"] > 0)
    if c.get("mde_80") is None:
        return f"underpowered ({c['n']} scenes: no difference detectable)"
    if c.get("p_holm") is not None and c["p_holm"] <= ALPHA:
        return "supported" if worse else "opposite"
    if c["p_permutation"] <= ALPHA:
        return "not after correction"
    return "not shown"


def verdicts_markdown(root: Path) -> str:
    """The findings table: per :data:`FINDINGS` entry kept under ``root``, its table's stack
    (planner), size and budget, the mean difference with its interval, the count of scenes
    where a is worse, the permutation p, Holm's p across the table's tests, the smallest
    difference the design detects at 80 % power, and the verdict."""
    from ..attack.protocol import LOWER_IS_WORSE

    lines = ["| finding (the paper's) | kept table | planner | scenes x run seeds, budget | metric | mean Δ [95 % CI] "
             "| a worse | p | p Holm (tests) | MDE 80 % | scenes for Δ | verdict |",
             "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for f in FINDINGS:
        doc = _table(root, f.folder)
        c = comparison(doc, f.a, f.b, f.metric) if doc else None
        if c is None:
            continue
        proto = doc.get("protocol", {})
        seeds = sorted({s for r in doc["rows"].values() for s in r["seeds"]})
        planner = (doc.get("versions") or {}).get("planner", "?")
        m = (doc.get("multiplicity") or {}).get("m", "?")
        ci = f"{_fmt(c['mean_diff'])} [{_fmt(c['ci'][0])}, {_fmt(c['ci'][1])}]"
        lines.append(f"| {f.claim} | `{f.folder}` | `{planner}` | {c['n']} x {len(seeds)}, {proto.get('budget')} | "
                     f"{f.metric} | {ci} | {c['worse_for_stack']}/{c['n']} | {_fmt(c['p_permutation'])} | "
                     f"{_fmt(c.get('p_holm'))} ({m}) | {_fmt(c.get('mde_80'))} | "
                     f"{c.get('scenes_to_detect_80') or '-'} | {verdict(c, f.metric in LOWER_IS_WORSE)} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ compute

def unit_episodes(spec: TableSpec, budget: int, eval_seeds: int, n_library: int = 28) -> dict[str, float]:
    """Closed-loop episodes of each unit (run seed, setting, scene: one sharded search) of a
    table, by setting: each search mode spends its budget (Table 5's algorithms their scaled
    budgets, brute force one query per library vehicle) and the original and each mode's best
    shape are evaluated on ``eval_seeds`` held-out seeds. A transfer unit spends only the
    held-out evaluations of the original and the two modes' shapes."""
    if spec.name == "transfer":
        return {"shapes": 3.0 * eval_seeds}
    out = {}
    for setting, knobs in spec.settings.items():
        modes = 2 if knobs.get("mode") == "both" else 1
        scale = spec.budget_scale.get(setting)
        b = n_library if scale == "all" else budget * (1.0 if scale is None else float(scale))
        out[setting] = modes * b + eval_seeds * (1 + modes)
    return out


def kept_rate(root: Path, folder: str) -> tuple[float, int, float] | None:
    """(CPU s, episodes, CPU s per episode) of a kept table folder from its compute records
    (queries and held-out evaluations of every invocation); None without records."""
    comp = load_compute(root / folder)
    inv = comp.get("invocations") or []
    episodes = sum(int(e.get("queries", 0)) + int(e.get("heldout_evaluations", 0)) for e in inv)
    if not inv or episodes == 0:
        return None
    cpu = float(comp["cpu_s_total"])
    return cpu, episodes, cpu / episodes


#: The full campaign the protocol asks for: Table 1 for the three stacks on the realistic
#: region and for A and B on the paper's box; the other tables for Autonomy-A; each at the
#: paper's budget on the scenes x run seeds below.
CAMPAIGN_SCENES, CAMPAIGN_SEEDS, CAMPAIGN_BUDGET, CAMPAIGN_EVAL_SEEDS = 30, 3, 100, 3
CAMPAIGN = (("table1", "A, realistic region", 1), ("table1", "B, realistic region", 1),
            ("table1", "C, realistic region", 1), ("table1", "A and B, the paper's box", 2),
            ("table2", "A", 1), ("table3", "A", 1), ("table4", "A", 1), ("table5", "A", 1), ("table6", "A", 1),
            ("realism", "A", 1), ("transfer", "A <-> B", 2))


def compute_markdown(root: Path, rate_folder: str, rate_scale: dict[str, float] | None = None,
                     nodes: tuple[int, ...] = (1, 8, 32), cores_per_node: int = 16) -> str:
    """Measured compute of every kept table, and the projected campaign.

    Args:
        root: the kept tables' folder (``docs/results``).
        rate_folder: the kept table (relative to ``root``) whose measured CPU s per episode
            prices the campaign (the shipped stack's).
        rate_scale: per campaign row label, a factor on that rate (e.g. Autonomy-C's slower
            episodes), each stated in the output.
    """
    rate_scale = rate_scale or {}
    lines = ["| kept table | planner | invocations | episodes (queries + held-out) | CPU-hours | CPU s / episode |",
             "|---|---|---:|---:|---:|---:|"]
    for table_json in sorted(root.glob("*/table.json")) + sorted(root.glob("*/*/table.json")):
        folder = str(table_json.parent.relative_to(root))
        r = kept_rate(root, folder)
        if r is None:
            continue
        doc = json.loads(table_json.read_text())
        planner = (doc.get("versions") or {}).get("planner", "older, not recorded")
        lines.append(f"| `{folder}` | `{planner}` | {doc['compute'].get('invocations')} | {r[1]} | "
                     f"{r[0] / 3600:.2f} | {r[2]:.2f} |")
    rate = kept_rate(root, rate_folder)
    if rate is None:
        return "\n".join(lines) + "\n"
    r0 = rate[2]
    lines += ["", f"Projected campaign at {CAMPAIGN_SCENES} scenes x {CAMPAIGN_SEEDS} run seeds, budget "
              f"{CAMPAIGN_BUDGET}, {CAMPAIGN_EVAL_SEEDS} held-out seeds, priced at r = {r0:.2f} CPU s per episode "
              f"(`{rate_folder}`, measured):", "",
              "| table | stacks | units (searches) | episodes | CPU-hours | longest unit, h |",
              "|---|---|---:|---:|---:|---:|"]
    total_cpu, longest, units_all = 0.0, 0.0, 0
    for name, label, copies in CAMPAIGN:
        per = unit_episodes(TABLES[name], CAMPAIGN_BUDGET, CAMPAIGN_EVAL_SEEDS)
        units = CAMPAIGN_SCENES * CAMPAIGN_SEEDS * copies * len(per)
        episodes = CAMPAIGN_SCENES * CAMPAIGN_SEEDS * copies * sum(per.values())
        r = r0 * rate_scale.get(label, 1.0)
        cpu_h = episodes * r / 3600
        unit_h = max(per.values()) * r / 3600
        total_cpu += cpu_h
        longest = max(longest, unit_h)
        units_all += units
        lines.append(f"| {name} | {label} | {units} | {episodes:.0f} | {cpu_h:.1f} | {unit_h:.2f} |")
    lines += [f"| all | | {units_all} | | {total_cpu:.0f} | {longest:.2f} |", ""]
    scaled = "; ".join(f"{k}: r x {v:g}" for k, v in rate_scale.items())
    if scaled:
        lines += [f"Rate factors: {scaled} (C: the mean query wall time of `{C_JOURNAL}` over the shipped A "
                  f"table's closed-loop search on the same scene, `{A_JOURNAL}`, two sittings at different loads; "
                  f"B, where its kept table is there: its measured CPU s per episode over A's).", ""]
    lines += ["Wall time: a unit (one run seed, setting and scene) is sequential (BO with batch 1 asks one query "
              "at a time), units are independent, so with c cores in all (one `--shard I/c` process per core, "
              "across machines sharing the kept folder) T = max(C / c, t_unit) with C the CPU-hours and t_unit "
              "the longest unit. On a Ray cluster the same holds with the shard processes started on its nodes "
              "(the driver has no Ray scheduler of its own units); Ray's per-query parallelism (`adv3d attack "
              "--ray-address`) helps only with `--batch` > 1, which is another protocol. T is a lower bound: "
              "shards whose units differ in length finish apart.", "",
              f"On N nodes of k cores: T(N) = max(C / (N k), t_unit) = max({total_cpu:.0f} / (N k), {longest:.2f}) h "
              f"(C and t_unit from the table above).", "",
              "| machine | cores c | wall time, h |", "|---|---:|---:|",
              f"| this machine | 2 | {max(total_cpu / 2, longest):.0f} ({max(total_cpu / 2, longest) / 24:.1f} days) |"]
    for n in nodes:
        c = n * cores_per_node
        lines.append(f"| {n}-node cluster, {cores_per_node} cores a node | {c} | {max(total_cpu / c, longest):.1f} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ the page

BLOCK = re.compile(r"(<!-- BEGIN generated: (?P<name>[a-z-]+) -->\n)(?P<body>.*?)(<!-- END generated: (?P=name) -->)",
                   re.S)


def mean_query_wall(path: Path, mode: str = "closed") -> float:
    """Mean ``wall_s`` of a journal's queries of one mode (plain or gzip JSON lines)."""
    import gzip

    raw = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    walls = [r["wall_s"] for r in map(json.loads, raw.decode().splitlines()) if r.get("mode") == mode]
    return sum(walls) / len(walls)


#: Autonomy-C's episode cost against Autonomy-A's, measured on one scene: the mean query wall
#: time of C's kept BO run and of the shipped A table's closed-loop search there.
C_JOURNAL = "autonomy_c_bo12/queries.jsonl"
A_JOURNAL = "shipped/table1_A_b20/runs/bo/seed0/highway-benchmark-000000/queries.jsonl.gz"


#: The kept tables whose measured CPU s per episode price the campaign: Autonomy-A's (every row
#: but B's) and Autonomy-B's (its row, as a factor on A's).
RATE_A, RATE_B = "shipped/table1_A_b20", "shipped/table1_B_realistic"

#: The shipped stack's kept tables, quoted whole on the page: generated block -> its tables.
SHIPPED = {"shipped-b": ("shipped/table1_B_realistic",), "shipped": ("shipped/table1_A_b20",)}


def stale_against(doc: dict) -> list[str]:
    """What of a kept table's stack differs from the stack in this checkout: the weights, the
    planner, the shape space or the stack's fingerprint (``tables.VERSION_KEYS``), each as
    ``"<what> <kept> (now <current>)"``; [] when it is the stack as it is now."""
    from .tables import VERSION_KEYS, model_versions

    kept = doc.get("versions") or {}
    now = model_versions(str(doc.get("autonomy") or (doc.get("protocol") or {}).get("autonomy")))
    out = []
    for key in VERSION_KEYS:
        a, b = kept.get(key), now.get(key)
        if a is None or a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{key} {k} `{a.get(k)}` (now `{b.get(k)}`)" for k in sorted(set(a) | set(b))
                    if a.get(k) != b.get(k) and k != "fingerprint"]
            if a.get("fingerprint") != b.get("fingerprint") and key == "stack":
                out.append(f"stack fingerprint `{a.get('fingerprint')}` (now `{b.get('fingerprint')}`)")
        else:
            out.append(f"{key} `{a}` (now `{b}`)")
    return out


def shipped_markdown(root: Path, folders: tuple[str, ...]) -> str:
    """The shipped stack's kept tables (their ``table.md``, headings one level down, the
    picture linked from the page's folder), each marked **stale** where the stack in this
    checkout is no longer the one it was made with (:func:`stale_against`)."""
    out = []
    for folder in folders:
        path = root / folder / "table.md"
        if not path.is_file():
            out.append(f"`{folder}`: not built yet.\n")
            continue
        text = path.read_text()
        stale = stale_against(json.loads((root / folder / "table.json").read_text()))
        if stale:
            head, _, rest = text.partition("\n")
            text = (head + "\n\n> **Stale:** made with a stack this checkout no longer ships: " + "; ".join(stale)
                    + ". Its numbers are of that stack; rerun the table's command to measure the shipped one.\n"
                    + rest)
        out.append(text.rstrip("\n") + "\n\n"
                   + f"![Held-out change against the original, scene by scene](results/{folder}/table.png)\n")
    return "\n".join(out)


def blocks(root: Path) -> dict[str, str]:
    """The generated blocks of docs/results.md, by name."""
    have = (root / C_JOURNAL).is_file() and (root / A_JOURNAL).is_file()
    c_factor = round(mean_query_wall(root / C_JOURNAL) / mean_query_wall(root / A_JOURNAL), 2) if have else 1.0
    scale = {"C, realistic region": c_factor}
    a_rate, b_rate = kept_rate(root, RATE_A), kept_rate(root, RATE_B)
    if a_rate and b_rate:  # B priced at its own measured rate
        scale["B, realistic region"] = round(b_rate[2] / a_rate[2], 2)
    return {"verdicts": verdicts_markdown(root), **{name: shipped_markdown(root, folders)
                                                    for name, folders in SHIPPED.items()},
            "compute": compute_markdown(root, RATE_A, rate_scale=scale)}


def write_docs(page: Path, root: Path) -> bool:
    """Fill ``page``'s generated blocks from the kept tables under ``root``; True when it
    changed."""
    from ..fileio import atomic_write_text

    text = page.read_text()
    new = fill_blocks(text, blocks(root))
    if new != text:
        atomic_write_text(page, new)
    return new != text


def fill_blocks(text: str, generated: dict[str, str]) -> str:
    """``text`` with every generated block's body replaced by ``generated[name]``."""
    def sub(m: re.Match) -> str:
        body = generated.get(m["name"])
        return m.group(0) if body is None else m.group(1) + body + m.group(4)

    return BLOCK.sub(sub, text)
