"""Argument types shared by every ``adv3d`` command: the one place a number or name typed on the
command line is checked.

Each function returns an ``argparse`` ``type=`` callable that parses the text or raises
``argparse.ArgumentTypeError``; argparse turns that into one line
``adv3d <command>: error: argument --seed: expected an integer >= 0 (got '-1')`` and exit code 2
(``adv3d_runner.cli.Parser``). Floats are finite: ``nan``, ``inf`` and ``1e400`` are refused
everywhere, so no command runs "zero frames" or a NaN-long episode silently.

Ground floor: imports nothing from adv3d but ``fileio`` (the safe-name rule).
"""
from __future__ import annotations

import argparse
import math
from typing import Callable

from .fileio import SAFE_NAME_EXPECTED, is_safe_name

#: Seeds go to ``numpy.random.default_rng`` and ``torch.manual_seed``: non-negative, 32 bits.
SEED_MAX = 2**32 - 1
#: The signed axes ``--up`` / ``--forward`` take.
AXES = ("+x", "-x", "+y", "-y", "+z", "-z", "x", "y", "z")


def _fmt(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def _range_text(kind: str, lo, hi, lo_open: bool) -> str:
    if lo is not None and hi is not None and not lo_open:
        return f"{kind} in [{_fmt(lo)}, {_fmt(hi)}]"
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {_fmt(lo)}")
    if hi is not None:
        parts.append(f"<= {_fmt(hi)}")
    return f"{kind} " + " and ".join(parts) if parts else kind


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An integer in ``[lo, hi]`` (either bound may be None)."""
    def parse(text: str) -> int:
        expected = _range_text("an integer", lo, hi, False)
        try:
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected} (got {text!r})") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected {expected} (got {text!r})")
        return value

    parse.__name__ = "integer"  # argparse names the type in its own messages
    return parse


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False) -> Callable[[str], float]:
    """A finite number in ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``)."""
    def parse(text: str) -> float:
        expected = _range_text("a finite number", lo, hi, lo_open)
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected} (got {text!r})") from None
        if (not math.isfinite(value) or (lo is not None and (value < lo or (lo_open and value == lo)))
                or (hi is not None and value > hi)):
            raise argparse.ArgumentTypeError(f"expected {expected} (got {text!r})")
        return value

    parse.__name__ = "number"
    return parse


def numbers(lo: float | None = None, hi: float | None = None, *, length: int | None = None) -> Callable[[str], list[float]]:
    """A comma-separated list of finite numbers in ``[lo, hi]`` (``0.5,0.5,0.5``), of
    ``length`` items when given."""
    item = number(lo, hi)

    def parse(text: str) -> list[float]:
        parts = [p for p in text.split(",") if p.strip() != ""]
        if not parts or (length is not None and len(parts) != length):
            what = f"{length} " if length is not None else ""
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {what}numbers (got {text!r})")
        return [item(p.strip()) for p in parts]

    parse.__name__ = "numbers"
    return parse


def name(text: str) -> str:
    """An id that becomes a file name (``fileio.SAFE_NAME``)."""
    if not is_safe_name(text):
        raise argparse.ArgumentTypeError(f"expected {SAFE_NAME_EXPECTED} (got {text!r})")
    return text


def axis(text: str) -> str:
    """A signed axis ``+x -x +y -y +z -z`` (``x`` means ``+x``). ``--up -y`` is accepted as
    written in the docs: the CLI joins an axis option and a following ``-y`` before parsing."""
    t = text.strip().lower()
    if t not in AXES:
        raise argparse.ArgumentTypeError(f"expected one of +x -x +y -y +z -z (got {text!r})")
    return t if t[0] in "+-" else "+" + t


#: Upper bound of counts without a natural one (epochs, scenes, frame numbers): far above any
#: use, low enough that nothing sizes an array or a loop by an absurd number.
MAX_COUNT = 10**9

seed = integer(0, SEED_MAX)
seed.__name__ = "seed"
positive_int = integer(1, MAX_COUNT)
count = integer(0, MAX_COUNT)
positive = number(0.0, lo_open=True)
