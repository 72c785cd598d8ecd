"""``adv3d attack`` and ``adv3d report``."""
from __future__ import annotations

import argparse

#: ``--batch`` of a new run: one query at a time, as the paper's BO (and every run made before
#: the option existed without --workers); a resumed run keeps its stored batch.
DEFAULT_BATCH = 1


def register(subparsers) -> None:
    from .config import MODES
    from .search import ALGORITHMS

    p = subparsers.add_parser(
        "attack", help="search adversarial actor shapes on scenes (paper section 3.3)",
        description="Search the shape space for the actor shapes that hurt the autonomy stack most "
                    "(maximising the objective of paper Eq. 3-5). Results go to the run bundle OUT; "
                    "running the same command again resumes a killed run without redoing queries.")
    p.add_argument("scenes", nargs="+", metavar="SCENE", help="scene files (.json/.json.gz)")
    p.add_argument("--algo", choices=ALGORITHMS, default="bo", help="search algorithm (default bo)")
    p.add_argument("--budget", type=int, default=100, help="queries per scene and mode (default 100)")
    p.add_argument("--actors", type=int, default=1, help="attack the m closest actors in front of the ego (default 1)")
    p.add_argument("--mode", choices=MODES, default="closed",
                   help="closed: attack in closed loop; open: attack with the ego on its log, then evaluate "
                        "in closed loop; both: the two (paper Table 1)")
    p.add_argument("--seconds", type=float, default=5.0, help="episode length in s (default 5)")
    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes (default 1), or with --ray-address the Ray workers "
                        "(default: one per CPU of the cluster); the results do not depend on it")
    p.add_argument("--batch", type=int, default=None,
                   help="queries asked of a search at once (default 1, or the stored value when resuming); "
                        "part of the run's configuration: the results depend on it, not on --workers")
    p.add_argument("--seed", type=int, default=0, help="search and LiDAR-noise seed (default 0)")
    p.add_argument("--out", required=True, help="run folder, e.g. runs/NAME")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="evaluate queries on an existing Ray cluster (e.g. 127.0.0.1:6379 or auto)")
    p.add_argument("--objective", default="M0",
                   help="M0 (all terms, default) .. M5 (paper ablations), or key=value list "
                        "(det, pred, plan, alpha, beta), e.g. 'M1,beta=2' or 'pred=0.2'")
    p.add_argument("--autonomy", default="A", choices=("A", "oracle"),
                   help="stack under test: A (learned detector + predictor) or oracle perception")
    p.add_argument("--reactive", action="store_true", help="actors react to the ego (IDM/MOBIL)")
    p.add_argument("--n-initial", type=int, default=11, help="BO initial queries (default 11)")
    p.add_argument("--shape-space", default=None, help="shape space .npz (default: the shipped one)")
    p.add_argument("--no-incremental", action="store_true",
                   help="simulate every LiDAR ray of every frame instead of reusing the static hits between "
                        "the queries of a scene (same results, slower; for checks)")
    p.set_defaults(func=_attack)

    r = subparsers.add_parser("report", help="markdown report of attack runs",
                              description="Write a markdown report (Table-1-style metrics, convergence plot, "
                                          "best shapes) of one or more attack run folders.")
    r.add_argument("runs", nargs="+", metavar="RUN", help="run folders (runs/NAME)")
    r.add_argument("--out", default=None, help="report file (default RUN/report.md of the first run)")
    r.set_defaults(func=_report)


def _attack(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..progress import is_quiet, status
    from .config import AttackConfig
    from .driver import run_attack

    from .driver import stored_batch

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    workers = args.workers if args.workers is not None or args.ray_address else 1
    batch = args.batch if args.batch is not None else (stored_batch(args.out) or DEFAULT_BATCH)
    cfg = AttackConfig(scenes=tuple(args.scenes), algo=args.algo, budget=args.budget, actors=args.actors,
                       mode=args.mode, seconds=args.seconds, seed=args.seed, objective=args.objective,
                       autonomy=args.autonomy, reactive=args.reactive, batch=batch,
                       n_initial=args.n_initial, shape_space=args.shape_space)
    summary = run_attack(cfg, args.out, workers=workers, ray_address=args.ray_address,
                         show_progress=not is_quiet(), incremental=not args.no_incremental)
    for sid, entry in summary.get("scenes", {}).items():
        for mode, m in entry.get("modes", {}).items():
            status(f"{sid} [{mode}]: best cost {m.get('best_cost')} at query {m.get('best_index')} "
                   f"({m.get('n_failed', 0)} failed of {m.get('n_queries')})")
    status(f"run bundle: {args.out}  (adv3d report {args.out})")
    return 0


def _report(args: argparse.Namespace) -> int:
    from ..progress import status
    from .report import write_report

    path = write_report(args.runs, args.out)
    status(f"wrote {path}")
    return 0
