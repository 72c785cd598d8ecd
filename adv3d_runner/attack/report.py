"""``adv3d report``: a markdown report of one or more attack runs.

Sections: the paper's Table 1 (Original / Adv. open-loop / Adv. closed-loop, every shape
evaluated in closed loop: AP, recall, minADE, meanADE, planning and driving comfort; for runs
against the instance-free Autonomy-B its lower block: occupancy mAP and Soft-IoU, flow-grounded
mAP and Soft-IoU, flow EPE, planning and driving comfort), as mean +- std over scenes, and the same metrics as paired per-scene changes against the original; per
algorithm the best cost against the number of queries and against wall
time (table + ``convergence.png``) and a head-to-head comparison of algorithms at equal budget
(wins per scene, Wilcoxon signed-rank test); the best shapes per scene as thumbnails (matplotlib renders
of the decoded meshes, plus one grid of all of them at a common scale, `best_shapes.png`).

Realism (docs/realism.md): every results table has a JSD column (the paper's realism figure of the best
shapes: the largest over a scene's attacked actors; the library's own leave-one-out maximum is
the limit), and a section lists every best shape's realism report. Runs journalled before the
realism figures existed get them computed from their best unit vectors (:func:`attach_realism`).
Runs with a restricted search region, a realism penalty or vertex deformation are labelled
with their knobs (:func:`run_label`), so they get rows of their own.

Criticality (docs/attack.md, Criticality): beside the objective, CommonRoad CriMe's time to collision, headways,
required deceleration, BTN, closest encounter, TTC* and TTB of each original and best-shape
closed-loop episode (:func:`criticality_table`).

Objective (paper Eq. 3-5, docs/attack.md): every run is listed with its objective and prediction form
(:func:`objective_label`), and the paired change of each objective term is given unweighted and
weighted, apart (:func:`objective_split`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..fileio import atomic_write_text
from .journal import read_run, record_cost

COLUMNS = (("Objective", ("_objective", "cost"), 1.0), ("AP", ("detection", "ap"), 100.0), ("Recall", ("detection", "recall"), 100.0),
           ("minADE", ("prediction", "min_ade"), 1.0), ("meanADE", ("prediction", "mean_ade"), 1.0),
           ("Plan lat.", ("planning_comfort", "lat"), 1.0), ("Plan jerk", ("planning_comfort", "jerk"), 1.0),
           ("Drive lat.", ("driving_comfort", "lat"), 1.0), ("Drive jerk", ("driving_comfort", "jerk"), 1.0))
#: Table 1's lower block (Autonomy-B, instance-free): occupancy instead of boxes and trajectories
COLUMNS_B = (("Objective", ("_objective", "cost"), 1.0), ("Occ. mAP", ("occupancy", "map"), 100.0),
             ("Occ. Soft-IoU", ("occupancy", "soft_iou"), 100.0),
             ("Flow-gr. mAP", ("occupancy", "flow_grounded_map"), 100.0),
             ("Flow-gr. Soft-IoU", ("occupancy", "flow_grounded_soft_iou"), 100.0),
             ("EPE", ("occupancy", "epe"), 1.0),
             ("Plan lat.", ("planning_comfort", "lat"), 1.0), ("Plan jerk", ("planning_comfort", "jerk"), 1.0),
             ("Drive lat.", ("driving_comfort", "lat"), 1.0), ("Drive jerk", ("driving_comfort", "jerk"), 1.0))


def stack_label(run: dict) -> str:
    """``C (0.2, 1a2b...)``: the stack a run attacked (run.json ``versions.stack``; older runs
    recorded only its name, ``autonomy``)."""
    stack = (run.get("versions") or {}).get("stack")
    if not isinstance(stack, dict):
        return str(run.get("autonomy"))
    return f"{stack.get('name')} ({stack.get('version')}, {stack.get('fingerprint') or '-'})"


def run_label(run: dict) -> str:
    """The run's name in tables: its algorithm, plus its shape model and realism knobs when set
    (``bo``, ``bo, vd 0.5 m``, ``bo, R 3.37, class scales, W 100``)."""
    parts = [str(run.get("algo", "?"))]
    if run.get("shape_model", "latent") == "vd":
        parts.append(f"vd {float(run.get('vd_bound', 0.5)):g} m")
    if run.get("max_mahalanobis") is not None:
        parts.append(f"R {float(run['max_mahalanobis']):g}")
    if run.get("class_scales"):
        parts.append("class scales")
    if run.get("realism_weight"):
        parts.append(f"W {float(run['realism_weight']):g}")
    return ", ".join(parts)


def attach_realism(runs: list[tuple[str, dict, list, dict]]) -> None:
    """Give every closed-loop evaluation of a best shape its realism reports (in memory), where
    its run predates them: recomputed from ``best_unit`` through the run's shape model (the
    scene gives the actors' classes; without the scene file, latent runs are measured without a
    class). Evaluations that have them are left as they are, and so are runs made with another
    shape space than the one loaded (their unit vectors decode to other shapes now)."""
    from ..errors import Adv3dError
    from ..shapes.realism import realism_report
    from .config import AttackConfig
    from .shape_models import ActorShapes
    from .targets import split_query

    for _, run, _, summary in runs:
        config = None
        for sid, entry in summary.get("scenes", {}).items():
            for mode, m in entry.get("modes", {}).items():
                ev = m.get("closed_loop_eval")
                if not ev or ev.get("realism") is not None or not m.get("best_unit"):
                    continue
                config = config or AttackConfig.from_run_json(run)
                space = config.settings.load_shape_space()
                made_with = (run.get("versions") or {}).get("shape_space")
                if made_with is not None and made_with != space.content_hash:
                    continue  # another shape space decodes the unit vector to another shape: no figure
                unit = np.asarray(m["best_unit"], dtype=np.float64).reshape(-1)
                try:
                    from ..scene.schema import load_scene

                    shapes = ActorShapes(config.settings, load_scene(entry["ref"]), entry["targets"], space,
                                         config.settings.load_library())
                    ev["realism"] = shapes.full_reports(unit)
                except (Adv3dError, OSError, KeyError):
                    if config.shape_model != "latent" or config.max_mahalanobis is not None or config.class_scales:
                        continue
                    ev["realism"] = [realism_report(space, u) for u in split_query(unit, len(entry["targets"]), space.dim)]


def _jsd(ev: dict | None) -> float:
    """Largest JSD over a closed-loop evaluation's attacked actors (NaN without realism)."""
    reps = (ev or {}).get("realism") or []
    vals = [r.get("jsd") for r in reps if isinstance(r, dict) and isinstance(r.get("jsd"), (int, float))]
    return float(max(vals)) if vals else float("nan")


def _jsd_limit(evs: list[dict]) -> float:
    for ev in evs:
        for r in (ev or {}).get("realism") or []:
            lim = (r.get("limits") or {}).get("jsd") if isinstance(r, dict) else None
            if isinstance(lim, (int, float)):
                return float(lim)
    return float("nan")


def _get(metrics: dict | None, path: tuple[str, str]) -> float:
    try:
        v = metrics[path[0]][path[1]]
    except (KeyError, TypeError):
        return float("nan")
    return float(v) if isinstance(v, (int, float)) else float("nan")


def _cell(values: list[float], scale: float) -> str:
    v = np.asarray(values, dtype=np.float64) * scale
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return "-"
    return f"{v.mean():.3g} ± {v.std():.2g}" if len(v) > 1 else f"{v.mean():.3g}"


def is_instance_free(run: dict) -> bool:
    """The run attacked an instance-free stack (its metrics are occupancy, not boxes)."""
    from ..autonomy.stacks import INSTANCE_FREE

    return run.get("autonomy") in INSTANCE_FREE


def table1(runs: list[tuple[str, dict, list, dict]], columns=COLUMNS) -> str:
    """Markdown Table 1 over all scenes of all runs (``columns``: :data:`COLUMNS`, or
    :data:`COLUMNS_B` for Autonomy-B's runs)."""
    rows: dict[str, list[dict]] = {}
    seen_original: set[str] = set()
    for _, run, _, summary in runs:
        label = run_label(run)
        for sid, entry in summary.get("scenes", {}).items():
            if "original" in entry and sid not in seen_original:
                o = entry["original"]
                rows.setdefault("Original", []).append({**o["metrics"], "_objective": {"cost": o["cost"]}})
                seen_original.add(sid)
            for mode, m in entry.get("modes", {}).items():
                ev = m.get("closed_loop_eval")
                if ev:
                    rows.setdefault(f"Adv. {mode}-loop ({label})", []).append(
                        {**ev["metrics"], "_objective": {"cost": ev["cost"]}, "_realism": {"jsd": _jsd(ev)}})
    if not rows:
        return "_No closed-loop evaluations in these runs._\n"
    cols = columns + (("JSD", ("_realism", "jsd"), 1.0),)
    head = "| | scenes | " + " | ".join(c for c, _, _ in cols) + " |\n"
    head += "|---|---:|" + "---:|" * len(cols) + "\n"
    order = sorted(rows, key=lambda k: (k != "Original", "closed" in k, k))
    body = ""
    for name in order:
        ms = rows[name]
        body += f"| {name} | {len(ms)} | " + " | ".join(_cell([_get(m, p) for m in ms], s) for _, p, s in cols) + " |\n"
    jsd_note = ("JSD: the paper's realism figure of the best shape (largest over a scene's attacked actors; the "
                "library's own vehicles score up to its leave-one-out maximum, docs/realism.md); ")
    if columns is COLUMNS_B:
        return head + body + ("\nObjective: Autonomy-B's Eq. 3 (l_det = -Soft-IoU of occupancy, l_pred = foreground "
                              "flow EPE, lambda_pred 1.0) summed over the frames (higher = worse for the stack); mAP "
                              "and Soft-IoU in %, EPE in m/s, lateral acceleration in m/s², jerk in m/s³; " + jsd_note +
                              "mean ± std over scenes; every row evaluated in closed loop.\n")
    return head + body + ("\nObjective: Eq. 3-5 summed over the frames (higher = worse for the stack); AP and "
                          "recall in %, ADE in m, lateral acceleration in m/s², jerk in m/s³; JSD: the paper's "
                          "realism figure of the best shape (largest over a scene's attacked actors; the library's "
                          "own vehicles score up to its leave-one-out maximum, docs/realism.md); mean ± std over "
                          "scenes; every row evaluated in closed loop.\n")


def per_scene(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: per scene the original closed-loop objective and, per run and mode, the
    closed-loop objective of the best shape found."""
    cols: list[str] = []
    table: dict[str, dict[str, str]] = {}
    for root, run, _, summary in runs:
        for sid, entry in summary.get("scenes", {}).items():
            row = table.setdefault(sid, {})
            if "skipped" in entry:
                row["Original"] = "skipped: " + entry["skipped"][:60]
                continue
            if "original" in entry:
                row["Original"] = f"{entry['original']['cost']:.4g}"
            for mode, m in entry.get("modes", {}).items():
                key = f"{run_label(run)} {mode}"
                if key not in cols:
                    cols.append(key)
                ev = m.get("closed_loop_eval")
                best = m.get("best_cost")
                jsd = _jsd(ev)
                row[key] = ((f"{ev['cost']:.4g}" if ev else "-") + (f" (search {best:.4g})" if best is not None and mode == "open" else "")
                            + (f", JSD {jsd:.3f}" if np.isfinite(jsd) else ""))
    if not table:
        return ""
    cols = ["Original"] + cols
    out = "| scene | " + " | ".join(cols) + " |\n|---|" + "---:|" * len(cols) + "\n"
    for sid in sorted(table):
        out += f"| {sid} | " + " | ".join(table[sid].get(c, "-") for c in cols) + " |\n"
    return out + ("\nClosed-loop objective of the original scene and of each run's best shape (for open-loop "
                  "attacks the open-loop search value in parentheses), and the best shape's JSD.\n")


#: the criticality table's columns: (header, key of the evaluation's ``criticality`` block)
CRITICALITY_COLUMNS = (("min TTC s", "ttc"), ("min THW s", "thw"), ("min DHW m", "dhw"),
                       ("max req. decel. m/s²", "required_deceleration"), ("max BTN", "btn"), ("min DCE m", "dce"),
                       ("TTC* s", "ttc_star"), ("TTB s", "ttb"))


def _criticality_cell(fig: dict | None) -> str:
    """``value (actor #id, frame k)``; ``never`` for a null value (e.g. no vehicle ever ahead in
    the ego's lane); ``unavoidable`` for a TTB whose braking cannot avoid the collision."""
    if not isinstance(fig, dict):
        return "-"
    if fig.get("value") is None:
        return "unavoidable" if fig.get("unavoidable") else "never"
    where = []
    if fig.get("actor") is not None:
        where.append(f"#{fig['actor']}")
    if fig.get("frame") is not None and "actor" in fig:
        where.append(f"@{fig['frame']}")
    return f"{fig['value']:.3g}" + (f" ({' '.join(where)})" if where else "")


def criticality_table(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: CommonRoad CriMe's criticality figures (``criticality`` block of the
    closed-loop evaluations, :mod:`adv3d_runner.sim.criticality`) of each scene's original
    episode and of every best shape's, beside the objective. Empty when no evaluation has the
    block (runs made before it)."""
    rows: list[str] = []
    seen_original: set[str] = set()

    def row(run_name: str, sid: str, episode: str, ev: dict) -> None:
        crit = ev.get("criticality")
        if not isinstance(crit, dict):
            return
        cost = ev.get("cost")
        head = f"| {run_name} | {sid} | {episode} | {'-' if cost is None else f'{cost:.4g}'} | "
        if "note" in crit:
            rows.append(head + " | ".join([crit["note"]] + [""] * (len(CRITICALITY_COLUMNS) - 1)) + " |")
        else:
            rows.append(head + " | ".join(_criticality_cell(crit.get(k)) for _, k in CRITICALITY_COLUMNS) + " |")

    for root, run, _, summary in runs:
        for sid, entry in sorted(summary.get("scenes", {}).items()):
            if "original" in entry and sid not in seen_original:
                seen_original.add(sid)
                row("-", sid, "original", entry["original"])
            for mode, m in entry.get("modes", {}).items():
                if m.get("closed_loop_eval"):
                    row(run_label(run), sid, f"best ({mode})", m["closed_loop_eval"])
    if not rows:
        return ""
    return ("| run | scene | episode | objective | " + " | ".join(h for h, _ in CRITICALITY_COLUMNS) + " |\n"
            "|---|---|---|---:|" + "---:|" * len(CRITICALITY_COLUMNS) + "\n" + "\n".join(rows) + "\n\n"
            "Closed-loop episodes, computed by CommonRoad CriMe (commonroad-crime; docs/attack.md, \"Criticality "
            "(CriMe)\"): the most critical value over the episode's frames and actors, with the actor (#id) and the "
            "frame (@k) where it occurs; TTC* and TTB from the first frame. never: no finite value (no vehicle "
            "ahead in the ego's lane, not closing, no collision); unavoidable: braking at once does not avoid the "
            "collision. TTC, THW, DHW, DCE, TTC*, TTB: lower is more critical; required deceleration, BTN: higher "
            "is (BTN >= 1: braking alone cannot avoid it).\n")


def avoidability_table(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: per best shape, its avoidability (``RUN/avoidability.json``,
    :mod:`.avoidability`): the finding and, per failure kind, on how many held-out seeds it is
    stack-induced / scenario-induced. Empty when no run has the file."""
    from .avoidability import FAILURE_KINDS, SCENARIO_INDUCED, STACK_INDUCED, kind_totals, read_avoidability, summary_line

    rows, notes = [], []
    for root, run, _, _ in runs:
        doc = read_avoidability(root)
        if doc is None:
            continue
        totals = kind_totals(doc)
        notes.append(f"{run_label(run)}: {summary_line(doc)}; per kind, best shapes stack-induced / scenario-induced: "
                     + ", ".join(f"{k.replace('_', ' ')} {t[STACK_INDUCED]}/{t[SCENARIO_INDUCED]}"
                                 for k, t in totals.items()))
        for sid, sc in sorted(doc["scenes"].items()):
            for mode, m in sc.get("modes", {}).items():
                cells = []
                for kind in FAILURE_KINDS:
                    k = m["kinds"][kind]
                    cells.append("-" if k["verdict"] == "none" else
                                 f"{k['verdict']} ({k['stack_induced']}s/{k['scenario_induced']}b of {k['seeds']}"
                                 + (f", {k['in_original']} in orig." if k.get("in_original") else "") + ")")
                rows.append(f"| {run_label(run)} | {sid} | {mode} | **{m['finding']}** | " + " | ".join(cells) + " |")
    if not rows:
        return ""
    return ("| run | scene | mode | finding | " + " | ".join(k.replace("_", " ") for k in FAILURE_KINDS) + " |\n"
            "|---|---|---|---|" + "---|" * len(FAILURE_KINDS) + "\n" + "\n".join(rows) + "\n\n"
            + "\n".join(f"- {n}" for n in notes) + "\n\n"
            "Each best shape re-simulated on held-out seeds with the stack under test and with the reference stack "
            "(ground-truth perception, same planner). Per kind: the verdict, and on how many seeds only the stack "
            "failed (s) or both failed (b); in orig.: seeds where the stack's original episode fails that way too. "
            "finding: stack-induced when some failure only the stack shows is not already in the original; "
            "scenario-induced when the reference fails too (docs/attack.md, \"Avoidability\").\n")


def rate_table(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: per scene, the worst case the search found beside the share of realistic
    shapes that make the stack fail (``RUN/failure_rate.json``, :mod:`.failure_rate`). Empty when
    no run has the file."""
    from .avoidability import FAILURE_KINDS
    from .failure_rate import format_rate, read_failure_rate

    rows, foot = [], []
    for root, run, _, _ in runs:
        doc = read_failure_rate(root)
        if doc is None:
            continue
        for sid, sc in sorted(doc["scenes"].items()):
            w = sc.get("worst_case") or {}
            fails = [k.replace("_", " ") for k, v in (w.get("failures") or {}).items() if v]
            cost = w.get("cost")
            worst = f"{'-' if cost is None else f'{cost:.4g}'}: {', '.join(fails) or 'no failure'}"
            orig = sorted({k for v in (sc.get("original_failures") or {}).values() for k in v})
            rows.append(f"| {run_label(run)} | {sid} | {worst} | {sc['accepted']} ({sc['rejected_draws']} rejected) | "
                        + " | ".join(format_rate(sc["rates"].get(k)) for k in (*FAILURE_KINDS, "any"))
                        + f" | {', '.join(k.replace('_', ' ') for k in orig) or '-'} |")
        pooled = doc.get("pooled") or {}
        rows.append(f"| {run_label(run)} | all scenes | | | "
                    + " | ".join(format_rate(pooled.get(k)) for k in (*FAILURE_KINDS, "any")) + " | |")
        foot.append(f"{run_label(run)}: {doc['samples']} draws per scene, {100 * doc['confidence']:.0f} % "
                    f"{doc['interval']} intervals, prior: {doc['prior']}")
    if not rows:
        return ""
    kinds = [k.replace("_", " ") for k in (*FAILURE_KINDS, "any")]
    return ("| run | scene | worst case (search objective: failures) | realistic shapes | " + " | ".join(kinds)
            + " | original fails |\n|---|---|---|---:|" + "---:|" * len(kinds) + "---|\n" + "\n".join(rows) + "\n\n"
            + "\n".join(f"- {f}" for f in foot) + "\n\n"
            "Rates: k/n (share, interval) of the realistic shapes whose closed-loop episode fails that way; the worst "
            "case is the search's best shape on its own seed. original fails: failures the original scene shows on "
            "the same seeds (they count in the rates too; docs/attack.md, \"How often\").\n")


# metrics where a lower value is worse for the stack (the others: higher is worse)
LOWER_IS_WORSE = ("AP", "Recall", "Occ. mAP", "Occ. Soft-IoU", "Flow-gr. mAP", "Flow-gr. Soft-IoU")


def paired_deltas(runs: list[tuple[str, dict, list, dict]], columns=COLUMNS) -> str:
    """Markdown table: per attack row, the per-scene change against the same scene's original
    (attacked - original), mean ± std over scenes, and on how many scenes it is worse for the
    stack. Pairing by scene removes the scene-to-scene spread that dominates Table 1."""
    originals: dict[str, dict] = {}
    attacked: dict[str, dict[str, dict]] = {}
    for _, run, _, summary in runs:
        for sid, entry in summary.get("scenes", {}).items():
            if "original" in entry:
                o = entry["original"]
                originals.setdefault(sid, {**o["metrics"], "_objective": {"cost": o["cost"]}})
            for mode, m in entry.get("modes", {}).items():
                ev = m.get("closed_loop_eval")
                if ev:
                    attacked.setdefault(f"Adv. {mode}-loop ({run_label(run)})", {})[sid] = {
                        **ev["metrics"], "_objective": {"cost": ev["cost"]}, "_jsd": _jsd(ev), "_jsd_limit": _jsd_limit([ev])}
    rows = {name: {sid: m for sid, m in by.items() if sid in originals} for name, by in attacked.items()}
    rows = {name: by for name, by in rows.items() if by}
    if not rows:
        return ""
    head = "| Δ against original | scenes | " + " | ".join(c for c, _, _ in columns) + " | JSD |\n"
    head += "|---|---:|" + "---:|" * (len(columns) + 1) + "\n"
    body = ""
    for name in sorted(rows, key=lambda k: ("closed" in k, k)):
        by = rows[name]
        jsd = np.array([m["_jsd"] for m in by.values()])
        limit = np.array([m["_jsd_limit"] for m in by.values()])
        ok = np.isfinite(jsd)
        jsd_cell = "-"
        if ok.any():
            spread = f" ± {jsd[ok].std():.2g}" if ok.sum() > 1 else ""
            jsd_cell = f"{jsd[ok].mean():.3g}{spread} ({int(np.sum(jsd[ok] > limit[ok]))}/{int(ok.sum())})"
        cells = []
        for col, path, scale in columns:
            d = np.array([_get(m, path) - _get(originals[sid], path) for sid, m in by.items()]) * scale
            d = d[np.isfinite(d)]
            worse = int(np.sum(d < -1e-9)) if col in LOWER_IS_WORSE else int(np.sum(d > 1e-9))
            spread = f" ± {d.std():.2g}" if len(d) > 1 else ""
            cells.append(f"{d.mean():+.3g}{spread} ({worse}/{len(d)})" if len(d) else "-")
        body += f"| {name} | {len(by)} | " + " | ".join(cells + [jsd_cell]) + " |\n"
    return head + body + ("\nPer scene: attacked - original, both in closed loop; mean ± std over scenes, in "
                          "parentheses the number of scenes where the change is worse for the stack (lower AP "
                          "or recall, higher objective, ADE, acceleration or jerk). JSD: the best shapes' "
                          "(not a change), in parentheses the number above the library's leave-one-out "
                          "maximum.\n")


def objective_label(run: dict) -> str:
    """The run's objective and its form: ``M0, pred sum`` (``pred_reduction``; a run.json without
    it predates the option and used the horizon mean); ``M0, pred flow EPE`` for an
    instance-free stack, whose prediction term has no waypoints."""
    from .objective import LEGACY_PRED_REDUCTION

    if is_instance_free(run):
        return f"{run.get('objective')}, pred flow EPE"
    return f"{run.get('objective')}, pred {run.get('pred_reduction', LEGACY_PRED_REDUCTION)}"


def objective_split(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: per attack row, the paired change (attacked - original, closed loop) of
    each objective term, unweighted and weighted, never summed across the two: the unweighted
    frame sums of l_det, l_pred and c_plan are in different units; only weight x term adds up to
    the objective."""
    from ..errors import Adv3dError
    from .config import AttackConfig
    from .objective import TERMS, term_split

    rows: dict[str, list[dict]] = {}
    for root, run, _, summary in runs:
        try:
            weights = AttackConfig.from_run_json(run, Path(root) / "run.json").settings.weights
        except Adv3dError:
            continue
        for sid, entry in summary.get("scenes", {}).items():
            o = (entry.get("original") or {}).get("components")
            for mode, m in entry.get("modes", {}).items():
                a = (m.get("closed_loop_eval") or {}).get("components")
                if not (o and a):
                    continue
                so, sa = term_split(o, weights), term_split(a, weights)
                rows.setdefault(f"Adv. {mode}-loop ({run_label(run)}; {objective_label(run)})", []).append(
                    {t: (sa[t]["unweighted"] - so[t]["unweighted"], sa[t]["weight"]) for t in TERMS})
    if not rows:
        return ""
    head = ("| Δ against original | scenes | " + " | ".join(f"{t} (unweighted) | weight | {t} (weighted)" for t in TERMS)
            + " |\n|---|---:|" + "---:|---:|---:|" * len(TERMS) + "\n")
    body = ""
    for name in sorted(rows, key=lambda k: ("closed" in k, k)):
        cells = []
        for t in TERMS:
            d = np.array([r[t][0] for r in rows[name]])
            w = sorted({r[t][1] for r in rows[name]})
            cells += [_cell(list(d), 1.0), "/".join(f"{x:g}" for x in w),
                      _cell([r[t][0] * r[t][1] for r in rows[name]], 1.0)]
        body += f"| {name} | {len(rows[name])} | " + " | ".join(cells) + " |\n"
    return head + body + ("\nPer scene: the attacked shape's frame sum of each term minus the original's, both in "
                          "closed loop, mean ± std over scenes. Unweighted: l_det (confidence-weighted IoU), l_pred "
                          "(m x waypoints for pred sum, m for pred mean), c_plan (m/s² + m/s³); weighted: times "
                          "the run's weight. Only the weighted columns add up (to the objective's change). A dash: "
                          "not available (a term the stack does not provide) or no finite value.\n")


def _record_jsd(rec: dict) -> float:
    """Largest JSD over a journal record's actors (NaN when the record has no realism figures)."""
    vals = [r.get("jsd") for r in (rec.get("realism") or []) if isinstance(r, dict)]
    vals = [v for v in vals if isinstance(v, (int, float))]
    return float(max(vals)) if vals else float("nan")


def search_curves(records: list[dict]) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """(scene, mode) -> ``cost`` (N,) per query in index order (NaN = failed), ``best`` (N,)
    best-so-far cost (failed queries count as -inf), ``wall`` (N,) cumulative query seconds and
    ``best_jsd`` (N,) the JSD of the best-so-far query (NaN where the journal has no realism)."""
    by: dict[tuple[str, str], list] = {}
    for r in records:
        by.setdefault((r["scene"], r["mode"]), []).append(r)
    out = {}
    for key, recs in by.items():
        recs = sorted(recs, key=lambda r: r["index"])
        c = np.array([record_cost(r) for r in recs])
        best = np.fmax.accumulate(np.where(np.isfinite(c), c, -np.inf))
        jsd = np.array([_record_jsd(r) for r in recs])
        best_jsd = np.full(len(c), np.nan)
        at = -1
        for i in range(len(c)):
            if np.isfinite(c[i]) and (at < 0 or c[i] > c[at]):
                at = i
            best_jsd[i] = jsd[at] if at >= 0 else np.nan
        out[key] = {"cost": c, "best": best, "wall": np.cumsum([r.get("wall_s", 0.0) for r in recs]),
                    "best_jsd": best_jsd}
    return out


def head_to_head(runs: list[tuple[str, dict, list, dict]], budgets: Sequence[int] = (11, 25, 50, 100)) -> str:
    """Markdown table: every pair of algorithms that searched the same scenes in the same mode,
    compared scene by scene on the best search cost after the same number of queries: mean ±
    std of the difference, wins / ties / losses and a two-sided Wilcoxon signed-rank p-value."""
    from scipy.stats import wilcoxon

    curves: dict[tuple[str, str], dict[str, np.ndarray]] = {}   # (run label, mode) -> scene -> curve
    jsds: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for _, run, records, _ in runs:
        for (sid, mode), curve in search_curves(records).items():
            curves.setdefault((run_label(run), mode), {})[sid] = curve["best"]
            jsds.setdefault((run_label(run), mode), {})[sid] = curve["best_jsd"]
    keys = sorted(curves)
    lines = []
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            if a[1] != b[1]:
                continue
            shared = sorted(set(curves[a]) & set(curves[b]))
            if not shared:
                continue
            n_max = min(min(len(curves[a][s]), len(curves[b][s])) for s in shared)
            for n in sorted({q for q in budgets if q <= n_max} | {n_max}):
                d = np.array([curves[a][s][n - 1] - curves[b][s][n - 1] for s in shared])
                d = d[np.isfinite(d)]
                if not len(d):
                    continue
                tie = np.abs(d) <= 1e-9
                wins, losses = int(np.sum(d > 1e-9)), int(np.sum(d < -1e-9))
                try:
                    p = f"{wilcoxon(d[~tie]).pvalue:.3g}" if np.sum(~tie) >= 2 else "-"
                except ValueError:
                    p = "-"
                spread = f" ± {d.std():.2g}" if len(d) > 1 else ""
                dj = np.array([jsds[a][s][n - 1] - jsds[b][s][n - 1] for s in shared])
                dj = dj[np.isfinite(dj)]
                jsd_cell = (f"{dj.mean():+.3g}" + (f" ± {dj.std():.2g}" if len(dj) > 1 else "")) if len(dj) else "-"
                lines.append(f"| {a[0]} vs {b[0]} [{a[1]}] | {n} | {len(d)} | {d.mean():+.3g}{spread} | "
                             f"{wins} / {int(tie.sum())} / {losses} | {p} | {jsd_cell} |")
    if not lines:
        return ""
    return ("| pair [mode] | queries | scenes | Δ best cost (mean ± std) | wins / ties / losses | Wilcoxon p | "
            "Δ JSD of best |\n"
            "|---|---:|---:|---:|---:|---:|---:|\n" + "\n".join(lines) +
            "\n\nΔ = first algorithm's best search cost minus the second's after the same number of queries, "
            "per scene (higher = the first found a worse case for the stack); wins count scenes where the "
            "first is higher. Δ JSD: the same difference of the best-so-far shapes' JSD (from the journals' "
            "realism figures; - for journals without them).\n")


def convergence(runs: list[tuple[str, dict, list, dict]]) -> dict[str, dict]:
    """Per algorithm (and mode): best-so-far cost per query index and per cumulative wall
    time, averaged over scenes (each scene's curve relative to its first query's cost)."""
    curves: dict[str, dict] = {}
    for _, run, records, summary in runs:
        for (sid, mode), curve in search_curves(records).items():
            c, best, wall = curve["cost"], curve["best"], curve["wall"]
            key = f"{run_label(run)} [{mode}]"
            d = curves.setdefault(key, {"best": [], "wall": [], "final": [], "failed": 0, "queries": 0, "jsd": []})
            jsd = curve["best_jsd"][-1] if len(c) else float("nan")
            if not np.isfinite(jsd):  # an older journal: the summary's best shape
                jsd = _jsd(summary.get("scenes", {}).get(sid, {}).get("modes", {}).get(mode, {}).get("closed_loop_eval"))
            d["jsd"].append(jsd)
            finite0 = best[np.isfinite(best)]
            ref = finite0[0] if len(finite0) else 0.0
            d["best"].append(best - ref)
            d["wall"].append(wall)
            d["final"].append(best[-1] if len(best) else np.nan)
            d["failed"] += int(np.sum(~np.isfinite(c)))
            d["queries"] += len(c)
    return curves


def plot_convergence(curves: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for key, d in sorted(curves.items()):
        n = min(len(b) for b in d["best"])
        B = np.array([b[:n] for b in d["best"]])
        B = np.where(np.isfinite(B), B, np.nan)
        mean = np.nanmean(B, axis=0)
        line, = axes[0].plot(np.arange(1, n + 1), mean, label=f"{key} ({len(B)} scenes)")
        W = np.array([w[:n] for w in d["wall"]]).mean(axis=0)
        axes[1].plot(W, mean, label=key)
        if len(B) > 2:  # spread over scenes: the middle half
            q1, q3 = np.nanpercentile(B, [25, 75], axis=0)
            axes[0].fill_between(np.arange(1, n + 1), q1, q3, color=line.get_color(), alpha=0.15, linewidth=0)
    axes[0].set_xlabel("queries")
    axes[1].set_xlabel("wall time (s, summed over workers)")
    axes[0].set_ylabel("best cost − first query's cost\n(mean over scenes; band: 25-75 %)")
    axes[1].set_ylabel("best cost − first query's cost\n(mean over scenes)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _shaded_triangles(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) triangles and (F, 4) RGBA colours, flat-shaded by normal against a fixed light."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([0.4, -0.6, 0.7]) / np.linalg.norm([0.4, -0.6, 0.7])
    shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
    return tri, np.c_[0.95 * shade, 0.55 * shade, 0.2 * shade, np.ones_like(shade)]


def _draw_mesh(ax, vertices: np.ndarray, faces: np.ndarray, elev: float, azim: float, zoom: float = 1.0,
               lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> None:
    """Orthographic flat-shaded view of a mesh on a 3-D axes; ``lo``/``hi`` (3,) fix the box (m)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    tri, colors = _shaded_triangles(vertices, faces)
    v = np.asarray(vertices, dtype=np.float64)
    lo = v.min(axis=0) if lo is None else lo
    hi = v.max(axis=0) if hi is None else hi
    ax.add_collection3d(Poly3DCollection(tri, facecolors=colors, edgecolor="none"))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-3)), zoom=zoom)
    ax.set_proj_type("ortho")
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()


def render_shape(vertices: np.ndarray, faces: np.ndarray, path: Path, title: str = "") -> None:
    """A side view and a three-quarter view of a mesh (flat shading by normal) to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8, 2.8))
    for i, (elev, azim) in enumerate(((0, -90), (25, -50))):
        _draw_mesh(fig.add_subplot(1, 2, i + 1, projection="3d"), vertices, faces, elev, azim,
                   zoom=1.0 if i == 0 else 1.1)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def render_shape_sheet(cells: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, str]], path: Path) -> None:
    """One PNG grid: rows = scenes, columns = run/mode; every cell the three-quarter view of a
    mesh at one common scale (so sizes compare across cells) with its caption.

    Args:
        cells: (row label, column label) -> (vertices (V, 3) m, faces (F, 3), caption).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted({r for r, _ in cells})
    cols = list(dict.fromkeys(c for _, c in cells))
    allv = np.concatenate([v for v, _, _ in cells.values()])
    half = (allv.max(axis=0) - allv.min(axis=0)).max() / 2
    fig = plt.figure(figsize=(2.6 * len(cols), 1.9 * len(rows) + 0.4))
    for (r, c), (v, f, caption) in cells.items():
        ax = fig.add_subplot(len(rows), len(cols), rows.index(r) * len(cols) + cols.index(c) + 1, projection="3d")
        mid = (v.min(axis=0) + v.max(axis=0)) / 2
        lo, hi = mid - half, mid + half
        lo[2], hi[2] = v[:, 2].min(), v[:, 2].min() + half
        _draw_mesh(ax, v, f, 22, -55, zoom=1.5, lo=lo, hi=hi)
        ax.set_title(caption, fontsize=7, pad=-4)
    for i, c in enumerate(cols):
        fig.text((i + 0.5) / len(cols), 1 - 0.15 / fig.get_figheight(), c, ha="center", va="top", fontsize=9,
                 weight="bold")
    for j, r in enumerate(rows):
        fig.text(0.002, 1 - (0.4 + (j + 0.5) * 1.9) / fig.get_figheight(), r.replace("highway-benchmark-", "scene "),
                 rotation=90, va="center", fontsize=8)
    fig.subplots_adjust(left=0.02, right=1, bottom=0, top=1 - 0.4 / fig.get_figheight(), wspace=0, hspace=0.1)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _best_meshes(config, entry: dict, unit: np.ndarray) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """The best shape's mesh per attacked actor (None where it does not decode): the shape
    space's decode for the paper's attack, the run's shape model (which needs the scene) else."""
    from ..errors import Adv3dError
    from .targets import split_query

    space = config.settings.load_shape_space()
    if config.shape_model == "latent" and config.max_mahalanobis is None and not config.class_scales:
        out = []
        for u in split_query(unit, len(entry["targets"]), space.dim):
            try:
                out.append(space.decode_arrays(u))
            except Adv3dError:
                out.append(None)
        return out
    from ..scene.schema import load_scene
    from .shape_models import ActorShapes

    try:
        shapes = ActorShapes(config.settings, load_scene(entry["ref"]), entry["targets"], space)
        U = split_query(unit, len(entry["targets"]), shapes.per_actor)
        return [shapes.decode_actor(i, u)[:2] for i, u in enumerate(U)]
    except (Adv3dError, OSError):
        return [None] * len(entry["targets"])


def thumbnails(runs: list[tuple[str, dict, list, dict]], out_dir: Path,
               sheet: Path | None = None) -> list[tuple[str, str]]:
    """Render the best shape of every scene, mode and attacked actor; (caption, png path).
    With ``sheet``, also one grid of all of them (rows scenes, columns run/mode/actor) there."""
    from .config import AttackConfig

    out = []
    cells: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, str]] = {}
    for root, run, _, summary in runs:
        label = run_label(run)
        for sid, entry in summary.get("scenes", {}).items():
            for mode, m in entry.get("modes", {}).items():
                # no closed-loop evaluation: the evaluator simulated nothing (no shape to show)
                if not m.get("best_unit") or not m.get("closed_loop_eval"):
                    continue
                meshes = _best_meshes(AttackConfig.from_run_json(run), entry,
                                      np.asarray(m["best_unit"], dtype=np.float64).reshape(-1))
                reps = m["closed_loop_eval"].get("realism") or [None] * len(meshes)
                for aid, mesh, rep in zip(entry["targets"], meshes, reps):
                    png = out_dir / f"thumb_{Path(root).name}_{sid}_{mode}_actor{aid}.png"
                    if mesh is None:
                        continue
                    v, f = mesh
                    d = v.max(axis=0) - v.min(axis=0)
                    jsd = f", JSD {rep['jsd']:.3f}" if isinstance(rep, dict) and "jsd" in rep else ""
                    render_shape(v, f, png, f"{sid} [{mode}, {label}] actor {aid}: "
                                             f"{d[0]:.2f} x {d[1]:.2f} x {d[2]:.2f} m{jsd}")
                    out.append((f"{sid} [{mode}, {label}] actor {aid}, cost {m.get('best_cost'):.4g}{jsd}", png))
                    column = f"{label} {mode}" + (f" #{aid}" if len(entry["targets"]) > 1 else "")
                    cells[(sid, column)] = (v, f, f"{d[0]:.1f} x {d[1]:.1f} x {d[2]:.1f} m, cost {m.get('best_cost'):.3g}")
    if sheet is not None and cells:
        render_shape_sheet(cells, sheet)
    return out


def realism_table(runs: list[tuple[str, dict, list, dict]]) -> str:
    """Markdown table: the realism report of every best shape (every run, scene, mode and
    attacked actor), with the checks it fails (docs/realism.md)."""
    lines = []
    for root, run, _, summary in runs:
        for sid, entry in sorted(summary.get("scenes", {}).items()):
            for mode, m in entry.get("modes", {}).items():
                reps = (m.get("closed_loop_eval") or {}).get("realism") or []
                for aid, r in zip(entry.get("targets", []), reps):
                    if not isinstance(r, dict):
                        continue
                    dims = r.get("dimensions_m") or []
                    size = " x ".join(f"{x:.2f}" for x in dims) if dims else "-"
                    excess = r.get("dimension_excess")
                    cls = f"{r.get('dimension_class') or '-'} {100 * max(excess):.0f} %" if excess else "-"
                    maha = r.get("mahalanobis")
                    genus = (f"{r['genus']}/{r['genus_robust']}" if "genus" in r else "-")
                    wall = f"{r['thinnest_wall_m']:.2f}" if "thinnest_wall_m" in r else "-"
                    lines.append(
                        f"| {run_label(run)} | {sid} | {mode} | {aid} | {r.get('jsd', float('nan')):.3f} | "
                        f"{r.get('nearest_asset', '-')} ({r.get('nearest_chamfer_m', float('nan')):.3f}) | "
                        f"{'-' if maha is None else f'{maha:.2f}'} | {size} | {cls} | {genus} | {wall} | "
                        f"{', '.join(r.get('flags') or []) or '-'} |")
    if not lines:
        return ""
    return ("| run | scene | mode | actor | JSD | nearest (Chamfer m) | Mahalanobis | L x W x H m | class, excess | "
            "genus raw/robust | wall m | flags |\n|---|---|---|---:|---:|---|---:|---|---|---|---:|---|\n"
            + "\n".join(lines) + "\n\nFlags name the failed checks (limits: the library's own leave-one-out "
            "maxima for JSD, Chamfer and Mahalanobis; robust genus 0, floating volume <= 0.1 %, walls >= one "
            "voxel, dimensions within the class's real ranges; docs/realism.md). Vertex-deformed shapes have "
            "no latent and no decoder field: Mahalanobis, genus and wall are not measured.\n")


def write_report(run_dirs: Sequence[str | Path], out: str | Path | None = None) -> Path:
    """Write the markdown report (and its PNGs next to it). Returns the report path."""
    runs = []
    for d in run_dirs:
        run, records, summary = read_run(d)
        runs.append((str(d), run, records, summary))
    attach_realism(runs)
    out_path = Path(out) if out else Path(run_dirs[0]) / "report.md"
    out_path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# Adversarial shape attack report", ""]
    lines.append("| run | algorithm | mode | budget | seed | objective | stack (version, fingerprint) | scenes |")
    lines.append("|---|---|---|---:|---:|---|---|---|")
    for root, run, _, _ in runs:
        seed = f"{run.get('seed')}" + (" (per scene)" if run.get("scene_seeds") else "")
        lines.append(f"| {root} | {run_label(run)} | {run.get('mode')} | {run.get('budget')} | {seed} | "
                     f"{objective_label(run)} | {stack_label(run)} | {', '.join(run.get('scene_ids', []))} |")
    groups = [("", [r for r in runs if not is_instance_free(r[1])], COLUMNS),
              ("Autonomy-B (instance-free): ", [r for r in runs if is_instance_free(r[1])], COLUMNS_B)]
    for prefix, group, columns in groups:
        if not group:
            continue
        title = "Closed-loop evaluation (paper Table 1)" if not prefix else \
            "Closed-loop evaluation of Autonomy-B (paper Table 1, lower block)"
        lines += ["", f"## {title}", "", table1(group, columns), ""]
        deltas = paired_deltas(group, columns)
        if deltas:
            lines += [f"### {prefix}Paired change against the original", "", deltas, ""]
        split = objective_split(group)
        if split:
            lines += [f"### {prefix}Objective terms, paired change", "", split, ""]
    ps = per_scene(runs)
    if ps:
        lines += ["### Per scene", "", ps, ""]
    crit = criticality_table(runs)
    if crit:
        lines += ["### Criticality (CommonRoad CriMe)", "", crit, ""]
    avoid = avoidability_table(runs)
    if avoid:
        lines += ["### Avoidability: stack-induced or scenario-induced", "", avoid, ""]
    rates = rate_table(runs)
    if rates:
        lines += ["### How often: worst case and failure rate of realistic shapes", "", rates, ""]
    curves = convergence(runs)
    lines += ["## Search: best cost against queries and wall time", ""]
    if curves:
        png = out_path.parent / "convergence.png"
        plot_convergence(curves, png)
        lines.append("| algorithm [mode] | scene runs | queries | failed | best cost (mean ± std over scenes) | "
                     "gain over first query | wall s per query | JSD of best |")
        lines.append("|---|---:|---:|---:|---:|---:|---:|---:|")
        for key, d in sorted(curves.items()):
            gain = [b[-1] for b in d["best"] if len(b)]
            wall = sum(w[-1] for w in d["wall"] if len(w)) / max(d["queries"], 1)
            lines.append(f"| {key} | {len(d['final'])} | {d['queries']} | {d['failed']} | {_cell(d['final'], 1.0)} | "
                         f"{_cell(gain, 1.0)} | {wall:.3g} | {_cell(d['jsd'], 1.0)} |")
        lines += ["", f"![convergence]({png.name})", ""]
        h2h = head_to_head(runs)
        if h2h:
            lines += ["### Head to head at equal budget", "", h2h, ""]
    else:
        lines += ["_No queries journalled._", ""]
    rt = realism_table(runs)
    if rt:
        lines += ["## Realism of the best shapes", "", rt, ""]
    sheet = out_path.parent / "best_shapes.png"
    thumbs = thumbnails(runs, out_path.parent, sheet=sheet)
    if thumbs:
        lines += ["## Best shapes", "", "All best shapes at one scale (three-quarter view; search cost under each):", "",
                  f"![best shapes]({sheet.name})", "", "<details><summary>Each shape, side and three-quarter view</summary>", ""]
        for caption, png in thumbs:
            lines += [f"**{caption}**", "", f"![{caption}]({png.name})", ""]
        lines += ["</details>", ""]
    atomic_write_text(out_path, "\n".join(lines) + "\n")
    return out_path
