"""One exception family for everything adv3d raises on purpose.

The CLI catches ``Adv3dError`` and prints its message without a traceback; anything else is a
bug and keeps its traceback.
"""
from __future__ import annotations

from pathlib import Path


class Adv3dError(Exception):
    """Base class of every error adv3d raises deliberately."""


class FileFormatError(Adv3dError):
    """A file is unreadable or does not match its contract.

    The message names the file, the field as a JSON path (``$.actors[3].track.x``) and what was
    expected, so a user can fix the file without reading code.
    """

    def __init__(self, path: str | Path | None, field: str, expected: str, got: object = None):
        self.path = None if path is None else str(path)
        self.field = field
        self.expected = expected
        self.got = got
        where = f"{self.path}: " if self.path else ""
        got_txt = "" if got is None else f" (got {_short(got)})"
        super().__init__(f"{where}{field}: expected {expected}{got_txt}")


class MeshImportError(Adv3dError):
    """A mesh file cannot be imported (missing, corrupt, not a mesh, empty)."""


class InvalidQueryError(Adv3dError):
    """An attack query cannot be evaluated; callers record it and penalise it, never crash."""


class EmptySurfaceError(InvalidQueryError):
    """A latent decodes to a field with no zero level set (no surface to extract)."""


class RunFailedError(Adv3dError):
    """A command ran but produced nothing usable (every attack query failed, or every scene was
    skipped); the message says why."""


class StackFailure(Adv3dError):
    """The stack under test failed: it crashed, hung past its per-frame timeout, or answered
    something malformed (docs/stacks.md). In an attack the query fails with this reason and
    the run goes on."""


class ConfigError(Adv3dError):
    """Bad command-line or configuration value."""


class UsageError(ConfigError):
    """A command line that cannot run as given: an option value that is wrong for the other
    options or for the files it names (``--vd-bound`` without ``--shape-model vd``, ``--frame``
    past the scene's last frame). The CLI prints it as argparse prints a bad option value, one
    usage line, exit code 2 (docs/reliability.md, "Exit codes")."""


class UnknownIdError(ConfigError, KeyError):
    """An id (asset, actor, lane) that is not there; a ``KeyError`` too, for callers that look
    things up, and a ``ConfigError``, so the CLI reports it in one line."""

    def __str__(self) -> str:  # KeyError would print the message with quotes
        return str(self.args[0]) if self.args else ""


def _short(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
