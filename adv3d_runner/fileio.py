"""Safe file writing and versioned JSON loading shared by every data contract.

Writes go to a temporary file in the same folder and are renamed over the target, so a failed
or killed run never leaves a half-written file where the user's file was.
"""
from __future__ import annotations

import gzip
import io
import json
import os
import re
import tempfile
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Generator, Iterator, Mapping

import numpy as np

from .errors import FileFormatError

#: Timestamp of every member of a reproducible .npz (zip's earliest representable date).
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)

REPO_ROOT = Path(__file__).resolve().parent.parent


@contextmanager
def atomic_path(target: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``target``; rename it over ``target`` on success.

    Args:
        target: final file path.
        suffix: extension for the temporary file (some writers pick the format from it).
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix, dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _mode_for(target))  # mkstemp makes 0600; keep the usual file mode
        os.replace(tmp_path, target)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


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


def read_json(path: str | Path) -> Any:
    """Read a JSON (or ``.json.gz``) file, raising ``FileFormatError`` naming the file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FileFormatError(path, "$", "an existing file", "file not found") from None
    except OSError as exc:
        raise FileFormatError(path, "$", "a readable file", str(exc)) from None
    if path.suffix == ".gz":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as exc:
            raise FileFormatError(path, "$", "gzip-compressed JSON", str(exc)) from None
    try:
        return json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, "$", "valid UTF-8 JSON", str(exc)) from None


def npz_bytes(members: Mapping[str, np.ndarray]) -> bytes:
    """The bytes of an ``.npz`` holding ``members`` (name -> array, in this order), reproducible:
    fixed timestamps, permissions and creator system, deflate level 6, no pickled objects, so
    the same arrays give the same file on every machine (files that carry a content hash or are
    compared byte for byte rely on it)."""
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


def read_json_steps(path: str | Path, step_bytes: int = STEP_BYTES) -> Generator[None, None, Any]:
    """:func:`read_json` in pieces, for callers that must stay responsive (the Blender add-on
    loading a long replay): a steps generator (``progress.run_steps``) yielding after each
    ~``step_bytes`` of gzip decompression or JSON parsing; returns the same value.

    A top-level object's list values (a replay's frames) are parsed item by item with json's
    own scanner (``JSONDecoder.raw_decode``), everything else in one call, so the result is what
    ``json.loads`` gives, key order and duplicate keys included.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FileFormatError(path, "$", "an existing file", "file not found") from None
    except OSError as exc:
        raise FileFormatError(path, "$", "a readable file", str(exc)) from None
    yield
    if path.suffix == ".gz":
        d = zlib.decompressobj(16 + zlib.MAX_WBITS)
        parts = []
        try:
            for s in range(0, len(raw), step_bytes):
                parts.append(d.decompress(raw[s : s + step_bytes]))
                yield
            parts.append(d.flush())
        except zlib.error as exc:
            raise FileFormatError(path, "$", "gzip-compressed JSON", str(exc)) from None
        if d.unused_data or not d.eof:  # several gzip members, or cut short: as read_json does
            try:
                parts = [gzip.decompress(raw)]
            except (OSError, EOFError) as exc:
                raise FileFormatError(path, "$", "gzip-compressed JSON", str(exc)) from None
        raw = b"".join(parts)
    try:
        text = raw.decode("utf-8")
        return (yield from _parse_json_steps(text, step_bytes))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, "$", "valid UTF-8 JSON", str(exc)) from None


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
