"""``adv3d attack`` and ``adv3d report``."""
from __future__ import annotations

import argparse

#: ``--batch`` of a new run: one query at a time, as the paper's BO (and every run made before
#: the option existed without --workers); a resumed run keeps its stored batch.
DEFAULT_BATCH = 1


def _lattice(text: str) -> tuple[int, int, int]:
    """``--vd-lattice NX,NY,NZ``: three integers >= 2 (``vertex_deform.check_lattice``)."""
    from ..errors import ConfigError
    from .vertex_deform import check_lattice

    try:
        return check_lattice(tuple(int(x, 10) for x in text.split(",")))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NX,NY,NZ: three integers >= 2 (got {text!r})") from None
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--vd-lattice ")) from None


def _objective(text: str) -> str:
    """``--objective``: a preset M0..M5 and/or key=value weights (``objective.parse_objective``;
    checked again against the stack's own presets once --autonomy is known)."""
    from ..errors import ConfigError
    from .objective import parse_objective

    try:
        parse_objective(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--objective: ")) from None
    return text


def register(subparsers) -> None:
    from .. import argtypes as at
    from ..autonomy.names import stack_spec
    from .names import ALGORITHMS, MAX_MAHALANOBIS, MAX_REALISM_WEIGHT, MAX_VD_BOUND, MODES, PRESETS, SHAPE_MODELS

    p = subparsers.add_parser(
        "attack", help="search adversarial actor shapes on scenes (paper section 3.3)",
        description="Search the shape space for the actor shapes that hurt the autonomy stack most "
                    "(maximising the objective of paper Eq. 3-5). Results go to the run bundle OUT; "
                    "running the same command again resumes a killed run without redoing queries.")
    p.add_argument("scenes", nargs="+", metavar="SCENE", help="scene files (.json/.json.gz)")
    p.add_argument("--algo", choices=ALGORITHMS, default="bo", help="search algorithm (default bo)")
    p.add_argument("--budget", type=at.integer(1, 1_000_000), default=100, help="queries per scene and mode (default 100)")
    p.add_argument("--actors", type=at.integer(1, 64), default=1, help="attack the m closest actors in front of the ego (default 1)")
    p.add_argument("--target-rank", type=at.integer(0, 63), default=0,
                   help="skip the K closest actors in front first (default 0): --actors 1 --target-rank 1 attacks the "
                        "second closest alone (the paper's Table 2 attacks each of the 3 closest alone)")
    p.add_argument("--mode", choices=MODES, default="closed",
                   help="closed: attack in closed loop; open: attack with the ego on its log, then evaluate "
                        "in closed loop; both: the two (paper Table 1)")
    p.add_argument("--seconds", type=at.number(0.0, 3600.0, lo_open=True), default=5.0, help="episode length in s (default 5)")
    p.add_argument("--workers", type=at.integer(1, 256), default=None,
                   help="local worker processes (default 1), or with --ray-address the Ray workers "
                        "(default: one per CPU of the cluster); the results do not depend on it")
    p.add_argument("--batch", type=at.integer(1, 4096), default=None,
                   help="queries asked of a search at once (default 1, or the stored value when resuming); "
                        "part of the run's configuration: the results depend on it, not on --workers")
    p.add_argument("--seed", type=at.seed, default=0,
                   help="search and LiDAR-noise seed (default 0; per scene derived from it with --scene-seeds)")
    p.add_argument("--out", required=True, help="run folder, e.g. runs/NAME")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="evaluate queries on an existing Ray cluster (e.g. 127.0.0.1:6379 or auto)")
    p.add_argument("--objective", type=_objective, default="M0",
                   help="M0 (all terms, default) .. M5 (paper ablations), or key=value list "
                        "(det, pred, plan, alpha, beta), e.g. 'M1,beta=2' or 'pred=0.2'; with --autonomy B the "
                        "presets are Autonomy-B's (det = -Soft-IoU of occupancy, pred = flow EPE, lambda_pred 1.0)")
    p.add_argument("--pred-reduction", choices=("sum", "mean"), default="sum",
                   help="the prediction term over the H waypoints: sum (paper Eq. 5 as written, default) or "
                        "mean (the ADE; the form of runs made before this option); Autonomy-A's term (B's flow "
                        "EPE has no waypoints)")
    p.add_argument("--scene-seeds", action="store_true",
                   help="derive each scene's search seed and LiDAR-noise seed from --seed and the scene's "
                        "content (recorded in summary.json), so searches differ per scene; default: --seed for all")
    p.add_argument("--autonomy", default="A", type=stack_spec, metavar="STACK",
                   help="stack under test: any stack of `adv3d stacks list`, package.module:factory, exec:COMMAND, "
                        "tcp://HOST:PORT or unix:PATH (docs/stacks.md); A (learned detector + predictor), B (instance-free: learned implicit "
                        "occupancy-and-flow model), oracle perception, or A-fast (A with the 0.4 m detector: "
                        "about 10 %% less CPU per query)")
    p.add_argument("--reactive", action="store_true", help="actors react to the ego (IDM/MOBIL)")
    p.add_argument("--n-initial", type=at.integer(1, 1_000_000), default=11, help="BO and skopt initial queries (default 11)")
    p.add_argument("--shape-space", default=None, help="shape space .npz (default: the shipped one)")
    p.add_argument("--no-incremental", action="store_true",
                   help="simulate every LiDAR ray of every frame instead of reusing the static hits between "
                        "the queries of a scene (same results, slower; for checks)")
    p.add_argument("--library", default=None,
                   help="vehicle library of the benign actors' meshes (default: the bundled one; 'none': boxes); "
                        "its fingerprint is recorded in run.json and checked on resume")
    g = p.add_argument_group("shape model and realism (docs/realism.md)")
    g.add_argument("--shape-model", choices=SHAPE_MODELS, default="latent",
                   help="latent: the shape space (default); vd: vertex deformation of the actor's own mesh "
                        "(the paper's baseline)")
    g.add_argument("--vd-bound", type=at.number(0.0, MAX_VD_BOUND, lo_open=True), default=None, metavar="M",
                   help=f"vd: l-infinity bound of every vertex displacement in m, at most {MAX_VD_BOUND:g} "
                        "(paper: 0.1, 0.2, 0.5, 1.0; default 0.5)")
    g.add_argument("--vd-lattice", type=_lattice, default=None, metavar="NX,NY,NZ",
                   help="vd: control lattice nodes along length, width, height (default 6,3,3: 162 dimensions)")
    g.add_argument("--region", choices=("realistic", "paper"), default=None,  # config.REGIONS, without importing it
                   help="realistic: search only where the realism report passes (latents within its Mahalanobis "
                        "limit, class-plausible scales, every shape checked; a shape that fails is an invalid "
                        "query, not simulated); paper: the paper's box (latent min/max, scales 0.8-1.3). Default "
                        "realistic, paper with --shape-model vd or --algo bruteforce")
    g.add_argument("--max-mahalanobis", type=at.number(0.0, MAX_MAHALANOBIS, lo_open=True), default=None, metavar="R",
                   help="search only latents within Mahalanobis distance R of the library mean (inside the box)")
    g.add_argument("--class-scales", action="store_true", default=None,
                   help="search only width/length scales that keep the actor's class within real dimensions")
    g.add_argument("--realism-weight", type=at.number(0.0, MAX_REALISM_WEIGHT), default=None, metavar="W",
                   help="maximise objective - W x (JSD excess over the library's leave-one-out maximum); default 0")
    g.add_argument("--realism-preset", choices=sorted(PRESETS), default=None,
                   help="named setting of the three realism knobs (explicit knobs override it)")
    g = p.add_argument_group("after the search (docs/attack.md, \"Avoidability\" and \"How often\")")
    g.add_argument("--avoidability", type=at.integer(1, 1000), default=None, metavar="K",
                   help="re-run every best shape on K held-out seeds with the stack and with ground-truth "
                        "perception (adv3d avoidability): are its failures stack- or scenario-induced")
    g.add_argument("--failure-rate", type=at.integer(1, 1_000_000), default=None, metavar="N",
                   help="simulate N shapes per scene drawn from the realistic prior and report the share that "
                        "make the stack fail, per failure kind, with a Clopper-Pearson interval (adv3d rate)")
    p.set_defaults(func=_attack)

    v = subparsers.add_parser(
        "avoidability", help="are a run's failures the stack's fault? (oracle re-run on held-out seeds)",
        description="Re-simulate every best shape of an attack run (and each scene's original) on held-out noise "
                    "seeds with the run's stack and with a reference stack (default oracle: ground-truth perception, "
                    "the same planner). A failure (collision, at-fault collision, braking below -4 m/s^2, leaving the "
                    "road, progress below 0.8 of the original) the reference shows too is scenario-induced; one only "
                    "the stack shows is stack-induced. Writes RUN/avoidability.json; adv3d report shows it.")
    v.add_argument("run", metavar="RUN", help="attack run folder")
    v.add_argument("--eval-seeds", type=at.integer(1, 1000), default=3, help="held-out seeds per shape (default 3)")
    v.add_argument("--reference", type=stack_spec, default="oracle", metavar="STACK",
                   help="the reference stack (default oracle)")
    v.add_argument("--workers", type=at.integer(1, 256), default=1, help="local worker processes (default 1)")
    v.set_defaults(func=_avoidability)

    q = subparsers.add_parser(
        "rate", help="how often a realistic shape makes the stack fail (rates with confidence intervals)",
        description="Draw N shapes per attacked scene of a run from the realistic prior (the realistic region, "
                    "uniform, conditioned on passing the realism report), simulate each with the run's stack on the "
                    "scene's held-out seeds, and write the share that fail, per failure kind, with a Clopper-Pearson "
                    "interval (RUN/failure_rate.json); adv3d report shows it beside the worst case.")
    q.add_argument("run", metavar="RUN", help="attack run folder")
    q.add_argument("--samples", type=at.integer(1, 1_000_000), required=True, metavar="N",
                   help="realistic shapes per scene")
    q.add_argument("--eval-seeds", type=at.integer(1, 1000), default=3,
                   help="held-out seeds the draws cycle through (default 3)")
    q.add_argument("--confidence", type=at.number(0.0, 0.9999, lo_open=True), default=0.95,
                   help="confidence level of the intervals (default 0.95)")
    q.set_defaults(func=_rate)

    r = subparsers.add_parser("report", help="markdown report of attack runs",
                              description="Write a markdown report (Table-1-style metrics, convergence plot, "
                                          "best shapes) of one or more attack run folders.")
    r.add_argument("runs", nargs="+", metavar="RUN", help="run folders (runs/NAME)")
    r.add_argument("--out", default=None, help="report file (default RUN/report.md of the first run)")
    r.set_defaults(func=_report)


def _attack(args: argparse.Namespace) -> int:
    from ..errors import ConfigError, UsageError
    from ..progress import is_quiet, status
    from .config import AttackConfig
    from .driver import check_outcome, run_attack, stored_batch
    from .journal import read_run

    workers = args.workers if args.workers is not None or args.ray_address else 1
    batch = args.batch if args.batch is not None else (stored_batch(args.out) or DEFAULT_BATCH)
    try:  # options that do not go together (--algo grid with --shape-model vd, ...): a usage error
        cfg = AttackConfig(scenes=tuple(args.scenes), algo=args.algo, budget=args.budget, actors=args.actors,
                           mode=args.mode, seconds=args.seconds, seed=args.seed, objective=args.objective,
                           autonomy=args.autonomy, reactive=args.reactive, batch=batch,
                           n_initial=args.n_initial, shape_space=args.shape_space, library=args.library,
                           pred_reduction=args.pred_reduction, scene_seeds=args.scene_seeds,
                           target_rank=args.target_rank, **_shape_options(args))
    except UsageError:
        raise
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    summary = run_attack(cfg, args.out, workers=workers, ray_address=args.ray_address,
                         show_progress=not is_quiet(), incremental=not args.no_incremental)
    for sid, entry in summary.get("scenes", {}).items():
        for mode, m in entry.get("modes", {}).items():
            status(f"{sid} [{mode}]: best cost {m.get('best_cost')} at query {m.get('best_index')} "
                   f"({m.get('n_failed', 0)} failed of {m.get('n_queries')})")
    check_outcome(summary, read_run(args.out)[1])  # exit 1 saying why when nothing worked
    if args.avoidability:
        _avoidability(argparse.Namespace(run=args.out, eval_seeds=args.avoidability, reference="oracle",
                                         workers=workers if not args.ray_address else 1))
    if args.failure_rate:
        _rate(argparse.Namespace(run=args.out, samples=args.failure_rate, eval_seeds=3, confidence=0.95))
    status(f"run bundle: {args.out}  (adv3d report {args.out})")
    return 0


def _avoidability(args: argparse.Namespace) -> int:
    from ..progress import status
    from .avoidability import run_avoidability, summary_line

    doc = run_avoidability(args.run, eval_seeds=args.eval_seeds, reference=args.reference, workers=args.workers)
    status(f"avoidability: {summary_line(doc)} -> {args.run}/avoidability.json")
    return 0


def _rate(args: argparse.Namespace) -> int:
    from ..progress import status
    from .failure_rate import format_rate, run_failure_rate

    doc = run_failure_rate(args.run, samples=args.samples, eval_seeds=args.eval_seeds, confidence=args.confidence)
    for sid, e in doc["scenes"].items():
        status(f"{sid}: {e['accepted']} realistic shapes, any failure {format_rate(e['rates']['any'])}")
    status(f"failure rates: {args.run}/failure_rate.json")
    return 0


def _shape_options(args: argparse.Namespace) -> dict:
    """The AttackConfig fields of the shape-model and realism options: a preset first, then the
    knobs given explicitly; options left out keep their defaults."""
    from ..errors import UsageError
    from .realism_constraints import preset_knobs

    out: dict = {"shape_model": args.shape_model}
    region = getattr(args, "region", None)
    if region is None:
        region = "paper" if args.shape_model == "vd" or getattr(args, "algo", None) == "bruteforce" else "realistic"
    out["region"] = region
    if args.realism_preset:
        out.update(preset_knobs(args.realism_preset))
    for key in ("max_mahalanobis", "class_scales", "realism_weight", "vd_bound", "vd_lattice"):
        if getattr(args, key) is not None:
            out[key] = getattr(args, key)
    if args.shape_model != "vd" and ("vd_bound" in out or "vd_lattice" in out):
        raise UsageError("--vd-bound and --vd-lattice need --shape-model vd")
    return out


def _report(args: argparse.Namespace) -> int:
    from ..progress import status
    from .report import write_report

    path = write_report(args.runs, args.out)
    status(f"wrote {path}")
    return 0
