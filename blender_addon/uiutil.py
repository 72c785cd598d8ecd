# SPDX-License-Identifier: GPL-3.0-or-later
"""Operator helpers shared by the panels: errors as reports, exporters with a format choice.

* :func:`reported` wraps an operator's ``execute``: a bad file, an unwritable path or a folder
  given as a file becomes one ``self.report({'ERROR'}, ...)`` line, never a traceback (an
  unexpected exception is reported as an internal error, its traceback printed on the console
  for a bug report).
* :class:`FormatExportHelper` is ``ExportHelper`` for exporters that write several formats, as
  Blender's glTF exporter does: an enum ``file_format`` chooses the format, its extension is
  ``filename_ext``; in the file browser a typed known extension (``car.obj``, ``scene.json.gz``)
  selects that format instead of being rewritten, and a name without one gets the chosen
  format's extension.
"""
from __future__ import annotations

import functools
import os
import traceback
from pathlib import Path

from bpy_extras.io_utils import ExportHelper

from . import runner

#: What an operator reports instead of raising (bad files, paths, values).
EXPECTED_ERRORS = (runner.Adv3dError, OSError, ValueError, KeyError)


def error_text(exc: BaseException) -> str:
    """One line for the status bar / info log."""
    if isinstance(exc, KeyError) and exc.args:
        return str(exc.args[0])
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc) or type(exc).__name__


def reported(execute):
    """Decorator for ``Operator.execute``: errors become ``self.report({'ERROR'}, ...)``."""

    @functools.wraps(execute)
    def wrapper(self, context):
        try:
            return execute(self, context)
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, error_text(exc))
        except Exception as exc:  # a bug: one line for the user, the traceback on the console
            traceback.print_exc()
            self.report({"ERROR"}, f"internal error ({type(exc).__name__}: {exc})")
        return {"CANCELLED"}

    return wrapper


def writable_target(path: str) -> Path:
    """The file ``path`` names, checked before any work: not empty, not a folder, its folder
    exists (raises ``Adv3dError`` / ``OSError`` with the path)."""
    if not path or not os.path.basename(path):
        raise runner.Adv3dError(f"{path or '(no path)'}: choose a file name, not a folder")
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(21, "is a folder, not a file", str(p))
    if not p.parent.is_dir():
        raise FileNotFoundError(2, "the folder does not exist", str(p.parent))
    if not os.access(p.parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise PermissionError(13, "not writable", str(p))
    return p


class FormatExportHelper(ExportHelper):
    """``ExportHelper`` with a ``file_format`` enum; subclasses set ``FORMATS`` (enum identifier
    -> extension, longest first where one ends another: ``.json.gz`` before ``.json``) and declare
    ``file_format: EnumProperty(...)`` with the same identifiers."""

    FORMATS: dict[str, str] = {}
    check_extension = None  # ExportHelper.check would rewrite ".json.gz" to ".json": done here

    @property
    def filename_ext(self) -> str:  # read by ExportHelper.invoke for the default file name
        return self.FORMATS[self.file_format]

    @classmethod
    def format_of(cls, name: str) -> str | None:
        """The format whose extension ``name`` ends with (None if no known one)."""
        low = name.lower()
        for fmt, ext in sorted(cls.FORMATS.items(), key=lambda kv: -len(kv[1])):
            if low.endswith(ext):
                return fmt
        return None

    def check(self, context):
        return self.fix_extension()

    def fix_extension(self) -> bool:
        """Keep a typed known extension (and select its format), else add the chosen format's;
        returns whether ``filepath`` or ``file_format`` changed."""
        name = os.path.basename(self.filepath)
        if not name:
            return False
        fmt = self.format_of(name)
        if fmt is not None:
            if fmt != self.file_format:
                self.file_format = fmt
                return True
            return False
        stem, ext = os.path.splitext(self.filepath)
        # an unknown extension is replaced (as ExportHelper does); a bare name gets one
        self.filepath = (stem if ext and len(ext) <= 5 else self.filepath) + self.filename_ext
        return True

    def target_path(self) -> Path:
        """The file to write: a known extension decides the format; a name without an extension
        gets the chosen format's; anything else is an error naming the allowed extensions."""
        name = os.path.basename(self.filepath)
        if name and self.format_of(name) is None:
            if os.path.splitext(name)[1]:
                raise runner.Adv3dError(f"{name}: files of this kind must end in one of "
                                        f"{', '.join(self.FORMATS.values())}")
            self.filepath += self.filename_ext
        elif name:
            self.file_format = self.format_of(name)
        return writable_target(self.filepath)
