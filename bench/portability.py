"""What changes when the numerical kernels change: the same jobs under two numerical configurations.

    .venv/bin/python bench/portability.py [--configs native,avx2] [--workloads demo,sanity,heldout]
        [--heldout-run docs/results/table1_A_b20/runs/bo/seed0/commonroad-USA_US101-4_1_T-1]
        [--heldout-seeds 3] [--heldout-what original,open,closed] [--sanity-workers 1]
        [--scratch out/portability] [--out bench/results/portability.json]

The same code and seed give the same bits only where Embree, numpy, OpenBLAS, torch and numba
run the same kernels (docs/reliability.md, "Same seed, same result"). This machine runs one
configuration (``native``: whatever this CPU chooses, e.g. AVX-512); ``adv3d numerics --emulate
NAME -- CMD`` runs a command with the kernels an ``avx2`` (or ``sse4.2``) CPU would choose
(``adv3d_runner.machine.EMULATIONS``). Every workload runs once per configuration, in its own
subprocess (``native``: this environment without any of the kernel-choosing variables;
otherwise through ``adv3d numerics --emulate NAME --``), one thread per numerical library:

* ``demo``: ``adv3d demo --out DIR`` (the README's job: two decoded vehicles, a 16-query
  closed-loop BO attack of 3 s episodes on a bundled highway scene). Compared: the decoded
  meshes (bytes), the original scene's and the best shape's closed-loop evaluation (objective,
  AP, recall, ADE, comfort), the best query (index, objective, unit vector, latent) and the
  journal ``queries.jsonl`` query by query (identical records, first query that differs, the
  largest objective difference, the largest L-inf distance between the queried unit vectors).
* ``sanity``: ``bench/sanity.py --quick`` (10 generated and the real benchmark scenes, one 5 s
  closed-loop Autonomy-A episode each), written under a temporary name
  (``bench/results/portability.sanity.quick.<config>.json``, removed once read). Compared per
  scene and on the summaries of both parts: AP, recall, minADE, meanADE, planning and driving
  comfort, progress, collisions; and each configuration against the rows of the same scenes in
  the kept ``bench/results/sanity.json`` (summaries made again from those rows).
* ``heldout``: one kept run of a paper table (one scene, one run seed; default a real scene of
  ``docs/results/table1_A_b20``): its held-out evaluations (``protocol.heldout_tasks``: the
  original scene and each mode's best shape on the scene's evaluation seeds) simulated again
  under each configuration. Compared with each other and with the kept ``heldout.json.gz``:
  the objective and its terms, AP, recall, ADE, comfort.

Every subprocess reports its own ``numerical_config()`` (run.json ``versions.numerics`` for the
demo, the sanity file's ``machine.numerics``, the held-out worker's own), kept per workload
next to the configuration ``adv3d numerics --json`` reports under the same environment.
Writes ``bench/results/portability.json`` (``largest_differences``: one row per workload and
quantity, the largest difference of every configuration against the first) and prints it.
About 4 minutes wall (2.5 CPU-minutes) for native and avx2 on a 2-core AMD EPYC (the
subprocesses run one at a time; ``--sanity-workers 2`` shortens the sanity part on an idle
machine). The kept results: ``bench/results/portability.json`` (native vs avx2, the defaults)
and ``bench/results/portability.sse4.2.json`` (``--configs native,sse4.2 --out ...``).
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import NUMERICS_ENV, machine_info, single_thread_env  # noqa: E402

WORKLOADS = ("demo", "sanity", "heldout")
DEFAULT_HELDOUT_RUN = "docs/results/table1_A_b20/runs/bo/seed0/commonroad-USA_US101-4_1_T-1"
KEPT_SANITY = "bench/results/sanity.json"

#: Metrics of one closed-loop episode compared everywhere: name -> path into its metrics.
EPISODE_METRICS: dict[str, tuple[str, ...]] = {
    "ap": ("detection", "ap"), "recall": ("detection", "recall"), "n_det": ("detection", "n_det"),
    "min_ade": ("prediction", "min_ade"), "mean_ade": ("prediction", "mean_ade"),
    "plan_jerk": ("planning_comfort", "jerk"), "drive_lat": ("driving_comfort", "lat"),
    "drive_jerk": ("driving_comfort", "jerk"), "progress_m": ("progress_m",),
    "min_distance": ("min_distance",), "collided": ("collision", "collided"),
}
#: The objective's terms (``components`` of a query or evaluation).
TERMS = ("det", "tp", "fp", "pred", "plan")
#: Sanity summary fields compared (means over the scenes of a part).
SANITY_SUMMARY = ("ap", "recall", "min_ade", "mean_ade", "plan_jerk", "drive_lat", "drive_jerk", "drive_peak_jerk",
                  "progress_ratio_mean", "progress_ratio_min", "collisions", "at_fault_collisions", "ok_rate",
                  "min_ade_recorded", "mean_ade_recorded")
#: Per-row fields that are timings, not results.
TIMING_KEYS = ("ms_per_frame", "fps", "world_build_s", "wall_s")


# --------------------------------------------------------------------------- helpers

def _get(d, path):
    for k in path:
        d = d.get(k) if isinstance(d, dict) else None
    return d


def _num(x) -> float | None:
    if isinstance(x, bool):
        return float(x)
    return float(x) if isinstance(x, (int, float)) and math.isfinite(float(x)) else None


def _diff(a, b) -> float | None:
    """|a - b| for two numbers (booleans as 0/1); None when either is missing."""
    a, b = _num(a), _num(b)
    return None if a is None or b is None else abs(a - b)


def _max(values) -> float | None:
    vals = [v for v in values if v is not None]
    return max(vals) if vals else None


def _linf(a, b) -> float | None:
    if a is None or b is None:
        return None
    fa = [float(x) for x in _flatten(a)]
    fb = [float(x) for x in _flatten(b)]
    if len(fa) != len(fb):
        return None
    return max((abs(x - y) for x, y in zip(fa, fb)), default=0.0)


def _flatten(x):
    if isinstance(x, (list, tuple)):
        for v in x:
            yield from _flatten(v)
    else:
        yield x


def _without_times(rec: dict) -> dict:
    r = {k: v for k, v in rec.items() if k not in TIMING_KEYS}
    if isinstance(r.get("metrics"), dict):
        r["metrics"] = {k: v for k, v in r["metrics"].items() if k not in TIMING_KEYS}
    return r


def _episode(metrics: dict) -> dict:
    return {name: _get(metrics, path) for name, path in EPISODE_METRICS.items()}


def _read_json(path: Path):
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt") as f:
        return json.load(f)


def _sha256(path: Path) -> str:
    return "sha256:" + hashlib.sha256(path.read_bytes()).hexdigest()[:16]


# --------------------------------------------------------------------------- running a command under a configuration

def config_env(config: str) -> dict[str, str]:
    """This environment without any kernel-choosing variable (so ``native`` is the CPU's own
    choice), one thread per numerical library."""
    env = {k: v for k, v in os.environ.items() if k not in NUMERICS_ENV}
    env.update(single_thread_env())
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def config_argv(config: str, cmd: list[str]) -> list[str]:
    """``cmd`` as run under ``config``: itself for native, else through ``adv3d numerics --emulate``."""
    if config == "native":
        return list(cmd)
    return [sys.executable, "-m", "adv3d_runner.cli", "numerics", "--emulate", config, "--", *cmd]


def run_under(config: str, cmd: list[str], log: Path) -> dict:
    """Run ``cmd`` under ``config`` (cwd: the repository), its output to ``log``."""
    argv = config_argv(config, cmd)
    log.parent.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), os.times()
    with open(log, "w") as out:
        rc = subprocess.call(argv, env=config_env(config), cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    c1 = os.times()
    wall = time.perf_counter() - t0
    cpu = (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)
    if rc != 0:
        tail = log.read_text(errors="replace").splitlines()[-15:]
        print(f"    exit status {rc}; the end of {log}:\n      " + "\n      ".join(tail), flush=True)
    return {"argv": [_short(a) for a in argv], "rc": rc, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
            "log": _short(str(log))}


def _short(text: str) -> str:
    """Paths inside the repository written relative to it; the interpreter by its name."""
    if text == sys.executable:
        return "python"
    try:
        return str(Path(text).resolve().relative_to(ROOT)) if os.path.isabs(text) else text
    except ValueError:
        return text


def probe_numerics(config: str) -> dict:
    """``adv3d numerics --json`` under ``config``: the configuration a command run there sees."""
    argv = config_argv(config, [sys.executable, "-m", "adv3d_runner.cli", "numerics", "--json"])
    if config != "native":  # ``--emulate NAME`` without a command prints the emulated configuration
        argv = [sys.executable, "-m", "adv3d_runner.cli", "numerics", "--emulate", config, "--json"]
    out = subprocess.run(argv, env=config_env(config), cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"configuration {config}: {out.stderr.strip() or out.stdout.strip()}")
    return json.loads(out.stdout)


# --------------------------------------------------------------------------- workload 1: the demo

def run_demo(config: str, scratch: Path) -> dict:
    folder = scratch / config / "demo"
    if folder.exists():
        shutil.rmtree(folder)  # the demo resumes an attack it finds: start from nothing
    proc = run_under(config, [sys.executable, "-m", "adv3d_runner.cli", "demo", "--out", str(folder)],
                     scratch / config / "demo.log")
    value: dict = {"process": proc}
    if proc["rc"] != 0:
        return value
    run_dir = folder / "attack"
    run = _read_json(run_dir / "run.json")
    summary = _read_json(run_dir / "summary.json")
    journal = [json.loads(line) for line in (run_dir / "queries.jsonl").read_text().splitlines() if line.strip()]
    value["numerics"] = run.get("versions", {}).get("numerics")
    value["meshes"] = {p.name: _sha256(p) for p in sorted(folder.glob("*.glb"))}
    value["_mesh_paths"] = {p.name: str(p) for p in sorted(folder.glob("*.glb"))}
    scene_id, entry = next(iter(summary["scenes"].items()))
    value["scene"] = scene_id
    value["original"] = {"cost": entry["original"]["cost"], **_episode(entry["original"]["metrics"])}
    value["modes"] = {}
    for mode, m in entry["modes"].items():
        best = next((r for r in journal if r["mode"] == mode and r["index"] == m.get("best_index")), {})
        ev = m.get("closed_loop_eval") or {}
        value["modes"][mode] = {
            "best_index": m.get("best_index"), "best_cost": m.get("best_cost"), "best_unit": m.get("best_unit"),
            "best_latent": best.get("latent"), "best_scales": best.get("scales"),
            "closed_loop_eval": {"cost": ev.get("cost"), **{t: _get(ev, ("components", t)) for t in TERMS},
                                 **_episode(ev.get("metrics") or {})}}
    value["journal"] = [{k: r.get(k) for k in ("mode", "index", "cost", "status")} for r in journal]
    value["_records"] = journal  # compared, not kept
    return value


def compare_demo(a: dict, b: dict) -> dict:
    if "_records" not in a or "_records" not in b:
        return {"error": "a run failed"}
    d: dict = {"meshes_identical": a["meshes"] == b["meshes"],
               "meshes_differing": sorted(k for k in a["meshes"] if a["meshes"].get(k) != b["meshes"].get(k))}
    d["mesh_vertices"] = {k: _mesh_diff(a["_mesh_paths"][k], b["_mesh_paths"][k]) for k in d["meshes_differing"]
                          if k in b["_mesh_paths"]}
    d["original"] = {k: _diff(a["original"][k], b["original"][k]) for k in a["original"]}
    d["modes"] = {}
    for mode, ma in a["modes"].items():
        mb = b["modes"].get(mode, {})
        d["modes"][mode] = {
            "same_best_index": ma["best_index"] == mb.get("best_index"),
            "best_cost": _diff(ma["best_cost"], mb.get("best_cost")),
            "best_unit_linf": _linf(ma["best_unit"], mb.get("best_unit")),
            "best_latent_linf": _linf(ma["best_latent"], mb.get("best_latent")),
            "closed_loop_eval": {k: _diff(v, mb.get("closed_loop_eval", {}).get(k))
                                 for k, v in ma["closed_loop_eval"].items()}}
    rb = {(r["mode"], r["index"]): r for r in b["_records"]}
    n = identical = same_cost = same_unit = 0
    first_diff = first_cost_diff = first_unit_diff = None
    cost_diffs, unit_diffs = [], []
    for r in a["_records"]:
        o = rb.get((r["mode"], r["index"]))
        if o is None:
            continue
        n += 1
        if _without_times(r) == _without_times(o):
            identical += 1
        elif first_diff is None:
            first_diff = {"mode": r["mode"], "index": r["index"],
                          "fields": sorted(k for k in _without_times(r) if _without_times(r)[k] != _without_times(o).get(k))}
        if r.get("cost") == o.get("cost"):
            same_cost += 1
        elif first_cost_diff is None:
            first_cost_diff = r["index"]
        if r.get("unit") == o.get("unit"):
            same_unit += 1
        elif first_unit_diff is None:
            first_unit_diff = r["index"]
        cost_diffs.append(_diff(r.get("cost"), o.get("cost")))
        unit_diffs.append(_linf(r.get("unit"), o.get("unit")))
    d["journal"] = {"queries": n, "identical_records": identical, "identical_objectives": same_cost,
                    "identical_units": same_unit, "first_differing_record": first_diff,
                    "first_differing_objective_index": first_cost_diff, "first_differing_unit_index": first_unit_diff,
                    "max_abs_objective_diff": _max(cost_diffs), "max_unit_linf": _max(unit_diffs)}
    return d


def _mesh_diff(path_a: str, path_b: str) -> dict:
    """Two decoded meshes: vertex and face counts, and the largest vertex distance (m) when
    the counts agree."""
    import numpy as np
    import trimesh

    a = trimesh.load(path_a, force="mesh")
    b = trimesh.load(path_b, force="mesh")
    out = {"vertices": [len(a.vertices), len(b.vertices)], "faces": [len(a.faces), len(b.faces)]}
    if a.vertices.shape == b.vertices.shape:
        out["max_vertex_diff_m"] = float(np.abs(np.asarray(a.vertices) - np.asarray(b.vertices)).max())
        out["same_faces"] = bool(np.array_equal(a.faces, b.faces))
    return out


# --------------------------------------------------------------------------- workload 2: sanity --quick

def run_sanity(config: str, scratch: Path, workers: int, keep: bool) -> dict:
    name = f"portability.sanity.quick.{config}"
    path = ROOT / "bench" / "results" / f"{name}.json"
    proc = run_under(config, [sys.executable, str(ROOT / "bench" / "sanity.py"), "--quick", "--workers", str(workers),
                              "--name", name], scratch / config / "sanity.log")
    value: dict = {"process": proc}
    if proc["rc"] != 0 or not path.exists():
        return value
    doc = _read_json(path)
    if keep:
        shutil.copy(path, scratch / config / path.name)
    path.unlink()  # a temporary name: the kept sanity files stay as they are
    value["numerics"] = doc.get("machine", {}).get("numerics")
    value["parts"] = _sanity_parts(doc)
    return value


def _sanity_parts(doc: dict) -> dict:
    parts = {}
    for part, summary, rows in (("generated", doc.get("summary"), doc.get("rows")),
                                ("real", _get(doc, ("real", "summary")), _get(doc, ("real", "rows")))):
        if summary is None:
            continue
        parts[part] = {"summary": {k: summary.get(k) for k in SANITY_SUMMARY if k in summary},
                       "scenes": {r["scene"]: {**_episode(r), "progress_ratio": _get(r, ("ego", "progress_ratio")),
                                               "min_ade_recorded": _get(r, ("prediction_recorded", "min_ade"))}
                                  for r in rows},
                       "_rows": {r["scene"]: _without_times({k: v for k, v in r.items() if k != "plans"}) for r in rows}}
    return parts


def compare_sanity(a: dict, b: dict) -> dict:
    if "parts" not in a or "parts" not in b:
        return {"error": "a run failed"}
    out = {}
    for part, pa in a["parts"].items():
        pb = b["parts"].get(part)
        if pb is None:
            continue
        common = [s for s in pa["scenes"] if s in pb["scenes"]]
        per_metric = {}
        for k in next(iter(pa["scenes"].values()), {}):
            diffs = [(_diff(pa["scenes"][s].get(k), pb["scenes"][s].get(k)), s) for s in common]
            diffs = [x for x in diffs if x[0] is not None]
            worst = max(diffs, default=(None, None))
            per_metric[k] = {"max_abs_diff": worst[0], "scene": worst[1] if worst[0] else None,
                             "scenes_differing": sum(1 for x in diffs if x[0] > 0)}
        out[part] = {
            "scenes": len(common),
            "identical_scenes": sum(1 for s in common if "_rows" in pa and pa["_rows"].get(s) == pb.get("_rows", {}).get(s)),
            "per_scene": per_metric,
            "summary": {k: _diff(v, pb["summary"].get(k)) for k, v in pa["summary"].items()}}
    return out


def kept_sanity(path: Path, scenes: dict[str, list[str]]) -> dict | None:
    """The kept sanity result ``path`` (default the full ``bench/results/sanity.json``) cut to
    the scenes that ran here (``scenes``: part -> names), its summaries made again from those
    rows (``bench/sanity.py``'s ``summarise``)."""
    if not path.exists():
        return None
    sys.path.insert(0, str(ROOT / "bench"))
    from sanity import summarise

    doc = _read_json(path)
    cut = {}
    for part, rows in (("generated", doc.get("rows")), ("real", _get(doc, ("real", "rows")))):
        rows = [r for r in rows or [] if r["scene"] in scenes.get(part, ())]
        if rows:
            cut[part] = rows
    made = {"summary": summarise(cut["generated"], real=False) if "generated" in cut else None,
            "rows": cut.get("generated", []),
            "real": {"summary": summarise(cut["real"], real=True), "rows": cut["real"]} if "real" in cut else None}
    return {"file": _short(str(path)), "command": doc.get("command"),
            "numerics": doc.get("machine", {}).get("numerics"),
            "scenes": {part: len(rows) for part, rows in cut.items()}, "parts": _sanity_parts(made)}


# --------------------------------------------------------------------------- workload 3: one kept held-out evaluation

def run_heldout(config: str, scratch: Path, run_dir: str, seeds: int, what: list[str]) -> dict:
    out = scratch / config / "heldout.json"
    if out.exists():
        out.unlink()
    proc = run_under(config, [sys.executable, str(Path(__file__).resolve()), "--heldout-worker", run_dir,
                              "--heldout-seeds", str(seeds), "--heldout-what", ",".join(what), "--out", str(out)],
                     scratch / config / "heldout.log")
    value: dict = {"process": proc}
    if proc["rc"] != 0 or not out.exists():
        return value
    doc = _read_json(out)
    value.update({k: doc[k] for k in ("numerics", "versions", "kept_versions", "kept_numerics", "evaluations")})
    return value


def heldout_worker(run_dir: Path, seeds: int, what: list[str], out: Path) -> int:
    """In the subprocess: simulate the held-out evaluations of ``run_dir`` again (each distinct
    shape and seed once), with the kept records beside them."""
    import numpy as np

    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.evaluator import EpisodeEvaluator
    from adv3d_runner.attack.protocol import heldout_evaluate, heldout_tasks
    from adv3d_runner.fileio import write_json
    from adv3d_runner.machine import limit_threads, numerical_config

    limit_threads()
    run = _read_json(run_dir / "run.json")
    summary = _read_json(run_dir / "summary.json")
    kept = _read_json(run_dir / "heldout.json.gz")["evaluations"] if (run_dir / "heldout.json.gz").exists() else {}
    settings = AttackConfig.from_run_json(run).settings
    tasks = [t for t in heldout_tasks(summary, int(run["seed"]), seeds) if t.what in what]
    done: dict = {}
    evaluations = {}
    for t in tasks:
        ident = (t.seed, t.unit)
        t0 = time.perf_counter()
        if ident not in done:
            done[ident] = heldout_evaluate(t.ref, settings, None if t.unit is None else np.asarray(t.unit), t.seed)
        rec = done[ident]
        evaluations[t.key] = {"what": t.what, "seed": t.seed, "unit": t.unit, "cost": rec["cost"],
                              "components": rec["components"], "metrics": rec["metrics"],
                              "kept": {k: kept[t.key][k] for k in ("cost", "components", "metrics")} if t.key in kept else None}
        print(f"{t.key}: objective {rec['cost']:.6f} (kept {kept.get(t.key, {}).get('cost')}), "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    doc = {"run": str(run_dir), "numerics": numerical_config(),
           "versions": EpisodeEvaluator(settings).versions(),
           "kept_versions": {k: v for k, v in run.get("versions", {}).items() if k != "numerics"},
           "kept_numerics": run.get("versions", {}).get("numerics"), "evaluations": evaluations}
    write_json(out, doc)
    return 0


def _heldout_values(rec: dict) -> dict:
    return {"cost": rec.get("cost"), **{t: _get(rec, ("components", t)) for t in TERMS}, **_episode(rec.get("metrics") or {})}


def compare_heldout(a: dict, b: dict | None = None) -> dict:
    """Two configurations' evaluations (or, with ``b`` None, ``a`` against the kept records)."""
    if "evaluations" not in a or (b is not None and "evaluations" not in b):
        return {"error": "a run failed"}
    pairs = []
    for key, ra in a["evaluations"].items():
        rb = ra.get("kept") if b is None else b["evaluations"].get(key)
        if rb is not None:
            pairs.append((key, ra, rb))
    per = {}
    for name in _heldout_values({}):
        diffs = [(_diff(_heldout_values(ra)[name], _heldout_values(rb)[name]), key) for key, ra, rb in pairs]
        diffs = [x for x in diffs if x[0] is not None]
        worst = max(diffs, default=(None, None))
        per[name] = {"max_abs_diff": worst[0], "evaluation": worst[1] if worst[0] else None,
                     "evaluations_differing": sum(1 for x in diffs if x[0] > 0)}
    same = sum(1 for _, ra, rb in pairs if all(_without_times(ra)[k] == _without_times(rb)[k]
                                               for k in ("cost", "components", "metrics")))
    return {"evaluations": len(pairs), "identical": same, "per_quantity": per}


# --------------------------------------------------------------------------- the table

def largest_differences(doc: dict, configs: list[str]) -> list[dict]:
    """One row per workload and quantity: the largest difference of each configuration against
    the first (and, for sanity and heldout, of each configuration against the kept result)."""
    rows = []

    def row(workload, quantity, values: dict):
        rows.append({"workload": workload, "quantity": quantity, **values})

    ref = configs[0]
    pairs = [f"{ref} vs {c}" for c in configs[1:]]
    if "demo" in doc["workloads"]:
        diffs = doc["workloads"]["demo"]["differences"]
        if all("error" not in diffs[p] for p in pairs):
            mode = next(iter(diffs[pairs[0]]["modes"]), None) if pairs else None
            for q, f in [
                ("journal: identical records / queries", lambda d: f"{d['journal']['identical_records']}/{d['journal']['queries']}"),
                ("journal: identical objectives / queries", lambda d: f"{d['journal']['identical_objectives']}/{d['journal']['queries']}"),
                ("journal: identical unit vectors / queries", lambda d: f"{d['journal']['identical_units']}/{d['journal']['queries']}"),
                ("journal: first query whose objective differs", lambda d: d["journal"]["first_differing_objective_index"]),
                ("journal: first query whose unit vector differs", lambda d: d["journal"]["first_differing_unit_index"]),
                ("journal: max |objective diff|", lambda d: d["journal"]["max_abs_objective_diff"]),
                ("journal: max L-inf between queried units", lambda d: d["journal"]["max_unit_linf"]),
                (f"{mode}: same best query index", lambda d: d["modes"][mode]["same_best_index"]),
                (f"{mode}: |best objective diff|", lambda d: d["modes"][mode]["best_cost"]),
                (f"{mode}: best unit L-inf", lambda d: d["modes"][mode]["best_unit_linf"]),
                (f"{mode}: best latent L-inf", lambda d: d["modes"][mode]["best_latent_linf"]),
                (f"{mode}: best shape closed-loop |objective diff|", lambda d: d["modes"][mode]["closed_loop_eval"]["cost"]),
                (f"{mode}: best shape closed-loop |AP diff|", lambda d: d["modes"][mode]["closed_loop_eval"]["ap"]),
                (f"{mode}: best shape closed-loop |minADE diff|", lambda d: d["modes"][mode]["closed_loop_eval"]["min_ade"]),
                ("original scene |objective diff|", lambda d: d["original"]["cost"]),
                ("original scene |AP diff|", lambda d: d["original"]["ap"]),
                ("original scene |minADE diff|", lambda d: d["original"]["min_ade"]),
                ("decoded meshes identical", lambda d: d["meshes_identical"]),
                ("decoded meshes: max vertex diff (m)", lambda d: _max(m.get("max_vertex_diff_m")
                                                                        for m in d["mesh_vertices"].values())),
            ]:
                row("demo", q, {p: f(diffs[p]) for p in pairs})
    if "sanity" in doc["workloads"]:
        w = doc["workloads"]["sanity"]
        cols = {p: w["differences"][p] for p in pairs}
        cols.update({f"kept vs {c}": w["vs_kept"][c] for c in configs if c in w.get("vs_kept", {})})
        if all("error" not in d for d in cols.values()):
            for part in ("generated", "real"):
                if not all(part in d for d in cols.values()):
                    continue
                row("sanity", f"{part}: identical scenes", {p: f"{d[part]['identical_scenes']}/{d[part]['scenes']}"
                                                            for p, d in cols.items()})
                for k in ("ap", "recall", "min_ade", "mean_ade", "drive_jerk", "progress_m", "collided"):
                    row("sanity", f"{part}: max |{k} diff| over scenes", {p: d[part]["per_scene"][k]["max_abs_diff"]
                                                                          for p, d in cols.items()})
                for k in ("ap", "min_ade", "drive_jerk", "collisions"):
                    row("sanity", f"{part}: |summary {k} diff|", {p: d[part]["summary"].get(k) for p, d in cols.items()})
    if "heldout" in doc["workloads"]:
        w = doc["workloads"]["heldout"]
        cols = {p: w["differences"][p] for p in pairs}
        cols.update({f"kept vs {c}": w["vs_kept"][c] for c in configs if c in w.get("vs_kept", {})})
        if all("error" not in d for d in cols.values()):
            row("heldout", "identical evaluations", {p: f"{d['identical']}/{d['evaluations']}" for p, d in cols.items()})
            for k in ("cost", "det", "pred", "plan", "ap", "recall", "min_ade", "mean_ade", "drive_jerk"):
                row("heldout", f"max |{'objective' if k == 'cost' else k} diff|",
                    {p: d["per_quantity"][k]["max_abs_diff"] for p, d in cols.items()})
    return rows


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "0" if v == 0 else f"{v:.3g}"
    return str(v)


def print_table(rows: list[dict]) -> None:
    if not rows:
        return
    cols = [k for k in rows[0] if k not in ("workload", "quantity")]
    for r in rows[1:]:
        cols += [k for k in r if k not in ("workload", "quantity") and k not in cols]
    print("\n| workload | quantity | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for r in rows:
        print(f"| {r['workload']} | {r['quantity']} | " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")


def _strip_private(x):
    if isinstance(x, dict):
        return {k: _strip_private(v) for k, v in x.items() if not k.startswith("_")}
    if isinstance(x, list):
        return [_strip_private(v) for v in x]
    return x


# --------------------------------------------------------------------------- main

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="native,avx2",
                    help="comma-separated numerical configurations: native and/or an emulation "
                         "(adv3d_runner.machine.EMULATIONS: avx2, sse4.2); the first is the reference")
    ap.add_argument("--workloads", default=",".join(WORKLOADS), help=f"comma-separated: {', '.join(WORKLOADS)}")
    ap.add_argument("--heldout-run", default=DEFAULT_HELDOUT_RUN,
                    help=f"a kept run folder of one scene with heldout.json.gz (default {DEFAULT_HELDOUT_RUN})")
    ap.add_argument("--heldout-seeds", type=int, default=3, help="evaluation seeds (the kept tables use 3)")
    ap.add_argument("--heldout-what", default="original,open,closed",
                    help="which held-out evaluations: original and/or the modes whose best shape (default all)")
    ap.add_argument("--sanity-workers", type=int, default=1, help="bench/sanity.py --workers (default 1)")
    ap.add_argument("--kept-sanity", default=KEPT_SANITY,
                    help=f"kept sanity result whose rows of the same scenes each configuration is compared with "
                         f"(default {KEPT_SANITY}: the full run of the current planner)")
    ap.add_argument("--keep-sanity-files", action="store_true", help="keep a copy of each sanity file in --scratch")
    ap.add_argument("--scratch", default=str(ROOT / "out" / "portability"),
                    help="folder of the runs' outputs and logs (default out/portability; emptied per workload)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "portability.json"))
    ap.add_argument("--heldout-worker", default=None, help=argparse.SUPPRESS)  # the held-out subprocess
    args = ap.parse_args()
    what = [w.strip() for w in args.heldout_what.split(",") if w.strip()]
    if args.heldout_worker:
        return heldout_worker(Path(args.heldout_worker), args.heldout_seeds, what, Path(args.out))

    from adv3d_runner.errors import ConfigError
    from adv3d_runner.fileio import write_json
    from adv3d_runner.machine import EMULATIONS
    from adv3d_runner.machine_cli import emulation_env

    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    workloads = [w.strip() for w in args.workloads.split(",") if w.strip()]
    if len(configs) < 2 or len(set(configs)) != len(configs):
        ap.error("--configs takes at least two different configurations")
    if set(workloads) - set(WORKLOADS) or not workloads:
        ap.error(f"--workloads takes {', '.join(WORKLOADS)}")
    for c in configs:
        if c != "native":
            if c not in EMULATIONS:
                ap.error(f"--configs: {c!r} is neither native nor one of {', '.join(EMULATIONS)}")
            try:
                emulation_env(c)
            except ConfigError as exc:
                ap.error(str(exc))
    held = ROOT / args.heldout_run
    if "heldout" in workloads and not (held / "heldout.json.gz").exists():
        ap.error(f"--heldout-run {args.heldout_run}: no heldout.json.gz there")
    scratch = Path(args.scratch)

    t0 = time.time()
    info = machine_info("numpy", "embreex", "torch", "numba")
    doc: dict = {"format": "adv3d-bench", "version": 1, "topic": "portability",
                 "command": " ".join(["python", "bench/portability.py"] + sys.argv[1:]), "machine": info,
                 "configs": {}, "workloads": {}}
    print(f"configurations: {', '.join(configs)}; workloads: {', '.join(workloads)}", flush=True)
    for c in configs:
        cfg = probe_numerics(c)
        doc["configs"][c] = {"numerics": cfg, "prefix": [_short(a) for a in config_argv(c, [])]}
        print(f"  {c}: key {cfg['key']}  Embree {cfg['embree_isa']}, numpy {cfg['numpy_simd']}, {cfg['blas']}, "
              f"torch {cfg['torch_capability']}, numba {cfg['numba_target']}", flush=True)

    ref = configs[0]
    for w in workloads:
        values = {}
        for c in configs:
            print(f"{w} under {c} ...", flush=True)
            if w == "demo":
                values[c] = run_demo(c, scratch)
            elif w == "sanity":
                values[c] = run_sanity(c, scratch, args.sanity_workers, args.keep_sanity_files)
            else:
                values[c] = run_heldout(c, scratch, args.heldout_run, args.heldout_seeds, what)
            p = values[c]["process"]
            got = (values[c].get("numerics") or {}).get("key")
            print(f"  {w} under {c}: exit {p['rc']}, {p['wall_s']:.0f} s wall, {p['cpu_s']:.0f} s CPU; "
                  f"numerical key inside {got} (expected {doc['configs'][c]['numerics']['key']})", flush=True)
        compare = {"demo": compare_demo, "sanity": compare_sanity, "heldout": compare_heldout}[w]
        entry = {"per_config": values,
                 "differences": {f"{ref} vs {c}": compare(values[ref], values[c]) for c in configs[1:]}}
        if w == "sanity":
            ran = next((v["parts"] for v in values.values() if "parts" in v), {})
            kept = kept_sanity(ROOT / args.kept_sanity, {part: list(x["scenes"]) for part, x in ran.items()})
            if kept is not None:
                entry["kept"] = {k: v for k, v in kept.items() if k != "parts"}
                entry["vs_kept"] = {c: compare_sanity({"parts": kept["parts"]}, values[c]) for c in configs}
        if w == "heldout":
            entry["run"] = args.heldout_run
            entry["seeds"] = args.heldout_seeds
            entry["what"] = what
            entry["vs_kept"] = {c: compare_heldout(values[c]) for c in configs}
            v = values[ref]
            if "versions" in v:  # the kept records were made by the code of their day
                entry["versions_differing_from_kept"] = sorted(
                    k for k in set(v["versions"]) | set(v["kept_versions"]) if k in v["versions"]
                    and v["versions"].get(k) != v["kept_versions"].get(k))
                if entry["versions_differing_from_kept"]:
                    print(f"  note: the kept held-out records were made with other versions of "
                          f"{', '.join(entry['versions_differing_from_kept'])} "
                          + str({k: [v['kept_versions'].get(k), v['versions'][k]]
                                 for k in entry['versions_differing_from_kept']}), flush=True)
        doc["workloads"][w] = entry
    for c in configs:  # what each subprocess reported, per workload
        doc["configs"][c]["inside"] = {w: (doc["workloads"][w]["per_config"][c].get("numerics") or {}).get("key")
                                       for w in workloads}
        doc["configs"][c]["consistent"] = all(k == doc["configs"][c]["numerics"]["key"]
                                              for k in doc["configs"][c]["inside"].values())
    doc["largest_differences"] = largest_differences(doc, configs)
    doc["wall_s"] = round(time.time() - t0, 1)
    doc = _strip_private(doc)
    print_table(doc["largest_differences"])
    for c in configs:
        print(f"{c}: key {doc['configs'][c]['numerics']['key']}, inside the workloads {doc['configs'][c]['inside']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, doc)
    print(f"wrote {_short(str(out))} ({doc['wall_s']:.0f} s wall)")
    failed = [f"{w}/{c}" for w in workloads for c in configs if doc["workloads"][w]["per_config"][c]["process"]["rc"]]
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
