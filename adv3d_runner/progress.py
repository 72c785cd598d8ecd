"""Progress bars for long work; silenced globally by the CLI's ``--quiet``."""
from __future__ import annotations

from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
_QUIET = False


def set_quiet(quiet: bool) -> None:
    """Silence (or re-enable) every progress bar and status line."""
    global _QUIET
    _QUIET = bool(quiet)


def is_quiet() -> bool:
    return _QUIET


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterable[T]:
    """Wrap ``iterable`` in a progress bar unless quiet."""
    return tqdm(iterable, desc=desc, total=total, unit=unit, disable=_QUIET, leave=False, dynamic_ncols=True)


def status(message: str) -> None:
    """Print one status line unless quiet."""
    if not _QUIET:
        print(message, flush=True)
