"""The shared typed readers (``adv3d_runner.validate``): JSON paths, messages, npz members."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.validate import Arrays, Node, check_header, describe, read_npz, shape_text


def _err(fn) -> FileFormatError:
    with pytest.raises(FileFormatError) as info:
        fn()
    return info.value


def doc(value, file="f.json") -> Node:
    return Node(value, "$", file)


# ------------------------------------------------------------------ paths and the message format

def test_message_names_file_json_path_expected_and_got():
    d = doc({"actors": [{"track": {"x": [1.0, 2.0, float("nan")]}}]}, "scenes/s.json")
    e = _err(lambda: d["actors"][0]["track"]["x"].numbers())
    assert (e.path, e.field, e.expected) == ("scenes/s.json", "$.actors[0].track.x[2]", "a finite number")
    assert str(e) == "scenes/s.json: $.actors[0].track.x[2]: expected a finite number (got nan)"


def test_missing_field_and_wrong_container():
    d = doc({"map": {"lanes": []}, "id": 3})
    assert str(_err(lambda: d["source"])) == "f.json: $.source: expected a value (field is missing)"
    assert _err(lambda: d["id"]["x"]).field == "$.id"  # not an object: the parent is named
    e = _err(lambda: d["map"]["lanes"].objects("a non-empty list of lanes", non_empty=True))
    assert str(e) == "f.json: $.map.lanes: expected a non-empty list of lanes (got 'an empty list')"
    assert _err(lambda: doc({"a": [1, 2]})["a"][5]).field == "$.a"


def test_optional_fields_and_defaults():
    d = doc({"a": None})
    assert d.get("a").value is None and d.get("a").present
    b = d.get("b", 0.8)
    assert (b.value, b.present, b.path) == (0.8, False, "$.b")
    assert b.number(lo=0.0) == 0.8
    assert "a" in d and "b" not in d


def test_unknown_and_required_keys():
    d = doc({"x": 1, "mystery": 2})
    e = _err(lambda: d.check_keys(("x", "y")))
    assert (e.field, e.expected) == ("$.mystery", "no such field (known: x, y)")
    e = _err(lambda: d.check_keys(("x", "y", "mystery"), required=("y",)))
    assert (e.field, e.expected) == ("$.y", "a value (field is missing)")


# ------------------------------------------------------------------ scalars

@pytest.mark.parametrize("value, kwargs, expected", [
    ("0.1", {}, "a number"),
    (True, {}, "a number"),
    (float("inf"), {}, "a finite number"),
    (0.0, {"lo": 0.0, "lo_open": True}, "a number > 0.0"),
    (-1, {"lo": 0.0}, "a number >= 0.0"),
    (7, {"hi": 5}, "a number <= 5"),
    (0, {"lo": 0.0, "lo_open": True, "expected": "a positive size in m"}, "a positive size in m"),
])
def test_number(value, kwargs, expected):
    e = _err(lambda: doc({"v": value})["v"].number(**kwargs))
    assert (e.field, e.expected, e.got) == ("$.v", expected, value)


def test_number_accepts_ints_and_returns_float():
    v = doc({"v": 3})["v"].number(lo=0.0)
    assert v == 3.0 and isinstance(v, float)


@pytest.mark.parametrize("value, kwargs, expected", [
    (2.0, {}, "an integer"),
    (False, {}, "an integer"),
    (-1, {"lo": 0}, "an integer >= 0"),
    (600, {"lo": 8, "hi": 512}, "an integer in [8, 512]"),
    (0, {"lo": 1, "expected": "an integer > 0"}, "an integer > 0"),
])
def test_integer(value, kwargs, expected):
    assert _err(lambda: doc({"v": value})["v"].integer(**kwargs)).expected == expected


def test_strings_booleans_and_patterns():
    d = doc({"s": "", "k": "hedge", "b": "yes", "c": "Sedan!", "n": None})
    assert _err(lambda: d["s"].string()).expected == "a non-empty string"
    assert d["s"].string(empty=True) == ""
    assert _err(lambda: d["k"].string(choices=("concrete", "guardrail"))).expected == "one of ['concrete', 'guardrail']"
    assert _err(lambda: d["b"].boolean()).expected == "true or false"
    assert _err(lambda: d["c"].string(pattern=re.compile(r"^[a-z]+$"), expected="a lower-case name")).expected \
        == "a lower-case name"
    assert d["n"].string(nullable=True) is None
    assert _err(lambda: d["n"].string()).expected == "a non-empty string"


def test_unique():
    seen: set = set()
    d = doc({"ids": [1, 2, 1]})
    items = d["ids"].items()
    for node in items[:2]:
        node.unique(node.integer(), seen, "actor id")
    e = _err(lambda: items[2].unique(items[2].integer(), seen, "actor id"))
    assert (e.field, e.expected, e.got) == ("$.ids[2]", "a unique actor id", 1)


def test_rel_path():
    for bad in ("../x.glb", "/abs/x.glb", "a\\b.glb"):
        e = _err(lambda: doc({"f": bad})["f"].rel_path(inside="the library folder"))
        assert e.expected == "a relative POSIX path inside the library folder (no '..', no absolute path)"
    assert doc({"f": "p/a.glb"})["f"].rel_path() == "p/a.glb"


# ------------------------------------------------------------------ numeric lists and arrays

def test_numbers_flags_points():
    d = doc({"x": [1, 2, True], "y": [1.0], "v": [1, 0, 2], "p": [[0, 0], [1, 2, 3]]})
    assert _err(lambda: d["x"].numbers()).field == "$.x[2]"
    e = _err(lambda: d["y"].numbers(length=3))
    assert (e.expected, e.got) == ("a list of 3 numbers", "1 item")
    assert _err(lambda: d["v"].flags(3)).field == "$.v[2]"
    assert _err(lambda: d["p"].points()).field == "$.p[1]"
    out = doc({"x": [1, 2.5]})["x"].numbers(lo=0.0)
    assert out.dtype == np.float64 and out.tolist() == [1.0, 2.5]


def test_nested_array_shapes_nulls_and_empty():
    d = doc({"boxes": [[1, 2, 3]], "s": [1.0, None], "e": [], "t": [[0.0, float("nan")]]})
    e = _err(lambda: d["boxes"].array((None, 5)))
    assert (e.expected, e.got) == ("an array of shape (N, 5) of numbers", "1 item")
    assert np.isnan(d["s"].array((2,), nullable=True)[1])
    assert _err(lambda: d["s"].array((2,))).field == "$.s[1]"
    assert d["e"].array((None, 5)).shape == (0, 5)   # an empty list stands for (0, 5)
    assert _err(lambda: d["e"].array((3,))).field == "$.e"  # but not for a fixed length 3
    assert _err(lambda: d["t"].array((1, 2))).field == "$.t[0][1]"


def test_describe_and_shape_text():
    assert describe([]) == "an empty list" and describe([1]) == "1 item" and describe([1, 2]) == "2 items"
    assert describe("x") == "x"
    assert shape_text((None, 5)) == "(N, 5)" and shape_text((3,)) == "(3)" and shape_text(("P", 3)) == "(P, 3)"


# ------------------------------------------------------------------ header

def test_check_header():
    assert check_header(doc({"format": "adv3d-scene", "version": 1}), "adv3d-scene", (1,)) == 1
    e = _err(lambda: check_header(doc({"format": "other", "version": 1}), "adv3d-scene", (1,)))
    assert (e.field, e.expected, e.got) == ("$.format", '"adv3d-scene"', "other")
    e = _err(lambda: check_header({"format": "adv3d-scene", "version": 9}, "adv3d-scene", (1,), file="f.json"))
    assert (e.path, e.field, e.expected) == ("f.json", "$.version", "one of [1]")
    assert _err(lambda: check_header(doc({"format": "x", "version": True}), "x", (1,))).field == "$.version"
    assert _err(lambda: check_header(doc([1]), "x", (1,))).field == "$"
    meta = Node({"format": "x", "version": 2}, "$.meta", "s.npz")
    assert _err(lambda: check_header(meta, "x", (1,))).field == "$.meta.version"


# ------------------------------------------------------------------ npz

def test_arrays_dtype_shape_finite_and_header():
    z = Arrays({"format": np.array("fmt"), "version": np.array(1, np.int64),
                "mean": np.zeros(4, np.float64), "xyz": np.zeros((5, 2), np.int16),
                "bad": np.array([1.0, np.nan], np.float32), "meta": np.array('{"k": 3}')}, "s.npz")
    z.header("fmt", 1)
    e = _err(lambda: z.array("mean", dtype=np.float32, shape=(4,)))
    assert (e.field, e.expected, e.got) == ("$.mean", "float32 array of shape (4)", "float64 (4,)")
    e = _err(lambda: z.array("xyz", dtype=np.int16, shape=("P", 3)))
    assert (e.expected, e.got) == ("int16 array of shape (P, 3)", "int16 (5, 2)")
    assert _err(lambda: z.array("bad", dtype=np.float32, finite=True)).expected == "finite values"
    e = _err(lambda: z.array("missing"))
    assert (e.field, e.expected) == ("$.missing", "array member missing.npy")
    assert _err(lambda: z.header("fmt", 2)).field == "$.version"
    assert _err(lambda: z.header("other", 1)).field == "$.format"
    assert z.json("meta")["k"].integer() == 3
    assert _err(lambda: z.json("meta")["k"].string()).field == "$.meta.k"


def test_read_npz_refuses_missing_corrupt_pickled_and_plain_npy(tmp_path):
    e = _err(lambda: read_npz(tmp_path / "none.npz", "points file"))
    assert (e.field, e.expected, e.got) == ("$", "an existing points file", "file not found")
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not a zip")
    assert _err(lambda: read_npz(tmp_path / "junk.npz", "points file")).field == "$"
    np.savez(tmp_path / "obj.npz", a=np.array([{"x": 1}], dtype=object))  # needs pickle
    assert "pickled" in _err(lambda: read_npz(tmp_path / "obj.npz", "points file")).expected
    np.save(tmp_path / "one.npy", np.zeros(3))
    assert _err(lambda: read_npz(tmp_path / "one.npy", "points file")).got == "a single .npy array"
    np.savez(tmp_path / "ok.npz", a=np.arange(3))
    assert read_npz(tmp_path / "ok.npz", "points file").members["a"].tolist() == [0, 1, 2]


# ------------------------------------------------------------------ layering

def test_validate_is_ground_floor():
    """validate imports only errors and fileio from the project (every layer may use it)."""
    src = Path(__file__).resolve().parent.parent / "adv3d_runner" / "validate.py"
    project = set()
    for node in ast.walk(ast.parse(src.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            project.add(node.module)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("adv3d_runner"):
            project.add(node.module)
    assert project <= {"errors", "fileio"}


def test_old_helper_families_are_gone():
    root = Path(__file__).resolve().parent.parent / "adv3d_runner"
    text = {p: p.read_text() for p in root.rglob("*.py")}
    for pattern in (r"class _V\b", r"class _Check\b", r"def _require\(", r"def _fail\(", r"def check_header\("):
        hits = [str(p.relative_to(root)) for p, t in text.items() if re.search(pattern, t)]
        assert hits == (["validate.py"] if "check_header" in pattern else []), (pattern, hits)


def test_read_npz_steps_names_the_file_for_a_corrupt_deflate_stream(tmp_path):
    """A flipped byte inside a compressed member (zlib: "invalid distance too far back"), found
    by the slow fuzz run on a replay's points file: a FileFormatError, not a zlib.error."""
    from adv3d_runner.errors import FileFormatError
    from adv3d_runner.progress import run_steps
    from adv3d_runner.validate import read_npz_steps

    path = tmp_path / "replay.points.npz"
    np.savez_compressed(path, xyz_cm=np.tile(np.arange(3000, dtype=np.int16), 20))
    blob = bytearray(path.read_bytes())
    start = blob.index(b"xyz_cm.npy") + len("xyz_cm.npy") + 200  # inside the deflate data
    hits = 0
    for k in range(start, start + 40):
        bad = blob.copy()
        bad[k] ^= 0xFF
        path.write_bytes(bytes(bad))
        try:
            run_steps(read_npz_steps(path, "points file"))
        except FileFormatError as exc:
            assert "replay.points.npz" in str(exc)
            hits += 1
    assert hits > 0


def test_optional_contract_absent_is_none_and_a_bad_header_names_the_file(tmp_path):
    import json

    from adv3d_runner.errors import FileFormatError
    from adv3d_runner.validate import read_optional_contract

    path = tmp_path / "avoidability.json"
    assert read_optional_contract(path, "adv3d-avoidability", (1,)) is None
    path.write_text(json.dumps({"format": "adv3d-avoidability", "version": 1, "scenes": {}}))
    assert read_optional_contract(path, "adv3d-avoidability", (1,)).value["scenes"] == {}
    path.write_text(json.dumps({"format": "adv3d-failure-rate", "version": 1}))
    with pytest.raises(FileFormatError, match=r"avoidability\.json.*format"):
        read_optional_contract(path, "adv3d-avoidability", (1,))
