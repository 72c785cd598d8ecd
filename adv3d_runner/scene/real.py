"""The bundled real-traffic scenes (``scenes/real/``, NGSIM US-101 via CommonRoad) and their split.

``scenes/real/split.json`` (format ``adv3d-real-split``, see docs/formats.md) says which scene
belongs to the **train** part (for training and tuning: the predictor's real samples, the
planner's comfort limits, the generator's ``us101`` profile) and which to the **benchmark**
part (only ever evaluated). The split is by NGSIM recording: the CommonRoad files of one
recording (``USA_US101-R_V_T-1``, R the recording, V a variant) share their traffic, so a
recording lies in exactly one part.

    split = load_real_split()                # validated (files exist, recordings disjoint)
    split.paths("benchmark")                 # [Path, ...] of the part's scene files
    recording_of("USA_US101-4_1_T-1")        # 4
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ..fileio import REPO_ROOT

REAL_DIR = REPO_ROOT / "scenes" / "real"
SPLIT_NAME = "split.json"
SPLIT_FORMAT = "adv3d-real-split"
SPLIT_VERSION = 1
PARTS = ("train", "benchmark")
_NAME = re.compile(r"^[A-Z]{3}_[A-Za-z0-9]+-(\d+)_(\d+)_T-\d+$")


def recording_of(name: str) -> int:
    """The recording number R of a CommonRoad benchmark id / scene file stem
    ``<COUNTRY>_<Location>-R_V_T-N`` (e.g. ``USA_US101-4_1_T-1`` -> 4).

    Raises:
        ValueError: the name does not follow the CommonRoad benchmark-id pattern.
    """
    m = _NAME.match(name)
    if m is None:
        raise ValueError(f"{name!r} is not a CommonRoad benchmark id like USA_US101-4_1_T-1")
    return int(m.group(1))



def longest_file_per_recording(source: str | Path, recordings) -> dict[int, Path]:
    """Per recording of ``recordings``, its largest ``USA_US101-*.xml`` file in ``source`` (the
    one that records longest: a recording's variants share its traffic), by recording number."""
    files: dict[int, tuple[int, Path]] = {}
    for f in sorted(Path(source).glob("USA_US101-*.xml")):
        r = recording_of(f.stem)
        if r in recordings and (r not in files or f.stat().st_size > files[r][0]):
            files[r] = (f.stat().st_size, f)
    return {r: f for r, (_, f) in files.items()}

@dataclass(frozen=True)
class RealSplit:
    """The parts of the real scenes.

    Attributes:
        folder: where the scene files are (``<name>.json.gz``).
        recordings: part -> recording numbers (disjoint between parts).
        scenes: part -> scene file stems (benchmark ids), in file order.
        rule: how the split was made (free text from the file).
    """

    folder: Path
    recordings: dict[str, tuple[int, ...]]
    scenes: dict[str, tuple[str, ...]]
    rule: str

    def paths(self, part: str) -> list[Path]:
        """Scene files of ``part`` (``train`` | ``benchmark``)."""
        if part not in PARTS:
            raise ValueError(f"unknown part {part!r}; choose one of {list(PARTS)}")
        return [self.folder / f"{name}.json.gz" for name in self.scenes[part]]


def load_real_split(path: str | Path | None = None) -> RealSplit:
    """Read and check ``split.json`` (default ``scenes/real/split.json``).

    Checks: the header; exactly the parts ``train`` and ``benchmark``, each with a non-empty
    list of recordings and of scene names; no recording in both parts; every scene name is a
    CommonRoad benchmark id whose recording belongs to its part, listed once, and its file
    exists next to ``split.json``.

    Raises:
        FileFormatError: naming the file and the JSON path of the first problem.
    """
    from ..validate import Node, check_header

    path = Path(path) if path is not None else REAL_DIR / SPLIT_NAME
    doc = Node.load(path)
    check_header(doc, SPLIT_FORMAT, (SPLIT_VERSION,))
    doc.check_keys(("format", "version", "rule", "recordings", "scenes"), ("recordings", "scenes"))
    rule = doc.get("rule", "").string(empty=True)
    rec_node, scene_node = doc["recordings"], doc["scenes"]
    for node in (rec_node, scene_node):
        node.check_keys(PARTS, PARTS)
    recordings: dict[str, tuple[int, ...]] = {}
    owner: dict[int, str] = {}
    for part in PARTS:
        seen: set = set()
        recs = []
        for item in rec_node[part].items("a non-empty list of recording numbers", non_empty=True):
            r = item.unique(item.integer(lo=0), seen, "recording number")
            if r in owner:
                item.fail(f"a recording that is not already in the {owner[r]} part", r)
            owner[r] = part
            recs.append(r)
        recordings[part] = tuple(recs)
    scenes: dict[str, tuple[str, ...]] = {}
    seen_names: set = set()
    for part in PARTS:
        names = []
        for item in scene_node[part].items("a non-empty list of scene names", non_empty=True):
            name = item.unique(item.string(pattern=_NAME, expected="a CommonRoad benchmark id like USA_US101-4_1_T-1"),
                               seen_names, "scene name")
            if recording_of(name) not in recordings[part]:
                item.fail(f"a scene of a {part} recording {list(recordings[part])}", name)
            if not (path.parent / f"{name}.json.gz").is_file():
                item.fail(f"a scene with a file {name}.json.gz next to {path.name}", name)
            names.append(name)
        scenes[part] = tuple(names)
    return RealSplit(path.parent, recordings, scenes, rule)


#: The fresh benchmark part (``scenes/real-fresh/``, made by ``bench/real_fresh.py``): NGSIM
#: recordings that no model, planner setting or generator profile was fitted or tuned on;
#: evaluation only. Its manifest is ``index.csv`` (one row per scene).
FRESH_DIR = REPO_ROOT / "scenes" / "real-fresh"
FRESH_RECORDINGS = (10, 11, 12, 13, 14, 15, 16, 17, 18)
FRESH_INDEX = "index.csv"
FRESH_INDEX_HEADER = ("scene", "recording", "commonroad_file", "commonroad_sha256", "ego_obstacle_id",
                      "speed_min_first_5s", "speed_max_first_5s")


@dataclass(frozen=True)
class FreshPart:
    """The fresh benchmark part.

    Attributes:
        folder: where the scene files are (``<scene>.json.gz``).
        rows: the manifest's rows (column -> text), in file order.
    """

    folder: Path
    rows: tuple[dict[str, str], ...]

    @property
    def recordings(self) -> tuple[int, ...]:
        """The recordings the part's scenes come from, ascending."""
        return tuple(sorted({int(r["recording"]) for r in self.rows}))

    def paths(self) -> list[Path]:
        """Scene files, in manifest order."""
        return [self.folder / f"{r['scene']}.json.gz" for r in self.rows]


def load_fresh_part(folder: str | Path | None = None, split: RealSplit | None = None) -> FreshPart:
    """Read and check the fresh part's manifest ``<folder>/index.csv`` (default
    ``scenes/real-fresh``).

    Checks: the header; every row's scene name is ``<CommonRoad id>.ego<obstacle id>`` naming its
    row's file and ego, listed once, with a file next to the manifest; its recording is one of
    ``FRESH_RECORDINGS`` and in neither part of ``split`` (default ``scenes/real/split.json``),
    so no recording is both trained or tuned on and evaluated here.

    Raises:
        FileFormatError: naming the manifest, the row and the column of the first problem.
    """
    import csv

    from ..errors import FileFormatError

    folder = Path(folder) if folder is not None else FRESH_DIR
    path = folder / FRESH_INDEX
    split = split if split is not None else load_real_split()
    used = {r: part for part, recs in split.recordings.items() for r in recs}
    try:
        text = path.read_text()
    except OSError as exc:
        raise FileFormatError(path, "$", "a readable CSV manifest", exc.strerror or str(exc)) from None
    reader = csv.DictReader(text.splitlines())
    if tuple(reader.fieldnames or ()) != FRESH_INDEX_HEADER:
        raise FileFormatError(path, "line 1", f"the header {','.join(FRESH_INDEX_HEADER)}", reader.fieldnames)
    rows, seen = [], set()
    for n, row in enumerate(reader, start=2):
        where = f"line {n}"
        name, rec, ego = row["scene"], row["recording"], row["ego_obstacle_id"]
        stem = Path(row["commonroad_file"] or "").stem
        if f"{stem}.ego{ego}" != name:
            raise FileFormatError(path, f"{where}.scene", f"<commonroad_file stem>.ego<ego_obstacle_id> = {stem}.ego{ego}", name)
        try:
            r = recording_of(stem)
        except ValueError:
            raise FileFormatError(path, f"{where}.commonroad_file", "a CommonRoad US-101 file name", stem) from None
        if not rec.isdigit() or int(rec) != r:
            raise FileFormatError(path, f"{where}.recording", f"the file's recording {r}", rec)
        if r not in FRESH_RECORDINGS:
            raise FileFormatError(path, f"{where}.recording", f"a fresh recording {list(FRESH_RECORDINGS)}", r)
        if r in used:
            raise FileFormatError(path, f"{where}.recording", f"a recording outside split.json's {used[r]} part", r)
        if name in seen:
            raise FileFormatError(path, f"{where}.scene", "a scene listed once", name)
        seen.add(name)
        if not (folder / f"{name}.json.gz").is_file():
            raise FileFormatError(path, f"{where}.scene", f"a scene with a file {name}.json.gz next to {FRESH_INDEX}", name)
        rows.append(dict(row))
    if not rows:
        raise FileFormatError(path, "$", "at least one scene row", "none")
    return FreshPart(folder, tuple(rows))
