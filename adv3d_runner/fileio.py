"""Safe file writing, bounded file reading and the one rule for names and paths that every
data contract shares.

* Writes go to a temporary file in the same folder and are renamed over the target, so a failed
  or killed run never leaves a half-written file where the user's file was.
* Reads are bounded: only regular files (a FIFO, a device such as ``/dev/zero`` or a folder is
  refused before it is opened), at most a size per contract (:data:`MAX_JSON_BYTES`, read in
  chunks, so a file that grows while read is cut off too), gzip decompressed to at most the same
  size (a gzip bomb stops there), JSON nested at most :data:`MAX_JSON_DEPTH` levels.
* Names and paths: an id that becomes a file or folder name (scene id, asset id) matches
  :data:`SAFE_NAME` (:func:`is_safe_name`); a path stored in a file is relative, POSIX, without
  ``..`` (:func:`rel_path_problem`) and, resolved with its symlinks, stays inside the folder it
  belongs to (:func:`resolve_inside`). Every reader and writer uses these three functions.
"""
from __future__ import annotations

import gzip
import io
import json
import math
import os
import re
import stat
import tempfile
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any, Generator, Iterator, Mapping

if TYPE_CHECKING:  # numpy is imported where used: ``adv3d --help`` loads this module, not numpy
    import numpy as np


from .errors import ConfigError, FileFormatError

#: Timestamp of every member of a reproducible .npz (zip's earliest representable date).
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)

REPO_ROOT = Path(__file__).resolve().parent.parent

#: Largest JSON document read (bytes, after gzip decompression). The biggest files the tool
#: writes are replays of long episodes (~10 MB); 256 MiB leaves room and bounds memory.
MAX_JSON_BYTES = 256 * 2**20
#: Deepest JSON nesting accepted. Contracts nest at most ~8 levels (replay trajectories); free
#: objects (``metadata``, ``source.details``) get the rest. Deeper documents would make
#: recursive code (copy, dump) fail with RecursionError.
MAX_JSON_DEPTH = 64
_CHUNK = 1 << 20

#: The memory budget of one input: the most an array, or the working set of one step, sized by
#: a number the user or a file gives (a lattice, a frame or actor count, a search budget) may
#: take. A size that would need more is refused before anything is allocated, naming the option
#: or field that sets it (docs/reliability.md, "Memory"): a laptop runs a worker process per
#: core beside the driver, each of which may hold such an input.
MEMORY_BUDGET = 4 * 2**30


def user_cache_dir() -> Path:
    """The user's cache folder of adv3d: ``$ADV3D_CACHE``, else ``$XDG_CACHE_HOME/adv3d``, else
    ``~/.cache/adv3d``. What is kept there is derived data keyed by its inputs' content: deleting
    it costs time only."""
    base = os.environ.get("ADV3D_CACHE")
    if base:
        return Path(base)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "adv3d"


def gib(nbytes: float) -> str:
    """Bytes in GiB for messages (``246 GiB``, ``0.012 GiB``)."""
    return f"{nbytes / 2**30:.3g} GiB"

#: An id that becomes a file or folder name: letters, digits, ``_ . -``, starting with a letter
#: or digit (so never ``.`` / ``..``, never a hidden file, never a separator), at most 128 chars.
SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,127}")
SAFE_NAME_EXPECTED = ("a file-name-safe id (letters, digits, '_', '.', '-', starting with a letter or digit, "
                      "at most 128 characters)")


@contextmanager
def atomic_path(target: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``target``; rename it over ``target`` on success.

    Args:
        target: final file path.
        suffix: extension for the temporary file (some writers pick the format from it).
    """
    target = Path(target)
    made = make_parent(target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix, dir=target.parent)
    except OSError as exc:  # e.g. a name too long for the file system
        _remove_empty(made)
        raise ConfigError(f"{target}: cannot write this file ({exc.strerror or exc})") from None
    os.close(fd)
    tmp_path = Path(tmp)
    done = False
    try:
        yield tmp_path
        os.chmod(tmp_path, _mode_for(target))  # mkstemp makes 0600; keep the usual file mode
        os.replace(tmp_path, target)
        done = True
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
        if not done:
            _remove_empty(made)  # a failed write leaves no new empty folder behind


def make_parent(target: str | Path) -> list[Path]:
    """Create the folders above ``target``; return those created (deepest first). A path that
    runs through a file (``FILE/x.glb``) or cannot be made is one ``ConfigError`` naming it."""
    target = Path(target)
    missing = [p for p in [target.parent, *target.parent.parents] if not p.exists()]
    blocker = next((p for p in [target.parent, *target.parent.parents] if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise ConfigError(f"{target}: cannot write here: {blocker} is a file, not a folder")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _remove_empty([p for p in missing if p.exists()])
        raise ConfigError(f"{target}: cannot create its folder ({exc.strerror or exc})") from None
    return missing


def _remove_empty(folders: list[Path]) -> None:
    """Remove the given folders, deepest first, where they are (still) empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            pass


def _mode_for(target: Path) -> int:
    """The existing file's mode, or the default mode a new file gets under the umask."""
    try:
        return target.stat().st_mode & 0o777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def atomic_write_bytes(target: str | Path, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(target: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``target`` atomically (gzip-compressed if it ends in .gz)."""
    data = text.encode("utf-8")
    if str(target).endswith(".gz"):
        data = gzip.compress(data, mtime=0)  # mtime=0: same content, same bytes
    atomic_write_bytes(target, data)


def dump_json(obj: Any, *, indent: int | None = 1) -> str:
    """Serialise ``obj`` deterministically (sorted keys are NOT used: field order is part of
    readability; callers build dicts in a fixed order)."""
    return json.dumps(obj, indent=indent, ensure_ascii=False, allow_nan=False) + "\n"


def write_json(target: str | Path, obj: Any, *, indent: int | None = 1) -> None:
    """Write ``obj`` as JSON atomically (``.json.gz`` is compressed)."""
    atomic_write_text(target, dump_json(obj, indent=indent))


# ------------------------------------------------------------------------------ names and paths

def is_safe_name(text: Any) -> bool:
    """True when ``text`` is a string usable as one file or folder name (:data:`SAFE_NAME`)."""
    return isinstance(text, str) and SAFE_NAME.fullmatch(text) is not None


def safe_name(text: str, what: str) -> str:
    """``text`` if it is a safe name (:func:`is_safe_name`), else ``ConfigError`` naming
    ``what`` (a command-line option, e.g. ``"--id"``)."""
    if not is_safe_name(text):
        raise ConfigError(f"{what} {text!r}: expected {SAFE_NAME_EXPECTED}")
    return text


def rel_path_problem(text: Any) -> str | None:
    """None when ``text`` is a relative POSIX path that cannot leave its folder by its letters
    (not empty, not absolute, no ``..`` part, no backslash, no NUL); else what is wrong."""
    if not isinstance(text, str) or not text:
        return "not a non-empty string"
    if "\\" in text or "\0" in text:
        return "a backslash or NUL character"
    p = PurePosixPath(text)
    if p.is_absolute() or text.startswith("~"):
        return "an absolute path"
    if ".." in p.parts:
        return "a '..' part"
    return None


def resolve_inside(root: str | Path, rel: str, *, file: str | Path | None = None, field: str = "$",
                   inside: str | None = None) -> Path:
    """``root / rel`` after checking that it stays inside ``root``: ``rel`` passes
    :func:`rel_path_problem` and the resolved path (symlinks followed) lies under the resolved
    ``root``.

    Raises:
        FileFormatError: naming ``file`` and ``field`` (where ``rel`` was read from).
    """
    where = inside or str(root)
    expected = f"a relative path inside {where} (no '..', no absolute path, no symlink leading out)"
    problem = rel_path_problem(rel)
    if problem:
        raise FileFormatError(file, field, expected, rel)
    target = Path(root) / rel
    try:
        real_root = Path(root).resolve()
        real = target.resolve()
    except (OSError, RuntimeError) as exc:  # symlink loops
        raise FileFormatError(file, field, expected, f"{rel} ({exc})") from None
    if real != real_root and real_root not in real.parents:
        raise FileFormatError(file, field, expected, f"{rel} -> {real}")
    return target


# ------------------------------------------------------------------------------ bounded reads

def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular_file(path: str | Path, what: str = "file") -> os.stat_result:
    """The ``stat`` of ``path`` (symlinks followed) if it is an existing regular file.

    Raises:
        FileFormatError: missing, unreadable, or a folder, device, FIFO or socket (reading
            ``/dev/zero`` or a FIFO would never end).
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileFormatError(path, "$", f"an existing {what}", "file not found") from None
    except OSError as exc:
        raise FileFormatError(path, "$", f"a readable {what}", str(exc)) from None
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(path, "$", f"a regular {what}", _kind(st.st_mode))
    return st


def _size_text(n: int) -> str:
    return f"{n / 2**20:.0f} MiB" if n >= 2**20 else f"{n} bytes"


def read_bytes(path: str | Path, *, limit: int = MAX_JSON_BYTES, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes, read in chunks.

    Raises:
        FileFormatError: see :func:`check_regular_file`; larger than ``limit``.
    """
    st = check_regular_file(path, what)
    too_big = f"a {what} of at most {_size_text(limit)}"
    if st.st_size > limit:
        raise FileFormatError(path, "$", too_big, _size_text(st.st_size))
    chunks, total = [], 0
    try:
        with open(path, "rb") as fh:
            while True:
                chunk = fh.read(min(_CHUNK, limit + 1 - total))
                if not chunk:
                    break
                chunks.append(chunk)
                total += len(chunk)
                if total > limit:  # grew while we read it
                    raise FileFormatError(path, "$", too_big, "more bytes")
    except OSError as exc:
        raise FileFormatError(path, "$", f"a readable {what}", str(exc)) from None
    return b"".join(chunks)


def gunzip(raw: bytes, *, limit: int = MAX_JSON_BYTES, path: str | Path | None = None) -> bytes:
    """Decompress gzip ``raw`` to at most ``limit`` bytes (``FileFormatError`` naming ``path``
    for a corrupt or truncated body or a larger result)."""
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as fh:
            # in chunks: read(limit + 1) would set aside limit + 1 bytes for a file of any size
            chunks, total = [], 0
            while total <= limit:
                chunk = fh.read(min(_CHUNK, limit + 1 - total))
                if not chunk:
                    break
                chunks.append(chunk)
                total += len(chunk)
            data = b"".join(chunks)
    except (OSError, EOFError, zlib.error) as exc:
        raise FileFormatError(path, "$", "gzip-compressed data", f"{type(exc).__name__}: {exc}") from None
    if len(data) > limit:
        raise FileFormatError(path, "$", f"at most {_size_text(limit)} once decompressed", "more")
    return data


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
#: ``[`` / ``{`` -> 1, ``]`` / ``}`` -> -1, other bytes 0 (as bytes: a table numpy reads as int8).
_BRACKETS = bytes(1 if c in b"[{" else 255 if c in b"]}" else 0 for c in range(256))


_NON_FINITE = re.compile(rb"NaN|Infinity")


def json_depth(raw: bytes) -> int:
    """Deepest bracket nesting of JSON text (``[]`` is 1), strings skipped: computed on the
    bytes before parsing (the parser itself would recurse), in C speed (~2 % of a parse)."""
    return _depth(_JSON_STRING.sub(b"", raw))


#: Bytes of JSON text per block of :func:`_depth` (its temporaries are ~5 times that).
_DEPTH_BLOCK = 8 << 20


def _depth(stripped: bytes) -> int:
    """Deepest bracket nesting of JSON text without strings, block by block (the running depth
    carried over), so its temporaries stay small whatever the document's size."""
    import numpy as np

    codes = np.frombuffer(stripped, np.uint8)
    table = np.frombuffer(_BRACKETS, np.int8)
    deepest = level = 0
    for i in range(0, len(codes), _DEPTH_BLOCK):
        run = np.cumsum(table[codes[i:i + _DEPTH_BLOCK]], dtype=np.int32)
        deepest = max(deepest, level + int(run.max()))
        level += int(run[-1])
    return deepest


def _first_non_finite(doc: Any) -> str | None:
    """JSON path of the first NaN / inf number in a parsed document, or None."""
    stack: list[tuple[Any, str]] = [(doc, "$")]
    while stack:
        value, path = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            return path
        if isinstance(value, dict):
            stack.extend((v, f"{path}.{k}") for k, v in reversed(list(value.items())))
        elif isinstance(value, list):
            stack.extend((v, f"{path}[{i}]") for i, v in reversed(list(enumerate(value))))
    return None


def parse_json(raw: bytes, path: str | Path | None = None, *, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse UTF-8 JSON bytes nested at most ``max_depth`` levels, without the ``NaN`` /
    ``Infinity`` tokens Python's parser would accept (they are not JSON; the tool never writes
    them), raising ``FileFormatError`` naming ``path`` (and the JSON path of a non-finite
    number) otherwise."""
    stripped = _JSON_STRING.sub(b"", raw)
    if _depth(stripped) > max_depth:
        raise FileFormatError(path, "$", f"JSON nested at most {max_depth} levels", "deeper")
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, "$", "valid UTF-8 JSON", str(exc)) from None
    except RecursionError:  # not reached after the depth check; kept as a guard
        raise FileFormatError(path, "$", f"JSON nested at most {max_depth} levels", "deeper") from None
    if _NON_FINITE.search(stripped):  # rare: only then walk the document for the field
        where = _first_non_finite(doc)
        if where is not None:
            raise FileFormatError(path, where, "a finite number (JSON has no NaN or Infinity)", "NaN or Infinity")
    return doc


def read_json(path: str | Path, *, limit: int = MAX_JSON_BYTES) -> Any:
    """Read a JSON (or ``.json.gz``) file, bounded (regular file, at most ``limit`` bytes
    decompressed, :data:`MAX_JSON_DEPTH` levels), raising ``FileFormatError`` naming the file."""
    path = Path(path)
    raw = read_bytes(path, limit=limit)
    if path.suffix == ".gz":
        raw = gunzip(raw, limit=limit, path=path)
    return parse_json(raw, path)


def npz_bytes(members: Mapping[str, np.ndarray]) -> bytes:
    """The bytes of an ``.npz`` holding ``members`` (name -> array, in this order), reproducible:
    fixed timestamps, permissions and creator system, deflate level 6, no pickled objects, so
    the same arrays give the same file on every machine (files that carry a content hash or are
    compared byte for byte rely on it)."""
    import numpy as np

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, array in members.items():
            npy = io.BytesIO()
            np.lib.format.write_array(npy, np.asanyarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            info.create_system = 3  # unix, whatever the building machine is
            zf.writestr(info, npy.getvalue(), compresslevel=6)
    return buf.getvalue()


#: Bytes of work per step of :func:`read_json_steps` (inflating or parsing 512 kB: ~10-50 ms).
STEP_BYTES = 1 << 19
_WS = re.compile(r"[ \t\n\r]*")  # json's own whitespace rule


def read_json_steps(
    path: str | Path, step_bytes: int = STEP_BYTES, *, limit: int = MAX_JSON_BYTES
) -> Generator[None, None, Any]:
    """:func:`read_json` in pieces, for callers that must stay responsive (the Blender add-on
    loading a long replay): a steps generator (``progress.run_steps``) yielding after each
    ~``step_bytes`` of gzip decompression or JSON parsing; returns the same value.

    A top-level object's list values (a replay's frames) are parsed item by item with json's
    own scanner (``JSONDecoder.raw_decode``), everything else in one call, so the result is what
    ``json.loads`` gives, key order and duplicate keys included. Bounded like
    :func:`read_json`: a regular file of at most ``limit`` bytes, decompressed to at most
    ``limit`` bytes (a gzip bomb stops there).
    """
    path = Path(path)
    raw = read_bytes(path, limit=limit)
    yield
    if path.suffix == ".gz":
        too_big = FileFormatError(path, "$", f"at most {_size_text(limit)} once decompressed", "more")
        d = zlib.decompressobj(16 + zlib.MAX_WBITS)
        parts, total = [], 0
        try:
            for s in range(0, len(raw), step_bytes):
                # max_length bounds each piece, so a bomb never inflates past the limit
                part = d.decompress(raw[s : s + step_bytes], limit + 1 - total)
                while True:
                    parts.append(part)
                    total += len(part)
                    if total > limit:
                        raise too_big
                    if not d.unconsumed_tail:
                        break
                    part = d.decompress(d.unconsumed_tail, limit + 1 - total)
                yield
            parts.append(d.flush())
        except zlib.error as exc:
            raise FileFormatError(path, "$", "gzip-compressed JSON", str(exc)) from None
        if d.unused_data or not d.eof:  # several gzip members, or cut short: as read_json does
            parts = [gunzip(raw, limit=limit, path=path)]
        raw = b"".join(parts)
    # the same bounds as read_json: nesting depth, and no NaN / Infinity tokens
    stripped = _JSON_STRING.sub(b"", raw)
    if _depth(stripped) > MAX_JSON_DEPTH:
        raise FileFormatError(path, "$", f"JSON nested at most {MAX_JSON_DEPTH} levels", "deeper")
    try:
        text = raw.decode("utf-8")
        doc = yield from _parse_json_steps(text, step_bytes)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, "$", "valid UTF-8 JSON", str(exc)) from None
    if _NON_FINITE.search(stripped):
        where = _first_non_finite(doc)
        if where is not None:
            raise FileFormatError(path, where, "a finite number (JSON has no NaN or Infinity)", "NaN or Infinity")
    return doc


def _parse_json_steps(text: str, step_bytes: int) -> Generator[None, None, Any]:
    dec = json.JSONDecoder()
    i = _WS.match(text, 0).end()
    if not text.startswith("{", i):
        return json.loads(text)
    obj: dict = {}
    i = _WS.match(text, i + 1).end()
    mark = i
    if text.startswith("}", i):
        i += 1
    else:
        while True:
            if not text.startswith('"', i):
                raise json.JSONDecodeError("Expecting property name enclosed in double quotes", text, i)
            key, i = dec.raw_decode(text, i)
            i = _WS.match(text, i).end()
            if not text.startswith(":", i):
                raise json.JSONDecodeError("Expecting ':' delimiter", text, i)
            i = _WS.match(text, i + 1).end()
            if text.startswith("[", i):
                value = []
                i = _WS.match(text, i + 1).end()
                if text.startswith("]", i):
                    i += 1
                else:
                    while True:
                        item, i = dec.raw_decode(text, i)
                        value.append(item)
                        if i - mark >= step_bytes:
                            mark = i
                            yield
                        i = _WS.match(text, i).end()
                        if text.startswith(",", i):
                            i = _WS.match(text, i + 1).end()
                        elif text.startswith("]", i):
                            i += 1
                            break
                        else:
                            raise json.JSONDecodeError("Expecting ',' delimiter", text, i)
            else:
                value, i = dec.raw_decode(text, i)
            obj[key] = value
            if i - mark >= step_bytes:
                mark = i
                yield
            i = _WS.match(text, i).end()
            if text.startswith(",", i):
                i = _WS.match(text, i + 1).end()
            elif text.startswith("}", i):
                i += 1
                break
            else:
                raise json.JSONDecodeError("Expecting ',' delimiter", text, i)
    if _WS.match(text, i).end() != len(text):
        raise json.JSONDecodeError("Extra data", text, i)
    return obj
