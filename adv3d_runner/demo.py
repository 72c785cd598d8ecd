"""``adv3d demo``: the README's main job on the bundled defaults.

Loads the shipped vehicle library and shape space (building the shape space if it is missing),
decodes a vehicle from the centre of the latent box and one random sample, writes them as
meshes, then runs a short closed-loop Bayesian-optimisation attack with Autonomy-A in the
realistic region on a bundled highway scene, writes its report, re-runs the best shape with
ground-truth perception (avoidability) and ends on the finding: a realistic, stack-induced
failure with its criticality figures and an export, or a line saying the scene has none. The
full protocol (budget 100, 5 s) is ``adv3d attack``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .fileio import REPO_ROOT

DEMO_SCENE = REPO_ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"


def register(subparsers) -> None:
    from . import argtypes as at

    parser = subparsers.add_parser("demo", help="run the main job on the bundled defaults")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--seed", type=at.seed, default=0, help="seed of the random shape sample and the attack")
    parser.add_argument("--scene", type=Path, default=DEMO_SCENE, help=f"scene to attack (default {DEMO_SCENE})")
    parser.add_argument("--budget", type=at.integer(1, 1_000_000), default=16, help="attack queries (default 16; the paper uses 100)")
    parser.add_argument("--seconds", type=at.number(0.0, 3600.0, lo_open=True), default=3.0, help="episode length in seconds (default 3)")
    parser.add_argument("--no-attack", action="store_true", help="only decode the sample vehicles")
    parser.add_argument("--library", default=None,
                        help="vehicle library of the scene's actors (default: the bundled one; 'none': boxes)")
    parser.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from .progress import status
    from .shapes.library import load_library, resolve_library
    from .shapes.mesh_io import write_mesh
    from .shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace, build_shape_space

    library = resolve_library(getattr(args, "library", None))
    if library is not None:
        status(f"vehicle library: {len(library.assets)} assets, {len(library.shape_space_assets())} in the shape space")
    if DEFAULT_SHAPE_SPACE.exists():
        space = ShapeSpace.load(DEFAULT_SHAPE_SPACE)
    else:
        status(f"{DEFAULT_SHAPE_SPACE} is missing: building it (adv3d shapes build)")
        space = build_shape_space(load_library())  # the shipped space is the bundled library's
        space.save(DEFAULT_SHAPE_SPACE)
    status(f"shape space: K={space.k}, explained variance {np.round(space.explained_variance_ratio, 3).tolist()}")

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    samples = {"mean_vehicle": np.full(space.k + 2, 0.5), f"sample_seed{args.seed}": space.sample_unit(rng)}
    for name, u in samples.items():
        mesh = space.decode(u)
        path = args.out / f"{name}.glb"
        write_mesh(mesh, path)
        length, width, height = mesh.extents
        status(
            f"{path}: {len(mesh.faces)} triangles, {length:.2f} x {width:.2f} x {height:.2f} m, "
            f"watertight={mesh.is_watertight}, nearest library asset: {space.nearest_asset(u)}"
        )
    if not args.no_attack:
        run_demo_attack(args)
    return 0


def run_demo_attack(args: argparse.Namespace) -> None:
    """A short closed-loop BO attack (Autonomy-A) in the realistic region on one scene, its
    markdown report, then the finding: the best shape re-run with ground-truth perception on a
    held-out seed (avoidability), its criticality figures and, when it is a stack-induced
    failure, its export (:func:`report_finding`)."""
    from .attack.driver import AttackConfig, run_attack
    from .attack.report import write_report
    from .progress import status

    run_dir = args.out / "attack"
    config = AttackConfig(scenes=[str(args.scene)], algo="bo", budget=args.budget, mode="closed",
                          seconds=args.seconds, seed=args.seed, autonomy="A",
                          n_initial=min(11, max(2, args.budget // 3)), library=getattr(args, "library", None),
                          region="realistic")
    status(f"attacking {args.scene.name}: BO, {args.budget} queries, {args.seconds:g} s closed-loop episodes, "
           f"realistic region (a run that is stopped resumes from {run_dir}/queries.jsonl)")
    run_attack(config, run_dir, workers=1)
    from .attack.avoidability import run_avoidability

    run_avoidability(run_dir, eval_seeds=DEMO_EVAL_SEEDS)
    report = write_report([run_dir])
    status(f"attack report: {report}")
    for line in report_finding(run_dir, args.out / "finding"):
        status(line)


#: held-out seeds of the demo's avoidability check (one keeps the demo at about a minute)
DEMO_EVAL_SEEDS = 1


def report_finding(run_dir: Path, export_dir: Path) -> list[str]:
    """What the demo ends on, one line each: for every best shape of the run, whether it passes
    the realism report and its avoidability finding; for a realistic, stack-induced one, its
    failures, its criticality figures (CommonRoad CriMe, or why they are not there) and the
    export written to ``export_dir`` (``adv3d export``); otherwise that the scene has none."""
    from .attack.avoidability import FAILURE_KINDS, STACK_INDUCED, read_avoidability
    from .attack.journal import read_run

    _, _, summary = read_run(run_dir)
    doc = read_avoidability(run_dir) or {"scenes": {}}
    lines: list[str] = []
    found = None
    for sid, entry in summary.get("scenes", {}).items():
        for mode, m in entry.get("modes", {}).items():
            ev = m.get("closed_loop_eval") or {}
            realistic = bool(ev.get("realism")) and all(r.get("realistic") for r in ev["realism"])
            av = ((doc["scenes"].get(sid) or {}).get("modes") or {}).get(mode)
            finding = av["finding"] if av else "not checked"
            lines.append(f"best shape of {sid} [{mode}]: {'passes' if realistic else 'fails'} the realism report; "
                         f"avoidability: {finding}")
            if found is None and realistic and finding == STACK_INDUCED:
                kinds = [k.replace("_", " ") for k in FAILURE_KINDS if av["kinds"][k]["verdict"] == STACK_INDUCED]
                found = (sid, mode, ev, kinds)
    if found is None:
        lines.append("no realistic, stack-induced finding on this scene: every failure of the best shape (if any) "
                     "also happens with ground-truth perception or in the original scene (adv3d avoidability)")
        return lines
    sid, mode, ev, kinds = found
    lines.append(f"finding: {sid} [{mode}]: {', '.join(kinds)} with the stack, not with ground-truth perception")
    lines.append("criticality: " + criticality_line(ev.get("criticality")))
    try:
        from .attack.export import export_run, manifest_summary

        result = export_run(run_dir, sid, export_dir, mode=mode,
                            command=f"adv3d export {run_dir} --scene {sid} --mode {mode} --out {export_dir}")
        lines.append(f"export: {manifest_summary(result.manifest)} -> {result.out}")
    except Exception as exc:  # noqa: BLE001 - e.g. the export extra is not installed: the demo says so
        lines.append(f"export: not written ({exc})")
    return lines


def criticality_line(crit: dict | None) -> str:
    """CriMe's figures of an episode in one line (``sim.criticality`` block), or why there are none."""
    if not isinstance(crit, dict):
        return "not computed"
    if "note" in crit:
        return f"not available ({crit['note']})"
    parts = []
    for key, label, unit in (("ttc", "min TTC", "s"), ("thw", "min THW", "s"), ("dhw", "min DHW", "m"),
                             ("required_deceleration", "max required deceleration", "m/s^2"), ("ttb", "TTB", "s")):
        fig = crit.get(key)
        if isinstance(fig, dict):
            value = fig.get("value")
            parts.append(f"{label} {'never' if value is None else f'{value:.3g} {unit}'}")
    return ", ".join(parts) + f" (CommonRoad {crit.get('tool') or 'CriMe'})"
