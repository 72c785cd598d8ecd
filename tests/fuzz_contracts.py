"""Hostile inputs for every file contract and the CLI's numeric arguments (hypothesis), shared by
``tests/test_fuzz.py`` (a fixed-seed subset in CI, the full run marked slow) and
``bench/fuzz.py`` (the outcome counts in ``bench/results/fuzz.json``, docs/reliability.md).

Each contract has a small valid file set (:class:`Contract` ``make``), the reader the tool uses
for it (``load``: the same calls the commands make) and the checks a file that is *accepted*
must pass (``accept``: a round trip gives the same data, every number is finite and within the
contract's bounds). A case mutates one file (:func:`mutations`: a JSON value replaced by a
hostile one, a field deleted or added, a list emptied or duplicated, nesting deepened;
truncated, corrupted or swapped bytes; an npz member dropped, retyped, reshaped or filled with
NaN/1e308; an XML number replaced or an element dropped or repeated) and ends in exactly one
outcome (:func:`run_case`):

* ``error``: an ``Adv3dError`` whose message is one line naming the file (what the CLI prints
  as ``adv3d: error: ...`` with exit code 1);
* ``accepted``: the reader returned and ``accept`` held (a documented acceptance: e.g. another
  valid number, or a free-form field such as ``metadata``);
* anything else is a finding (``crash``: another exception; ``vague``: an error that does not
  name the file or spans lines; ``bad-accept``: accepted but ``accept`` failed) and fails the
  test.
"""
from __future__ import annotations

import copy
import gzip
import io
import json
import math
import shutil
import zipfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from adv3d_runner.errors import Adv3dError

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "highway" / "highway-benchmark-000000.json.gz"

# ----------------------------------------------------------------------------- hostile values

HOSTILE_VALUES: list[Any] = [
    float("nan"), float("inf"), float("-inf"), 1e308, -1e308, 1e-320, -1, 0, 1, 2**63, -(2**63), 0.5,
    "", "x", "../../outside", "/etc/passwd", "a/../../b", "C:\\evil", "nul\x00byte", "é" * 3, "x" * 5000,
    None, True, False, [], {}, [[]], [None], [1, 2, 3], {"unknown": 1},
]
KINDS = ("replace", "delete", "add_key", "empty", "duplicate", "deepen", "type_swap")


def json_paths(doc: Any, limit: int = 4000) -> list[tuple]:
    """Paths (tuples of keys / indices) to the values of a JSON document, breadth first (the
    structure near the root before the long number lists), at most ``limit``."""
    out: list[tuple] = []
    queue: list[tuple[tuple, Any]] = [((), doc)]
    while queue and len(out) < limit:
        path, value = queue.pop(0)
        out.append(path)
        if isinstance(value, dict):
            queue.extend((path + (k,), v) for k, v in value.items())
        elif isinstance(value, list):
            queue.extend((path + (i,), v) for i, v in enumerate(value[:50]))  # long lists: their head
    return out


def _get(doc: Any, path: tuple) -> Any:
    for key in path:
        doc = doc[key]
    return doc


def mutate_json(doc: Any, data: st.DataObject) -> tuple[Any, str]:
    """One mutation of a copy of ``doc`` drawn from ``data``; returns (new doc, description)."""
    doc = copy.deepcopy(doc)
    paths = json_paths(doc)
    path = paths[data.draw(st.integers(0, len(paths) - 1), label="path")]
    kind = data.draw(st.sampled_from(KINDS), label="kind")
    where = "$" + "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path)
    if not path:  # the document itself
        kind = "replace" if kind in ("delete", "duplicate") else kind
    parent = _get(doc, path[:-1]) if path else None
    value = _get(doc, path)

    def put(v: Any) -> None:
        nonlocal doc
        if path:
            parent[path[-1]] = v
        else:
            doc = v

    if kind == "replace":
        v = data.draw(st.sampled_from(HOSTILE_VALUES), label="value")
        put(copy.deepcopy(v))
        return doc, f"{where} = {v!r:.40}"
    if kind == "delete":
        del parent[path[-1]]
        return doc, f"delete {where}"
    if kind == "add_key":
        if isinstance(value, dict):
            value["zz_unknown_field"] = 1
            return doc, f"unknown field in {where}"
        put({"zz_unknown_field": value})
        return doc, f"{where} wrapped in an object"
    if kind == "empty":
        put({} if isinstance(value, dict) else [] if isinstance(value, list) else "")
        return doc, f"empty {where}"
    if kind == "duplicate":
        if isinstance(parent, list):
            parent.insert(path[-1], copy.deepcopy(value))
            return doc, f"duplicate {where}"
        put([value, copy.deepcopy(value)])
        return doc, f"{where} doubled into a list"
    if kind == "deepen":  # json.dumps cannot write it: a marker that to_text() expands
        depth = data.draw(st.sampled_from([70, 1000, 5000]), label="depth")
        put(f"@@DEEP:{depth}@@")
        return doc, f"{where} nested {depth} deep"
    # type_swap: the same value in another JSON type
    swapped = (str(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
               else [value] if not isinstance(value, list) else {"0": value})
    put(swapped)
    return doc, f"{where} as {type(swapped).__name__}"


def to_text(doc: Any, **kw) -> str:
    """``json.dumps`` (NaN and inf written as the tokens Python reads), with every deep-nesting
    marker of :func:`mutate_json` expanded to ``[[[...null...]]]``."""
    import re

    text = json.dumps(doc, allow_nan=True, **kw)
    return re.sub(r'"@@DEEP:(\d+)@@"', lambda m: "[" * int(m.group(1)) + "null" + "]" * int(m.group(1)), text)


def mutate_bytes(raw: bytes, data: st.DataObject, gz: bool) -> tuple[bytes, str]:
    """Byte-level damage: truncation, a flipped byte, garbage, empty file, (for .gz) plain or
    corrupt compression, trailing junk."""
    kind = data.draw(st.sampled_from(["truncate", "flip", "garbage", "empty", "plain", "trailing"]), label="bytes")
    if kind == "truncate":
        cut = data.draw(st.integers(0, max(0, len(raw) - 1)), label="cut")
        return raw[:cut], f"truncated to {cut} bytes"
    if kind == "flip":
        pos = data.draw(st.integers(0, max(0, len(raw) - 1)), label="pos")
        b = bytearray(raw)
        if b:
            b[pos] ^= 0xFF
        return bytes(b), f"byte {pos} flipped"
    if kind == "garbage":
        n = data.draw(st.integers(1, 64), label="n")
        return bytes((i * 37 + 11) % 256 for i in range(n)), f"{n} garbage bytes"
    if kind == "empty":
        return b"", "empty file"
    if kind == "plain" and gz:
        return gzip.decompress(raw), "not compressed under a .gz name"
    return raw + b"\x00junk", "trailing junk"


# ----------------------------------------------------------------------------- outcomes

@dataclass
class Outcome:
    """How one case ended: ``kind`` (error / accepted / crash / vague / bad-accept), the case and
    the message."""

    kind: str
    case: str
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.kind in ("error", "accepted")


def run_case(load: Callable[[], Any], accept: Callable[[Any], None], file: Path, case: str) -> Outcome:
    """Run the reader on a mutated file and classify the outcome (module docstring)."""
    try:
        result = load()
    except Adv3dError as exc:
        text = str(exc)
        if "\n" in text or file.name not in text:
            return Outcome("vague", case, text[:300])
        return Outcome("error", case, text[:300])
    except Exception as exc:  # noqa: BLE001 - anything else is what we are looking for
        return Outcome("crash", case, f"{type(exc).__name__}: {exc}"[:300])
    try:
        accept(result)
    except Exception as exc:  # noqa: BLE001
        return Outcome("bad-accept", case, f"{type(exc).__name__}: {exc}"[:300])
    return Outcome("accepted", case)


def _finite_tree(value: Any, where: str = "$") -> None:
    """Every number in a parsed JSON value is finite (accepted files never smuggle NaN/inf)."""
    stack = [(value, where)]
    while stack:
        v, w = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            raise AssertionError(f"{w} is {v}")
        if isinstance(v, dict):
            stack.extend((x, f"{w}.{k}") for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((x, f"{w}[{i}]") for i, x in enumerate(v))


# ----------------------------------------------------------------------------- contracts

@dataclass
class Contract:
    """A file contract under fuzz: ``make(folder)`` writes the valid files and returns the
    file to mutate; ``mutate(file, data)`` damages it and describes how; ``load(file)`` reads
    it as the tool does; ``accept(result, folder)`` checks an accepted result."""

    name: str
    make: Callable[[Path], Path]
    mutate: Callable[[Path, st.DataObject], str]
    load: Callable[[Path], Any]
    accept: Callable[[Any, Path], None]


def _json_mutator(gz: bool = False, lines: bool = False) -> Callable[[Path, st.DataObject], str]:
    def mutate(file: Path, data: st.DataObject) -> str:
        raw = file.read_bytes()
        if data.draw(st.integers(0, 4), label="level") == 0:  # one in five: damage the bytes
            new, what = mutate_bytes(raw, data, gz)
            file.write_bytes(new)
            return what
        text = gzip.decompress(raw) if gz else raw
        if lines:
            rows = text.decode().splitlines()
            k = data.draw(st.integers(0, len(rows) - 1), label="line")
            doc, what = mutate_json(json.loads(rows[k]), data)
            rows[k] = to_text(doc, separators=(",", ":"))
            out = ("\n".join(rows) + "\n").encode()
            what = f"line {k + 1}: {what}"
        else:
            doc, what = mutate_json(json.loads(text), data)
            out = to_text(doc).encode()
        file.write_bytes(gzip.compress(out, mtime=0) if gz else out)
        return what
    return mutate


# --- scene --------------------------------------------------------------------------------

def small_scene_doc() -> dict:
    """The first bundled benchmark scene cut to 20 frames and 4 actors, with one background
    mesh (``sign.obj`` beside it): small enough that mutations hit structure, not numbers."""
    from adv3d_runner.fileio import read_json

    doc = read_json(SCENE)
    T = 20
    doc["frames"] = T
    doc["ego"]["track"] = {k: (v[:T] if isinstance(v, list) else v) for k, v in doc["ego"]["track"].items()}
    actors = []
    for a in doc["actors"]:
        t = a["track"]
        if t["start"] >= T:
            continue
        n = T - t["start"]
        a["track"] = {k: (v[:n] if isinstance(v, list) else v) for k, v in t.items()}
        if "valid" in a["track"] and not any(a["track"]["valid"]):
            continue
        actors.append(a)
    doc["actors"] = actors[:4]
    doc["actors"][0]["asset"] = "kenney-car-kit.sedan"
    doc["background"]["meshes"] = [{"file": "sign.obj", "pose": [10.0, 5.0, 0.0, 0.0], "surface": "metal"}]
    for lane in doc["map"]["lanes"]:
        lane["centerline"] = lane["centerline"][:6]
        if isinstance(lane["width"], list):
            lane["width"] = lane["width"][:6]
    return doc


SIGN_OBJ = "v 0 0 0\nv 1 0 0\nv 0 0 2\nv 1 0 2\nf 1 2 4\nf 1 4 3\n"


def _make_scene(folder: Path, gz: bool) -> Path:
    from adv3d_runner.fileio import write_json

    (folder / "sign.obj").write_text(SIGN_OBJ)
    path = folder / ("scene.json.gz" if gz else "scene.json")
    write_json(path, small_scene_doc())
    return path


def _load_scene(path: Path):
    from adv3d_runner.scene.actors import check_assets
    from adv3d_runner.scene.background import background_mesh
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sim.episode import default_library

    scene = load_scene(path)
    check_assets(scene, default_library(), str(path))
    background_mesh(scene, scene_dir=path.parent)  # follows background.meshes[].file
    return scene


def _accept_scene(scene, folder: Path) -> None:
    from adv3d_runner.scene.schema import MAX_COORD, load_scene, save_scene, scene_equal

    out = folder / "roundtrip.json"
    save_scene(scene, out)
    assert scene_equal(load_scene(out), scene), "round trip changed the scene"
    poses = scene.ego_poses()
    assert np.isfinite(poses).all() and np.abs(poses[:, :2]).max() <= MAX_COORD


# --- replay ---------------------------------------------------------------------------------

def _make_replay(folder: Path) -> Path:
    import trimesh

    from adv3d_runner.shapes.mesh_io import write_library_glb
    from adv3d_runner.sim.replay import Replay, ReplayActor, ReplayFrame, save_replay

    rng = np.random.default_rng(0)
    T = 4
    write_library_glb(trimesh.creation.box((4.0, 1.8, 1.5)), folder / "actor1.glb")
    actors = [ReplayActor(1, "sedan", [4.5, 1.8, 1.5], np.c_[np.arange(T) + 10.0, np.zeros(T), np.zeros(T)],
                          adversarial=True, mesh="actor1.glb"),
              ReplayActor(2, "suv", [4.8, 1.9, 1.7], np.c_[np.arange(T) + 30.0, np.full(T, 3.5), np.zeros(T)])]
    frames = [ReplayFrame(rng.random((2, 5)), rng.random(2), [1, 2], rng.random((2, 5)), rng.random((2, 2)),
                          [1], rng.random((1, 3, 6, 2)), [[0.5, 0.3, 0.2]], rng.random((5, 3)), rng.random(5),
                          "keep", 1.5) for _ in range(T)]
    points = [np.c_[rng.normal(size=(30, 3)) * 10, rng.random(30), rng.integers(-1, 2, 30)].astype(np.float32)
              for _ in range(T)]
    replay = Replay("scene-x", 0.1, [4.6, 1.9, 1.5], np.c_[np.arange(T) * 1.0, np.zeros(T), np.zeros(T)],
                    np.full(T, 10.0), actors, frames, points=points, metadata={"attack": {"query": 3}})
    return save_replay(replay, folder / "replay.json.gz")


def _make_replay_v2(folder: Path) -> Path:
    """The replay above with occupancy heat maps (version 2, Autonomy-B), one frame without."""
    from adv3d_runner.sim.replay import OccupancyMap, load_replay, save_replay

    path = _make_replay(folder)
    replay = load_replay(path, points=True)
    rng = np.random.default_rng(1)
    for k, f in enumerate(replay.frames[:-1]):
        poses = np.array([[20.0 + k + 10.0 * t, 1.0, 0.05] for t in (0.0, 1.0)])
        f.occupancy = OccupancyMap([0.0, 1.0], poses, 0.5, rng.integers(0, 256, (2, 6, 3)))
    return save_replay(replay, path)


def _load_replay(path: Path):
    from adv3d_runner.shapes.mesh_io import read_library_mesh
    from adv3d_runner.sim.replay import actor_mesh_path, load_replay

    replay = load_replay(path, points=True)
    for i, a in enumerate(replay.actors):  # what the add-on's review does with each adversarial actor
        mesh = actor_mesh_path(path, replay, i)
        if a.adversarial and mesh is not None:
            read_library_mesh(mesh)
    return replay


def _accept_replay(replay, folder: Path) -> None:
    from adv3d_runner.sim.replay import load_replay, replay_equal, save_replay

    out = save_replay(replay, folder / "rt" / "replay.json.gz")
    assert replay_equal(load_replay(out), replay), "round trip changed the replay"
    assert np.isfinite(replay.ego_poses).all()


# --- npz (points, shape space, realism reference) -----------------------------------------

NPZ_KINDS = ("drop", "dtype", "shape", "nan", "huge", "object", "rename", "meta", "bytes")


def _read_members(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write_members(path: Path, members: dict[str, np.ndarray]) -> None:
    buf = io.BytesIO()
    np.savez(buf, **members)
    path.write_bytes(buf.getvalue())


def mutate_npz(path: Path, data: st.DataObject, rehash: Callable[[dict], None] | None = None) -> str:
    """One damage to an npz contract file: a member dropped, retyped, reshaped, filled with
    NaN or 1e308, replaced by an object array (pickle), renamed; the JSON ``meta`` member
    mutated (and, with ``rehash``, its content hash recomputed so deeper checks are reached);
    or the bytes damaged."""
    kind = data.draw(st.sampled_from(NPZ_KINDS), label="npz")
    if kind == "bytes":
        new, what = mutate_bytes(path.read_bytes(), data, gz=False)
        path.write_bytes(new)
        return what
    members = _read_members(path)
    names = sorted(members)
    name = data.draw(st.sampled_from(names), label="member")
    a = members[name]
    if kind == "meta" and "meta" in members:
        doc, what = mutate_json(json.loads(str(members["meta"])), data)
        members["meta"] = np.array(to_text(doc))
        if rehash is not None and data.draw(st.booleans(), label="rehash"):
            rehash(members)
            what += " (content hash recomputed)"
        _write_members(path, members)
        return f"meta: {what}"
    if kind == "drop":
        del members[name]
        what = f"member {name} dropped"
    elif kind == "dtype":
        members[name] = (np.zeros(a.shape, np.float64) if a.dtype.kind == "U"
                         else a.astype(np.float64) if a.dtype != np.float64 else a.astype(np.int32))
        what = f"{name} as {members[name].dtype}"
    elif kind == "shape":
        members[name] = a.reshape(-1)[: max(0, a.size - 1)] if a.size else np.zeros(3)
        what = f"{name} reshaped to {members[name].shape}"
    elif kind in ("nan", "huge") and a.dtype.kind == "f" and a.size:
        b = a.copy()
        b.reshape(-1)[data.draw(st.integers(0, a.size - 1), label="at")] = np.nan if kind == "nan" else 1e308 if \
            a.dtype == np.float64 else np.float32(3e38)
        members[name] = b
        what = f"{kind} in {name}"
    elif kind == "object":
        members[name] = np.array([{"x": 1}], dtype=object)
        what = f"{name} as an object array"
    else:
        members[name + "_x"] = members.pop(name)
        what = f"{name} renamed"
    if kind == "object":  # np.savez would pickle: write it as a pickled member on purpose
        buf = io.BytesIO()
        np.savez(buf, **{k: v for k, v in members.items()})
        path.write_bytes(buf.getvalue())
    else:
        _write_members(path, members)
    return what


def _make_points(folder: Path) -> Path:
    _make_replay(folder)
    return folder / "replay.points.npz"


def _load_points(path: Path):
    from adv3d_runner.sim.replay import load_replay

    return load_replay(path.parent / "replay.json.gz", points=True)


def _accept_points(replay, folder: Path) -> None:
    assert replay.points is not None and all(np.isfinite(p).all() for p in replay.points)
    assert all(p.shape[1] == 5 for p in replay.points)


def _make_space(folder: Path) -> Path:
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE

    return Path(shutil.copy(DEFAULT_SHAPE_SPACE, folder / "space.npz"))


def _rehash_space(members: dict) -> None:
    from adv3d_runner.shapes.shape_space import _content_hash

    try:
        meta = json.loads(str(members["meta"]))
        meta["content_hash"] = _content_hash(meta, members)
        members["meta"] = np.array(json.dumps(meta, allow_nan=True))
    except Exception:  # noqa: BLE001 - a member the hash needs is gone: leave it
        pass


def _load_space(path: Path):
    from adv3d_runner.shapes.shape_space import ShapeSpace

    space = ShapeSpace.load(path)
    space.decode_arrays([0.5] * space.dim)  # what `shapes decode` does next
    return space


def _accept_space(space, folder: Path) -> None:
    from adv3d_runner.shapes.shape_space import MAX_EXTENT_M, SCALE_LIMITS

    v, _ = space.decode_arrays([1.0] * space.dim)  # the largest scales
    assert np.isfinite(v).all() and np.ptp(v, axis=0).max() <= MAX_EXTENT_M * SCALE_LIMITS[1]


def _make_reference(folder: Path) -> Path:
    from adv3d_runner.shapes.realism import DEFAULT_REFERENCE

    return Path(shutil.copy(DEFAULT_REFERENCE, folder / "reference.npz"))


def _load_reference(path: Path):
    from adv3d_runner.shapes.realism import load_reference

    return load_reference(path)


def _accept_reference(ref, folder: Path) -> None:
    assert np.isfinite(ref.points).all() and (ref.histogram >= 0).all()
    assert all(np.isfinite(getattr(ref, k)).all() for k in ("jsd_loo", "chamfer_loo", "mahalanobis_loo"))


# --- vehicle library ------------------------------------------------------------------------

def _make_library(folder: Path) -> Path:
    import trimesh

    from adv3d_runner.fileio import write_json
    from adv3d_runner.shapes.library import FORMAT, VERSION
    from adv3d_runner.shapes.mesh_io import read_library_mesh, write_library_glb

    (folder / "pack").mkdir()
    box = trimesh.creation.box((4.0, 1.8, 1.5))
    box.apply_translation([0, 0, 0.75])
    write_library_glb(box, folder / "pack" / "box.glb")
    (folder / "pack" / "LICENSE.txt").write_text("CC0 1.0")
    stored = read_library_mesh(folder / "pack" / "box.glb")
    asset = {"id": "pack.box", "file": "pack/box.glb", "class": "sedan", "dimensions": [4.0, 1.8, 1.5],
             "in_shape_space": True, "triangle_count": int(len(stored.faces)),
             "source": {"pack": "pack", "file": "box.obj"}, "licence": {"name": "CC0-1.0", "file": "pack/LICENSE.txt"},
             "curation": {}, "cleaning": {}}
    path = folder / "library.json"
    write_json(path, {"format": FORMAT, "version": VERSION, "assets": [asset],
                      "excluded": [{"pack": "pack", "file": "old.obj", "reason": "test"}]})
    return path


def _load_library(path: Path):
    from adv3d_runner.errors import MeshImportError
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.shapes.library_cli import check_library

    library = load_library(path)
    for asset in library.assets:
        library.path_of(asset)  # inside the library folder
    problems = check_library(library)  # `adv3d assets check`: every mesh loads and matches
    if problems:
        raise MeshImportError(f"{path}: {problems[0]}")
    return library


def _accept_library(library, folder: Path) -> None:
    from adv3d_runner.shapes.library import load_library, save_library

    out = save_library(library, folder / "rt.json")
    assert load_library(out).to_json() == library.to_json()


# --- model configs ----------------------------------------------------------------------------

def _make_model(which: str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        src = REPO / "assets" / "models" / which
        for f in src.iterdir():
            if f.suffix in (".json", ".pt"):
                shutil.copy(f, folder / f.name)
        return folder / "config.json"
    return make


def _load_detector(path: Path):
    from adv3d_runner.autonomy.detector import load_detector

    return load_detector(path.parent)


def _load_occupancy(path: Path):
    from adv3d_runner.autonomy.occupancy import load_occupancy

    return load_occupancy(path.parent)


def _load_predictor(path: Path):
    from adv3d_runner.autonomy.predictor import load_predictor

    return load_predictor(path.parent)


def _accept_model(model, folder: Path) -> None:
    assert model is not None


# --- run bundle -------------------------------------------------------------------------------

def _make_run(name: str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        import sys

        sys.path.insert(0, str(REPO / "tests"))
        from attack_synthetic import SyntheticEvaluator

        from adv3d_runner.attack.config import AttackConfig
        from adv3d_runner.attack.driver import run_attack

        run_attack(AttackConfig(["synthetic:peak"], algo="random", budget=6, seed=3), folder / "run",
                   evaluator=SyntheticEvaluator, show_progress=False)
        return folder / "run" / name
    return make


def _load_run(path: Path):
    from adv3d_runner.attack.journal import read_run

    return read_run(path.parent)


def _accept_run(result, folder: Path) -> None:
    run, records, summary = result
    _finite_tree(summary)
    for r in records:
        _finite_tree(r)
        assert r["status"] in ("ok", "invalid", "error")


# --- CommonRoad XML ---------------------------------------------------------------------------

def commonroad_xml(dt: str = "0.1", steps: int = 20) -> str:
    """A minimal CommonRoad 2018b scenario: two parallel 200 m lanelets, three cars driving
    along +x for ``steps`` time steps."""
    def pt(x, y):
        return f"<point><x>{x}</x><y>{y}</y></point>"

    def lanelet(lid, y0, adj):
        xs = (0.0, 100.0, 200.0)
        return (f'<lanelet id="{lid}"><leftBound>{"".join(pt(x, y0 + 1.75) for x in xs)}</leftBound>'
                f'<rightBound>{"".join(pt(x, y0 - 1.75) for x in xs)}</rightBound>{adj}</lanelet>')

    def state(tag, x, y, t, v):
        return (f"<{tag}><position>{pt(x, y)}</position><orientation><exact>0.0</exact></orientation>"
                f"<time><exact>{t}</exact></time><velocity><exact>{v}</exact></velocity></{tag}>")

    lanes = (lanelet(10, 1.75, '<adjacentLeft ref="11" drivingDir="same"/>')
             + lanelet(11, 5.25, '<adjacentRight ref="10" drivingDir="same"/>'))
    obs = ""
    for oid, x0, y, v in ((1, 5.0, 1.75, 12.0), (2, 30.0, 1.75, 11.0), (3, 20.0, 5.25, 13.0)):
        traj = "".join(state("state", round(x0 + v * 0.1 * k, 4), y, k, v) for k in range(1, steps))
        obs += (f'<obstacle id="{oid}"><role>dynamic</role><type>car</type><shape><rectangle><length>4.5</length>'
                f"<width>1.8</width></rectangle></shape>{state('initialState', x0, y, 0, v)}"
                f"<trajectory>{traj}</trajectory></obstacle>")
    return (f'<?xml version="1.0" encoding="utf-8"?>\n<commonRoad timeStepSize="{dt}" commonRoadVersion="2018b" '
            f'author="test" affiliation="test" source="test" tags="interstate" benchmarkID="ZAM_Test-1_1_T-1" '
            f'date="2024-01-01">{lanes}{obs}</commonRoad>\n')


XML_VALUES = ["nan", "inf", "-inf", "1e308", "-1e308", "-1", "0", "abc", "", "1e-320", "99999999999999999999"]


def mutate_xml(path: Path, data: st.DataObject) -> str:
    """One damage to a CommonRoad XML: a number (element text or ``timeStepSize``) replaced by
    a hostile one, an element removed or repeated, or the bytes damaged."""
    import re

    text = path.read_text()
    kind = data.draw(st.sampled_from(["number", "attr", "drop", "repeat", "bytes"]), label="xml")
    if kind == "bytes":
        new, what = mutate_bytes(text.encode(), data, gz=False)
        path.write_bytes(new)
        return what
    if kind == "attr":
        v = data.draw(st.sampled_from(XML_VALUES), label="value")
        path.write_text(text.replace('timeStepSize="0.1"', f'timeStepSize="{v}"'))
        return f"timeStepSize={v!r}"
    spans = [m.span(1) for m in re.finditer(r">(-?[0-9.]+)<", text)]
    if kind == "number":
        a, b = spans[data.draw(st.integers(0, len(spans) - 1), label="at")]
        v = data.draw(st.sampled_from(XML_VALUES), label="value")
        path.write_text(text[:a] + v + text[b:])
        return f"number {text[a:b]} at {a} -> {v!r}"
    tags = [m for m in re.finditer(r"<(point|state|lanelet|obstacle|shape|position|time|velocity|orientation)\b.*?</\1>",
                                   text, flags=re.S)]
    m = tags[data.draw(st.integers(0, len(tags) - 1), label="element")]
    new = text[:m.start()] + (m.group(0) * 2 if kind == "repeat" else "") + text[m.end():]
    path.write_text(new)
    return f"{kind} <{m.group(1)}> at {m.start()}"


def _make_xml(folder: Path) -> Path:
    path = folder / "scenario.xml"
    path.write_text(commonroad_xml())
    return path


def _load_xml(path: Path):
    from adv3d_runner.scene.commonroad import import_commonroad

    return import_commonroad(path)


def _accept_xml(scene, folder: Path) -> None:
    from adv3d_runner.scene.schema import load_scene, save_scene, scene_equal

    save_scene(scene, folder / "imported.json.gz")  # validated before writing
    assert scene_equal(load_scene(folder / "imported.json.gz"), scene)
    assert scene.frames >= 1 and np.isfinite(scene.ego_poses()).all()


CONTRACTS: dict[str, Contract] = {c.name: c for c in [
    Contract("scene.json", lambda f: _make_scene(f, False), _json_mutator(), _load_scene, _accept_scene),
    Contract("scene.json.gz", lambda f: _make_scene(f, True), _json_mutator(gz=True), _load_scene, _accept_scene),
    Contract("replay.json.gz", _make_replay, _json_mutator(gz=True), _load_replay, _accept_replay),
    Contract("replay-v2.json.gz", _make_replay_v2, _json_mutator(gz=True), _load_replay, _accept_replay),
    Contract("replay.points.npz", _make_points, mutate_npz, _load_points, _accept_points),
    Contract("library.json", _make_library, _json_mutator(), _load_library, _accept_library),
    Contract("shape_space.npz", _make_space, lambda p, d: mutate_npz(p, d, _rehash_space), _load_space, _accept_space),
    Contract("detector/config.json", _make_model("detector"), _json_mutator(), _load_detector, _accept_model),
    Contract("predictor/config.json", _make_model("predictor"), _json_mutator(), _load_predictor, _accept_model),
    Contract("occupancy/config.json", _make_model("occupancy"), _json_mutator(), _load_occupancy, _accept_model),
    Contract("run.json", _make_run("run.json"), _json_mutator(), _load_run, _accept_run),
    Contract("queries.jsonl", _make_run("queries.jsonl"), _json_mutator(lines=True), _load_run, _accept_run),
    Contract("summary.json", _make_run("summary.json"), _json_mutator(), _load_run, _accept_run),
    Contract("realism_reference.npz", _make_reference, mutate_npz, _load_reference, _accept_reference),
    Contract("commonroad.xml", _make_xml, mutate_xml, _load_xml, _accept_xml),
]}


class Pristine:
    """A contract's valid files, made once; each case works on a fresh copy of the folder."""

    def __init__(self, contract: Contract, root: Path):
        self.contract = contract
        self.root = root
        self.src = root / "pristine"
        self.src.mkdir(parents=True)
        self.file = contract.make(self.src).relative_to(self.src)
        self.n = 0

    def copy(self) -> Path:
        self.n += 1
        dst = self.root / f"case{self.n}"
        shutil.copytree(self.src, dst, symlinks=True)
        return dst


def _phases(findings: list | None) -> tuple:
    """Collecting findings (bench): generate only, every case counted once; in a test: shrink a
    failure to its simplest form too."""
    return (Phase.generate,) if findings is not None else (Phase.explicit, Phase.generate, Phase.shrink)


def fuzz_contract(name: str, root: Path, max_examples: int, counts: Counter | None = None,
                  findings: list | None = None, seed_only: bool = True, accepted: list | None = None) -> None:
    """Run ``max_examples`` hypothesis cases on contract ``name`` (derandomized: the same cases
    every run), counting outcomes in ``counts``, collecting non-ok outcomes in ``findings`` and
    the descriptions of accepted cases in ``accepted``; raises AssertionError at the first
    finding unless ``findings`` is given."""
    contract = CONTRACTS[name]
    pristine = Pristine(contract, root)
    folder = pristine.copy()  # the untouched files are accepted: errors below are the mutations'
    first = run_case(lambda: contract.load(folder / pristine.file), lambda r: contract.accept(r, folder),
                     folder / pristine.file, "pristine")
    assert first.kind == "accepted", f"{name}: the valid files are not accepted: {first}"

    @settings(max_examples=max_examples, derandomize=seed_only, deadline=None, database=None,
              suppress_health_check=list(HealthCheck), phases=_phases(findings))
    @given(st.data())
    def case(data):
        folder = pristine.copy()
        file = folder / pristine.file
        what = contract.mutate(file, data)
        outcome = run_case(lambda: contract.load(file), lambda r: contract.accept(r, folder), file, what)
        if counts is not None:
            counts[outcome.kind] += 1
        if accepted is not None and outcome.kind == "accepted":
            accepted.append(outcome.case)
        if not outcome.ok:
            if findings is not None:
                findings.append({"contract": name, **outcome.__dict__})
            else:
                raise AssertionError(f"{name}: {outcome.kind} for {outcome.case}: {outcome.message}")
        shutil.rmtree(folder, ignore_errors=True)

    case()


# ----------------------------------------------------------------------------- special files

def special_files(folder: Path) -> dict[str, Path]:
    """Files no mutation makes: a symlink to ``/dev/zero``, a FIFO, a folder, a 300 MiB sparse
    file, a gzip bomb (320 MiB of spaces in ~1.4 MB), a zip bomb (1.1 GiB of zeros in ~1 MB), a
    symlink loop, a dangling symlink."""
    import os

    out = {}
    (folder / "zero.json").symlink_to("/dev/zero")
    out["symlink to /dev/zero"] = folder / "zero.json"
    os.mkfifo(folder / "fifo.json")
    out["FIFO"] = folder / "fifo.json"
    (folder / "dir.json").mkdir()
    out["folder"] = folder / "dir.json"
    with open(folder / "sparse.json", "wb") as fh:
        fh.truncate(300 * 2**20)
    out["300 MiB sparse file"] = folder / "sparse.json"
    chunk = b" " * (32 * 2**20)  # bombs are written in chunks: never 300 MiB in memory
    with gzip.open(folder / "bomb.json.gz", "wb", compresslevel=1) as fh:
        for _ in range(10):
            fh.write(chunk)
    out[f"gzip bomb ({(folder / 'bomb.json.gz').stat().st_size // 1024} kB -> 320 MiB)"] = folder / "bomb.json.gz"
    (folder / "loop.json").symlink_to(folder / "loop.json")
    out["symlink loop"] = folder / "loop.json"
    (folder / "dangling.json").symlink_to(folder / "nowhere.json")
    out["dangling symlink"] = folder / "dangling.json"
    zeros = bytes(32 * 2**20)
    with zipfile.ZipFile(folder / "bomb.npz", "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("a.npy", "w", force_zip64=True) as fh:
            for _ in range(36):
                fh.write(zeros)
    out[f"zip bomb ({(folder / 'bomb.npz').stat().st_size // 1024} kB -> 1.1 GiB)"] = folder / "bomb.npz"
    return out


# ----------------------------------------------------------------------------- CLI numbers

#: (argv before the option, option, bounds of what it accepts): every numeric option of the CLI.
CLI_OPTIONS: list[tuple[list[str], str, tuple[float, float]]] = [
    (["attack", "s.json", "--out", "r"], "--budget", (1, 1e6)),
    (["attack", "s.json", "--out", "r"], "--actors", (1, 64)),
    (["attack", "s.json", "--out", "r"], "--seconds", (5e-324, 3600)),
    (["attack", "s.json", "--out", "r"], "--workers", (1, 256)),
    (["attack", "s.json", "--out", "r"], "--seed", (0, 2**32 - 1)),
    (["attack", "s.json", "--out", "r"], "--n-initial", (1, 1e6)),
    (["simulate", "s.json", "--out", "o"], "--seconds", (5e-324, 3600)),
    (["simulate", "s.json", "--out", "o"], "--seed", (0, 2**32 - 1)),
    (["simulate", "s.json", "--out", "o"], "--start-frame", (0, 1e9)),
    (["lidar", "render", "s.json", "-o", "p.ply"], "--frame", (0, 1e9)),
    (["lidar", "render", "s.json", "-o", "p.ply"], "--seed", (0, 2**32 - 1)),
    (["lidar", "render", "s.json", "-o", "p.ply"], "--extent", (5e-324, 1e4)),
    (["scenes", "generate", "--out", "d"], "--count", (1, 1e9)),
    (["scenes", "generate", "--out", "d"], "--seed", (0, 2**32 - 1)),
    (["scenes", "import-commonroad", "x.xml", "--out", "s.json"], "--seconds", (5e-324, 3600)),
    (["scenes", "import-commonroad", "x.xml", "--out", "s.json"], "--ego", (0, 1e9)),
    (["shapes", "build"], "--resolution", (8, 512)),
    (["shapes", "build"], "--k", (1, 64)),
    (["shapes", "build"], "--truncation", (5e-324, 1)),
    (["demo"], "--seed", (0, 2**32 - 1)),
    (["demo"], "--budget", (1, 1e6)),
    (["demo"], "--seconds", (5e-324, 3600)),
    (["train", "detector"], "--epochs", (1, 1e9)),
    (["train", "detector"], "--lr", (5e-324, 1.8e308)),
    (["train", "detector"], "--resolution", (0.01, 10)),
    (["train", "predictor"], "--modes", (3, 64)),
    (["blender", "render", "--what", "sweep", "--out", "x.png"], "--steps", (1, 100)),
    (["attack", "s.json", "--out", "r", "--shape-model", "vd"], "--vd-bound", (5e-324, 2)),
    (["attack", "s.json", "--out", "r"], "--max-mahalanobis", (5e-324, 1e6)),
    (["attack", "s.json", "--out", "r"], "--realism-weight", (0, 1e6)),
    (["train", "detector"], "--scenes", (1, 800_000)),
    (["train", "occupancy"], "--scenes", (1, 800_000)),
    (["train", "predictor"], "--real-weight", (1, 1000)),
]
CLI_TEXT = st.one_of(
    st.sampled_from(["nan", "NaN", "inf", "-inf", "1e400", "-1", "0", "-0", "1", "2", "1.5", "", " ", "abc",
                     "0x10", "1e3", "99999999999999999999999", "-1e-300", "3600", "3600.0001", "4294967296"]),
    st.integers(-2**70, 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)


def cli_case(argv: list[str], option: str, text: str, bounds: tuple[float, float]) -> Outcome:
    """Parse one command line with a hostile value: a one-line usage error (exit code 2), or a
    value that is finite and within ``bounds``."""
    import contextlib

    from adv3d_runner.cli import build_parser

    err = io.StringIO()
    case = f"{' '.join(argv[:2])} {option} {text!r}"
    try:
        with contextlib.redirect_stderr(err):
            args = build_parser().parse_args(argv + [f"{option}={text}"])
    except SystemExit as exc:
        msg = err.getvalue().strip()
        if exc.code == 2 and msg and "\n" not in msg and option in msg:
            return Outcome("error", case, msg)
        return Outcome("vague", case, f"exit {exc.code}: {msg}")
    value = getattr(args, option.lstrip("-").replace("-", "_"))
    lo, hi = bounds
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and lo <= value <= hi:
        return Outcome("accepted", case)
    return Outcome("bad-accept", case, f"parsed {value!r}")


def fuzz_cli(max_examples: int, counts: Counter | None = None, findings: list | None = None,
             accepted: list | None = None) -> None:
    """hypothesis over every numeric option of the CLI (:data:`CLI_OPTIONS`)."""

    @settings(max_examples=max_examples, derandomize=True, deadline=None, database=None,
              suppress_health_check=list(HealthCheck), phases=_phases(findings))
    @given(st.sampled_from(CLI_OPTIONS), CLI_TEXT)
    def case(option, text):
        outcome = cli_case(option[0], option[1], text, option[2])
        if counts is not None:
            counts[outcome.kind] += 1
        if accepted is not None and outcome.kind == "accepted":
            accepted.append(outcome.case)
        if not outcome.ok:
            if findings is not None:
                findings.append({"contract": "cli", **outcome.__dict__})
            else:
                raise AssertionError(f"cli: {outcome.kind} for {outcome.case}: {outcome.message}")

    case()
