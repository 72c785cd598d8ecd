"""``adv3d experiments TABLE ...``: the paper's tables on the protocol (docs/results.md).

``register`` builds the parser from light modules only (argument types, stack names); the
driver (:mod:`adv3d_runner.experiments.tables`, numpy, the attack) is imported when the command
runs, so ``adv3d --help`` stays fast.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ConfigError, UsageError
from ..fileio import REPO_ROOT

#: The tables the driver runs (``tables.TABLES``; a test keeps the two equal).
TABLE_NAMES = ("realism", "table1", "table2", "table3", "table4", "table5", "table6", "transfer")

#: Bounds of the options beyond the attack's own (``attack.config``, kept equal by a test):
#: run seeds and held-out seeds per table, the shard count, the attack's largest budget and
#: episode length.
MAX_SEEDS = 1000
MAX_SHARDS = 4096
ATTACK_MAX_BUDGET = 1_000_000
ATTACK_MAX_SECONDS = 3600.0

DESCRIPTION = ("Run one of the paper's tables on the protocol (docs/results.md): per run seed, setting and scene "
               "an attack in its own run folder under --work (a killed campaign resumes), the best shapes "
               "re-evaluated on held-out noise seeds, the kept files under --results/<table>_<stack>[_b<budget>], "
               "and the table (table.md, table.json, table.png) built from the kept files alone.")


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """``"I/N"`` -> (I, N) with 0 <= I < N <= :data:`MAX_SHARDS`; None for None.

    Raises:
        ConfigError: not of that form (naming ``--shard``)."""
    if text is None:
        return None
    try:
        i, n = (int(x, 10) for x in text.split("/"))
    except ValueError:
        raise ConfigError(f"--shard: expected I/N (e.g. 3/16), got {text!r}") from None
    if not (1 <= n <= MAX_SHARDS and 0 <= i < n):
        raise ConfigError(f"--shard: need 0 <= I < N <= {MAX_SHARDS}, got {text!r}")
    return i, n


def shard_type(text: str) -> tuple[int, int]:
    """``--shard``'s argparse type: :func:`parse_shard`, its error a usage error."""
    try:
        return parse_shard(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N <= {MAX_SHARDS}, e.g. 3/16 (got {text!r})") \
            from exc


def folder_type(text: str) -> str:
    """``--work`` / ``--results``: a folder, made absolute against the folder the command runs
    from; refused when it, or a folder above it, is a file (nothing could be written there)."""
    if not text or "\0" in text:
        raise argparse.ArgumentTypeError(f"expected a folder (got {text!r})")
    path = Path(text).expanduser().absolute()
    for q in (path, *path.parents):
        if q.exists() or q.is_symlink():
            if not q.is_dir():
                what = "is" if q == path else f"lies under {q}, which is"
                raise argparse.ArgumentTypeError(f"expected a folder, but {text!r} {what} not a folder")
            break
    return str(path)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The driver's options, typed and bounded like every ``adv3d`` command's
    (``adv3d_runner.argtypes``): a bad value is one usage line and exit code 2."""
    from .. import argtypes as at
    from ..autonomy.names import stack_spec

    p.add_argument("table", nargs="?", choices=TABLE_NAMES, help="which table")
    p.add_argument("--list", action="store_true", help="list the tables and what each still needs")
    p.add_argument("--autonomy", default="A", type=stack_spec, metavar="STACK",
                   help="stack under test: any of docs/stacks.md (A, B, C, oracle, a plugin, package.module:factory, "
                        "exec:COMMAND; default A)")
    p.add_argument("--scenes", type=at.integer(0, 10_000), default=5,
                   help="generated scenes, over every density (default 5)")
    p.add_argument("--real", type=at.integer(0, 10_000), default=2,
                   help="real benchmark scenes of scenes/real (the tuned-on part; default 2)")
    p.add_argument("--fresh", type=at.integer(0, 10_000), default=0,
                   help="scenes of the fresh real benchmark scenes/real-fresh (never trained or tuned on; default 0)")
    p.add_argument("--region", choices=("paper", "realistic"), default="paper",
                   help="the latent search region: paper (the paper's box, default: every kept table's) or realistic "
                        "(adv3d attack's default: where the calibrated realism report passes); vertex deformation and "
                        "brute force always search the box. A realistic table's folder ends in _realistic")
    p.add_argument("--seeds", type=at.integer(1, MAX_SEEDS), default=3, help="run seeds 0..S-1 (default 3)")
    # Table 5 runs random search on 5 x --budget queries: every setting's budget stays within the attack's
    p.add_argument("--budget", type=at.integer(1, ATTACK_MAX_BUDGET // 5), default=100,
                   help="queries per search (default 100, the paper's)")
    p.add_argument("--n-initial", type=at.integer(1, ATTACK_MAX_BUDGET), default=11,
                   help="BO's Latin-hypercube start (default 11)")
    p.add_argument("--seconds", type=at.number(0.0, ATTACK_MAX_SECONDS, lo_open=True), default=5.0,
                   help="episode length in s (default 5)")
    p.add_argument("--eval-seeds", type=at.integer(1, MAX_SEEDS), default=3,
                   help="held-out noise seeds per scene and run seed (default 3)")
    p.add_argument("--pred-reduction", default="sum", choices=("sum", "mean"),
                   help="the objective's prediction term over the waypoints (default sum, Eq. 5)")
    p.add_argument("--workers", type=at.integer(1, 256), default=1, help="worker processes (default 1)")
    p.add_argument("--batch", type=at.integer(1, 4096), default=1,
                   help="queries a search asks at once (default 1, the paper's BO)")
    p.add_argument("--work", type=folder_type, default=str(REPO_ROOT / "runs" / "paper"),
                   help="run folders (default runs/paper in the repository)")
    p.add_argument("--results", type=folder_type, default=str(REPO_ROOT / "docs" / "results"),
                   help="kept files (default docs/results in the repository)")
    p.add_argument("--shard", type=shard_type, default=None, metavar="I/N",
                   help="run only every N-th unit (seed, setting, scene) from the I-th: N processes side by side "
                        "on one machine, each with its own compute file; then --table-only")
    p.add_argument("--table-only", action="store_true", help="rebuild table.md/json from the kept files, run nothing")
    p.add_argument("--realism-verdicts", action="store_true",
                   help="with --table-only: first give every kept run without one its best shapes' calibrated realism "
                        "verdicts (realism.json; decoding and measuring shapes, no episode)")
    p.add_argument("--avoidability", action="store_true",
                   help="also re-simulate the originals and best shapes with the oracle reference stack on the "
                        "held-out seeds and keep each run's stack-induced / scenario-induced split "
                        "(avoidability.json; docs/results.md, Protocol)")
    p.add_argument("--docs", action="store_true",
                   help="rewrite docs/results.md's generated parts (verdicts, the shipped stack's tables, compute) "
                        "from the kept tables under --results; run nothing")
    p.add_argument("--source-autonomy", default=None, type=stack_spec, metavar="STACK",
                   help="transfer: the stack whose table1 shapes are evaluated (default: the other of A and B)")


def check_arguments(args: argparse.Namespace) -> None:
    """What the option types cannot see alone, refused before anything runs.

    Raises:
        UsageError: ``--source-autonomy`` equal to ``--autonomy``; no scene; more scenes than
            the benchmark holds."""
    if args.table == "transfer" and args.source_autonomy is not None and args.source_autonomy == args.autonomy:
        raise UsageError("argument --source-autonomy: must differ from --autonomy")
    if args.table and args.table != "transfer" and not (args.table_only or args.list or args.docs):
        from ..attack.protocol import select_scenes

        if args.scenes + args.real + args.fresh == 0:
            raise UsageError("argument --scenes/--real/--fresh: a table needs at least one scene "
                             "(got --scenes 0 --real 0 --fresh 0)")
        try:  # more scenes than the benchmark holds: a bad value, refused before anything runs
            select_scenes(args.scenes, args.real, n_fresh=args.fresh)
        except ConfigError as exc:
            raise UsageError(f"argument --scenes/--real/--fresh: {exc}") from None


def execute(args: argparse.Namespace, command: str) -> int:
    """Run a table, rebuild it (``--table-only``) or list the tables (``--list`` or no table).

    Args:
        command: the command line as typed, recorded in the table's compute file.

    Raises:
        UsageError: a bad combination of options (exit code 2).
        Adv3dError: anything else that stops the table (one line, exit code 1)."""
    import os

    from . import tables

    check_arguments(args)
    # Scene paths (protocol.json, run.json, summaries) are the repository's: run inside it,
    # whatever folder the command was started from (--work and --results are absolute by now).
    cwd = os.getcwd()
    os.chdir(REPO_ROOT)
    try:
        if args.docs:
            from .summary import write_docs

            page = REPO_ROOT / "docs" / "results.md"
            changed = write_docs(page, Path(args.results))
            print(f"{'wrote' if changed else 'unchanged:'} {page}")
            return 0
        if args.list or not args.table:
            print(tables.list_tables(Path(args.results)))
            return 0
        spec = tables.TABLES[args.table]
        if args.realism_verdicts and not args.table_only:
            raise UsageError("argument --realism-verdicts: only with --table-only (a run makes them itself)")
        if args.table_only:
            if args.realism_verdicts:
                n = tables.backfill_realism(Path(args.results) / spec.folder(args.autonomy, args.budget, args.region))
                print(f"{n} best shapes given their calibrated realism verdict")
            path = tables.build_table(spec, args.autonomy, Path(args.results), args.budget, only=True,
                                      region=args.region)
        else:
            path = tables.run_table(spec, args, command)
        print(f"wrote {path}")
        return 0
    finally:
        os.chdir(cwd)


def _run(args: argparse.Namespace) -> int:
    import shlex
    import sys

    return execute(args, "adv3d " + shlex.join(sys.argv[1:]))


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "experiments", help="run the paper's tables on the protocol (docs/results.md)", description=DESCRIPTION,
        epilog="e.g. adv3d experiments table1 --autonomy A --scenes 5 --real 2 --seeds 3 --budget 20 --n-initial 8; "
               "adv3d experiments table1 --autonomy A --budget 20 --table-only; adv3d experiments --list")
    add_arguments(p)
    p.set_defaults(func=_run)
