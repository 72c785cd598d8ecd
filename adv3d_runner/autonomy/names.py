"""Names of the stacks under test, without importing any stack (the CLI's parsers use it, so
``adv3d --help`` stays fast): the ``adv3d.stacks`` entry points and the spec forms of
docs/stacks.md. Building a stack: :mod:`.plugins`."""
from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import ConfigError
from ..fileio import REPO_ROOT

ENTRY_POINT_GROUP = "adv3d.stacks"
#: Folders of the shipped learned models (weights + config.json), by model.
MODEL_DIRS = {name: REPO_ROOT / "assets" / "models" / name for name in ("detector", "predictor", "occupancy")}

#: adv3d's own stacks (also in pyproject.toml's entry points: listed here so that a checkout
#: run without installing finds them too).
BUILTIN = {
    "A": "adv3d_runner.autonomy.stacks:autonomy_a",
    "A-fast": "adv3d_runner.autonomy.stacks:autonomy_a_fast",
    "A-lanefollow": "adv3d_runner.autonomy.stacks:autonomy_a_lanefollow",
    "B": "adv3d_runner.autonomy.stacks:autonomy_b",
    "oracle": "adv3d_runner.autonomy.stacks:oracle",
}
_TARGET = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
_REMOTE_PREFIXES = ("exec:", "tcp://", "unix:")


@dataclass(frozen=True)
class StackEntry:
    """A stack adv3d can build: its name, what builds it and where that was found."""

    name: str
    target: str
    source: str


def registered() -> dict[str, StackEntry]:
    """Every registered stack by name: adv3d's own, then the ``adv3d.stacks`` entry points of
    the installed packages (a plugin may not take a built-in's name)."""
    from importlib.metadata import entry_points

    out = {name: StackEntry(name, target, "adv3d") for name, target in BUILTIN.items()}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in BUILTIN:
            continue  # adv3d's own (its installed metadata) or a plugin shadowing one: built-in wins
        dist = getattr(ep, "dist", None)
        out[ep.name] = StackEntry(ep.name, ep.value, f"entry point of {dist.name if dist else '?'}")
    return out


def is_remote(spec: str) -> bool:
    return spec.startswith(_REMOTE_PREFIXES)


def check_spec(spec: str) -> str:
    """``spec`` if it can name a stack (a registered name, ``module:factory`` or a remote
    address), without importing anything; ConfigError otherwise (argparse's ``type=``)."""
    spec = str(spec).strip()
    if spec in registered() or _TARGET.match(spec) or is_remote(spec):
        return spec
    raise ConfigError(f"unknown stack {spec!r}: expected one of {', '.join(registered())}, "
                      "package.module:factory, exec:COMMAND, tcp://HOST:PORT or unix:PATH (adv3d stacks list)")


def stack_spec(text: str) -> str:
    """``argparse`` ``type=`` for ``--autonomy``: :func:`check_spec`, a bad name a usage error."""
    import argparse

    try:
        return check_spec(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
