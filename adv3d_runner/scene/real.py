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
