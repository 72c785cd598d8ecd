"""The run bundle ``runs/<name>/`` of an attack (DESIGN.md data contract 4, docs/formats.md).

::

    runs/NAME/
      run.json          config, seed, versions, scene ids (written once; a resume checks it)
      queries.jsonl     append-only journal, one JSON object per evaluated query
      summary.json      per scene and mode: best query, original / best metrics (rewritten)
      scenes/<scene>/<mode>/actor<ID>.glb     best shape per attacked actor
      scenes/<scene>/<mode>/replay.json.gz    replay of the best shape in closed loop (+ .points.npz)

Every journal line is written with one ``write`` + flush + fsync, so a killed run leaves at
most one truncated last line. :meth:`Journal.open` drops such a line (it is not valid JSON or
has no newline), truncates the file back to the last complete line and returns the finished
queries; the driver then re-asks its searchers and takes the recorded results for every query
already in the journal instead of evaluating it again (see :mod:`.driver`).

Line fields (fixed order): ``scene``, ``mode``, ``index`` (query number within the scene and
mode), ``actors``, ``unit`` (m lists of K + 2 numbers), ``latent``, ``scales``,
``dimensions``, ``cost`` (null when failed), ``components``, ``metrics``, ``status``
(``ok`` / ``invalid`` / ``error``), ``error`` (message or null), ``wall_s``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..errors import ConfigError, FileFormatError
from ..fileio import read_json, write_json

RUN_FORMAT = "adv3d.attack_run"
SUMMARY_FORMAT = "adv3d.attack_summary"
QUERY_FORMAT = "adv3d.attack_query"
VERSION = 1
STATUSES = ("ok", "invalid", "error")
_LINE_KEYS = ("scene", "mode", "index", "actors", "unit", "latent", "scales", "dimensions", "cost",
              "components", "metrics", "status", "error", "wall_s")
# Config keys that may differ between the first run and a resume (they do not change results).
RESUME_FREE_KEYS = ("workers", "ray_address", "quiet", "out")


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
                 latent=None, scales=None, dimensions=None, cost: float | None = None,
                 components: dict | None = None, metrics: dict | None = None, status: str = "ok",
                 error: str | None = None, wall_s: float = 0.0) -> dict:
    """One journal line as a dict with the fixed field order."""
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}")
    u = np.asarray(unit, dtype=np.float64).reshape(len(actors), -1)
    rec = {"scene": scene, "mode": mode, "index": int(index), "actors": [int(a) for a in actors],
           "unit": [[float(v) for v in row] for row in u], "latent": latent, "scales": scales,
           "dimensions": dimensions, "cost": cost, "components": components or {}, "metrics": metrics or {},
           "status": status, "error": error, "wall_s": round(float(wall_s), 4)}
    return _clean(rec)


def record_cost(rec: dict) -> float:
    """The record's cost as a float, NaN for failed queries."""
    c = rec.get("cost")
    return float(c) if isinstance(c, (int, float)) and rec.get("status") == "ok" else float("nan")


def record_unit(rec: dict) -> np.ndarray:
    """(m * (K+2),) the record's query vector."""
    return np.asarray(rec["unit"], dtype=np.float64).reshape(-1)


class Journal:
    """Append-only ``queries.jsonl`` plus ``run.json`` / ``summary.json`` of one run folder."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.path = self.root / "queries.jsonl"
        self.records: list[dict] = []

    # ------------------------------------------------------------------ run.json
    def start(self, config: dict) -> dict:
        """Create the folder and ``run.json``, or check that an existing run has the same
        config (up to :data:`RESUME_FREE_KEYS`) and load its journal. Returns the stored
        config (the first run's, e.g. its batch size, wins on resume).

        Raises:
            ConfigError: the folder holds a run with a different config.
        """
        self.root.mkdir(parents=True, exist_ok=True)
        run_path = self.root / "run.json"
        doc = _clean({"format": RUN_FORMAT, "version": VERSION, **config})
        if run_path.exists():
            old = read_json(run_path)
            if not isinstance(old, dict) or old.get("format") != RUN_FORMAT:
                raise FileFormatError(run_path, "$.format", RUN_FORMAT, old.get("format") if isinstance(old, dict) else old)
            diff = sorted(k for k in set(old) | set(doc)
                          if k not in RESUME_FREE_KEYS and k != "versions" and old.get(k) != doc.get(k))
            if diff:
                raise ConfigError(f"{self.root} holds a run with a different configuration ({', '.join(diff)}); "
                                  f"use another --out or the same options to resume it")
            self.load(repair=True)
            return old
        write_json(run_path, doc, indent=1)
        self.load(repair=True)
        return doc

    # ------------------------------------------------------------------ queries.jsonl
    def load(self, repair: bool = False) -> list[dict]:
        """Read the journal; a truncated or corrupt *last* line is dropped (and cut from the
        file when ``repair``). A corrupt line elsewhere is a FileFormatError."""
        self.records = []
        if not self.path.exists():
            return self.records
        data = self.path.read_bytes()
        good_end = 0
        pos = 0
        lines = data.split(b"\n")
        for i, raw in enumerate(lines):
            is_last = i == len(lines) - 1
            if is_last:  # bytes after the last newline: an unfinished write
                break
            try:
                rec = json.loads(raw.decode("utf-8"))
                if not isinstance(rec, dict) or "index" not in rec or "scene" not in rec:
                    raise ValueError("not a query record")
            except (ValueError, UnicodeDecodeError) as exc:
                if i == len(lines) - 2 and not lines[-1]:
                    break  # the last complete line is corrupt (e.g. zero-filled after a crash)
                raise FileFormatError(self.path, f"line {i + 1}", "one JSON query record per line", str(exc)) from None
            self.records.append(rec)
            pos += len(raw) + 1
            good_end = pos
        if repair and good_end != len(data):
            with open(self.path, "r+b") as fh:
                fh.truncate(good_end)
                fh.flush()
                os.fsync(fh.fileno())
        return self.records

    def append(self, rec: dict) -> None:
        """Append one record durably (single write, flush, fsync)."""
        line = json.dumps(_clean(rec), allow_nan=False, separators=(",", ":")) + "\n"
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())
        self.records.append(json.loads(line))

    def canonicalize(self, order: list[tuple[str, str]]) -> bool:
        """Rewrite ``queries.jsonl`` (atomically) with its lines in the canonical order: the
        (scene, mode) pairs in ``order``, each by query index; lines of other pairs keep their
        place after them. Lines are appended as queries finish, so a run with several workers
        writes them interleaved; this makes a finished run's journal independent of that.
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

        data = b"".join((json.dumps(_clean(r), allow_nan=False, separators=(",", ":")) + "\n").encode("utf-8")
                        for r in ordered)
        atomic_write_bytes(self.path, data)
        self.records = ordered
        return True

    def finished(self, scene: str, mode: str) -> dict[int, dict]:
        """{query index: record} already journalled for a scene and mode."""
        return {int(r["index"]): r for r in self.records if r.get("scene") == scene and r.get("mode") == mode}

    # ------------------------------------------------------------------ summary.json
    def write_summary(self, summary: dict) -> None:
        write_json(self.root / "summary.json", _clean({"format": SUMMARY_FORMAT, "version": VERSION, **summary}), indent=1)

    def read_summary(self) -> dict:
        path = self.root / "summary.json"
        return read_json(path) if path.exists() else {"format": SUMMARY_FORMAT, "version": VERSION, "scenes": {}}


def read_run(root: str | Path) -> tuple[dict, list[dict], dict]:
    """(run.json, journal records, summary.json) of a run folder (for the report)."""
    root = Path(root)
    run_path = root / "run.json"
    if not run_path.exists():
        raise ConfigError(f"{root} is not an attack run folder (no run.json)")
    run = read_json(run_path)
    if not isinstance(run, dict) or run.get("format") != RUN_FORMAT:
        raise FileFormatError(run_path, "$.format", RUN_FORMAT, run.get("format") if isinstance(run, dict) else run)
    j = Journal(root)
    j.load(repair=False)
    return run, j.records, j.read_summary()


def strip_times(records: Iterable[dict]) -> list[dict]:
    """Records without wall times (what must be identical between runs with the same seed)."""
    out = []
    for r in records:
        r = dict(r)
        r.pop("wall_s", None)
        m = dict(r.get("metrics") or {})
        for k in ("ms_per_frame", "fps"):
            m.pop(k, None)
        r["metrics"] = m
        out.append(r)
    return out
