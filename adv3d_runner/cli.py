"""The ``adv3d`` command.

Each subpackage owns its subcommands in a ``cli`` module with ``register(subparsers)``; the
parsers are cheap to build and every handler imports its heavy dependencies itself, so
``adv3d --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import Adv3dError
from .progress import set_quiet

# Modules that add subcommands, in the order they appear in --help. A module that is not
# written yet is skipped, so the command works while the project grows.
COMMAND_MODULES = (
    "adv3d_runner.demo",            # demo (the README's main job)
    "adv3d_runner.shapes.library_cli",  # assets ...
    "adv3d_runner.shapes.cli",      # shapes ...
    "adv3d_runner.scene.cli",       # scenes ...
    "adv3d_runner.sensors.cli",     # lidar ...
    "adv3d_runner.sim.cli",         # simulate
    "adv3d_runner.training.cli",    # train ...
    "adv3d_runner.attack.cli",      # attack, report
    "adv3d_runner.blender_cli",     # blender build/render (never imports bpy in-process)
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="adv3d",
        description="Generate safety-critical 3D vehicle shapes for LiDAR autonomy by closed-loop simulation.",
    )
    parser.add_argument("--version", action="version", version=f"adv3d {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or status lines")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue
            raise
        module.register(subparsers)
    return parser


#: Commands that choose their own threads (training uses every core); every other command runs
#: its numerical libraries on one thread (``machine.limit_threads``; bench/threads.py).
OWN_THREADS = ("train",)


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    command = next((w for w in words if not w.startswith("-")), None)
    if command not in OWN_THREADS:
        from .machine import limit_threads

        limit_threads()  # before numpy and torch load (building the parser imports numpy)
    parser = build_parser()
    args = parser.parse_args(argv)
    set_quiet(args.quiet)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        result = args.func(args)
    except Adv3dError as exc:
        print(f"adv3d: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # `adv3d ... | head`: the reader left; not an error of ours
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("adv3d: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
