"""Typed readers shared by every file contract (scene, replay, vehicle library, shape space,
model configs, run bundle).

A :class:`Node` is one parsed JSON value together with the file it came from and its JSON path
(``$.actors[3].track.x``). Indexing a node gives the child node with the longer path; each
reader checks a type (and bounds) and returns a plain Python or numpy value, or raises
:class:`~adv3d_runner.errors.FileFormatError` naming the file, the JSON path, what was expected
and what was found. Loaders therefore read like their contract, and the message format lives in
one place (the way glTF-Blender-IO shares one set of typed readers across its file format)::

    doc = Node.load(path)                      # read_json + Node(doc, "$", path)
    check_header(doc, FORMAT, (1,))
    frames = doc["frames"].integer(lo=1)       # $.frames: expected an integer >= 1 (got 0)
    for lane in doc["map"]["lanes"].objects("a non-empty list of lanes", non_empty=True):
        centerline = lane["centerline"].points()

``.npz`` contents go through :func:`read_npz` and :class:`Arrays` (dtype / shape / finite checks,
members named as ``$.NAME``).

Ground floor: imports only ``errors`` and ``fileio`` (and numpy), so every layer, the Blender
add-on included, can use it.
"""
from __future__ import annotations

import math
import zipfile
import zlib
from pathlib import Path
from typing import Any, Generator, Iterable, NoReturn, Sequence

import numpy as np

from .errors import FileFormatError
from .fileio import (SAFE_NAME_EXPECTED, check_regular_file, is_safe_name, parse_json, read_json,
                     rel_path_problem, resolve_inside)

#: What a missing required field expects (one wording for every contract).
MISSING = "a value (field is missing)"


def describe(value: Any) -> Any:
    """What an error's ``got`` shows for ``value``: a list as ``N items`` (lists can be long
    tracks), anything else as itself (the error message shortens long values)."""
    if isinstance(value, list):
        return "an empty list" if not value else "1 item" if len(value) == 1 else f"{len(value)} items"
    return value


def shape_text(shape: Sequence[int | str | None]) -> str:
    """``(N, 5)`` for an expected array shape; ``None`` entries (any length) print as ``N``."""
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"


_NUMBER_TYPES = frozenset((int, float))
_NULLABLE_TYPES = frozenset((int, float, type(None)))  # 1-d arrays: null reads as NaN (refused unless nullable)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Node:
    """A JSON value at a JSON path of a file.

    Attributes:
        value: the parsed value (``dict``, ``list``, ``str``, number, bool or ``None``).
        path: its JSON path (``$`` for the document).
        file: the file it was read from (named in errors), or None.
        present: False for an optional field that is absent (``value`` is then the default).
    """

    __slots__ = ("value", "file", "present", "_path", "_parent", "_key")

    def __init__(self, value: Any, path: str | None = "$", file: str | Path | None = None, present: bool = True):
        self.value = value
        self.file = file
        self.present = present
        self._path = path
        self._parent: Node | None = None
        self._key: str | int | None = None

    @property
    def path(self) -> str:
        """The JSON path, built on first use (most nodes are never named in an error)."""
        if self._path is None:
            key = self._key
            self._path = f"{self._parent.path}[{key}]" if isinstance(key, int) else f"{self._parent.path}.{key}"
        return self._path

    @classmethod
    def load(cls, file: str | Path) -> "Node":
        """The document of a JSON (or ``.json.gz``) file (``FileFormatError`` if unreadable)."""
        return cls(read_json(file), "$", file)

    def __repr__(self) -> str:
        return f"Node({self.path}={describe(self.value)!r})"

    # ------------------------------------------------------------------ errors
    def fail(self, expected: str, got: Any = None, *, at: str = "") -> NoReturn:
        """Raise ``FileFormatError(file, path + at, expected, got)``; ``at`` names a part of
        this value (``"[3]"``, ``".x"``)."""
        raise FileFormatError(self.file, self.path + at, expected, got)

    # ------------------------------------------------------------------ navigation
    def child(self, key: str | int, value: Any = None) -> "Node":
        """A node for ``value`` at ``self.path.key`` / ``self.path[key]`` (no checks)."""
        node = Node(value, None, self.file)
        node._parent = self
        node._key = key
        return node

    def __getitem__(self, key: str | int) -> "Node":
        """A required field of an object (``str`` key) or an item of a list (``int``)."""
        if isinstance(key, int):
            items = self.list()
            if not -len(items) <= key < len(items):
                self.fail(f"a list of at least {key + 1} items", describe(items))
            return self.child(key, items[key])
        obj = self.object()
        if key not in obj:
            self.child(key).fail(MISSING)
        return self.child(key, obj[key])

    def get(self, key: str, default: Any = None) -> "Node":
        """An optional field: its node, or a node holding ``default`` (``present`` False)."""
        obj = self.object()
        if key in obj:
            return self.child(key, obj[key])
        node = self.child(key, default)
        node.present = False
        return node

    def __contains__(self, key: str) -> bool:
        return isinstance(self.value, dict) and key in self.value

    # ------------------------------------------------------------------ containers
    def object(self, expected: str = "an object") -> dict:
        """The value as a JSON object (``dict``)."""
        if not isinstance(self.value, dict):
            self.fail(expected, type(self.value).__name__)
        return self.value

    def check_keys(self, known: Iterable[str], required: Iterable[str] = ()) -> "Node":
        """Every ``required`` key is present and no key outside ``known`` is (fields are never
        silently dropped on a round trip). Returns self."""
        obj = self.object()
        for key in required:
            if key not in obj:
                self.child(key).fail(MISSING)
        known = tuple(known)
        unknown = sorted(set(obj) - set(known))
        if unknown:
            self.child(unknown[0]).fail(f"no such field (known: {', '.join(known)})")
        return self

    def list(self, expected: str = "a list", *, length: int | None = None, non_empty: bool = False) -> list:
        """The value as a JSON list, optionally of a given ``length`` or non-empty."""
        value = self.value
        if not isinstance(value, list):
            self.fail(expected, value)
        if (length is not None and len(value) != length) or (non_empty and not value):
            self.fail(expected, describe(value))
        return value

    def items(self, expected: str = "a list", *, length: int | None = None, non_empty: bool = False) -> list["Node"]:
        """The list's items as nodes (``$.x[0]``, ``$.x[1]``, ...)."""
        return [self.child(i, item) for i, item in enumerate(self.list(expected, length=length, non_empty=non_empty))]

    def objects(self, expected: str = "a list of objects", *, item: str = "an object",
                non_empty: bool = False) -> list["Node"]:
        """A list of JSON objects as nodes; a non-object item fails with ``item``."""
        nodes = self.items(expected, non_empty=non_empty)
        for node in nodes:
            node.object(item)
        return nodes

    # ------------------------------------------------------------------ scalars
    def number(self, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
               expected: str | None = None) -> float:
        """A finite number in ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``) as ``float``.
        ``expected`` replaces the wording of the range (e.g. ``"a positive size in m"``)."""
        v = self.value
        if not _is_number(v):
            self.fail("a number", describe(v))
        if not math.isfinite(v):
            self.fail("a finite number", v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(expected or f"a number {'>' if lo_open else '>='} {lo}", v)
        if hi is not None and v > hi:
            self.fail(expected or f"a number <= {hi}", v)
        return float(v)

    def integer(self, *, lo: int | None = None, hi: int | None = None, expected: str | None = None) -> int:
        """A JSON integer (not a bool, not 2.0) in ``[lo, hi]``; ``expected`` replaces the
        wording of the range."""
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail("an integer", describe(v))
        if lo is not None and hi is not None and not lo <= v <= hi:
            self.fail(expected or f"an integer in [{lo}, {hi}]", v)
        if lo is not None and v < lo:
            self.fail(expected or f"an integer >= {lo}", v)
        if hi is not None and v > hi:
            self.fail(expected or f"an integer <= {hi}", v)
        return int(v)

    def boolean(self) -> bool:
        """``true`` or ``false``."""
        if not isinstance(self.value, bool):
            self.fail("true or false", describe(self.value))
        return self.value

    def string(self, *, choices: Sequence[str] | None = None, nullable: bool = False, empty: bool = False,
               pattern=None, expected: str | None = None) -> str | None:
        """A string: non-empty unless ``empty``; one of ``choices``; matching the compiled
        regex ``pattern`` (``expected`` then says what the pattern means); ``None`` allowed
        when ``nullable``."""
        v = self.value
        if v is None and nullable:
            return None
        if not isinstance(v, str) or (not v and not empty):
            base = "a string" if empty else "a non-empty string"
            self.fail(expected or (base + (" or null" if nullable else "")), describe(v))
        if choices is not None and v not in choices:
            self.fail(f"one of {list(choices)}", v)
        if pattern is not None and not pattern.match(v):
            self.fail(expected or f"a string matching {pattern.pattern}", v)
        return v

    def unique(self, value: Any, seen: set, what: str) -> Any:
        """Record ``value`` (read from this node) in ``seen``; a repeat fails as
        ``a unique <what>``."""
        if value in seen:
            self.fail(f"a unique {what}", value)
        seen.add(value)
        return value

    # ------------------------------------------------------------------ numeric lists
    def numbers(self, *, length: int | None = None, min_length: int = 0, lo: float | None = None,
                lo_open: bool = False, hi: float | None = None, expected: str | None = None) -> np.ndarray:
        """A flat JSON list of finite numbers in ``[lo, hi]`` -> (n,) float64; a bad item is
        named (``$.track.x[17]``). ``expected`` replaces the wording of the range."""
        v = self.value
        if not isinstance(v, list):
            self.fail("a list of numbers", describe(v))
        if length is not None and len(v) != length:
            self.fail(f"a list of {length} numbers", describe(v))
        if len(v) < min_length:
            self.fail(f"a list of at least {min_length} numbers", describe(v))
        for i, item in enumerate(v):
            if not _is_number(item):
                self.fail("a number", describe(item), at=f"[{i}]")
            if not math.isfinite(item):
                self.fail("a finite number", item, at=f"[{i}]")
            if lo is not None and (item < lo or (lo_open and item == lo)):
                self.fail(expected or f"a number {'>' if lo_open else '>='} {lo}", item, at=f"[{i}]")
            if hi is not None and item > hi:
                self.fail(expected or f"a number <= {hi}", item, at=f"[{i}]")
        return np.asarray(v, dtype=np.float64).reshape(-1)

    def flags(self, length: int) -> np.ndarray:
        """A JSON list of ``length`` 0/1 flags -> (length,) bool."""
        v = self.value
        if not isinstance(v, list) or len(v) != length:
            self.fail(f"a list of {length} flags (0 or 1)", describe(v))
        for i, item in enumerate(v):
            if item not in (0, 1) or isinstance(item, float):
                self.fail("0 or 1", item, at=f"[{i}]")
        return np.asarray(v, dtype=bool)

    def points(self, *, min_points: int = 2, limit: float | None = None) -> np.ndarray:
        """A JSON list of ``[x, y]`` -> (P, 2) float64, P >= ``min_points``; with ``limit``
        every coordinate lies in ``[-limit, limit]``."""
        v = self.value
        if not isinstance(v, list) or len(v) < min_points:
            self.fail(f"a list of at least {min_points} [x, y] points", describe(v))
        lo = None if limit is None else -limit
        for node in self.items():
            node.numbers(length=2, lo=lo, hi=limit)
        return np.asarray(v, dtype=np.float64).reshape(-1, 2)

    def array(self, shape: Sequence[int | None], *, nullable: bool = False, limit: float | None = None) -> np.ndarray:
        """A nested JSON list of numbers of ``shape`` (``None``: any length) -> float64 array.

        All values finite (and within ``[-limit, limit]`` when given); with ``nullable`` (1-d
        only) ``null`` items become NaN. An empty list stands for any shape whose first length
        is free or 0 (JSON cannot keep the other lengths of an empty array).
        """
        v = self.value
        if not isinstance(v, list):
            self.fail(f"an array of shape {shape_text(shape)}", type(v).__name__)
        try:
            a = np.array([np.nan if x is None else x for x in v] if len(shape) == 1 else v, dtype=np.float64)
        except (ValueError, TypeError):
            a = None
        if a is None or a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
            if len(v) == 0 and shape[0] in (None, 0):
                return np.zeros(tuple(0 if s is None else s for s in shape))
            self.fail(f"an array of shape {shape_text(shape)} of numbers", describe(v))
        # numpy would read "1.5" and true as numbers: every item must be a JSON number (or null)
        leaves = v if a.ndim == 1 else np.array(v, dtype=object).reshape(-1)
        allowed = _NUMBER_TYPES if a.ndim > 1 else _NULLABLE_TYPES
        if not set(map(type, leaves)) <= allowed:
            i = next(i for i, x in enumerate(leaves) if type(x) not in allowed)
            self.fail("a number", describe(leaves[i]),
                      at="".join(f"[{int(k)}]" for k in np.unravel_index(i, a.shape)))
        if not nullable and not np.isfinite(a).all():
            bad = np.argwhere(~np.isfinite(a))[0]
            self.fail("a finite number", None, at="".join(f"[{int(i)}]" for i in bad))
        if limit is not None and np.any(big := np.abs(a) > limit):
            bad = np.argwhere(big)[0]
            self.fail(f"a number in [-{limit:g}, {limit:g}]", float(a[tuple(bad)]),
                      at="".join(f"[{int(i)}]" for i in bad))
        return a

    def name(self, *, expected: str | None = None) -> str:
        """An id that becomes a file or folder name (``fileio.SAFE_NAME``: letters, digits,
        ``_ . -``, starting with a letter or digit; never a path)."""
        v = self.value
        if not is_safe_name(v):
            self.fail(expected or SAFE_NAME_EXPECTED, describe(v))
        return v

    def rel_path(self, *, inside: str = "the folder of the file") -> str:
        """A relative POSIX path that stays inside a folder by its letters (no ``..``, not
        absolute, no ``\\``); :meth:`file_in` also resolves it."""
        v = self.value
        if not isinstance(v, str) or not v:
            self.fail("a relative file path (string)", v)
        if rel_path_problem(v):
            self.fail(f"a relative POSIX path inside {inside} (no '..', no absolute path)", v)
        return v

    def file_in(self, root: str | Path, *, inside: str | None = None) -> Path:
        """``root / value`` for a relative path that stays inside ``root``, symlinks included
        (``fileio.resolve_inside``); errors name this file and field."""
        self.rel_path(inside=inside or str(root))
        return resolve_inside(root, self.value, file=self.file, field=self.path, inside=inside)


def read_optional_contract(path: str | Path, fmt: str, supported_versions: Sequence[int]) -> Node | None:
    """An optional contract file (a run's ``avoidability.json``, ``failure_rate.json``, ...): None
    when absent, else its root :class:`Node` with the ``format`` / ``version`` header checked
    (``node.value`` is the document).

    Raises:
        FileFormatError: naming the file and field.
    """
    path = Path(path)
    if not path.exists():
        return None
    node = Node(read_json(path), "$", path)
    check_header(node, fmt, supported_versions)
    return node


def check_header(doc: Node | Any, fmt: str, supported_versions: Sequence[int],
                 file: str | Path | None = None) -> int:
    """Check the ``format`` / ``version`` header every contract file carries.

    Args:
        doc: the document as a :class:`Node` (or a raw value, with ``file`` to name).
        fmt: the expected ``format`` string.
        supported_versions: versions this code reads.
    Returns:
        the file's version.
    """
    node = doc if isinstance(doc, Node) else Node(doc, "$", file)
    obj = node.object("a JSON object")
    if obj.get("format") != fmt:
        node.child("format").fail(f'"{fmt}"', obj.get("format"))
    version = obj.get("version")
    if isinstance(version, bool) or version not in supported_versions:
        node.child("version").fail(f"one of {list(supported_versions)}", version)
    return int(version)


# ------------------------------------------------------------------------------------- npz


class Arrays:
    """The members of an ``.npz`` file, each named ``$.NAME`` in errors.

    Attributes:
        members: {name: array}.
        file: the file (named in errors).
    """

    def __init__(self, members: dict[str, np.ndarray], file: str | Path | None):
        self.members = members
        self.file = file

    def __contains__(self, name: str) -> bool:
        return name in self.members

    def fail(self, name: str, expected: str, got: Any = None) -> NoReturn:
        raise FileFormatError(self.file, f"$.{name}" if name else "$", expected, got)

    def require(self, names: Iterable[str]) -> None:
        """Every member of ``names`` is present (got: the members there are)."""
        for name in names:
            if name not in self.members:
                self.fail(name, f"array member {name}.npy", f"members {sorted(self.members)}")

    def array(self, name: str, *, dtype=None, kind: str | None = None,
              shape: Sequence[int | str | None] | None = None, ndim: int | None = None,
              finite: bool = False) -> np.ndarray:
        """Member ``name`` with exactly ``dtype`` (or dtype ``kind``, e.g. ``"U"``), ``shape``
        (``None``/names: any length) or ``ndim``; ``finite``: no NaN/inf in float data."""
        self.require([name])
        a = self.members[name]
        dt = np.dtype(dtype) if dtype is not None else None
        want_ndim = len(shape) if shape is not None else ndim
        bad = ((dt is not None and a.dtype != dt) or (kind is not None and a.dtype.kind != kind)
               or (want_ndim is not None and a.ndim != want_ndim)
               or (shape is not None and any(isinstance(s, int) and s != n for s, n in zip(shape, a.shape))))
        if bad:
            parts = [f"{ndim}-d" if shape is None and ndim is not None else "",
                     dt.name if dt is not None else {"U": "unicode", "i": "integer", "f": "float"}.get(kind or "", ""),
                     "array", f"of shape {shape_text(shape)}" if shape is not None else ""]
            self.fail(name, " ".join(p for p in parts if p), f"{a.dtype} {a.shape}")
        if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            self.fail(name, "finite values", "NaN or inf")
        return a

    def text(self, name: str) -> str:
        """A 0-d unicode member (``np.array("...")``) as ``str``."""
        self.require([name])
        a = self.members[name]
        if a.dtype.kind != "U" or a.ndim != 0:
            self.fail(name, "a 0-d unicode array", f"{a.dtype} {a.shape}")
        return str(a)

    def integer(self, name: str) -> int:
        """A 0-d integer member as ``int``."""
        self.require([name])
        a = self.members[name]
        if a.dtype.kind not in "iu" or a.ndim != 0:
            self.fail(name, "a 0-d integer array", f"{a.dtype} {a.shape}")
        return int(a)

    def header(self, fmt: str, version: int) -> None:
        """The ``format`` / ``version`` scalars of an npz contract file."""
        got = self.text("format")
        if got != fmt:
            self.fail("format", f'"{fmt}"', got)
        got_version = self.integer("version")
        if got_version != version:
            self.fail("version", f"one of {[version]}", got_version)

    def json(self, name: str) -> Node:
        """A 0-d unicode member holding a JSON document, as a :class:`Node` at ``$.NAME``."""
        text = self.text(name)
        try:
            doc = parse_json(text.encode("utf-8"), self.file)
        except FileFormatError as exc:
            self.fail(name, exc.expected, exc.got)
        return Node(doc, f"$.{name}", self.file)


#: Largest ``.npz`` contents read (bytes, the members' sizes once decompressed). The biggest
#: files the tool writes are the LiDAR points of long replays (~250 MB for 20 s).
MAX_NPZ_BYTES = 2**30


def read_npz(path: str | Path, what: str, hint: str = "", *, limit: int = MAX_NPZ_BYTES) -> Arrays:
    """Every member of an ``.npz`` file, loaded without pickle, bounded.

    Only a regular file is opened; the members' declared sizes (the zip directory) sum to at
    most ``limit`` bytes, and each ``.npy`` header is checked against its member's size before
    any array is allocated, so neither a zip bomb nor a header claiming a huge shape gets far.

    Args:
        path: the file.
        what: what the file is, for errors (``"shape-space .npz file"``).
        hint: appended when the file does not exist (how to make one).
        limit: largest total decompressed size, bytes.
    Raises:
        FileFormatError: missing or not a regular file, not a zip of ``.npy`` arrays, truncated
            or corrupt, too large, or a member that would need pickle.
    """
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise FileFormatError(path, "$", f"an existing {what}{hint}", "file not found")
    check_regular_file(path, what)
    expected = f"a {what} (zip of .npy arrays, no pickled objects)"
    members: dict[str, np.ndarray] = {}
    try:
        with open(path, "rb") as fh:
            if fh.read(6) == b"\x93NUMPY":
                raise FileFormatError(path, "$", expected, "a single .npy array")
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            total = sum(i.file_size for i in infos)
            if total > limit:
                raise FileFormatError(path, "$", f"a {what} of at most {limit / 2**20:.0f} MiB decompressed",
                                      f"{total / 2**20:.0f} MiB")
            for info in infos:
                if not info.filename.endswith(".npy"):
                    raise FileFormatError(path, "$", expected, f"member {info.filename!r}")
                name = info.filename[:-4]
                with zf.open(info) as fh:
                    _check_npy_header(fh, info.file_size, path, name, expected)
                with zf.open(info) as fh:
                    members[name] = np.lib.format.read_array(fh, allow_pickle=False)
    except FileFormatError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, NotImplementedError,
            zlib.error, UnicodeDecodeError, SyntaxError) as exc:
        raise FileFormatError(path, "$", expected, f"{type(exc).__name__}: {exc}") from None
    return Arrays(members, path)


#: Bytes read per step of :func:`read_npz_steps` (~10-30 ms of inflating).
NPZ_STEP_BYTES = 1 << 22


def read_npz_steps(path: str | Path, what: str, hint: str = "",
                   step_bytes: int = NPZ_STEP_BYTES) -> Generator[Any, None, Arrays]:
    """:func:`read_npz` in pieces (a steps generator, ``progress.run_steps``): each member's
    data is inflated ``step_bytes`` at a time into its array, yielding between pieces, for
    callers that must stay responsive (the Blender add-on loading a replay's points). Gives the
    same arrays; anything but plain ``.npy`` members (or a file that is not a zip) is read by
    :func:`read_npz`, so the errors are the same too."""
    path = Path(path)
    if not path.exists() or not zipfile.is_zipfile(path):
        return read_npz(path, what, hint)
    expected = f"a {what} (zip of .npy arrays, no pickled objects)"
    members: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            total = max(sum(info.file_size for info in zf.infolist()), 1)
            done = 0
            for name in zf.namelist():
                with zf.open(name) as fh:
                    array = _npy_member(fh) if name.endswith(".npy") else None
                    if array is None:  # not a plain .npy: numpy's reader (and its message)
                        return read_npz(path, what, hint)
                    out, shape, fortran = array
                    view = memoryview(out).cast("B")
                    pos = 0
                    while pos < len(view):
                        got = fh.readinto(view[pos : pos + step_bytes])
                        if not got:
                            raise EOFError(f"{name}: the array data is cut short")
                        pos += got
                        yield (done + pos) / total,
                    done += zf.getinfo(name).file_size
                members[name[:-4]] = out.reshape(shape[::-1]).transpose() if fortran else out.reshape(shape)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, NotImplementedError,
            zlib.error) as exc:  # the same as read_npz: a corrupt deflate stream raises zlib.error
        raise FileFormatError(path, "$", expected, f"{type(exc).__name__}: {exc}") from None
    return Arrays(members, path)


def _npy_member(fh) -> tuple[np.ndarray, tuple, bool] | None:
    """(flat uninitialised array, shape, fortran order) for a ``.npy`` stream positioned at its
    start, or None when it is not a version 1/2 header of a plain (non-object) dtype."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        return None
    if dtype.hasobject:
        return None
    return np.empty(int(np.prod(shape, dtype=np.int64)), dtype=dtype), shape, fortran
def _check_npy_header(fh, size: int, path: Path, name: str, expected: str) -> None:
    """The member's ``.npy`` header: no object dtype, and a shape whose bytes fit the member."""
    fmt = np.lib.format
    version = fmt.read_magic(fh)
    if version not in ((1, 0), (2, 0)):  # what np.savez writes; 3.0 only adds UTF-8 field names
        raise FileFormatError(path, f"$.{name}", ".npy format 1.0 or 2.0", f"{version[0]}.{version[1]}")
    shape, _, dtype = (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(fh)
    if dtype.hasobject:
        raise FileFormatError(path, f"$.{name}", expected, f"an array of {dtype} (needs pickle)")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > size:
        raise FileFormatError(path, f"$.{name}", f"an array that fits its {size} stored bytes",
                              f"shape {shape} of {dtype} ({nbytes} bytes)")
