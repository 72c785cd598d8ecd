"""The run bundle ``runs/<name>/`` of an attack (DESIGN.md data contract 4, docs/formats.md).

::

    runs/NAME/
      run.json          config, seed, versions, scene ids (written once; a resume checks it)
      queries.jsonl     append-only journal, one JSON object per evaluated query
      summary.json      per scene and mode: best query, original / best metrics (rewritten)
      scenes/<scene>/<mode>/actor<ID>.glb     best shape per attacked actor
      scenes/<scene>/<mode>/replay.json.gz    replay of the best shape in closed loop (+ .points.npz)

Every journal line is written with one ``write`` + flush + fsync as soon as its query has
finished, so a killed run leaves at most one truncated last line and loses only the queries in
flight. :meth:`Journal.load` drops such a line (it is not valid JSON or has no newline),
truncates the file back to the last complete line and returns the finished queries; the driver
then re-asks its searchers and takes the recorded results for every query already in the
journal instead of evaluating it again (see :mod:`.driver`).

Order: ``queries.jsonl`` holds each scene and mode's queries in index order, whatever the
worker count and the order in which workers finish (so the same seed gives the same file). A
query that finishes before a lower-indexed one of its batch is written at once to
``queries.pending.jsonl`` (same line format, same fsync) and moved to ``queries.jsonl`` when its
turn comes; the pending file is emptied when its batch is complete. On resume both files are
read (a query in both counts once), so a kill at any moment loses no finished query.

Every line, ``run.json`` and ``summary.json`` are validated on load (``validate.Node``: known
fields, types, ranges), so a damaged or hand-edited bundle is one error naming the file and
field, never a crash of ``adv3d report``.

Verified before use (docs/formats.md, "Run bundle"; docs/reliability.md): every line carries
``sha256``, a checksum of its content (:func:`record_checksum`), so an edited line is refused;
against the run's ``run.json`` each record's scene is one of the run's, its mode one of the
run's, its index in ``[0, budget)`` and unique in its file (a pending line may repeat a journal
line only as the same record: a kill between the move and the clean-up); the driver checks that
each reused record holds the point its search asks at that index. Lines written before
checksums (runs whose run.json lacks ``journal_sha256``) are accepted without one when they pass
every other check.

Line fields (fixed order): ``scene``, ``mode``, ``index`` (query number within the scene and
mode), ``actors``, ``unit`` (m lists of the query's unit entries), ``latent``, ``scales``,
``dimensions``, ``realism`` (per actor the cheap realism figures, or null; absent in journals
written before the realism figures existed), ``cost`` (null when failed), ``components``, ``metrics``, ``status``
(``ok`` / ``invalid`` / ``error``), ``error`` (message or null), ``wall_s``.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..errors import ConfigError, FileFormatError
from ..fileio import MAX_JSON_BYTES, parse_json, read_bytes, resolve_inside, write_json
from ..validate import Node, check_header

#: The run folder's lock file: held (``flock``, exclusive) by the one process writing the run.
LOCK_NAME = ".adv3d-run.lock"

#: Run folders whose lock this process holds: real path -> (fd, id of the journal owning it).
_HELD_LOCKS: dict[str, tuple[int, int]] = {}

RUN_FORMAT = "adv3d.attack_run"
SUMMARY_FORMAT = "adv3d.attack_summary"
QUERY_FORMAT = "adv3d.attack_query"
VERSION = 1
#: run.json version: 2 adds ``library`` and ``library_fingerprint`` (the vehicle library the
#: benign actors' meshes come from); version 1 runs are still read (reports) but not resumed.
RUN_VERSION = 2
RUN_VERSIONS = (1, 2)
STATUSES = ("ok", "invalid", "error")
_LINE_KEYS = ("scene", "mode", "index", "actors", "unit", "latent", "scales", "dimensions", "realism", "cost",
              "components", "metrics", "status", "error", "wall_s", "sha256")
#: A journal line's checksum field (:func:`record_checksum`), written last.
CHECKSUM_KEY = "sha256"
#: run.json key of runs whose every journal line carries a checksum (runs started since).
CHECKSUM_RUN_KEY = "journal_sha256"
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
# Config keys that may differ between the first run and a resume (they do not change results).
# ``scenes`` (the paths as typed) is free when both runs store ``scene_sha256``: the scenes
# are then compared by content, so the same file given by another path resumes.
RESUME_FREE_KEYS = ("workers", "ray_address", "quiet", "out", CHECKSUM_RUN_KEY)
MODES = ("closed", "open")
PENDING_NAME = "queries.pending.jsonl"


def _clean(x: Any) -> Any:
    """JSON-ready copy: numpy -> Python, non-finite floats -> None."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if np.isfinite(x) else None
    return x


def query_record(scene: str, mode: str, index: int, actors: list[int], unit: np.ndarray, *,
                 latent=None, scales=None, dimensions=None, realism=None, cost: float | None = None,
                 components: dict | None = None, metrics: dict | None = None, status: str = "ok",
                 error: str | None = None, wall_s: float = 0.0) -> dict:
    """One journal line as a dict with the fixed field order."""
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}")
    u = np.asarray(unit, dtype=np.float64).reshape(len(actors), -1)
    rec = {"scene": scene, "mode": mode, "index": int(index), "actors": [int(a) for a in actors],
           "unit": [[float(v) for v in row] for row in u], "latent": latent, "scales": scales,
           "dimensions": dimensions, "realism": realism, "cost": cost, "components": components or {},
           "metrics": metrics or {}, "status": status, "error": error, "wall_s": round(float(wall_s), 4)}
    return _clean(rec)


def record_checksum(rec: dict) -> str:
    """The ``sha256`` of a journal record: SHA-256 (hex) of its JSON with sorted keys and no
    spaces, without ``wall_s`` and ``sha256`` itself. ``wall_s`` (the query's wall time) is left
    out so that the same query gives the same line up to its wall time, as before checksums
    (runs are compared that way); it is still validated (a finite number >= 0)."""
    body = {k: v for k, v in rec.items() if k not in ("wall_s", CHECKSUM_KEY)}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def record_cost(rec: dict) -> float:
    """The record's cost as a float, NaN for failed queries."""
    c = rec.get("cost")
    return float(c) if isinstance(c, (int, float)) and rec.get("status") == "ok" else float("nan")


def record_unit(rec: dict) -> np.ndarray:
    """(m * (K+2),) the record's query vector."""
    return np.asarray(rec["unit"], dtype=np.float64).reshape(-1)


class Journal:
    """Append-only ``queries.jsonl`` (+ ``queries.pending.jsonl``) plus ``run.json`` /
    ``summary.json`` of one run folder."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.path = self.root / "queries.jsonl"
        self.pending_path = self.root / PENDING_NAME
        self.records: list[dict] = []
        self.pending: dict[tuple[str, str, int], dict] = {}
        #: where each record was read or written: (scene, mode, index) -> (file, line number)
        self.lines: dict[tuple[str, str, int], tuple[Path, int]] = {}
        self._pending_lines = 0
        self._lock_key: str | None = None

    def _lock(self) -> None:
        """Hold the run folder's lock for as long as this journal lives (the OS drops it when
        the process ends, however it ends): two processes appending to one journal would
        interleave their queries and ruin the run, e.g. a campaign shard started twice. A
        journal of a run this process already holds (an earlier one not yet collected) takes
        the lock over."""
        key = os.path.realpath(self.root)
        if key in _HELD_LOCKS:
            _HELD_LOCKS[key] = (_HELD_LOCKS[key][0], id(self))
            self._lock_key = key
            return
        try:
            import fcntl
        except ImportError:  # no flock (Windows): one writer per folder is then the user's care
            return
        try:
            fd = os.open(self.root / LOCK_NAME, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as exc:  # a folder (or a symlink, a FIFO...) where the lock file belongs
            raise ConfigError(f"{self.root / LOCK_NAME}: cannot open the run's lock file ({exc.strerror or exc}); "
                              "it must be a plain file: remove what is there") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise ConfigError(f"{self.root / LOCK_NAME}: the run's lock file is not a plain file; remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ConfigError(f"{self.root}: another process is writing this run (its lock {LOCK_NAME} is "
                              f"held); wait for it to finish, or use another --out") from None
        _HELD_LOCKS[key] = (fd, id(self))
        self._lock_key = key

    def close(self) -> None:
        """Release the run folder's lock (also done when the journal is collected or the
        process ends)."""
        key, self._lock_key = self._lock_key, None
        if key is not None and _HELD_LOCKS.get(key, (0, None))[1] == id(self):
            os.close(_HELD_LOCKS.pop(key)[0])

    def __del__(self) -> None:
        self.close()

    # ------------------------------------------------------------------ run.json
    def start(self, config: dict) -> dict:
        """Create the folder and ``run.json``, or check that an existing run has the same
        config (up to :data:`RESUME_FREE_KEYS`) and load its journal. Returns the stored
        config (the first run's, e.g. its batch size, wins on resume).

        A folder that exists and holds anything but an adv3d run (no ``run.json``) is refused
        before anything is written: the user's files are never overwritten.

        Raises:
            ConfigError: the folder holds a run with a different config, or other files, or
                another process is writing it (the folder's lock, :data:`LOCK_NAME`).
            FileFormatError: its run.json or journal is damaged.
        """
        run_path = self.root / "run.json"
        if self.root.exists() or self.root.is_symlink():
            if not self.root.is_dir():
                raise ConfigError(f"--out {self.root}: exists and is not a folder; give a new or empty folder")
            names = sorted(p.name for p in self.root.iterdir() if p.name != LOCK_NAME)
            if not run_path.exists() and names:
                shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
                raise ConfigError(f"--out {self.root}: the folder holds files that are not an adv3d run "
                                  f"({shown}; no run.json); give a new or empty folder")
        doc = _clean({"format": RUN_FORMAT, "version": RUN_VERSION, **config, CHECKSUM_RUN_KEY: True})
        self.root.mkdir(parents=True, exist_ok=True)
        self._lock()
        if run_path.exists():
            old = _read_doc(run_path, RUN_FORMAT)
            if old.get("version") != RUN_VERSION:
                raise ConfigError(f"{self.root} holds a run.json version {old.get('version')} run, made before runs "
                                  "recorded their vehicle library's fingerprint: it can be reported, not resumed; "
                                  "use another --out")
            if old.get("library_fingerprint") != doc.get("library_fingerprint"):
                raise ConfigError(f"{self.root} was run with another vehicle library (fingerprint "
                                  f"{old.get('library_fingerprint')}, now {doc.get('library_fingerprint')}): the "
                                  "benign actors would change; give the run's --library or use another --out")
            free = set(RESUME_FREE_KEYS) | {"versions"}
            if "scene_sha256" in old and "scene_sha256" in doc:
                free.add("scenes")  # same scenes by content, whatever path they were given by
            else:
                free.add("scene_sha256")  # a bundle from before content hashes: paths compared
            diff = sorted(k for k in set(old) | set(doc) if k not in free and old.get(k) != doc.get(k))
            if "batch" in diff:  # the one the worker count used to set: say what to do
                others = [k for k in diff if k != "batch"]
                raise ConfigError(f"{self.root} was run with --batch {old.get('batch')} (run.json field 'batch'), "
                                  f"this command asks --batch {doc.get('batch')}: the queries a search asks depend on "
                                  f"it (--workers does not); give --batch {old.get('batch')} or leave it out to resume"
                                  + (f" (other differing fields: {', '.join(others)})" if others else "")
                                  + ", or use another --out")
            if diff:
                raise ConfigError(f"{self.root} holds a run with a different configuration ({', '.join(diff)}); "
                                  f"use another --out or the same options to resume it")
            changed = _changed_versions(old.get("versions"), doc.get("versions"))
            if changed:  # allowed (a resume checks each reused query), but the user should know
                from ..progress import note  # printed with -q too: it changes what the run's results mean

                numerics = [c for c in changed if c.startswith("numerics.")]
                if any(c.startswith("numerics.key:") for c in numerics):
                    note(f"note: {self.root} was started on another numerical configuration "
                         f"({'; '.join(numerics)}): new queries may differ from what that machine would give "
                         f"in the last bits, and searches may then diverge (docs/reliability.md)")
                others = [c for c in changed if not c.startswith("numerics.")]
                if others:
                    note(f"note: {self.root} was started with other versions ({'; '.join(others)}): its "
                         f"journalled queries keep their results; use another --out to evaluate them anew")
            self.load(repair=True, run=old)
            return old
        write_json(run_path, doc, indent=1)
        self.load(repair=True, run=doc)
        return doc

    # ------------------------------------------------------------------ queries.jsonl
    def load(self, repair: bool = False, run: dict | None = None) -> list[dict]:
        """Read the journal and the pending file; a truncated or corrupt *last* line is dropped
        (and cut from the file when ``repair``). A corrupt line elsewhere is a FileFormatError;
        every record is validated (:func:`check_record`) and verified: its checksum, and a
        (scene, mode, index) not already in its file. With ``run`` (the run's run.json) also the
        scene, mode and index range against the run, and checksums required where the run says
        every line has one (:data:`CHECKSUM_RUN_KEY`). Nothing refused is kept: the error names
        the file and line."""
        run = run or {}
        need = run.get(CHECKSUM_RUN_KEY) is True
        allowed = _run_scope(run)
        journal = _read_lines(self.path, repair, need)
        pending = _read_lines(self.pending_path, repair, need)
        self.records, self.pending, self.lines = [], {}, {}
        journalled: dict[tuple[str, str, int], dict] = {}
        for path, rows in ((self.path, journal), (self.pending_path, pending)):
            first: dict[tuple[str, str, int], int] = {}
            for line, rec in rows:
                _check_in_run(rec, allowed, path, line)
                key = _key(rec)
                if key in first:
                    raise FileFormatError(path, f"line {line}: $.index", f"a query not already in this file (line "
                                          f"{first[key]} holds query {key[2]} of {key[0]}/{key[1]})", key[2])
                first[key] = line
                if path == self.path:
                    self.records.append(rec)
                    journalled[key] = rec
                elif key in self.lines:  # a kill between the move and the clean-up: the same record
                    if strip_times([rec]) != strip_times([journalled[key]]):
                        raise FileFormatError(path, f"line {line}", f"the record of {self.path.name} line "
                                              f"{self.lines[key][1]} (query {key[2]} of {key[0]}/{key[1]}: a query "
                                              "finishes once)", "another record")
                    continue
                else:
                    self.pending[key] = rec
                self.lines[key] = (path, line)
        self._pending_lines = len(pending)
        return self.records

    def where(self, scene: str, mode: str, index: int) -> str:
        """``FILE line N`` of a loaded or written record (for errors)."""
        path, line = self.lines.get((scene, mode, int(index)), (self.path, 0))
        return f"{path}: line {line}" if line else str(path)

    def append(self, rec: dict) -> None:
        """Append one record to ``queries.jsonl`` durably (single write, flush, fsync)."""
        line = _line(rec)
        _append(self.path, line)
        self.records.append(_parsed(line))
        key = _key(self.records[-1])
        self.pending.pop(key, None)
        self.lines[key] = (self.path, len(self.records))

    def append_pending(self, rec: dict) -> None:
        """Record a query that finished before a lower-indexed one of its batch: durably in
        ``queries.pending.jsonl`` until :meth:`append` moves it to the journal."""
        line = _line(rec)
        _append(self.pending_path, line)
        parsed = _parsed(line)
        self.pending[_key(parsed)] = parsed
        self._pending_lines += 1
        self.lines[_key(parsed)] = (self.pending_path, self._pending_lines)

    def note_pending(self, rec: dict) -> None:
        """Record a query whose worker process wrote its line to ``queries.pending.jsonl``
        itself (durably, before the result left the worker: ``attack.driver.durable_query``), so
        nothing is written here; it waits there until :meth:`append` moves it to the journal.
        Its line number is not known here (workers append in any order)."""
        parsed = _parsed(_line(rec))
        self.pending[_key(parsed)] = parsed
        self.lines[_key(parsed)] = (self.pending_path, 0)

    def is_pending(self, scene: str, mode: str, index: int) -> bool:
        return (scene, mode, int(index)) in self.pending

    def clear_pending(self) -> None:
        """Empty the pending file once every query in it is in the journal (end of a batch)."""
        if not self.pending and self.pending_path.exists() and self.pending_path.stat().st_size:
            with open(self.pending_path, "r+b") as fh:
                fh.truncate(0)
                fh.flush()
                os.fsync(fh.fileno())
            self._pending_lines = 0

    def canonicalize(self, order: list[tuple[str, str]]) -> bool:
        """Rewrite ``queries.jsonl`` (atomically) with its lines in the canonical order: the
        (scene, mode) pairs in ``order``, each by query index; lines of other pairs keep their
        place after them. Each search's lines are in index order already, but searches worked on
        concurrently interleave theirs; this makes a finished run's journal independent of that.
        Returns True when the file was rewritten (False: already in order)."""
        rank = {pair: k for k, pair in enumerate(order)}

        def key(item):
            pos, rec = item
            pair = (rec.get("scene"), rec.get("mode"))
            return (rank.get(pair, len(rank)), int(rec["index"]) if pair in rank else 0, pos)

        ordered = [rec for _, rec in sorted(enumerate(self.records), key=key)]
        if all(a is b for a, b in zip(ordered, self.records)):
            return False
        from ..fileio import atomic_write_bytes

        data = b"".join(_line(r).encode("utf-8") for r in ordered)
        atomic_write_bytes(self.path, data)
        self.records = ordered
        for n, rec in enumerate(ordered, 1):
            self.lines[_key(rec)] = (self.path, n)
        return True

    def finished(self, scene: str, mode: str) -> dict[int, dict]:
        """{query index: record} already finished for a scene and mode (journal or pending)."""
        out = {int(r["index"]): r for r in self.pending.values() if r["scene"] == scene and r["mode"] == mode}
        out.update({int(r["index"]): r for r in self.records if r.get("scene") == scene and r.get("mode") == mode})
        return out

    # ------------------------------------------------------------------ summary.json
    def write_summary(self, summary: dict) -> None:
        write_json(self.root / "summary.json", _clean({"format": SUMMARY_FORMAT, "version": VERSION, **summary}), indent=1)

    def read_summary(self) -> dict:
        path = self.root / "summary.json"
        if not path.exists():
            return {"format": SUMMARY_FORMAT, "version": VERSION, "scenes": {}}
        doc = Node.load(path)
        check_header(doc, SUMMARY_FORMAT, (VERSION,))
        check_summary(doc, self.root)
        return doc.value


def _key(rec: dict) -> tuple[str, str, int]:
    return rec["scene"], rec["mode"], int(rec["index"])


def _line(rec: dict) -> str:
    """One journal line: the record's fields, then its checksum (:func:`record_checksum`)."""
    body = _clean({k: v for k, v in rec.items() if k != CHECKSUM_KEY})
    body[CHECKSUM_KEY] = record_checksum(body)
    return json.dumps(body, allow_nan=False, separators=(",", ":")) + "\n"


def _parsed(line: str) -> dict:
    """A line just written, as the record kept in memory (without its checksum)."""
    rec = json.loads(line)
    rec.pop(CHECKSUM_KEY, None)
    return rec


def _append(path: Path, line: str) -> None:
    """Append one line durably: one ``write`` on an ``O_APPEND`` descriptor, then fsync. Worker
    processes append to the pending file beside the driver, and one ``write`` per line keeps
    their lines whole whatever their length (a buffered file may split a long line in two)."""
    data = line.encode("utf-8")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(data)
        while view:  # a regular file takes it in one write; a short write (disk full) continues
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def _read_lines(path: Path, repair: bool, need_checksum: bool = False) -> list[tuple[int, dict]]:
    """(line number, record) of each validated, checksum-verified line of a journal file,
    records without their checksum (see :meth:`Journal.load`)."""
    records: list[tuple[int, dict]] = []
    if not path.exists():
        return records
    data = read_bytes(path, limit=4 * MAX_JSON_BYTES, what="journal")
    good_end = 0
    lines = data.split(b"\n")
    for i, raw in enumerate(lines):
        if i == len(lines) - 1:  # bytes after the last newline: an unfinished write
            break
        try:
            doc = parse_json(raw, path)
        except FileFormatError as exc:
            if i == len(lines) - 2 and not lines[-1]:
                break  # the last complete line is corrupt (e.g. zero-filled after a crash)
            raise FileFormatError(path, f"line {i + 1}", "one JSON query record per line", exc.got) from None
        rec = check_record(Node(doc, f"line {i + 1}: $", path))
        _verify_checksum(rec, path, i + 1, need_checksum)
        records.append((i + 1, rec))
        good_end += len(raw) + 1
    if repair and good_end != len(data):
        with open(path, "r+b") as fh:
            fh.truncate(good_end)
            fh.flush()
            os.fsync(fh.fileno())
    return records


def _verify_checksum(rec: dict, path: Path, line: int, required: bool) -> None:
    """Check and remove a record's ``sha256``; a record without one is refused when
    ``required`` (a run whose every line has one), else accepted as a line written before
    checksums."""
    if CHECKSUM_KEY not in rec:
        if required:
            raise FileFormatError(path, f"line {line}: $.{CHECKSUM_KEY}", "the record's checksum (every line of this "
                                  f"run carries one: run.json {CHECKSUM_RUN_KEY})", "no sha256")
        return
    stored = rec.pop(CHECKSUM_KEY)
    if stored != record_checksum(rec):
        raise FileFormatError(path, f"line {line}", "a record whose content matches its sha256 (the line was "
                              "changed after it was written)")


def _run_scope(run: dict) -> tuple[list[str] | None, list[str] | None, int | None]:
    """(scene ids, modes, budget) a run's records must lie in, each None where run.json does not
    say (a run.json of code before it, or a test's partial config)."""
    ids = run.get("scene_ids")
    ids = list(ids) if isinstance(ids, list) and all(isinstance(x, str) for x in ids) else None
    mode = run.get("mode")
    modes = ["open", "closed"] if mode == "both" else [mode] if mode in MODES else None
    budget = run.get("budget")
    budget = budget if isinstance(budget, int) and not isinstance(budget, bool) and budget >= 1 else None
    return ids, modes, budget


def _check_in_run(rec: dict, allowed: tuple, path: Path, line: int) -> None:
    """A record's scene, mode and index lie in its run (:func:`_run_scope`)."""
    ids, modes, budget = allowed
    if ids is not None and rec["scene"] not in ids:
        shown = ", ".join(ids[:5]) + (", ..." if len(ids) > 5 else "")
        raise FileFormatError(path, f"line {line}: $.scene", f"one of the run's scenes ({shown})", rec["scene"])
    if modes is not None and rec["mode"] not in modes:
        raise FileFormatError(path, f"line {line}: $.mode", f"one of the run's modes ({', '.join(modes)})", rec["mode"])
    if budget is not None and not 0 <= rec["index"] < budget:
        raise FileFormatError(path, f"line {line}: $.index", f"a query index in [0, {budget - 1}] (the run's "
                              f"budget is {budget})", rec["index"])


def _nested_numbers(node: Node, *, lo: float | None = None, hi: float | None = None) -> None:
    """null, or a list of lists of finite numbers (per attacked actor)."""
    if node.value is None:
        return
    for row in node.items("a list (one entry per attacked actor) or null"):
        row.numbers(lo=lo, hi=hi)


def check_record(node: Node) -> dict:
    """Validate one journal line (fields in ``_LINE_KEYS``; see docs/formats.md). Returns it."""
    node.object("a JSON object (one query record)")
    node.check_keys(_LINE_KEYS, required=("scene", "mode", "index", "actors", "unit", "cost", "status"))
    node["scene"].string()
    node["mode"].string(choices=MODES)
    node["index"].integer(lo=0)
    actors = [a.integer() for a in node["actors"].items("a list of actor ids", non_empty=True)]
    unit = node["unit"].items("one unit vector per attacked actor", length=len(actors))
    for row in unit:
        row.numbers(length=len(unit[0].list()), min_length=1, lo=0.0, hi=1.0)
    for key in ("latent", "scales", "dimensions"):
        _nested_numbers(node.get(key))
    status = node["status"].string(choices=STATUSES)
    cost = node["cost"]
    if cost.value is not None or status == "ok":
        cost.number()
    for key in ("components", "metrics"):
        node.get(key, {}).object()
    node.get("error").string(nullable=True, empty=True)
    node.get("wall_s", 0.0).number(lo=0.0)
    if CHECKSUM_KEY in node:
        node[CHECKSUM_KEY].string(pattern=_HEX64, expected="64 hex digits (the record's SHA-256)")
    return node.value


def check_summary(doc: Node, root: Path | None = None) -> None:
    """Validate ``summary.json`` beyond its header: per scene its ``targets`` and per mode the
    best query, counts and file paths (which must stay inside the run folder ``root``)."""
    doc.check_keys(("format", "version", "run", "wall_s", "scenes"))
    doc.get("run", {}).object()
    doc.get("wall_s", 0.0).number(lo=0.0)
    for sid, entry in doc.get("scenes", {}).object().items():
        e = doc["scenes"].child(sid, entry)
        e.object()
        e.check_keys(("ref", "targets", "original", "modes", "skipped"))
        e.get("ref", "").string(empty=True)
        e.get("skipped").string(nullable=True, empty=True)
        e.get("original", {}).object()
        n_targets = len([t.integer() for t in e.get("targets", []).items("a list of actor ids")])
        for mode, m in e.get("modes", {}).object().items():
            mn = e["modes"].child(mode, m)
            mn.object()
            mn.check_keys(("best_index", "best_cost", "best_unit", "n_queries", "n_failed", "closed_loop_eval",
                           "files", "search_seed", "noise_seed"),
                          required=("best_index", "best_cost", "best_unit", "n_queries", "n_failed"))
            mn["best_index"].integer(lo=-1)
            for key in ("search_seed", "noise_seed"):  # runs with scene_seeds (docs/results.md, Protocol)
                mn.get(key, 0).integer(lo=0, hi=2**32 - 1)
            if mn["best_cost"].value is not None or mn["best_unit"].value is not None:
                mn["best_cost"].number()  # a best query has a cost
            if mn["best_unit"].value is not None:
                rows = mn["best_unit"].items("one unit vector per target", length=n_targets)
                for row in rows:
                    row.numbers(length=len(rows[0].list()), min_length=1, lo=0.0, hi=1.0)
            n = mn["n_queries"].integer(lo=0)
            mn["n_failed"].integer(lo=0, hi=n)
            mn.get("closed_loop_eval", {}).object()
            files = mn.get("files", {})
            files.object()
            files.check_keys(("meshes", "replay"))
            paths = [files.get("replay")] if files.get("replay").value is not None else []
            paths += [files["meshes"].child(k, v) for k, v in files.get("meshes", {}).object().items()]
            for p in paths:
                p.rel_path(inside="the run folder")
                if root is not None:
                    resolve_inside(root, p.value, file=p.file, field=p.path, inside="the run folder")


def _read_doc(path: Path, fmt: str) -> dict:
    """A run-bundle JSON file (run.json, summary.json) with its format/version header checked."""
    doc = Node.load(path)
    check_header(doc, fmt, RUN_VERSIONS if fmt == RUN_FORMAT else (VERSION,))
    return doc.value


def read_run(root: str | Path) -> tuple[dict, list[dict], dict]:
    """(run.json, journal records, summary.json) of a run folder (for the report), all
    validated; the records of the journal and of its pending file, in file order."""
    from .config import AttackConfig

    root = Path(root)
    run_path = root / "run.json"
    if not run_path.exists():
        raise ConfigError(f"{root} is not an attack run folder (no run.json)")
    run = _read_doc(run_path, RUN_FORMAT)
    AttackConfig.from_run_json(run, run_path)  # typed: the report reads these fields
    if "scene_ids" in run:  # the journal's scenes are checked against them
        for node in Node(run, "$", run_path)["scene_ids"].items("one scene id per scene", length=len(run["scenes"])):
            node.string()
    j = Journal(root)
    j.load(repair=False, run=run)
    return run, j.records + list(j.pending.values()), j.read_summary()


def strip_times(records: Iterable[dict]) -> list[dict]:
    """Records without wall times (what must be identical between runs with the same seed)."""
    out = []
    for r in records:
        r = dict(r)
        r.pop("wall_s", None)
        r.pop(CHECKSUM_KEY, None)  # a function of the rest
        m = dict(r.get("metrics") or {})
        for k in ("ms_per_frame", "fps"):
            m.pop(k, None)
        r["metrics"] = m
        out.append(r)
    return out


def _changed_versions(old: Any, new: Any) -> list[str]:
    """``key: old -> new`` for each entry of two run.json ``versions`` that differs (nested one
    level, e.g. ``models.detector``)."""
    old, new = (old or {}), (new or {})
    if not isinstance(old, dict) or not isinstance(new, dict):
        return [] if old == new else [f"versions: {old!r} -> {new!r}"]
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{k}.{kk}: {a.get(kk)} -> {b.get(kk)}" for kk in sorted(set(a) | set(b)) if a.get(kk) != b.get(kk)]
        elif a != b:
            out.append(f"{k}: {a} -> {b}")
    return out
