"""The stepwise (generator) forms of long runner work that the Blender add-on drives from a timer:
each gives exactly what the one-call form gives, in short steps, with the same errors."""
from __future__ import annotations

import gzip
import json
import time

import numpy as np
import pytest

from adv3d_runner.errors import FileFormatError
from adv3d_runner.fileio import read_json, read_json_steps
from adv3d_runner.progress import progress, relay, run_steps, span
from adv3d_runner.validate import read_npz, read_npz_steps


def _steps(gen) -> tuple[object, int]:
    n = 0
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value, n
        n += 1


def test_run_steps_relay_span():
    def inner():
        yield (0.5,)
        yield
        return 7

    assert run_steps(inner()) == 7
    outer = relay(inner(), ("x", 1))
    assert [next(outer), next(outer)] == [("x", 1), ("x", 1)]
    assert list(span(inner(), 0.2, 0.4, "m")) == [(0.30000000000000004, "m"), (0.2, "m")]


DOCS = [
    {"format": "x", "outputs": [{"a": [1, 2.5, None]}, {"b": "é"}] * 50, "empty": [], "n": 3, "nested": {"l": [1]}},
    {"dup": 1, "dup": 2, "f": [-0.0, 1e308], "s": "a,b]}"},  # noqa: F601  (json keeps the last)
    [1, 2, {"x": 3}],  # not an object: one json.loads call
    {},
    "text",
]


@pytest.mark.parametrize("gz", [False, True])
@pytest.mark.parametrize("doc", DOCS)
def test_read_json_steps_equals_read_json(tmp_path, doc, gz):
    text = json.dumps(doc, indent=1)
    if isinstance(doc, dict) and "dup" in doc:
        text = '{"dup": 1, "dup": 2, "f": [-0.0, 1e308], "s": "a,b]}"}'
    path = tmp_path / ("d.json.gz" if gz else "d.json")
    path.write_bytes(gzip.compress(text.encode()) if gz else text.encode())
    got, n = _steps(read_json_steps(path, step_bytes=64))
    want = read_json(path)
    assert json.dumps(got, sort_keys=False) == json.dumps(want, sort_keys=False)
    assert list(got) == list(want) if isinstance(want, dict) else got == want
    if isinstance(doc, dict) and doc.get("outputs"):
        assert n > 20  # parsed in many small steps


@pytest.mark.parametrize("bad", ['{"a": 1,}', '{"a" 1}', '{"a": [1 2]}', '{"a": 1} x', '{1: 2}', "\ufeff{}",
                                 '{"a": [1, 2'])
def test_read_json_steps_rejects_what_json_rejects(tmp_path, bad):
    path = tmp_path / "bad.json"
    path.write_text(bad)
    with pytest.raises(FileFormatError, match="bad.json"):
        read_json(path)
    with pytest.raises(FileFormatError, match="bad.json"):
        run_steps(read_json_steps(path))


def test_read_json_steps_bad_gzip(tmp_path):
    path = tmp_path / "cut.json.gz"
    path.write_bytes(gzip.compress(b'{"a": [1, 2, 3]}')[:-6])
    with pytest.raises(FileFormatError, match="cut.json.gz"):
        run_steps(read_json_steps(path))
    path.write_bytes(b"not gzip at all")
    with pytest.raises(FileFormatError, match="gzip"):
        run_steps(read_json_steps(path))


def test_read_npz_steps_equals_read_npz(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {"xyz": rng.integers(-3000, 3000, (5000, 3)).astype(np.int16), "f": rng.random(77),
              "fortran": np.asfortranarray(rng.random((30, 4))), "scalar": np.array(3, np.int64),
              "text": np.array("adv3d-replay-points"), "empty": np.zeros((0, 5), np.float32)}
    for compress in (np.savez, np.savez_compressed):
        path = tmp_path / f"{compress.__name__}.npz"
        compress(path, **arrays)
        got, n = _steps(read_npz_steps(path, "test file", step_bytes=1000))
        want = read_npz(path, "test file")
        assert n > 20 and sorted(got.members) == sorted(want.members)
        for k, v in want.members.items():
            assert got.members[k].dtype == v.dtype and got.members[k].shape == v.shape
            np.testing.assert_array_equal(got.members[k], v)


def test_read_npz_steps_errors_match(tmp_path):
    np.save(tmp_path / "single.npy", np.zeros(3))
    (tmp_path / "single.npz").write_bytes((tmp_path / "single.npy").read_bytes())
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not a zip")
    np.savez(tmp_path / "obj.npz", o=np.array([{"a": 1}], dtype=object))
    for name in ("single.npz", "junk.npz", "obj.npz", "missing.npz"):
        with pytest.raises(FileFormatError) as a:
            read_npz(tmp_path / name, "test file")
        with pytest.raises(FileFormatError) as b:
            run_steps(read_npz_steps(tmp_path / name, "test file"))
        assert str(a.value) == str(b.value)
    good = tmp_path / "cut.npz"
    np.savez_compressed(good, x=np.arange(100000))
    good.write_bytes(good.read_bytes()[:-2000])  # cut short: not a zip any more
    with pytest.raises(FileFormatError, match="cut.npz"):
        run_steps(read_npz_steps(good, "test file"))


def test_replay_loads_the_same_in_steps(tmp_path):
    """load_replay is the stepwise loader driven to the end; its pieces stay short."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_blender_review import make_replay  # (no bpy needed to make one)

    from adv3d_runner.sim.replay import load_replay, load_replay_steps, replay_equal, save_replay

    replay = make_replay(seed=1, frames=60)
    path = save_replay(replay, tmp_path / "replay.json.gz")
    gen = load_replay_steps(path)
    worst, fractions = 0.0, []
    while True:
        t = time.perf_counter()
        try:
            step = next(gen)
        except StopIteration as stop:
            stepped = stop.value
            break
        worst = max(worst, time.perf_counter() - t)
        fractions.append(step[0])
    assert replay_equal(stepped, load_replay(path)) and replay_equal(stepped, replay)
    assert fractions == sorted(fractions) and worst < 0.5


def test_sdf_steps_are_bit_identical_to_one_call():
    """Chunking the per-point libigl queries changes nothing (each point's value is its own)."""
    import trimesh

    from adv3d_runner.shapes.sdf import grid_for_dimensions, sdf_volume, sdf_volume_steps

    body = trimesh.creation.box(extents=(4.0, 1.8, 0.8))
    body.apply_translation((0, 0, 0.4))
    cabin = trimesh.creation.box(extents=(2.0, 1.6, 0.6))
    cabin.apply_translation((-0.3, 0, 1.05))
    mesh = trimesh.util.concatenate([body, cabin])  # overlapping parts: boundary pieces matter
    grid = grid_for_dimensions([(4.0, 1.8, 1.35)], 24)
    one = run_steps(sdf_volume_steps(mesh.vertices, mesh.faces, grid, chunk=10**9))
    many, n = _steps(sdf_volume_steps(mesh.vertices, mesh.faces, grid, chunk=1000))
    assert n > 20
    assert one.tobytes() == many.tobytes() == sdf_volume(mesh.vertices, mesh.faces, grid).tobytes()


def test_progress_bars_are_optional(monkeypatch):
    """Without tqdm (a stock Blender) a progress bar is the plain iterable."""
    import builtins

    real = builtins.__import__

    def no_tqdm(name, *a, **kw):
        if name.startswith("tqdm"):
            raise ImportError("no tqdm here")
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", no_tqdm)
    items = [1, 2, 3]
    assert progress(items, desc="x") is items
