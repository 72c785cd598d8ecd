"""Every finding of the hostile-input review (docs/reliability.md), reproduced and fixed: nothing escapes its folder,
nothing the user had is lost, every bad input ends in one line naming the file and field.

The property-based counterpart over every contract is ``tests/test_fuzz.py``."""
from __future__ import annotations

import gzip
import json
import os
import shutil
from pathlib import Path

import pytest
from attack_synthetic import SyntheticEvaluator
from fuzz_contracts import SIGN_OBJ, _make_replay, commonroad_xml, small_scene_doc

from adv3d_runner.attack.config import AttackConfig
from adv3d_runner.attack.driver import check_outcome, run_attack
from adv3d_runner.attack.journal import Journal, read_run, record_checksum, strip_times
from adv3d_runner.cli import main
from adv3d_runner.errors import ConfigError, FileFormatError, RunFailedError
from adv3d_runner.fileio import is_safe_name, read_json, rel_path_problem, resolve_inside, write_json

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "highway" / "highway-benchmark-000000.json.gz"


def cli(capsys, *argv) -> tuple[int, str]:
    """(exit code, stderr) of ``adv3d ARGV`` run in-process; usage errors exit 2."""
    try:
        rc = main(["-q", *map(str, argv)])
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def one_error_line(err: str) -> str:
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def scene_file(tmp_path: Path, name: str = "scene.json", **changes) -> Path:
    doc = small_scene_doc()
    doc.update(changes)
    (tmp_path / "sign.obj").write_text(SIGN_OBJ)
    path = tmp_path / name
    write_json(path, doc)
    return path


# ------------------------------------------------------------------ the shared name / path rule

@pytest.mark.parametrize("text, ok", [("highway-benchmark-000000", True), ("commonroad-USA_US101-3_3_T-1", True),
                                      ("a.b", True), ("../../x", False), (".hidden", False), ("a/b", False),
                                      ("", False), ("x" * 129, False), ("a\\b", False), (None, False)])
def test_safe_name(text, ok):
    assert is_safe_name(text) == ok


@pytest.mark.parametrize("text", ["../x", "a/../../b", "/etc/passwd", "~/x", "a\\b", "", "x\x00y"])
def test_rel_path_problem(text):
    assert rel_path_problem(text)


def test_resolve_inside_follows_symlinks(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "ok.txt").write_text("x")
    (tmp_path / "in" / "out").symlink_to(tmp_path)  # a folder link leading out
    (tmp_path / "in" / "inner").symlink_to(tmp_path / "in" / "ok.txt")  # stays inside
    assert resolve_inside(tmp_path / "in", "ok.txt") == tmp_path / "in" / "ok.txt"
    assert resolve_inside(tmp_path / "in", "inner").name == "inner"
    for bad in ("out/secret", "../x", "/etc/passwd"):
        with pytest.raises(FileFormatError, match="inside"):
            resolve_inside(tmp_path / "in", bad, file="f.json", field="$.file")


# ------------------------------------------------------------------ 1. nothing escapes its folder

def test_asset_id_and_pack_cannot_leave_the_library(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    (src / "car.obj").write_text(SIGN_OBJ)
    (src / "License.txt").write_text("CC0 1.0 creativecommons.org/publicdomain/zero/1.0/")
    lib = tmp_path / "a" / "b" / "library.json"
    for extra, code in ((["--id", "../../outside"], 2), (["--id", "/abs"], 2), (["--source-pack", "../.."], 1)):
        rc, err = cli(capsys, "assets", "import", src / "car.obj", "--class", "sedan", "--library", lib, *extra)
        assert rc == code and "outside" not in str(list(tmp_path.rglob("*.glb")))
        one_error_line(err)
    assert not list(tmp_path.rglob("*.glb"))


def test_scene_id_that_is_a_path_is_refused_before_anything_is_written(tmp_path, capsys):
    bad = scene_file(tmp_path, id="../../../x")
    rc, err = cli(capsys, "attack", bad, "--budget", 1, "--seconds", 0.2, "--autonomy", "oracle",
                  "--out", tmp_path / "run")
    assert rc == 1 and "scene.json: $.id" in one_error_line(err)
    assert not (tmp_path / "run").exists() and not (tmp_path.parent / "x").exists()
    # the driver checks the output folder of any evaluator's scene id too
    class PathId(SyntheticEvaluator):
        def scene_id(self, ref):
            return "../../escaped"
    with pytest.raises(FileFormatError, match="inside the run folder"):
        run_attack(AttackConfig(["synthetic:peak"], budget=2), tmp_path / "r2", evaluator=PathId, show_progress=False)
    assert not (tmp_path / "r2").exists()


@pytest.mark.parametrize("file", ["../sign.obj", "/etc/passwd", "a/../../sign.obj"])
def test_background_mesh_path_must_stay_in_the_scene_folder(tmp_path, file):
    from adv3d_runner.scene.schema import load_scene

    doc = small_scene_doc()
    doc["background"]["meshes"][0]["file"] = file
    write_json(tmp_path / "s.json", doc)
    with pytest.raises(FileFormatError, match=r"\$\.background\.meshes\[0\]\.file"):
        load_scene(tmp_path / "s.json")


def test_background_mesh_symlink_leading_out_is_refused(tmp_path):
    from adv3d_runner.scene.background import background_mesh
    from adv3d_runner.scene.schema import load_scene

    (tmp_path / "outside.obj").write_text(SIGN_OBJ)
    (tmp_path / "scene").mkdir()
    path = scene_file(tmp_path / "scene")
    (tmp_path / "scene" / "sign.obj").unlink()
    (tmp_path / "scene" / "sign.obj").symlink_to(tmp_path / "outside.obj")
    with pytest.raises(FileFormatError, match="symlink leading out"):
        background_mesh(load_scene(path), scene_dir=path.parent)


def test_replay_points_and_actor_meshes_stay_in_the_replay_folder(tmp_path):
    from adv3d_runner.sim.replay import actor_mesh_path, load_replay

    path = _make_replay(tmp_path)
    doc = read_json(path)
    for field, value in (("points", "../replay.points.npz"), ("points", "/etc/passwd")):
        write_json(path, {**doc, field: value})
        with pytest.raises(FileFormatError, match=r"\$\.points"):
            load_replay(path)
    bad = json.loads(json.dumps(doc))
    bad["actors"][0]["mesh"] = "../../actor1.glb"
    write_json(path, bad)
    with pytest.raises(FileFormatError, match=r"\$\.actors\[0\]\.mesh"):
        load_replay(path)
    # a symlinked points file or mesh leading out of the folder
    write_json(path, doc)
    (tmp_path / "out").mkdir()
    shutil.move(tmp_path / "replay.points.npz", tmp_path / "out" / "p.npz")
    (tmp_path / "replay.points.npz").symlink_to(tmp_path / "out" / "p.npz")
    sub = tmp_path / "sub"
    sub.mkdir()
    for name in ("replay.json.gz", "replay.points.npz", "actor1.glb"):
        (sub / name).symlink_to(tmp_path / name)
    with pytest.raises(FileFormatError, match="symlink leading out"):
        load_replay(sub / "replay.json.gz")
    replay = load_replay(sub / "replay.json.gz", points=False)
    with pytest.raises(FileFormatError, match="symlink leading out"):
        actor_mesh_path(sub / "replay.json.gz", replay, 0)


def test_library_mesh_path_is_resolved_inside_the_library(tmp_path):
    from fuzz_contracts import _make_library

    from adv3d_runner.shapes.library import load_library

    path = _make_library(tmp_path)
    doc = read_json(path)
    doc["assets"][0]["file"] = "../outside.glb"
    write_json(path, doc)
    with pytest.raises(FileFormatError, match=r"\$\.assets\[0\]\.file"):
        load_library(path)
    doc["assets"][0]["file"] = "pack/box.glb"
    write_json(path, doc)
    (tmp_path / "box.glb").write_bytes((tmp_path / "pack" / "box.glb").read_bytes())
    (tmp_path / "pack" / "box.glb").unlink()
    (tmp_path / "lib").mkdir()
    shutil.move(tmp_path / "pack", tmp_path / "lib" / "pack")
    shutil.move(path, tmp_path / "lib" / "library.json")
    (tmp_path / "lib" / "pack" / "box.glb").symlink_to(tmp_path / "box.glb")
    library = load_library(tmp_path / "lib" / "library.json")
    with pytest.raises(FileFormatError, match="symlink leading out"):
        library.path_of("pack.box")


def test_addon_follows_only_summary_paths_inside_the_run(tmp_path):
    pytest.importorskip("bpy")
    from blender_addon.ops_review import find_replays

    run = tmp_path / "run"
    (run / "scenes" / "s" / "closed").mkdir(parents=True)
    (tmp_path / "evil.json.gz").write_bytes(b"x")
    (run / "scenes" / "s" / "closed" / "replay.json.gz").write_bytes(b"x")
    write_json(run / "summary.json", {"scenes": {"s": {"modes": {"closed": {"files": {"replay": "../evil.json.gz"}}}}}})
    found = find_replays(run)
    assert [p for _, p in found] == [run / "scenes" / "s" / "closed" / "replay.json.gz"]


# ------------------------------------------------------------------ 3. nothing the user had is lost

def test_attack_out_into_a_folder_that_is_not_a_run_is_refused(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "summary.json").write_text('{"my": "data"}')
    rc, err = cli(capsys, "attack", SCENE, "--budget", 1, "--seconds", 0.2, "--autonomy", "oracle", "--out", mine)
    assert rc == 1 and "not an adv3d run" in one_error_line(err)
    assert (mine / "summary.json").read_text() == '{"my": "data"}' and sorted(os.listdir(mine)) == ["summary.json"]
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ConfigError, match="not a folder"):
        run_attack(AttackConfig(["synthetic:peak"], budget=2), tmp_path / "afile", evaluator=SyntheticEvaluator,
                   show_progress=False)
    (tmp_path / "empty").mkdir()  # an empty folder is fine
    run_attack(AttackConfig(["synthetic:peak"], budget=2), tmp_path / "empty", evaluator=SyntheticEvaluator,
               show_progress=False)
    assert (tmp_path / "empty" / "run.json").exists()


def test_broken_mesh_under_an_existing_id_keeps_the_asset(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    box = ("v -2 -1 0\nv 2 -1 0\nv 2 1 0\nv -2 1 0\nv -2 -1 1.5\nv 2 -1 1.5\nv 2 1 1.5\nv -2 1 1.5\n"
           "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n")
    (src / "box.obj").write_text(box)
    (src / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")      # no height
    (src / "degen.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")     # no triangle survives cleaning
    (src / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (src / "License.txt").write_text("CC0 1.0 creativecommons.org/publicdomain/zero/1.0/")
    lib = tmp_path / "lib" / "library.json"
    common = ["--class", "sedan", "--id", "src.box", "--up", "+z", "--forward", "+x", "--library", lib]
    assert cli(capsys, "assets", "import", src / "box.obj", *common)[0] == 0
    before = {p: p.read_bytes() for p in sorted(lib.parent.rglob("*")) if p.is_file()}
    for broken in ("flat.obj", "degen.obj", "nan.obj"):
        rc, err = cli(capsys, "assets", "import", src / broken, *common)
        assert rc == 1, broken
        one_error_line(err)
        assert {p: p.read_bytes() for p in sorted(lib.parent.rglob("*")) if p.is_file()} == before, broken


def test_commonroad_zero_time_step_keeps_the_existing_scene(tmp_path, capsys):
    good = tmp_path / "s.xml"
    good.write_text(commonroad_xml())
    out = tmp_path / "scene.json.gz"
    assert cli(capsys, "scenes", "import-commonroad", good, "--out", out)[0] == 0
    before = out.read_bytes()
    for dt in ("0", "nan", "-0.1", "inf"):
        (tmp_path / "bad.xml").write_text(commonroad_xml(dt=dt))
        rc, err = cli(capsys, "scenes", "import-commonroad", tmp_path / "bad.xml", "--out", out)
        assert rc == 1 and "timeStepSize" in one_error_line(err), dt
        assert out.read_bytes() == before


@pytest.mark.parametrize("value", ["nan", "1e308", "-inf", "abc"])
def test_commonroad_bad_coordinates(tmp_path, capsys, value):
    text = commonroad_xml().replace("<x>100.0</x>", f"<x>{value}</x>", 1)
    (tmp_path / "bad.xml").write_text(text)
    rc, err = cli(capsys, "scenes", "import-commonroad", tmp_path / "bad.xml", "--out", tmp_path / "o.json")
    assert rc == 1 and "bad.xml" in one_error_line(err) and not (tmp_path / "o.json").exists()


# ------------------------------------------------------------------ tracebacks that were

def test_damaged_json_files_are_one_line_errors(tmp_path, capsys):
    raw = gzip.compress(json.dumps(small_scene_doc()).encode(), mtime=0)
    (tmp_path / "corrupt.json.gz").write_bytes(raw[:30] + bytes(b ^ 0x5A for b in raw[30:60]) + raw[60:])
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (tmp_path / "zero.json").symlink_to("/dev/zero")
    for name in ("corrupt.json.gz", "deep.json", "zero.json"):
        rc, err = cli(capsys, "simulate", tmp_path / name, "--out", tmp_path / "o")
        assert rc == 1 and name in one_error_line(err)
    rc = main(["-q", "scenes", "validate", str(tmp_path / "zero.json"), "--library", "none"])
    assert rc == 1 and "a regular file" in capsys.readouterr().out


def test_scene_without_actors_simulates(tmp_path, capsys):
    path = scene_file(tmp_path, actors=[])
    for autonomy in ("oracle", "A"):
        rc, err = cli(capsys, "simulate", path, "--seconds", 0.3, "--autonomy", autonomy, "--reactive",
                      "--out", tmp_path / autonomy)
        assert rc == 0, err
        assert read_json(tmp_path / autonomy / "metrics.json")["detection"]["n_gt"] == 0


def test_unknown_actor_asset_is_found_by_validate_and_named_by_every_command(tmp_path, capsys):
    doc = small_scene_doc()
    doc["actors"][1]["asset"] = "nope.nope"
    path = tmp_path / "s.json"
    (tmp_path / "sign.obj").write_text(SIGN_OBJ)
    write_json(path, doc)
    assert main(["-q", "scenes", "validate", str(path)]) == 1
    assert "$.actors[1].asset" in capsys.readouterr().out
    assert main(["-q", "scenes", "validate", str(path), "--library", "none"]) == 0  # the contract alone
    capsys.readouterr()
    for argv in (["simulate", path, "--seconds", 0.2, "--autonomy", "oracle", "--out", tmp_path / "o"],
                 ["lidar", "render", path, "-o", tmp_path / "p.ply"]):
        rc, err = cli(capsys, *argv)
        assert rc == 1 and "$.actors[1].asset" in one_error_line(err) and "nope.nope" in err


def test_truncated_points_file(tmp_path):
    from adv3d_runner.sim.replay import load_replay

    path = _make_replay(tmp_path)
    pts = tmp_path / "replay.points.npz"
    pts.write_bytes(pts.read_bytes()[: pts.stat().st_size // 2])
    with pytest.raises(FileFormatError, match="replay.points.npz"):
        load_replay(path)


@pytest.mark.parametrize("argv", [
    ["attack", "s.json", "--seed", "-1", "--out", "r"], ["attack", "s.json", "--n-initial", "-3", "--out", "r"],
    ["attack", "s.json", "--seconds", "nan", "--out", "r"], ["attack", "s.json", "--actors", "0", "--out", "r"],
    ["simulate", "s.json", "--seconds", "nan", "--out", "o"], ["simulate", "s.json", "--seconds", "1e400", "--out", "o"],
    ["lidar", "render", "s.json", "--frame", "-1", "-o", "p.ply"], ["scenes", "generate", "--out", "d", "--count", "0"],
    ["shapes", "decode", "--u", "0.5,nan,0.5", "-o", "x.glb"], ["assets", "import", "x.obj", "--class", "sedan",
                                                                 "--dimensions", "4", "inf", "1"],
])
def test_numeric_arguments_are_one_line_usage_errors(capsys, argv):
    rc, err = cli(capsys, *argv)
    assert rc == 2 and "argument" in one_error_line(err)


# ------------------------------------------------------------------ silent accepts that were

def test_unknown_fields_in_scenes_and_replays_are_refused(tmp_path):
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sim.replay import load_replay

    doc = small_scene_doc()
    doc["actors"][0]["colour"] = "red"
    write_json(tmp_path / "s.json", doc)
    with pytest.raises(FileFormatError, match=r"\$\.actors\[0\]\.colour: expected no such field"):
        load_scene(tmp_path / "s.json")
    path = _make_replay(tmp_path)
    doc = read_json(path)
    doc["outputs"][2]["plan"]["extra"] = 1
    write_json(path, doc)
    with pytest.raises(FileFormatError, match=r"\$\.outputs\[2\]\.plan\.extra"):
        load_replay(path)


def test_every_query_failed_is_an_error_saying_why(tmp_path, capsys, monkeypatch):
    from adv3d_runner.attack import evaluator
    from adv3d_runner.errors import EmptySurfaceError
    from adv3d_runner.shapes.shape_space import ShapeSpace

    def no_surface(self, z, scales=(1.0, 1.0)):
        raise EmptySurfaceError("test: no surface")

    monkeypatch.setattr(ShapeSpace, "decode_latent", no_surface)
    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    rc, err = cli(capsys, "attack", SCENE, "--algo", "random", "--budget", 2, "--seconds", 0.2, "--autonomy", "oracle",
                  "--out", tmp_path / "run")
    line = one_error_line(err)
    assert rc == 1 and "all 2 queries failed" in line and "EmptySurfaceError: test: no surface" in line
    # nothing attacked at all (every scene skipped) is an error too
    with pytest.raises(RunFailedError, match="every scene was skipped"):
        check_outcome({"scenes": {"a": {"ref": "a", "skipped": "no actor in front of the ego"}}}, [])
    check_outcome({"scenes": {"a": {"modes": {"closed": {"n_queries": 3, "n_failed": 2}}}}}, [])  # some worked


# ------------------------------------------------------------------ 4. journal and resume

class _Killed(Exception):
    pass


class _Backwards:
    """An executor of ``slots`` workers that finishes the tasks it holds in reverse order, one
    at a time, killed after ``kill_after`` results (the driver must have journalled those, and
    only those). Deterministic without threads: once every worker holds a query the last one
    finishes; each time the driver reads a result, the next held query (in reverse) finishes."""

    def __init__(self, kill_after: int | None = None, slots: int = 4):
        self.kill_after = kill_after
        self.slots = slots
        self.given = 0
        self.held: list = []  # (future, fn, args) submitted, not finished

    def submit(self, slot, fn, *args):
        import concurrent.futures as cf

        executor = self

        class Future(cf.Future):
            def result(self, timeout=None):
                try:
                    return super().result(timeout)
                finally:
                    executor._finish_next()

        from adv3d_runner.attack.evaluator import run_query

        fut = Future()
        self.held.append((fut, fn, args))
        if len(self.held) == self.slots or fn is not run_query:  # the best-shape task runs at once
            self._finish_next()
        return fut

    def _finish_next(self):
        if not self.held:
            return
        fut, fn, args = self.held.pop()
        if self.kill_after is not None and self.given >= self.kill_after:
            fut.set_exception(_Killed())
            return
        self.given += 1
        fut.set_result(fn(*args))

    def close(self):
        pass


def test_each_query_is_journalled_as_it_finishes_and_the_journal_stays_in_order(tmp_path, monkeypatch):
    from adv3d_runner.attack import driver

    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=8, batch=4, seed=2)
    run_attack(cfg, tmp_path / "serial", evaluator=SyntheticEvaluator, show_progress=False)
    monkeypatch.setattr(driver, "make_executor", lambda workers, ray_address: _Backwards(kill_after=6))
    with pytest.raises(_Killed):
        run_attack(cfg, tmp_path / "killed", evaluator=SyntheticEvaluator, show_progress=False)
    j = Journal(tmp_path / "killed")
    j.load()
    # batch 1 (0-3) complete, batch 2: 7 and 6 finished first, 4 and 5 were in flight
    assert [r["index"] for r in j.records] == [0, 1, 2, 3]
    assert sorted(k[2] for k in j.pending) == [6, 7]
    calls = []

    class Counting(SyntheticEvaluator):
        def evaluate(self, query):
            calls.append(1)
            return super().evaluate(query)

    # the two left (4 and 5) on two workers, again finishing backwards
    monkeypatch.setattr(driver, "make_executor", lambda workers, ray_address: _Backwards(slots=2))
    run_attack(cfg, tmp_path / "killed", evaluator=Counting, show_progress=False)
    assert len(calls) == 2  # only the two in flight
    serial = [json.loads(x) for x in (tmp_path / "serial" / "queries.jsonl").read_text().splitlines()]
    resumed = [json.loads(x) for x in (tmp_path / "killed" / "queries.jsonl").read_text().splitlines()]
    assert strip_times(resumed) == strip_times(serial)
    assert (tmp_path / "killed" / "queries.pending.jsonl").read_bytes() == b""


def test_resume_identifies_scenes_by_content_not_path(tmp_path, monkeypatch):
    import hashlib

    class FileScenes(SyntheticEvaluator):
        """Scenes are files; their content hash is their identity."""

        def scene_id(self, ref):
            return Path(ref).stem

        def scene_digest(self, ref):
            return hashlib.sha256(Path(ref).read_bytes()).hexdigest()

        def evaluate(self, query):
            return super().evaluate(type(query)("synthetic:peak", query.unit, query.closed_loop))

    (tmp_path / "scenes").mkdir()
    scene = tmp_path / "scenes" / "s1.txt"
    scene.write_text("scene one")
    monkeypatch.chdir(tmp_path)
    cfg = AttackConfig([str(scene)], algo="random", budget=3)
    run_attack(cfg, tmp_path / "run", evaluator=FileScenes, show_progress=False)
    # the same file by a relative path resumes (nothing new to evaluate)
    run_attack(AttackConfig(["scenes/s1.txt"], algo="random", budget=3), tmp_path / "run", evaluator=FileScenes,
               show_progress=False)
    scene.write_text("scene one, edited")  # same path, other content: another run
    with pytest.raises(ConfigError, match="scene_sha256"):
        run_attack(cfg, tmp_path / "run", evaluator=FileScenes, show_progress=False)


def test_scene_digest_is_the_content(tmp_path):
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import EpisodeEvaluator

    ev = EpisodeEvaluator(QuerySettings())
    plain = tmp_path / "a.json"
    plain.write_bytes(gzip.decompress(SCENE.read_bytes()))
    assert ev.scene_digest(str(SCENE)) == ev.scene_digest(str(plain))
    doc = read_json(plain)
    doc["ego"]["track"]["x"][0] += 0.01
    write_json(tmp_path / "b.json", doc)
    assert ev.scene_digest(str(tmp_path / "b.json")) != ev.scene_digest(str(plain))


def test_damaged_run_bundle_is_an_error_naming_file_and_field(tmp_path, capsys):
    run_attack(AttackConfig(["synthetic:peak"], algo="random", budget=3), tmp_path / "run",
               evaluator=SyntheticEvaluator, show_progress=False)
    summary = read_json(tmp_path / "run" / "summary.json")
    summary["scenes"]["synthetic:peak"]["modes"]["closed"]["best_cost"] = "high"
    write_json(tmp_path / "run" / "summary.json", summary)
    rc, err = cli(capsys, "report", tmp_path / "run")
    assert rc == 1 and "summary.json: $.scenes.synthetic:peak.modes.closed.best_cost" in one_error_line(err)
    summary["scenes"]["synthetic:peak"]["modes"]["closed"]["best_cost"] = 1.0
    summary["scenes"]["synthetic:peak"]["modes"]["closed"]["files"] = {"replay": "../../etc/passwd"}
    write_json(tmp_path / "run" / "summary.json", summary)
    with pytest.raises(FileFormatError, match="files.replay"):
        read_run(tmp_path / "run")


def test_quiet_after_the_subcommand_and_axis_values_as_documented(capsys):
    from adv3d_runner.cli import build_parser, _join_axis_values

    parser = build_parser()
    assert parser.parse_args(["lidar", "models", "-q"]).quiet
    assert parser.parse_args(["-q", "lidar", "models"]).quiet
    assert not parser.parse_args(["lidar", "models"]).quiet
    argv = _join_axis_values(parser, ["assets", "import", "x.obj", "--class", "sedan", "--up", "-y", "--forward", "-x"])
    args = parser.parse_args(argv)
    assert (args.up, args.forward) == ("-y", "-x")


def test_journal_line_whose_unit_does_not_match_the_run_is_refused_on_resume(tmp_path):
    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=3)
    run_attack(cfg, tmp_path / "run", evaluator=SyntheticEvaluator, show_progress=False)
    path = tmp_path / "run" / "queries.jsonl"
    rows = [json.loads(x) for x in path.read_text().splitlines()]
    rows[1]["unit"][0] = rows[1]["unit"][0][:4]  # one number short
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(FileFormatError, match=r"queries.jsonl: line 2: expected a record whose content matches its sha256"):
        run_attack(cfg, tmp_path / "run", evaluator=SyntheticEvaluator, show_progress=False)
    rows[1]["sha256"] = record_checksum(rows[1])  # checksum made anew: the search's own check refuses it
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(ConfigError, match="queries.jsonl: line 2: query 1 of synthetic:peak/closed does not match this run"):
        run_attack(cfg, tmp_path / "run", evaluator=SyntheticEvaluator, show_progress=False)
    rows[1]["unit"][0] = rows[1]["unit"][0] + [7.0]  # out of [0, 1]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(FileFormatError, match=r"queries.jsonl: line 2: \$\.unit\[0\]\[4\]"):
        read_run(tmp_path / "run")


def test_string_and_bool_numbers_are_refused(tmp_path):
    from adv3d_runner.sim.replay import load_replay

    path = _make_replay(tmp_path)
    doc = read_json(path)
    doc["ego"]["poses"][2][1] = "0.0"  # numpy would read it as a number
    write_json(path, doc)
    with pytest.raises(FileFormatError, match=r"\$\.ego\.poses\[2\]\[1\]: expected a number"):
        load_replay(path)
    doc["ego"]["poses"][2][1] = 0.0
    doc["outputs"][0]["plan"]["trajectory"][1][1] = True
    write_json(path, doc)
    with pytest.raises(FileFormatError, match=r"\$\.outputs\[0\]\.plan\.trajectory\[1\]\[1\]: expected a number"):
        load_replay(path)


def test_a_run_folder_has_one_writer_at_a_time(tmp_path):
    """Two processes on one run folder (a campaign shard started twice) would interleave their
    queries in one journal: the second is refused while the first holds the folder's lock, and
    may go on once it has let go; within one process a later journal takes the lock over."""
    import subprocess
    import sys

    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=2, seed=1)
    run_attack(cfg, tmp_path / "run", evaluator=SyntheticEvaluator, show_progress=False)
    held = Journal(tmp_path / "run")
    stored = held.start(read_run(tmp_path / "run")[0])
    probe = ("import sys; from adv3d_runner.attack.journal import Journal, read_run\n"
             "from adv3d_runner.errors import ConfigError\n"
             "try:\n    Journal(sys.argv[1]).start(read_run(sys.argv[1])[0])\n"
             "except ConfigError as e:\n    print(e); sys.exit(3)\n")
    other = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "run")], capture_output=True, text=True)
    assert other.returncode == 3, other.stderr
    assert "another process is writing this run" in other.stdout and str(tmp_path / "run") in other.stdout
    before = (tmp_path / "run" / "queries.jsonl").read_bytes()
    # the same process: the resumed run takes the lock over and finds nothing to do
    run_attack(cfg, tmp_path / "run", evaluator=SyntheticEvaluator, show_progress=False)
    assert (tmp_path / "run" / "queries.jsonl").read_bytes() == before
    held.close()
    again = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "run")], capture_output=True, text=True)
    assert again.returncode == 0, again.stdout + again.stderr
    assert stored["budget"] == 2
