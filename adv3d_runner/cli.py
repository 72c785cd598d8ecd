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
from .argtypes import axis
from .errors import Adv3dError, UsageError
from .progress import set_quiet

# Modules that add subcommands, in the order they appear in --help. A module that is not
# written yet is skipped, so the command works while the project grows.
COMMAND_MODULES = (
    "adv3d_runner.demo",            # demo (the README's main job)
    "adv3d_runner.shapes.library_cli",  # assets ...
    "adv3d_runner.shapes.cli",      # shapes ...
    "adv3d_runner.scene.cli",       # scenes ...
    "adv3d_runner.sensors.cli",     # lidar ...
    "adv3d_runner.autonomy.cli",    # stacks ...
    "adv3d_runner.sim.cli",         # simulate
    "adv3d_runner.training.cli",    # train ...
    "adv3d_runner.attack.cli",      # attack, report
    "adv3d_runner.attack.export_cli",  # export (a found failure as CommonRoad / OpenSCENARIO)
    "adv3d_runner.experiments.cli",  # experiments (the paper's tables on the protocol)
    "adv3d_runner.blender_cli",     # blender build/render (never imports bpy in-process)
    "adv3d_runner.machine_cli",     # numerics
)


class Parser(argparse.ArgumentParser):
    """``ArgumentParser`` whose usage errors are one line (``adv3d attack: error: argument
    --seed: expected ...``, exit code 2), like every other error of the tool; subcommand parsers
    are of this class too (argparse makes them with the parent's class)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _leaf_parsers(parser: argparse.ArgumentParser):
    """Every parser under ``parser`` (itself included), depth first."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases map to the same parser
                yield from _leaf_parsers(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
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
    # Every command takes -q/--quiet, before or after the subcommand (SUPPRESS: a subcommand
    # that is not given -q leaves the top-level value alone).
    for sub in _leaf_parsers(parser):
        if sub is not parser and "--quiet" not in sub._option_string_actions:
            sub.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                             help="no progress bars or status lines")
        sub.set_defaults(_prog=sub.prog)  # the innermost command's, for a UsageError's line
    return parser


#: Commands that choose their own threads (training uses every core); every other command runs
#: its numerical libraries on one thread (``machine.limit_threads``; bench/threads.py).
OWN_THREADS = ("train",)


def _join_axis_values(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``--up -y`` -> ``--up=-y`` for options of type :func:`adv3d_runner.argtypes.axis`
    (argparse would take ``-y`` for an option)."""
    flags = {flag for sub in _leaf_parsers(parser) for flag, action in sub._option_string_actions.items()
             if action.type is axis}
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in flags and i + 1 < len(argv) and argv[i + 1][:1] == "-" and len(argv[i + 1]) == 2:
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    command = next((w for w in words if not w.startswith("-")), None)
    if command not in OWN_THREADS:
        from .machine import limit_threads

        limit_threads()  # before numpy and torch load (building the parser imports numpy)
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(_join_axis_values(parser, argv))  # usage errors: one line, SystemExit(2)
    set_quiet(args.quiet)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        result = args.func(args)
    except UsageError as exc:  # the command line cannot run as given: as argparse says it, exit 2
        prog = getattr(args, "_prog", parser.prog)
        print(f"{prog}: error: {exc} (see {prog} --help)", file=sys.stderr)
        return 2
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
