"""Sanity of the closed loop on the bundled benchmarks: the generated highways and the real
NGSIM US-101 recordings (docs/episode.md, docs/autonomy.md).

Every scene: a 5 s closed-loop episode (actors replay their logs), the full LiDAR simulation
(the scene's 64-beam rig, library meshes) and the chosen stack. Two sets:

* **generated**: the 100 scenes of ``scenes/highway/`` (``--quick``: every 10th), or with
  ``--generated-dir DIR`` the scenes of DIR (tuning on the generator's *train* split:
  ``adv3d scenes generate --out runs/gentrain --count 40 --seed 500000 --split train``);
* **real**: the *benchmark* part of ``scenes/real/`` (``scenes/real/split.json``, recordings
  held out from every training and tuning step; ``--real-part train`` runs the training part,
  which is what the planner's comfort limits were tuned on; ``--real-part fresh`` runs
  ``scenes/real-fresh/``, recordings 10-18 that nothing was tuned on, docs/benchmark.md).

Reported per set, next to the paper's "Original" row for Autonomy-A: the share of scenes where
the ego neither collides nor leaves the road, collisions and whether the ego was at fault (the
first contact is with an actor ahead of it), AP / recall in the ROI, minADE / meanADE, planning
and driving comfort (mean |lateral acceleration|, mean |jerk| and the peak |jerk| of each
episode). For real scenes also: the ego's progress against the logged driver's over the same
frames, its slowest speed and hardest braking against the log's, and minADE / meanADE over the
recorded future only (the ``--extend``-ed tail of a recording is IDM, not real traffic). The
issue-17 targets on the real benchmark are checked at the end.

    .venv/bin/python bench/sanity.py [--quick] [--sets generated,real] [--real-part benchmark|train|fresh]
                                     [--autonomy A|B|oracle|A-lanefollow] [--workers 2] [--seconds 5] [--tag NAME]

``--autonomy A`` needs the trained detector and predictor (assets/models/); without them use
``--autonomy oracle``. ``--autonomy B`` (instance-free, the implicit occupancy model) reports the
occupancy metrics instead of AP and ADE (paper Table 1's lower block: occupancy mAP and
Soft-IoU, flow-grounded mAP and Soft-IoU, and the flow EPE) next to Autonomy-A's rows of the
same scenes from ``bench/results/sanity.json`` (its ``real`` rows for the real set); the real
targets on prediction do not apply to it (no trajectories). Writes ``bench/results/sanity[.<autonomy>][.quick].json`` when both sets
run (the generated set under ``summary`` / ``rows`` as before, the real one under ``real``), and
``bench/results/sanity.real-<part>[.<autonomy>].json`` for ``--sets real``; ``--tag NAME`` appends
``.NAME`` to the file name (before/after pairs, e.g. an old detector).

Tuning the planner without editing code (on ``--real-part train`` only, docs/autonomy.md):
``--planner-config '{"proposals": {"max_brake_jerk": 4}}'`` (or a .json file) runs every scene
with those fields of ``PlannerConfig`` / ``ProposalConfig`` / ``CostWeights`` replaced; unknown
fields are refused by name, and the result needs ``--name`` or ``--tag``. The overrides are kept
in the result (``planner_overrides``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.errors import ConfigError  # noqa: E402

PAPER_ORIGINAL_A = {"ap": 0.882, "recall": 0.894, "min_ade": 2.14, "mean_ade": 4.90, "plan_lat": 0.203,
                    "plan_jerk": 0.336, "drive_lat": 0.194, "drive_jerk": 0.331}
PAPER_ORIGINAL_B = {"map": 0.831, "soft_iou": 0.504, "fg_map": 0.946, "fg_soft_iou": 0.612, "plan_lat": 0.256,
                    "plan_jerk": 0.319, "drive_lat": 0.263, "drive_jerk": 0.315}
# the real benchmark part's targets (docs/autonomy.md, real traffic)
REAL_TARGETS = {"min_ade_max": 2.0, "drive_jerk_max": 1.0, "at_fault_collisions_max": 0, "progress_ratio_min": 0.8}

_STACK = None
_LIB = None


#: ``--planner-limits``: the proposals' jerk limits and leader speed window as they were
#: before the real-traffic tuning set them on real traffic (what Autonomy-B was developed with); a
#: diagnosis of how those limits change a stack, not a shipped configuration.
LIMITS_BEFORE_ISSUE17 = {"max_jerk": 4.0, "max_release_jerk": 10.0, "max_brake_jerk": 4.0, "leader_speed_window": 0.1}


def _run(job: tuple) -> dict:
    path, autonomy, seconds, real = job[:4]
    overrides = job[4] if len(job) > 4 else {}
    seed = job[5] if len(job) > 5 else 0
    global _STACK, _LIB
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors.world import world_from_scene
    from adv3d_runner.sim.episode import default_library, run_episode
    from adv3d_runner.sim.evaluate import episode_metrics
    from adv3d_runner.autonomy.stacks import make_stack

    if _STACK is None:
        _STACK = make_stack(autonomy)
        _LIB = default_library()
        if overrides:
            from adv3d_runner.autonomy.planner import PlannerConfig, SamplingPlanner

            _STACK.planner = SamplingPlanner(PlannerConfig.from_overrides(overrides))
    t0 = time.perf_counter()
    scene = load_scene(path)
    world = world_from_scene(scene, _LIB)
    t1 = time.perf_counter()
    result = run_episode(scene, _STACK, seconds=seconds, world=world, seed=seed)
    m = episode_metrics(result, scene.lanes)
    m["world_build_s"] = t1 - t0
    m["wall_s"] = time.perf_counter() - t0
    m["plans"] = {}  # which candidate kinds were chosen (diagnosis)
    for o in result.outputs:
        lab = o.plan.label.split("/")[0] if o.plan.label else "?"
        m["plans"][lab] = m["plans"].get(lab, 0) + 1
    m["ego"] = _ego_against_log(scene, result)
    if real:
        m["prediction_recorded"] = _recorded_prediction(scene, result)
    return m


def _ego_against_log(scene, result) -> dict:
    """The driven ego against the logged driver over the same frames: path length (m) and
    their ratio, slowest speed (m/s), hardest braking (m/s^2, from speed differences), time
    spent below 0.5 m/s (s)."""
    T, a = result.frames, result.start_frame
    log = scene.ego_poses()[a:a + T, :2]
    log_v = scene.ego_speeds()[a:a + T]
    logged = float(np.sum(np.hypot(*np.diff(log, axis=0).T)))
    driven = float(np.sum(np.hypot(*np.diff(result.ego_poses[:, :2], axis=0).T)))
    v = result.ego_speeds
    return {"progress_m": driven, "logged_progress_m": logged,
            "progress_ratio": driven / logged if logged > 1e-6 else None,
            "min_speed": float(v.min()), "logged_min_speed": float(log_v.min()),
            "min_accel": float(np.min(np.diff(v)) / result.dt) if T > 1 else 0.0,
            "logged_min_accel": float(np.min(np.diff(log_v)) / result.dt) if T > 1 else 0.0,
            "standstill_s": float(np.sum(v < 0.5) * result.dt)}


def _recorded_prediction(scene, result) -> dict:
    """minADE / meanADE (m) with the ground truth restricted to recorded frames: an actor's
    pose counts only where its track is not ``synthetic`` (a recording's ``--extend``-ed tail)."""
    from dataclasses import replace

    from adv3d_runner.metrics.prediction import prediction_metrics
    from adv3d_runner.sim.evaluate import prediction_pairs

    F = scene.frames
    frames = result.start_frame + np.arange(len(result.actor_poses))
    recorded = np.zeros((len(frames), len(result.actor_ids)), bool)
    inside = frames < F
    for i, aid in enumerate(result.actor_ids):
        recorded[inside, i] = ~scene.actor_synthetic(int(aid))[frames[inside]]
    masked = replace(result, actor_poses=np.where(recorded[..., None], result.actor_poses, np.nan))
    pairs = [p for p in prediction_pairs(masked) if len(p[0])]
    if not pairs:
        return {"min_ade": None, "mean_ade": None, "n": 0}
    pm = prediction_metrics(np.concatenate([p for p, _, _ in pairs]), np.concatenate([g for _, g, _ in pairs]),
                            np.concatenate([v for _, _, v in pairs]))
    f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {"min_ade": f(pm.min_ade), "mean_ade": f(pm.mean_ade), "n": int(sum(len(p) for p, _, _ in pairs))}


def _get(row: dict, keys: tuple[str, ...]):
    v = row
    for k in keys:
        v = v.get(k) if isinstance(v, dict) else None
    return v


def _mean(rows, *keys) -> float | None:
    vals = [v for v in (_get(r, keys) for r in rows) if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def _max(rows, *keys) -> float | None:
    vals = [v for v in (_get(r, keys) for r in rows) if v is not None and np.isfinite(v)]
    return float(np.max(vals)) if vals else None


def _min(rows, *keys) -> float | None:
    vals = [v for v in (_get(r, keys) for r in rows) if v is not None and np.isfinite(v)]
    return float(np.min(vals)) if vals else None


def summarise(rows: list[dict], real: bool) -> dict:
    """Means over the scenes (peaks: mean of the per-episode peaks and the largest one)."""
    collided = [r["collision"]["collided"] for r in rows]
    at_fault = [r["collision"]["at_fault"] for r in rows]
    off = [r["off_road"] for r in rows]
    s = {
        "scenes": len(rows),
        "ok_rate": float(np.mean([not c and not o for c, o in zip(collided, off)])),
        "ok_rate_at_fault_only": float(np.mean([not c and not o for c, o in zip(at_fault, off)])),
        "collision_rate": float(np.mean(collided)), "at_fault_collision_rate": float(np.mean(at_fault)),
        "collisions": int(np.sum(collided)), "at_fault_collisions": int(np.sum(at_fault)),
        "off_road_rate": float(np.mean(off)),
        "ap": _mean(rows, "detection", "ap"), "recall": _mean(rows, "detection", "recall"),
        "min_ade": _mean(rows, "prediction", "min_ade"), "mean_ade": _mean(rows, "prediction", "mean_ade"),
        "plan_lat": _mean(rows, "planning_comfort", "lat"), "plan_jerk": _mean(rows, "planning_comfort", "jerk"),
        "plan_peak_jerk": _mean(rows, "planning_comfort", "max_jerk"),
        "drive_lat": _mean(rows, "driving_comfort", "lat"), "drive_jerk": _mean(rows, "driving_comfort", "jerk"),
        "drive_peak_jerk": _mean(rows, "driving_comfort", "max_jerk"),
        "drive_peak_jerk_max": _max(rows, "driving_comfort", "max_jerk"),
        "min_accel_min": _min(rows, "ego", "min_accel"),
        "progress_ratio_mean": _mean(rows, "ego", "progress_ratio"),
        "progress_ratio_min": _min(rows, "ego", "progress_ratio"),
        "occ_map": _mean(rows, "occupancy", "map"), "occ_soft_iou": _mean(rows, "occupancy", "soft_iou"),
        "fg_map": _mean(rows, "occupancy", "flow_grounded_map"),
        "fg_soft_iou": _mean(rows, "occupancy", "flow_grounded_soft_iou"), "epe": _mean(rows, "occupancy", "epe"),
        "fps_mean": _mean(rows, "fps"),
        "failures": [{"scene": r["scene"], "collided": r["collision"]["collided"], "at_fault": r["collision"]["at_fault"],
                      "first_frame": r["collision"]["first_frame"], "actors": r["collision"]["actors"],
                      "off_road_m": r["off_road_m"]} for r in rows if r["collision"]["collided"] or r["off_road"]],
    }
    if real:
        s["min_ade_recorded"] = _mean(rows, "prediction_recorded", "min_ade")
        s["mean_ade_recorded"] = _mean(rows, "prediction_recorded", "mean_ade")
    return s


def check_targets(s: dict) -> dict:
    """The real benchmark part's targets on a real summary: name -> {value, target, met}."""
    t = REAL_TARGETS
    rows = {
        "min_ade": (s["min_ade"], f"<= {t['min_ade_max']}", s["min_ade"] is not None and s["min_ade"] <= t["min_ade_max"]),
        "min_ade_recorded": (s.get("min_ade_recorded"), f"<= {t['min_ade_max']}",
                             s.get("min_ade_recorded") is not None and s["min_ade_recorded"] <= t["min_ade_max"]),
        "drive_jerk": (s["drive_jerk"], f"<= {t['drive_jerk_max']}",
                       s["drive_jerk"] is not None and s["drive_jerk"] <= t["drive_jerk_max"]),
        "at_fault_collisions": (s["at_fault_collisions"], f"<= {t['at_fault_collisions_max']}",
                                s["at_fault_collisions"] <= t["at_fault_collisions_max"]),
        "progress_ratio_min": (s["progress_ratio_min"], f">= {t['progress_ratio_min']}",
                               s["progress_ratio_min"] is not None and s["progress_ratio_min"] >= t["progress_ratio_min"]),
    }
    return {k: {"value": v, "target": tt, "met": bool(ok)} for k, (v, tt, ok) in rows.items()}


def _planner_overrides(args) -> dict:
    """The planner overrides that ``--planner-limits`` / ``--planner-config`` ask for ({} for the
    shipped planner), checked against the config classes.

    Raises:
        ConfigError: both options, unreadable JSON, or a field the planner does not have.
    """
    from adv3d_runner.autonomy.planner import PlannerConfig

    if args.planner_config is None:
        return {"proposals": dict(LIMITS_BEFORE_ISSUE17)} if args.planner_limits == "before-issue17" else {}
    if args.planner_limits != "shipped":
        raise ConfigError("--planner-limits and --planner-config are exclusive")
    text, source = args.planner_config, "--planner-config"
    if text.strip().endswith(".json") and not text.lstrip().startswith("{"):
        source = text
        try:
            text = Path(text).read_text()
        except OSError as exc:
            raise ConfigError(f"--planner-config: cannot read {source}: {exc.strerror}") from None
    try:
        overrides = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{source}: not JSON ({exc.msg}, line {exc.lineno} column {exc.colno})") from None
    PlannerConfig.from_overrides(overrides, source)
    return overrides


def _train_scenes_of(folder: Path, split) -> list[Path]:
    """The scene files of ``folder``, each checked to come from a train recording of ``split``
    (its CommonRoad file named in ``source.details.file``), so that tuning on a folder of
    extra scenes cannot look at the benchmark part.

    Raises:
        ConfigError: no scene files, or a scene that is not from a train recording.
    """
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.real import recording_of

    paths = sorted(p for p in folder.glob("*.json*") if p.is_file() and p.name not in ("split.json",))
    if not paths:
        raise ConfigError(f"--real-dir {folder}: no scene files (*.json, *.json.gz)")
    train = set(split.recordings["train"])
    for p in paths:
        try:
            details = load_scene(p).source.details or {}
        except Exception as exc:  # noqa: BLE001 - any unreadable file: say which
            raise ConfigError(f"{p}: not a scene file ({exc})") from None
        try:
            rec = recording_of(Path(str(details.get("file", ""))).stem)
        except ValueError:
            raise ConfigError(f"{p}: source.details.file does not name a CommonRoad US-101 recording") from None
        if rec not in train:
            raise ConfigError(f"{p}: recording {rec} is not in the train part {sorted(train)} (split.json)")
    return paths


def _run_set(paths: list[Path], autonomy: str, seconds: float, workers: int, real: bool,
             overrides: dict | None = None, seed: int = 0) -> list[dict]:
    jobs = [(str(p), autonomy, seconds, real, overrides or {}, seed) for p in paths]
    rows = []
    if workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            for m in pool.imap(_run, jobs):
                rows.append(m)
                _line(m, len(rows), len(jobs))
    else:
        for job in jobs:
            rows.append(_run(job))
            _line(rows[-1], len(rows), len(jobs))
    return rows


def main() -> int:
    from adv3d_runner.autonomy.names import stack_spec

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 generated scenes instead of 100 (the real set is small)")
    ap.add_argument("--sets", default="generated,real", help="comma-separated: generated, real")
    ap.add_argument("--real-part", choices=("benchmark", "train", "fresh"), default="benchmark",
                    help="part of scenes/real/ (split.json; tune only on train), or fresh: scenes/real-fresh/ "
                         "(recordings 10-18, evaluation only)")
    ap.add_argument("--autonomy", type=stack_spec, default="A", metavar="STACK",
                    help="any stack (docs/stacks.md): A, B, oracle, A-lanefollow, A-fast, a registered plugin, "
                         "package.module:factory or exec:COMMAND (default A)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=0,
                    help="episode seed (LiDAR noise and dropout); the kept results use 0, other seeds show the "
                         "spread of a result over the sensor's noise (needs --name or --tag)")
    ap.add_argument("--planner-limits", choices=("shipped", "before-issue17"), default="shipped",
                    help="diagnosis: run the planner with the proposals' jerk limits of before issue 17")
    ap.add_argument("--planner-config", default=None, metavar="JSON",
                    help="diagnosis and tuning: planner fields to override, as JSON or a .json file: "
                         '{"proposals": {...}, "weights": {...}, "planner": {...}} (see PlannerConfig.from_overrides); '
                         "name the result with --name or --tag so the kept one is not overwritten")
    ap.add_argument("--generated-dir", default=None, metavar="DIR",
                    help="run the generated set on the scene files of DIR instead of scenes/highway (e.g. scenes of "
                         "the generator's train split, for tuning without looking at the benchmark)")
    ap.add_argument("--real-dir", default=None, metavar="DIR",
                    help="run the real set on the scene files of DIR (e.g. scenes/real-train-egos: other cars of "
                         "the train recordings as the ego); every scene must come from a train recording")
    ap.add_argument("--name", default=None,
                    help="result file stem under bench/results/ (default sanity[.<autonomy>][.quick])")
    ap.add_argument("--reference", default="bench/results/sanity.json",
                    help="Autonomy-A's sanity file that --autonomy B is compared with (same scenes)")
    ap.add_argument("--tag", default="",
                    help="suffix of the result file name (e.g. old-detector: sanity.old-detector.json), so a "
                         "before/after pair does not overwrite the kept result")
    args = ap.parse_args()
    if args.tag and not all(c.isalnum() or c in "-_" for c in args.tag):
        ap.error("--tag takes letters, digits, '-' and '_'")
    if args.name and not all(c.isalnum() or c in "-_." for c in args.name):
        ap.error("--name is a file stem under bench/results/: letters, digits, '-', '_' and '.'")
    if args.real_dir and not args.name:
        ap.error("--real-dir needs --name (the kept real-benchmark result would be overwritten)")
    if args.generated_dir and not args.name:
        ap.error("--generated-dir needs --name (the kept generated-benchmark result would be overwritten)")
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    if not sets or set(sets) - {"generated", "real"}:
        ap.error("--sets takes generated and/or real")
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene.real import load_real_split

    try:
        overrides = _planner_overrides(args)
    except ConfigError as exc:
        ap.error(str(exc))
    if args.seed != 0 and not (args.name or args.tag):
        ap.error("--seed other than 0 needs --name or --tag (the kept result would be overwritten)")
    if overrides and not (args.name or args.tag):
        ap.error("a planner other than the shipped one needs --name or --tag (the kept result would be overwritten)")
    probe = make_stack(args.autonomy)  # fail early (e.g. no weights) before starting workers
    stack_info = probe.stack_info.as_dict()
    if hasattr(probe, "close"):
        probe.close()
    t0 = time.time()
    out: dict = {}
    if "generated" in sets:
        if args.generated_dir:
            paths = sorted(p for p in Path(args.generated_dir).glob("*.json*") if p.is_file())
            if not paths:
                ap.error(f"--generated-dir {args.generated_dir}: no scene files (*.json, *.json.gz)")
        else:
            paths = sorted((ROOT / "scenes" / "highway").glob("highway-benchmark-*.json*"))
        if args.quick:
            paths = paths[::10]
        print(f"generated {'scenes of ' + args.generated_dir if args.generated_dir else 'benchmark'}: {len(paths)} scenes")
        rows = _run_set(paths, args.autonomy, args.seconds, args.workers, real=False, overrides=overrides,
                        seed=args.seed)
        out["generated"] = (summarise(rows, real=False), rows)
    if "real" in sets:
        split = load_real_split()
        if args.real_dir:
            try:
                paths = _train_scenes_of(Path(args.real_dir), split)
            except ConfigError as exc:
                ap.error(str(exc))
            print(f"real scenes of {args.real_dir}: {len(paths)} (train recordings only)")
        elif args.real_part == "fresh":
            from adv3d_runner.scene.real import load_fresh_part

            fresh = load_fresh_part(split=split)
            paths = fresh.paths()
            print(f"real fresh part: {len(paths)} scenes (recordings {list(fresh.recordings)})")
        else:
            paths = split.paths(args.real_part)
            print(f"real {args.real_part} part: {len(paths)} scenes (recordings {list(split.recordings[args.real_part])})")
        rows = _run_set(paths, args.autonomy, args.seconds, args.workers, real=True, overrides=overrides,
                        seed=args.seed)
        summary = summarise(rows, real=True)
        summary["part"] = args.real_dir or args.real_part
        summary["recordings"] = (list(fresh.recordings) if args.real_part == "fresh" and not args.real_dir
                                 else list(split.recordings["train" if args.real_dir else args.real_part]))
        summary["targets"] = check_targets(summary)
        if args.autonomy == "B":  # no trajectories: the prediction targets do not apply
            summary["targets"] = {k: v for k, v in summary["targets"].items() if not k.startswith("min_ade")}
        out["real"] = (summary, rows)
    wall = time.time() - t0
    reference = {}
    if args.autonomy == "B":  # Autonomy-A's rows of the same scenes, from its kept sanity run
        for key in out:
            reference[key] = _reference_a([r["scene"] for r in out[key][1]], real=key == "real",
                                          path=ROOT / args.reference)
            out[key][0]["autonomy_a_same_scenes"] = reference[key]
        _print_b(out, reference, args)
    else:
        _print(out, args)
    from adv3d_runner.fileio import write_json
    from adv3d_runner.machine import numerical_config

    tag = "" if args.autonomy == "A" else f".{args.autonomy}"
    if args.name:
        name = args.name
    elif "generated" in out:
        name = "sanity" + tag + (".quick" if args.quick else "")
    else:
        name = f"sanity.real-{args.real_part}" + tag
    if args.tag:
        name += f".{args.tag}"
    doc = {"format": "adv3d-bench", "version": 1, "topic": "sanity",
           "command": " ".join(["bench/sanity.py"] + sys.argv[1:]),
           "machine": {"python": platform.python_version(), "platform": platform.platform(),
                       "processor": platform.processor(), "cpus": os.cpu_count(),
                       "numerics": numerical_config()},
           "stack": stack_info,
           "planner_limits": args.planner_limits if args.planner_limits == "shipped" else LIMITS_BEFORE_ISSUE17,
           "planner_overrides": overrides,
           "paper_original_autonomy_a": PAPER_ORIGINAL_A, "paper_original_autonomy_b": PAPER_ORIGINAL_B,
           "wall_s": wall}
    strip = lambda rows: [{k: v for k, v in r.items() if k not in ("format", "version")} for r in rows]  # noqa: E731
    if "generated" in out:
        s, rows = out["generated"]
        doc["summary"] = dict(s, autonomy=args.autonomy, seconds=args.seconds)
        doc["rows"] = strip(rows)
    if "real" in out:
        s, rows = out["real"]
        doc["real"] = {"summary": dict(s, autonomy=args.autonomy, seconds=args.seconds), "rows": strip(rows)}
    path = ROOT / "bench" / "results" / f"{name}.json"
    write_json(path, doc)
    print(f"wrote {path.relative_to(ROOT)} ({wall:.0f} s wall with {args.workers} workers)")
    return 0


def _print(out: dict, args) -> None:
    f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    print(f"\n{args.seconds:g} s closed loop, autonomy {args.autonomy}\n")
    print("| set | scenes | ok | collisions (at fault) | AP | recall | minADE | meanADE | plan lat | plan jerk | "
          "plan peak jerk | drive lat | drive jerk | drive peak jerk (max) | progress vs log (min) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    gen_label = f"generated, {args.generated_dir}" if args.generated_dir else "generated benchmark"
    for key, label in (("generated", gen_label), ("real", f"real, {args.real_part} part")):
        if key not in out:
            continue
        s = out[key][0]
        ade = f"{f(s['min_ade'], 2)}" + (f" ({f(s['min_ade_recorded'], 2)} rec.)" if "min_ade_recorded" in s else "")
        print(f"| {label} | {s['scenes']} | {100 * s['ok_rate']:.0f}% | {s['collisions']} ({s['at_fault_collisions']}) | "
              f"{f(s['ap'])} | {f(s['recall'])} | {ade} | {f(s['mean_ade'], 2)} | {f(s['plan_lat'])} | {f(s['plan_jerk'])} | "
              f"{f(s['plan_peak_jerk'], 2)} | {f(s['drive_lat'])} | {f(s['drive_jerk'])} | "
              f"{f(s['drive_peak_jerk'], 2)} ({f(s['drive_peak_jerk_max'], 1)}) | "
              f"{f(s['progress_ratio_mean'], 2)} ({f(s['progress_ratio_min'], 2)}) |")
    p = PAPER_ORIGINAL_A
    print(f"| paper Table 1, Autonomy-A, Original | - | - | - | {p['ap']:.3f} | {p['recall']:.3f} | {p['min_ade']:.2f} | "
          f"{p['mean_ade']:.2f} | {p['plan_lat']:.3f} | {p['plan_jerk']:.3f} | - | {p['drive_lat']:.3f} | "
          f"{p['drive_jerk']:.3f} | - | - |")
    _print_failures_and_targets(out, args)


def _print_failures_and_targets(out: dict, args, note: str = "") -> None:
    """The tables' tail (A and B alike): every failed episode, then the issue-17 targets of the
    real part and whether each is met (``note`` after the heading)."""
    for key in out:
        for fail in out[key][0]["failures"]:
            print(f"failure ({key}):", fail)
    if "real" in out:
        print(f"\nissue-17 targets on the real {args.real_part} part{note}:")
        for name, t in out["real"][0]["targets"].items():
            v = t["value"]
            print(f"  {name}: {v if v is None or isinstance(v, int) else round(v, 3)} (target {t['target']}): "
                  f"{'met' if t['met'] else 'NOT met'}")


def _reference_a(scenes: list[str], real: bool = False, path: Path | None = None) -> dict | None:
    """Autonomy-A's sanity rows of the same scenes (``path``, default bench/results/sanity.json;
    its ``real`` rows for real scenes), averaged."""
    import json

    path = path or ROOT / "bench" / "results" / "sanity.json"
    if not path.is_file():
        return None
    doc = json.loads(path.read_text())
    source = (doc.get("real") or {}).get("rows", []) if real else doc.get("rows", [])
    rows = [r for r in source if r["scene"] in set(scenes)]
    if not rows:
        return None
    return {"source": str(path.relative_to(ROOT)) + (" (real)" if real else ""), "scenes": len(rows),
            "ok_rate": float(np.mean([not r["collision"]["collided"] and not r["off_road"] for r in rows])),
            "collisions": int(sum(r["collision"]["collided"] for r in rows)),
            "at_fault_collisions": int(sum(r["collision"]["at_fault"] for r in rows)),
            "ap": _mean(rows, "detection", "ap"), "recall": _mean(rows, "detection", "recall"),
            "min_ade": _mean(rows, "prediction", "min_ade"), "mean_ade": _mean(rows, "prediction", "mean_ade"),
            "plan_lat": _mean(rows, "planning_comfort", "lat"), "plan_jerk": _mean(rows, "planning_comfort", "jerk"),
            "drive_lat": _mean(rows, "driving_comfort", "lat"), "drive_jerk": _mean(rows, "driving_comfort", "jerk"),
            "progress_ratio_mean": _mean(rows, "ego", "progress_ratio"),
            "progress_ratio_min": _min(rows, "ego", "progress_ratio")}


def _print_b(out: dict, reference: dict, args) -> None:
    f = lambda x, p=3: "n/a" if x is None else f"{x:.{p}f}"  # noqa: E731
    print(f"\n{args.seconds:g} s closed loop, autonomy B\n")
    print("| set | scenes | ok | collisions (at fault) | occ. mAP | occ. Soft-IoU | flow-gr. mAP | flow-gr. Soft-IoU | "
          "EPE m/s | plan lat | plan jerk | drive lat | drive jerk | drive peak jerk (max) | progress vs log (min) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    gen_label = f"generated, {args.generated_dir}" if args.generated_dir else "generated benchmark"
    for key, label in (("generated", gen_label), ("real", f"real, {args.real_part} part")):
        if key not in out:
            continue
        s = out[key][0]
        print(f"| {label} | {s['scenes']} | {100 * s['ok_rate']:.0f}% | {s['collisions']} ({s['at_fault_collisions']}) | "
              f"{f(s['occ_map'])} | {f(s['occ_soft_iou'])} | {f(s['fg_map'])} | {f(s['fg_soft_iou'])} | "
              f"{f(s['epe'], 2)} | {f(s['plan_lat'])} | {f(s['plan_jerk'])} | {f(s['drive_lat'])} | "
              f"{f(s['drive_jerk'])} | {f(s['drive_peak_jerk'], 2)} ({f(s['drive_peak_jerk_max'], 1)}) | "
              f"{f(s['progress_ratio_mean'], 2)} ({f(s['progress_ratio_min'], 2)}) |")
    p = PAPER_ORIGINAL_B
    print(f"| paper Table 1, Autonomy-B, Original | - | - | - | {p['map']:.3f} | {p['soft_iou']:.3f} | {p['fg_map']:.3f} | "
          f"{p['fg_soft_iou']:.3f} | - | {p['plan_lat']:.3f} | {p['plan_jerk']:.3f} | {p['drive_lat']:.3f} | "
          f"{p['drive_jerk']:.3f} | - | - |")
    for key, ref in reference.items():
        if ref:
            print(f"\nAutonomy-A on the same {ref['scenes']} scenes ({ref['source']}): ok {100 * ref['ok_rate']:.0f}% "
                  f"(collisions {ref['collisions']}, at fault {ref['at_fault_collisions']}) | AP {f(ref['ap'])} recall "
                  f"{f(ref['recall'])} | minADE {f(ref['min_ade'], 2)} meanADE {f(ref['mean_ade'], 2)} | plan lat "
                  f"{f(ref['plan_lat'])} jerk {f(ref['plan_jerk'])} | drive lat {f(ref['drive_lat'])} jerk "
                  f"{f(ref['drive_jerk'])} | progress {f(ref['progress_ratio_mean'], 2)} "
                  f"({f(ref['progress_ratio_min'], 2)})")
    _print_failures_and_targets(out, args, " (prediction targets do not apply to B)")


def _line(m: dict, i: int, n: int) -> None:
    d, c, e = m["detection"], m["collision"], m["ego"]
    rec = m.get("prediction_recorded")
    if m.get("occupancy") is not None:  # Autonomy-B: occupancy instead of boxes and trajectories
        o = m["occupancy"]
        perception = (f"mAP={o['map'] and round(o['map'], 3)} softIoU={o['soft_iou'] and round(o['soft_iou'], 3)} "
                      f"EPE={o['epe'] and round(o['epe'], 2)}")
    else:  # None: the stack does not provide detections or predictions (docs/stacks.md)
        d, p = d or {"ap": None}, m["prediction"] or {"min_ade": None}
        perception = (f"AP={'n/a' if d['ap'] is None else round(d['ap'], 3)} "
                      f"minADE={'n/a' if p['min_ade'] is None else round(p['min_ade'], 2)}"
                      + (f" (rec {rec['min_ade'] and round(rec['min_ade'], 2)})" if rec else ""))
    print(f"[{i}/{n}] {m['scene']:30s} coll={int(c['collided'])} fault={int(c['at_fault'])} "
          f"off={m['off_road_m']:.2f} {perception}"
          + f" drive_jerk={m['driving_comfort']['jerk']:.3f} peak={m['driving_comfort']['max_jerk']:.1f} "
          f"progress={e['progress_ratio'] and round(e['progress_ratio'], 2)} vmin={e['min_speed']:.1f}"
          f"/{e['logged_min_speed']:.1f} amin={e['min_accel']:.1f}/{e['logged_min_accel']:.1f} "
          f"fps={m['fps']:.1f}", flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
