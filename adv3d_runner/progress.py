"""Progress bars for long work; silenced globally by the CLI's ``--quiet``.

Also the stepwise protocol for long work that must not block a caller's event loop (the
Blender add-on): a *steps generator* does its work in short pieces, yielding ``None`` or a
``(fraction, message)`` progress tuple between them, and returns its result
(``StopIteration.value``); :func:`run_steps` drives one to the end for callers that just want
the result, so the stepwise and the plain call are one code path.
"""
from __future__ import annotations

from typing import Any, Generator, Iterable, TypeVar

T = TypeVar("T")
_QUIET = False

#: A generator of progress steps (None or (fraction in [0, 1], message)) returning R.
Steps = Generator[Any, None, T]


def set_quiet(quiet: bool) -> None:
    """Silence (or re-enable) every progress bar and status line."""
    global _QUIET
    _QUIET = bool(quiet)


def is_quiet() -> bool:
    return _QUIET


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterable[T]:
    """Wrap ``iterable`` in a progress bar unless quiet (or tqdm is missing: a stock Blender)."""
    if _QUIET:
        return iterable
    try:  # imported here: the add-on runs code that calls this inside Blender, which has no tqdm
        from tqdm.auto import tqdm
    except ImportError:
        return iterable
    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False, dynamic_ncols=True)


def status(message: str) -> None:
    """Print one status line unless quiet."""
    if not _QUIET:
        print(message, flush=True)


def note(message: str) -> None:
    """Print one line that changes what a result means (a run resumed under other versions, a
    scene skipped), even when quiet: ``-q`` silences progress, not these."""
    print(message, flush=True)


def run_steps(steps: Steps[T]) -> T:
    """Drive a steps generator to its end and return its result."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


def relay(steps: Steps[T], step: Any) -> Steps[T]:
    """Re-yield every step of ``steps`` as ``step`` (the caller's own progress tuple) and return
    its result: ``value = yield from relay(inner, (0.5, "half way"))``."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value
        yield step


def span(steps: Steps[T], lo: float, hi: float, message: str) -> Steps[T]:
    """Re-yield the steps of ``steps`` as ``(fraction, message)`` with its own fractions (when
    it yields ``(f, ...)``) mapped into ``[lo, hi]``; return its result."""
    while True:
        try:
            step = next(steps)
        except StopIteration as stop:
            return stop.value
        f = step[0] if isinstance(step, tuple) and step else 0.0
        yield lo + (hi - lo) * float(f), message
