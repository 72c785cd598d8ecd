"""The stack interface (docs/stacks.md): discovery, a plugin stack in process and out of
process (docs/stack_protocol.md), outputs it lacks reported as not available, and stacks that
crash, hang or answer garbage failing cleanly without leaving a process behind."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.autonomy import plugins
from adv3d_runner.autonomy.remote import RemoteStack
from adv3d_runner.errors import ConfigError, StackFailure

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
TOY = ROOT / "examples" / "stacks" / "toy"
BROKEN = ROOT / "tests" / "stacks" / "broken_server.py"


def _env(**extra):
    path = os.pathsep.join([str(TOY), str(ROOT)])
    return {**os.environ, "PYTHONPATH": path, **extra}


def _adv3d(*args, **env):
    return subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "-q", *args], capture_output=True, text=True,
                          timeout=600, env=_env(**env), cwd=ROOT)


def _broken(mode: str) -> str:
    return f"exec:{sys.executable} {BROKEN} {mode}"


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_builtin_stacks_are_registered_with_their_fingerprints():
    names = plugins.registered()
    assert {"A", "A-fast", "A-lanefollow", "B", "oracle"} <= set(names)
    out = _adv3d("stacks", "list", "--json")
    assert out.returncode == 0, out.stderr
    rows = {r["name"]: r for r in json.loads(out.stdout)}
    assert rows["B"]["provides"] == ["occupancy"] and len(rows["A"]["fingerprint"]) == 16
    assert rows["A"]["fingerprint"] != rows["A-fast"]["fingerprint"]


def test_a_spec_is_checked_before_anything_runs():
    assert plugins.check_spec("pkg.mod:make") == "pkg.mod:make"
    assert plugins.check_spec("exec:python server.py") == "exec:python server.py"
    with pytest.raises(ConfigError, match="unknown stack 'Z'"):
        plugins.check_spec("Z")
    out = _adv3d("simulate", str(SCENE), "--autonomy", "Z", "--out", "unused")
    assert out.returncode == 2 and "unknown stack 'Z'" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("spec, said", [
    ("no_such_module:make", "cannot import no_such_module"),
    ("tests.stacks.factories:raises", "its factory tests.stacks.factories:raises raised RuntimeError: no licence server"),
    ("tests.stacks.factories:not_a_stack", "returned object, which lacks info, sensors, reset, run_step"),
    ("version", "speaks protocol version 99, adv3d speaks 1"),
])
def test_a_stack_that_cannot_be_built_is_one_line_naming_it(spec, said, tmp_path):
    spec = _broken(spec) if spec == "version" else spec
    out = _adv3d("simulate", str(SCENE), "--autonomy", spec, "--seconds", "0.5", "--out", str(tmp_path / "o"))
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and said in lines[0] and "stack" in lines[0], out.stderr
    assert not (tmp_path / "o").exists()  # nothing written


def test_a_stack_that_never_says_hello_times_out(monkeypatch):
    monkeypatch.setattr("adv3d_runner.autonomy.remote.START_TIMEOUT", 2.0)
    with pytest.raises(StackFailure, match="did not answer 'hello' within 2 s"):
        RemoteStack.from_spec(_broken("silent"))


def _toy_episode(spec: str, seconds: float = 1.0):
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sim.episode import run_episode
    from adv3d_runner.sim.evaluate import episode_metrics

    scene = load_scene(SCENE)
    stack = make_stack(spec)
    try:
        result = run_episode(scene, stack, seconds=seconds, seed=3)
    finally:
        if hasattr(stack, "close"):
            stack.close()
    return result, episode_metrics(result, scene.lanes)


def test_a_plan_only_stack_gets_no_zero_for_what_it_lacks(monkeypatch):
    monkeypatch.syspath_prepend(str(TOY))
    from adv3d_runner.attack.objective import ABLATIONS, episode_objective

    result, metrics = _toy_episode("toy_stack:make")
    assert metrics["detection"] is None and metrics["prediction"] is None
    assert metrics["not_available"] == ["detections", "tracks", "predictions"]
    value = episode_objective(result)
    c = value.components()
    assert c["det"] is None and c["tp"] is None and c["pred"] is None and c["not_available"] == ["det", "pred"]
    assert value.total == pytest.approx(ABLATIONS["M0"].plan * c["plan"])  # the plan term alone
    with pytest.raises(ConfigError, match="weighs only det, which this stack does not provide"):
        episode_objective(result, ABLATIONS["M1"])


def test_out_of_process_equals_in_process(monkeypatch):
    monkeypatch.syspath_prepend(str(TOY))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(TOY), str(ROOT)]))
    a, ma = _toy_episode("toy_stack:make")
    b, mb = _toy_episode(f"exec:{sys.executable} -m adv3d_runner.autonomy.remote toy_stack:make")
    assert np.array_equal(a.ego_poses, b.ego_poses) and np.array_equal(a.ego_speeds, b.ego_speeds)
    assert ma["driving_comfort"] == mb["driving_comfort"] and ma["progress_m"] == mb["progress_m"]


@pytest.mark.parametrize("mode, said", [
    ("crash", "exited with code 3; its last words: simulated crash of the stack"),
    ("hang", "did not answer 'step' within 2 s"),
    ("garbage", "malformed message: not msgpack"),
    ("nan", "plan.trajectory: not finite"),
    ("error", "reported an error during 'step': RuntimeError: the planner found no trajectory"),
])
def test_a_misbehaving_stack_fails_the_episode_cleanly_and_leaves_no_process(mode, said, monkeypatch):
    monkeypatch.setattr("adv3d_runner.autonomy.remote.STEP_TIMEOUT", 2.0)
    from adv3d_runner.autonomy.stacks import make_stack
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.sim.episode import run_episode

    stack = make_stack(_broken(mode))
    remote = stack.stack
    pid = remote._proc.pid
    with pytest.raises(StackFailure, match=said.replace("(", r"\(").replace(")", r"\)")):
        run_episode(load_scene(SCENE), stack, seconds=1.0, seed=1)
    remote.close()
    assert _gone(pid)


def test_an_attack_goes_on_past_a_crashing_stack(tmp_path):
    """Every other episode the stack dies at frame 3: those queries are journalled as failed
    with the reason, the others are scored, and no stack process is left behind."""
    out = tmp_path / "run"
    res = _adv3d("attack", str(SCENE), "--autonomy", _broken(f"crash-odd {tmp_path / 'count'}"), "--algo", "random",
                 "--budget", "4",
                 "--seconds", "0.6", "--out", str(out))
    assert res.returncode == 0, res.stderr
    records = [json.loads(line) for line in (out / "queries.jsonl").read_text().splitlines()]
    failed = [r for r in records if r["status"] != "ok"]
    assert 1 <= len(failed) < len(records)
    assert all("simulated crash of the stack" in r["error"] for r in failed)
    stack = json.loads((out / "run.json").read_text())["versions"]["stack"]
    assert stack["name"] == "broken-crash-odd" and stack["version"] == "0.1"
    ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
    assert str(BROKEN) not in ps


def test_a_stack_that_breaks_on_resume_loses_nothing_of_the_run(tmp_path):
    """An attack made with the toy stack, resumed when its module can no longer be imported:
    one line naming the stack, exit 1, and the run folder byte for byte as it was."""
    out = tmp_path / "run"
    args = ("attack", str(SCENE), "--autonomy", "toy_stack:make", "--algo", "random", "--budget", "2",
            "--seconds", "0.5", "--out", str(out))
    assert _adv3d(*args).returncode == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    res = subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "-q", *args], capture_output=True, text=True,
                         timeout=600, env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT)
    assert res.returncode == 1 and "cannot import toy_stack" in res.stderr and len(res.stderr.splitlines()) == 1
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_the_wire_round_trips_empty_arrays_tracks_and_plan_controls():
    """Zero-size arrays (no points, no actors), tracks and a plan's controls cross the wire."""
    from adv3d_runner.autonomy import wire
    from adv3d_runner.autonomy.api import Plan, StepOutput
    from adv3d_runner.autonomy.interface import Detections, Tracks
    from adv3d_runner.autonomy.remote import output_from_wire, output_to_wire

    msg = wire.decode(wire.encode({"type": "x", "points": np.zeros((0, 4), np.float32)})[4:])
    assert msg["points"].shape == (0, 4) and msg["points"].dtype == np.float32
    plan = Plan(np.c_[np.arange(4.0), np.zeros(4), np.zeros(4)], np.full(4, 10.0), acceleration=np.full(3, -1.5),
                curvature=np.zeros(3))
    out = StepOutput(plan, Detections(), Tracks([7], [[1.0, 2, 4.5, 1.8, 0]], [[10.0, 0]], [0.9], [0], np.zeros((1, 0, 3))))
    back = output_from_wire(wire.decode(wire.encode({"type": "step", **output_to_wire(out)})[4:]), "t")
    assert np.array_equal(back.plan.acceleration, plan.acceleration) and back.tracks.ids.tolist() == [7]
    assert len(back.detections) == 0
