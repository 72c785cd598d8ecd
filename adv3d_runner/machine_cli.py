"""``adv3d numerics``: the numerical configuration results depend on, and runs under another one.

docs/reliability.md ("Same seed, same result") says what the fields mean and what differs
between configurations.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from .errors import ConfigError
from .machine import EMBREE_TIERS, EMULATIONS, cpu_tier, numerical_config


def emulation_env(name: str, base: dict[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's environment) with the variables of emulation ``name``.

    Raises:
        ConfigError: an unknown name, or one above this CPU's tier (its kernels would die of an
            illegal instruction).
    """
    if name not in EMULATIONS:
        raise ConfigError(f"--emulate {name!r}: expected one of {', '.join(EMULATIONS)}")
    tiers = list(EMBREE_TIERS)
    have = cpu_tier()
    if have is None or tiers.index(name) > tiers.index(have):
        raise ConfigError(f"--emulate {name}: this CPU runs at most {have} (an emulation can only lower the kernels)")
    return {**(os.environ if base is None else base), **EMULATIONS[name]}


def _numerics(args: argparse.Namespace) -> int:
    command = list(args.cmd)
    if command and command[0] == "--":
        command = command[1:]
    if args.emulate is None:
        if command:
            raise ConfigError("a command to run needs --emulate NAME (adv3d numerics --emulate avx2 -- CMD ...)")
        cfg = numerical_config()
        if args.json:
            print(json.dumps(cfg, indent=1))
        else:
            width = max(map(len, cfg))
            for key, value in cfg.items():
                print(f"{key:<{width}}  {value}")
        return 0
    env = emulation_env(args.emulate)
    if not command:  # show the emulated configuration
        command = [sys.executable, "-m", "adv3d_runner.cli", "numerics"] + (["--json"] if args.json else [])
    try:
        return subprocess.call(command, env=env)
    except FileNotFoundError as exc:
        raise ConfigError(f"cannot run {command[0]!r}: {exc.strerror}") from None


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "numerics", help="the numerical configuration (CPU, Embree ISA, BLAS, torch, numba), or run under another",
        description="Print the numerical configuration that results depend on bit for bit (run.json records it), "
                    "or run a command with the kernels another CPU would choose: "
                    f"--emulate {{{','.join(EMULATIONS)}}} -- CMD ... (docs/reliability.md).")
    p.add_argument("--json", action="store_true", help="print the configuration as JSON")
    p.add_argument("--emulate", choices=sorted(EMULATIONS), default=None, metavar="NAME",
                   help=f"run CMD (default: this command) under an emulated CPU: {', '.join(EMULATIONS)}")
    p.add_argument("cmd", nargs=argparse.REMAINDER, help="-- CMD ...: the command to run under --emulate")
    p.set_defaults(func=_numerics)
