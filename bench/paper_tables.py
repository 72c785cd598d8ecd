"""``adv3d experiments`` under its old name (the driver is :mod:`adv3d_runner.experiments`;
docs/results.md). The same options, rules and kept files::

    python bench/paper_tables.py table1 --autonomy A --scenes 5 --real 2 --seeds 3 --budget 20 --n-initial 8
    python bench/paper_tables.py table1 --autonomy A --budget 20 --table-only
    python bench/paper_tables.py --list

The driver's functions (``TABLES``, ``build_table``, ``load_kept`` ...) are re-exported here.
"""
from __future__ import annotations

import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from adv3d_runner.experiments.cli import add_arguments, execute  # noqa: E402
from adv3d_runner.experiments.tables import *  # noqa: E402,F401,F403 (the driver's API under its old name)
from adv3d_runner.experiments.tables import (  # noqa: E402,F401
    MAX_SEEDS, MAX_SHARDS, TABLES, baseline_row, build_table, campaign_units, collect, complete_block, folder_type,
    growth_words, list_tables, load_compute, load_kept, model_versions, parse_shard, read_protocol, run_table,
    shard_type, stack_folder, unit_complete, VERSION_KEYS)


def build_parser():
    """The command line of ``adv3d experiments``, as ``paper_tables.py``."""
    from adv3d_runner.cli import Parser

    p = Parser(prog="paper_tables.py", description="The paper's tables on the protocol (adv3d experiments).")
    add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    """Exit codes as ``adv3d``'s: 0 done, 1 an error (one line), 2 a bad option value (one usage line)."""
    from adv3d_runner.errors import Adv3dError, UsageError

    p = build_parser()
    args = p.parse_args(argv)  # a bad value: one usage line, SystemExit(2)
    words = sys.argv[1:] if argv is None else list(argv)
    try:
        return execute(args, "python bench/paper_tables.py " + shlex.join(words))
    except UsageError as exc:
        p.error(str(exc))
    except Adv3dError as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
