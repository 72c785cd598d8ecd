"""Avoidability: is a found failure the stack's fault, or would any driver fail there?

Every best shape of an attack is re-simulated in closed loop on the held-out evaluation seeds of
the experiment protocol (:func:`~.protocol.evaluation_seeds`: never the search's noise), once
with the stack under test and once with a *reference* stack: by default ``oracle``, the same
tracker and planner as Autonomy-A fed the simulator's ground-truth boxes
(:mod:`adv3d_runner.autonomy.oracle`). Each episode's failures (:data:`FAILURE_KINDS`) are
read from its metrics (:func:`episode_failures`); on each seed, a failure that the reference
shows too is **scenario-induced** (the shape and scenario defeat a driver that sees perfectly),
one only the stack under test shows is **stack-induced** (:func:`classify_failures`). Over the
seeds, a kind is scenario-induced as soon as the reference shows it on one seed where the stack
shows it too, stack-induced when the stack shows it on some seeds and the reference never does
on those (:func:`shape_verdict`; the per-seed counts are kept beside the verdict). A failure the
stack's own original episode shows on the same seed is counted apart (``in_original``): a best
shape is a **stack-induced finding** only when some stack-induced failure is not already in the
original (:func:`finding_of`).

Failure kinds (episode metrics, ``sim.evaluate.episode_metrics``):

* ``collision``: the ego's footprint overlaps an actor's;
* ``at_fault_collision``: the first collision is with an actor ahead of the ego;
* ``hard_braking``: the ego's hardest braking is below :data:`HARD_BRAKING` (-4 m/s^2);
* ``off_road``: a footprint corner leaves the lanes by more than the metric's tolerance;
* ``low_progress``: the ego drives less than :data:`PROGRESS_FRACTION` (0.8) of the path it
  drives in the original scene, with the same stack and the same seed.

``adv3d avoidability RUN`` (and ``adv3d attack --avoidability K``) writes ``avoidability.json``
into the run folder, and the simulations it made into ``heldout.json.gz`` (the stack under test:
the file name ``bench/paper_tables.py`` uses for the held-out evaluations) and
``heldout.<reference>.json.gz`` (:class:`~.protocol.HeldoutStore`: a killed command resumes
without redoing any). ``adv3d report`` shows the split. Tables that already hold held-out
records call :func:`avoidability_of` directly.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..errors import ConfigError

#: The failure kinds, in report order.
FAILURE_KINDS = ("collision", "at_fault_collision", "hard_braking", "off_road", "low_progress")
#: Hardest braking (m/s^2) below which an episode counts as braking hard (the export's rule).
HARD_BRAKING = -4.0
#: Progress below this fraction of the original's (same stack, same seed) is a failure.
PROGRESS_FRACTION = 0.8
#: Default reference stack: ground-truth perception, the same planner.
DEFAULT_REFERENCE = "oracle"
#: Per-seed classes of one failure kind (:func:`classify_failures`).
STACK_INDUCED, SCENARIO_INDUCED, REFERENCE_ONLY, NO_FAILURE, UNKNOWN = (
    "stack-induced", "scenario-induced", "reference-only", "none", "unknown")
FORMAT = "adv3d-avoidability"
VERSION = 1
FILE = "avoidability.json"
STACK_STORE = "heldout.json.gz"


def reference_store_name(reference: str) -> str:
    """File name of the reference stack's held-out evaluations in a run folder."""
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in str(reference))[:64]
    return f"heldout.{safe}.json.gz"


def episode_failures(metrics: Mapping[str, Any] | None, original: Mapping[str, Any] | None = None
                     ) -> dict[str, bool | None]:
    """Which failures an episode shows, from its metrics document (``episode_metrics``).

    Args:
        metrics: the episode's metrics (``collision``, ``hardest_braking_mps2``, ``off_road``,
            ``progress_m``).
        original: the metrics of the original scene's episode with the same stack and seed
            (for ``low_progress``); None leaves ``low_progress`` unknown.
    Returns:
        kind -> True / False, or None where the metrics lack the figure (e.g. records made
        before ``hardest_braking_mps2`` existed).
    """
    m = metrics or {}
    col = m.get("collision") if isinstance(m.get("collision"), dict) else None
    brake = m.get("hardest_braking_mps2")
    out: dict[str, bool | None] = {
        "collision": None if col is None else bool(col.get("collided", False)),
        "at_fault_collision": None if col is None else bool(col.get("collided", False) and col.get("at_fault", False)),
        "hard_braking": None if not _number(brake) else bool(brake < HARD_BRAKING),
        "off_road": None if "off_road" not in m else bool(m["off_road"]),
        "low_progress": None,
    }
    base = (original or {}).get("progress_m")
    prog = m.get("progress_m")
    if _number(base) and _number(prog):
        out["low_progress"] = bool(prog < PROGRESS_FRACTION * base)
    return out


def _number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and x == x


def classify_failures(stack: Mapping[str, bool | None], reference: Mapping[str, bool | None]
                      ) -> dict[str, str]:
    """Per failure kind, one seed: ``stack-induced`` (only the stack under test fails),
    ``scenario-induced`` (the reference fails too), ``reference-only`` (only the reference
    fails), ``none``, or ``unknown`` (a figure is missing).

    Args:
        stack, reference: :func:`episode_failures` of the same shape, scene and seed with the
            stack under test and with the reference stack.
    """
    out = {}
    for kind in FAILURE_KINDS:
        s, r = stack.get(kind), reference.get(kind)
        if s is None or r is None:
            out[kind] = UNKNOWN
        elif s and r:
            out[kind] = SCENARIO_INDUCED
        elif s:
            out[kind] = STACK_INDUCED
        elif r:
            out[kind] = REFERENCE_ONLY
        else:
            out[kind] = NO_FAILURE
    return out


def shape_verdict(per_seed: Sequence[Mapping[str, str]], in_original: Sequence[Sequence[str]] | None = None
                  ) -> dict[str, dict[str, Any]]:
    """Per failure kind over the seeds of one shape: the count of each per-seed class and the
    verdict: ``scenario-induced`` when the reference fails with the stack on some seed,
    ``stack-induced`` when the stack fails on some seed and the reference never with it,
    ``none`` when the stack never fails, ``unknown`` when no seed could be classified.

    Args:
        per_seed: :func:`classify_failures` of each seed.
        in_original: per seed, the kinds the stack's original episode on that seed shows too;
            counted as ``in_original`` and left out of ``new_stack_induced`` (the stack-induced
            seeds whose failure the shape brought about).
    """
    in_original = in_original if in_original is not None else [[] for _ in per_seed]
    out = {}
    for kind in FAILURE_KINDS:
        classes = [c[kind] for c in per_seed]
        counts = {c: classes.count(c) for c in (STACK_INDUCED, SCENARIO_INDUCED, REFERENCE_ONLY, NO_FAILURE, UNKNOWN)}
        if counts[SCENARIO_INDUCED]:
            verdict = SCENARIO_INDUCED
        elif counts[STACK_INDUCED]:
            verdict = STACK_INDUCED
        elif counts[UNKNOWN] == len(classes):
            verdict = UNKNOWN
        else:
            verdict = NO_FAILURE
        out[kind] = {"verdict": verdict, "seeds": len(classes), **{k.replace("-", "_"): v for k, v in counts.items()},
                     "in_original": sum(kind in o for o in in_original),
                     "new_stack_induced": sum(c == STACK_INDUCED and kind not in o for c, o in zip(classes, in_original))}
    return out


#: A best shape's overall finding (:func:`finding_of`).
FINDINGS = (STACK_INDUCED, SCENARIO_INDUCED, "pre-existing", "no failure")


def finding_of(kinds: Mapping[str, Mapping[str, Any]]) -> str:
    """A shape's overall finding from :func:`shape_verdict`: ``stack-induced`` when some kind is
    stack-induced on a seed whose original episode does not fail that way; else
    ``scenario-induced`` when some kind is scenario-induced; else ``pre-existing`` when the stack
    fails only as it does in the original scene; else ``no failure``."""
    if any(v["verdict"] == STACK_INDUCED and v.get("new_stack_induced", 1) for v in kinds.values()):
        return STACK_INDUCED
    if any(v["verdict"] == SCENARIO_INDUCED for v in kinds.values()):
        return SCENARIO_INDUCED
    if any(v["verdict"] == STACK_INDUCED for v in kinds.values()):
        return "pre-existing"
    return "no failure"


def avoidability_of(summary: Mapping[str, Any], stack_evals: Mapping[str, dict], reference_evals: Mapping[str, dict],
                    seeds: Mapping[str, Sequence[int]], *, reference: str = DEFAULT_REFERENCE) -> dict[str, Any]:
    """The avoidability document of a run from its held-out records.

    Args:
        summary: the run's summary.json (scenes, their modes' best shapes).
        stack_evals, reference_evals: held-out records keyed ``scene|what|seed``
            (:func:`~.protocol.heldout_key`; ``what`` is ``original`` or a mode) with the stack
            under test and with the reference stack (:class:`~.protocol.HeldoutStore`'s
            ``evaluations``).
        seeds: scene id -> its evaluation seeds.
        reference: the reference stack's name (recorded).
    Returns:
        ``{"format", "version", "reference", "rules", "scenes": {sid: {"seeds", "modes": {mode:
        {"per_seed": [{"seed", "stack", "reference", "classes", "in_original"}], "kinds",
        "finding"}}}}, "totals"}``; a best shape whose records are missing is left out.
    """
    from .protocol import heldout_key

    scenes: dict[str, Any] = {}
    totals = {f: 0 for f in FINDINGS}
    for sid, entry in summary.get("scenes", {}).items():
        if "skipped" in entry or not entry.get("modes") or sid not in seeds:
            continue
        modes = {}
        for mode, m in entry["modes"].items():
            if m.get("best_unit") is None:
                continue
            rows = []
            for s in seeds[sid]:
                keys = (heldout_key(sid, mode, s), heldout_key(sid, "original", s))
                if not all(k in stack_evals and k in reference_evals for k in keys):
                    rows = []
                    break
                st = episode_failures(stack_evals[keys[0]].get("metrics"), stack_evals[keys[1]].get("metrics"))
                rf = episode_failures(reference_evals[keys[0]].get("metrics"), reference_evals[keys[1]].get("metrics"))
                orig = episode_failures(stack_evals[keys[1]].get("metrics"), stack_evals[keys[1]].get("metrics"))
                rows.append({"seed": int(s), "stack": st, "reference": rf, "classes": classify_failures(st, rf),
                             "in_original": [k for k in FAILURE_KINDS if orig.get(k) and st.get(k)]})
            if not rows:
                continue
            kinds = shape_verdict([r["classes"] for r in rows], [r["in_original"] for r in rows])
            finding = finding_of(kinds)
            totals[finding] += 1
            modes[mode] = {"per_seed": rows, "kinds": kinds, "finding": finding}
        if modes:
            scenes[sid] = {"seeds": [int(s) for s in seeds[sid]], "modes": modes}
    return {"format": FORMAT, "version": VERSION, "reference": reference,
            "rules": {"hard_braking_mps2": HARD_BRAKING, "progress_fraction": PROGRESS_FRACTION,
                      "kinds": list(FAILURE_KINDS)},
            "scenes": scenes, "totals": totals}


def kind_totals(doc: Mapping[str, Any]) -> dict[str, dict[str, int]]:
    """Per failure kind, over every best shape of an avoidability document: how many are
    stack-induced and how many scenario-induced (their verdicts; the table row a paper table
    splits its failures by)."""
    out = {k: {STACK_INDUCED: 0, SCENARIO_INDUCED: 0} for k in FAILURE_KINDS}
    for sc in doc.get("scenes", {}).values():
        for m in sc.get("modes", {}).values():
            for kind, v in m.get("kinds", {}).items():
                if kind in out and v.get("verdict") in out[kind]:
                    out[kind][v["verdict"]] += 1
    return out


def run_avoidability(run_dir: str | Path, *, eval_seeds: int = 3, reference: str = DEFAULT_REFERENCE,
                     workers: int = 1) -> dict[str, Any]:
    """Re-simulate every best shape of the run (and each scene's original) on ``eval_seeds``
    held-out seeds with the run's stack and with ``reference``, then write and return the
    avoidability document (``RUN/avoidability.json``; module docstring).

    Raises:
        ConfigError: not a run folder, or ``eval_seeds`` < 1.
    """
    from ..fileio import write_json
    from .config import AttackConfig
    from .evaluator import EpisodeEvaluator
    from .journal import read_run
    from .protocol import HeldoutStore, evaluation_seeds, heldout_tasks, run_heldout

    if eval_seeds < 1:
        raise ConfigError(f"--eval-seeds must be at least 1, got {eval_seeds}")
    root = Path(run_dir)
    run, _, summary = read_run(root)
    config = AttackConfig.from_run_json(run, root / "run.json")
    tasks = heldout_tasks(summary, config.seed, eval_seeds)
    stack_store = HeldoutStore(root / STACK_STORE)
    reference_store = HeldoutStore(root / reference_store_name(reference))
    run_heldout(tasks, config.settings, stack_store, workers=workers)
    run_heldout(tasks, replace(config.settings, autonomy=reference), reference_store, workers=workers)
    digest_of = EpisodeEvaluator(config.settings).scene_digest
    seeds = {sid: evaluation_seeds(config.seed, digest_of(e["ref"]), eval_seeds)
             for sid, e in summary.get("scenes", {}).items() if "skipped" not in e and e.get("modes")}
    doc = avoidability_of(summary, stack_store.evaluations, reference_store.evaluations, seeds, reference=reference)
    doc["stack"] = config.autonomy
    doc["eval_seeds"] = int(eval_seeds)
    write_json(root / FILE, doc)
    return doc


def read_avoidability(run_dir: str | Path) -> dict[str, Any] | None:
    """``RUN/avoidability.json`` when there (checked: its format and version), else None.

    Raises:
        FileFormatError: naming the file and field.
    """
    from ..validate import read_optional_contract

    node = read_optional_contract(Path(run_dir) / FILE, FORMAT, (VERSION,))
    if node is None:
        return None
    node["scenes"].object("scene id -> the scene's avoidability")
    node["reference"].string()
    return node.value


def summary_line(doc: Mapping[str, Any]) -> str:
    """One line: how many best shapes are stack-induced, scenario-induced or without failure."""
    t = doc.get("totals", {})
    return (f"best shapes: {t.get(STACK_INDUCED, 0)} stack-induced, {t.get(SCENARIO_INDUCED, 0)} scenario-induced, "
            f"{t.get('pre-existing', 0)} failing only as the original does, {t.get('no failure', 0)} without failure "
            f"(reference stack {doc.get('reference')}, {doc.get('eval_seeds', '?')} held-out seeds)")
