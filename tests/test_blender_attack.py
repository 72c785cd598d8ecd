"""The Scenes panel's "Attack this scene" on the ``bpy`` module: a tiny real attack
(``adv3d attack --autonomy oracle --budget 2 --seconds 0.5``) runs as a separate process started
with the runner from the add-on preferences, its progress is polled from the journal, Esc
terminates it, pressing again resumes the same run, and the finished run opens in Review.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

SCENE = "highway-benchmark-000002.json.gz"  # has an actor in front of the ego to attack


@pytest.fixture
def ctx(addon, repo_root, tmp_path):
    from blender_addon import prefs

    bpy.ops.wm.read_factory_settings(use_empty=True)
    entry = bpy.context.preferences.addons.new()
    entry.module = prefs.PACKAGE
    p = prefs.get()
    p.runner = sys.executable  # a Python with adv3d installed: run as `python -m adv3d_runner.cli`
    p.runs_folder = str(tmp_path / "runs")
    assert bpy.ops.adv3d.scene_load(filepath=str(repo_root / "scenes" / "highway" / SCENE)) == {"FINISHED"}
    sc = bpy.context.scene.adv3d.scene
    sc.attack_budget, sc.attack_seconds, sc.attack_autonomy = 2, 0.5, "oracle"
    yield bpy.context
    bpy.context.preferences.addons.remove(entry)


def _journal(run: Path) -> list[dict]:
    path = run / "queries.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_attack_this_scene_runs_and_opens_in_review(ctx):
    from blender_addon import ops_attack, review

    assert bpy.ops.adv3d.scene_attack() == {"FINISHED"}
    run = Path(ctx.scene.adv3d.scene.last_run)
    assert len(_journal(run)) == 2 and (run / "summary.json").is_file()
    assert (run.with_name(run.name + ".blender") / SCENE).is_file()  # the scene as exported from Blender
    # the finished run is open in Review
    assert ctx.scene.adv3d.review.path == str(run) and review.data_of(ctx.scene) is not None
    assert "review ego" in bpy.data.objects and ctx.scene.adv3d.review.loaded.startswith(str(run))
    assert ops_attack.journal_progress(run)[0] == 2


def test_attack_is_cancelled_by_esc_and_resumes(ctx):
    """Esc terminates the runner process; the same button then resumes the same run (the
    journal's queries are kept) and finishes it."""
    from blender_addon import jobs

    sc = ctx.scene.adv3d.scene
    sc.attack_budget = 3
    started = []
    op_steps = _attack_steps(ctx, started)
    job = jobs.Job("Attack", op_steps)
    import time

    t0 = time.perf_counter()
    run = Path(sc.last_run)
    while not _journal(run) and time.perf_counter() - t0 < 120:  # until the first query is in
        assert jobs.handle_event(ctx, job, "TIMER") == jobs.RUNNING
        time.sleep(0.1)
    first = _journal(run)
    assert first and "query" in job.message
    assert jobs.handle_event(ctx, job, "ESC") == jobs.CANCELLED
    assert started[0].poll() is not None  # the process is gone
    assert bpy.ops.adv3d.scene_attack() == {"FINISHED"}  # same scene, same settings: resumed
    assert Path(sc.last_run) == run
    done = _journal(run)
    assert len(done) == 3 and done[0] == first[0]


def _attack_steps(ctx, started: list):
    """The operator's job (``prepare_attack`` + ``attack_steps``), the process handed out."""
    from blender_addon import ops_attack

    cmd, run_dir, settings = ops_attack.prepare_attack(ctx)
    steps = ops_attack.attack_steps(cmd, run_dir, settings["budget"], started=started)
    next(steps)  # starts the process
    return steps


def test_algorithms_match_the_attack_cli():
    from adv3d_runner.attack.search import ALGORITHMS
    from blender_addon.ops_attack import ALGORITHMS as ADDON

    assert ADDON == ALGORITHMS


def test_missing_runner_is_reported(ctx):
    from blender_addon import prefs

    prefs.get().runner = "/no/such/adv3d"
    with pytest.raises(RuntimeError, match="adv3d attack failed|No such file|no adv3d runner"):
        bpy.ops.adv3d.scene_attack()


def test_the_stack_menu_lists_the_runners_stacks_and_plugins(ctx, tmp_path):
    """The Autonomy menu is what `adv3d stacks list` says (its own stacks and any registered
    plugin, with a broken plugin left out); a runner that cannot be asked gives adv3d's own."""
    from blender_addon import props, runner

    sc = ctx.scene.adv3d.scene
    names = {item[0] for item in props._stack_items(sc, ctx)}  # a dynamic enum: its items callback
    assert {"A", "A-fast", "B", "oracle"} <= names
    fake = tmp_path / "fake_runner.py"
    fake.write_text("import json, sys\nprint(json.dumps([{'name': 'A', 'source': 'adv3d', 'version': '0.1.0', "
                    "'provides': []}, {'name': 'my-stack', 'source': 'entry point of mypkg', 'version': '2.0', "
                    "'provides': ['detections']}, {'name': 'broken', 'source': 'x', 'error': 'cannot import'}]))\n")
    items = runner.runner_stacks([sys.executable, str(fake)])
    assert [i[0] for i in items] == ["A", "my-stack"] and "provides detections" in items[1][2]
    assert runner.runner_stacks([str(tmp_path / "no-such-runner")]) == runner.FALLBACK_STACKS
    sc.attack_autonomy = "oracle"
    assert sc.attack_autonomy == "oracle"


@pytest.fixture
def own_files(tmp_path):
    """The test suite's own library (fx.* assets, not in the bundled one) and its shape space."""
    from test_blender_addon import make_library, make_space

    return make_library(tmp_path / "own" / "library"), make_space(tmp_path / "own" / "space.npz")


def test_attack_with_your_own_library_and_shape_space(ctx, own_files):
    """Actors that use assets of the panel's own library: the runner gets the panels' library,
    shape space and stack (the bundled library lacks these assets, so without them it fails)."""
    from blender_addon import ops_attack

    lib, space = own_files
    ctx.scene.adv3d.library.path = str(lib)
    ctx.scene.adv3d.shapes.space_path = str(space)
    for obj in bpy.data.objects:
        if obj.adv3d.role == "ACTOR":
            obj.adv3d.asset_id = "fx.sedan"
    cmd, run_dir, settings = ops_attack.prepare_attack(ctx)
    assert cmd[cmd.index("--library") + 1] == str(lib.resolve())
    assert cmd[cmd.index("--shape-space") + 1] == str(space.resolve())
    assert cmd[cmd.index("--autonomy") + 1] == "oracle"
    sc = ctx.scene.adv3d.scene
    sc.attack_budget = 1
    assert bpy.ops.adv3d.scene_attack() == {"FINISHED"}
    run = Path(sc.last_run)
    info = json.loads((run / "run.json").read_text())
    assert str(lib.resolve()) in json.dumps(info) and sc.attack_error == ""
    assert len(_journal(run)) == 1


def test_failed_start_shows_the_runners_error_line_and_each_attempt_has_its_log(ctx, own_files, tmp_path):
    from blender_addon import ops_attack

    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"not a zip file")
    ctx.scene.adv3d.shapes.space_path = str(bad)
    sc = ctx.scene.adv3d.scene
    for _ in range(2):
        with pytest.raises(RuntimeError) as err:
            bpy.ops.adv3d.scene_attack()
        assert "Traceback" not in str(err.value) and "TypeError" not in str(err.value)
        assert sc.attack_error.startswith("adv3d: error: ") and str(bad) in sc.attack_error
    logs = sorted(p.name for p in ops_attack.side_folder(Path(sc.last_run)).glob("*.log"))
    assert logs == ["attack-01.log", "attack-02.log"]


def test_journal_progress_tolerates_failed_episodes(tmp_path):
    from blender_addon import ops_attack

    (tmp_path / "queries.jsonl").write_text('{"cost": null}\n{"cost": 2.5}\n{"cost": "x"}\n{"cost": 1.5')
    assert ops_attack.journal_progress(tmp_path) == (2, 2.5)
