# SPDX-License-Identifier: GPL-3.0-or-later
"""Scenes panel: "Attack this scene" - the loop from authoring to review without leaving Blender.

The scene as edited in Blender is written (``ops_scene.export_scene``, the same bytes Export
scene writes) into a run folder under the preferences' runs folder, and ``adv3d attack`` runs on
it as a separate process started with the runner from the preferences (the add-on never
imports torch, the attack needs it). The operator is modal: a timer polls the process and the
run's journal (``queries.jsonl``: one line per evaluated query) and shows "query n / budget,
best cost" in the status bar; Esc terminates the process. The journal makes a cancelled or
killed attack resumable: the run folder is named after the scene's content and the attack
settings, so pressing the button again on the same scene continues the same run. When the
process finishes, the run opens in the Review panel.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
from pathlib import Path

import bpy

from . import jobs, prefs, runner

#: The attack CLI's searchers (``adv3d_runner.attack.search.ALGORITHMS``; a test keeps them equal:
#: the add-on does not import the attack package, which needs torch).
ALGORITHMS = ("bo", "random", "grid", "blendsearch", "bruteforce", "skopt")
POLL_S = 0.25  # how often the process and its journal are looked at
TERMINATE_WAIT_S = 5.0


def run_name(scene_bytes: bytes, settings: dict, scene_id: str) -> str:
    """The run folder's name: the scene id and a hash of the scene file and the settings (the
    same scene and settings resume the same run; an edited scene starts a new one)."""
    h = hashlib.sha256(scene_bytes)
    h.update(json.dumps(settings, sort_keys=True).encode())
    return f"{scene_id}-{settings['algo']}-{h.hexdigest()[:10]}"


def attack_command(cmd: list[str], scene_file: Path, run_dir: Path, settings: dict) -> list[str]:
    """The ``adv3d attack`` command line (``cmd``: the runner, ``prefs.runner_command``): the
    panel's search settings, stack (``--autonomy``) and the Library and Shape space panels' files
    (``--library``, ``--shape-space``; left out when a panel has none, so the runner uses its
    bundled ones)."""
    out = cmd + ["--quiet", "attack", str(scene_file), "--out", str(run_dir), "--algo", settings["algo"],
                 "--budget", str(settings["budget"]), "--seconds", f"{settings['seconds']:g}",
                 "--autonomy", settings["autonomy"], "--seed", str(settings["seed"])]
    if settings.get("library"):
        out += ["--library", settings["library"]]
    if settings.get("shape_space"):
        out += ["--shape-space", settings["shape_space"]]
    return out


def journal_progress(run_dir: Path) -> tuple[int, float]:
    """(queries evaluated, best cost so far) from the run's journal (complete lines only)."""
    path = run_dir / "queries.jsonl"
    try:
        data = path.read_bytes()
    except OSError:
        return 0, float("nan")
    done, best = 0, float("inf")
    for line in data.split(b"\n")[:-1]:  # the part after the last newline is still being written
        try:
            cost = json.loads(line).get("cost")
            cost = float("nan") if cost is None else float(cost)  # null: a failed episode
        except (ValueError, TypeError, AttributeError):
            continue
        done += 1
        if cost == cost:  # not NaN (failed episodes)
            best = min(best, cost)
    return done, best if done else float("nan")


def _stop(proc: subprocess.Popen) -> None:
    """Terminate the attack (and any worker it started: it leads its own process group)."""
    if proc.poll() is not None:
        return
    try:
        if hasattr(os, "killpg"):
            os.killpg(proc.pid, signal.SIGTERM)
        else:
            proc.terminate()
        proc.wait(TERMINATE_WAIT_S)
    except (subprocess.TimeoutExpired, ProcessLookupError, PermissionError):
        proc.kill()
        proc.wait()


def side_folder(run_dir: Path) -> Path:
    """``<run>.blender/`` beside the run: the exported scene and the attack's log. Nothing but
    the runner writes into the run folder itself (``adv3d attack --out`` refuses a folder that
    holds anything but a run)."""
    return run_dir.with_name(run_dir.name + ".blender")


def new_log_path(run_dir: Path) -> Path:
    """A log file of its own for this attempt: ``<run>.blender/attack-NN.log``, NN one above the
    highest there (so the last attempt's log ends with the last attempt's outcome)."""
    folder = side_folder(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    taken = [int(m.group(1)) for p in folder.glob("attack-*.log") if (m := re.fullmatch(r"attack-(\d+)\.log", p.name))]
    return folder / f"attack-{max(taken, default=0) + 1:02d}.log"


def runner_error(log_text: str) -> str:
    """The runner's own one-line error from its log: the last ``...: error: ...`` line
    (``adv3d: error: ...``, an argument error), else the last non-empty line."""
    lines = [ln.strip() for ln in log_text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ": error: " in ln]
    return errors[-1] if errors else (lines[-1] if lines else "no output")


def attack_steps(cmd: list[str], run_dir: Path, budget: int, env: dict | None = None,
                 started: list | None = None):
    """Steps generator: run the attack command and wait for it, yielding
    ``jobs.Waiting(fraction, message)`` every ``POLL_S``; closing the generator (Esc) terminates
    the process. Returns ``run_dir``; raises ``Adv3dError`` with the runner's error line when
    the attack fails. Each attempt writes its own log (:func:`new_log_path`). ``started``: the
    ``Popen`` is appended to it (for callers that watch it)."""
    log_path = new_log_path(run_dir)
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                start_new_session=hasattr(os, "killpg"))
    if started is not None:
        started.append(proc)
    try:
        while proc.poll() is None:
            done, best = journal_progress(run_dir)
            best_text = f", best cost {best:.4g}" if best == best else ""
            yield jobs.Waiting(min(done / max(budget, 1), 1.0), f"query {done}/{budget}{best_text}", POLL_S)
    finally:
        _stop(proc)  # cancelled (GeneratorExit) or failed: never leave it running
    if proc.returncode != 0:
        raise runner.Adv3dError(f"{runner_error(log_path.read_text(errors='replace'))} "
                                f"(exit {proc.returncode}, log: {log_path})")
    return run_dir


class ADV3D_OT_scene_attack(jobs.JobOperator, bpy.types.Operator):
    """Attack the loaded scene (with your edits) with `adv3d attack` in a separate process;
    progress in the status bar, Esc stops it (pressing again resumes); the finished run opens in
    Review"""

    bl_idname = "adv3d.scene_attack"
    bl_label = "Attack this scene"
    bl_options = {"REGISTER"}
    job_label = "Attack"

    def start_job(self, context):
        context.scene.adv3d.scene.attack_error = ""
        try:
            cmd, run_dir, settings = prepare_attack(context)
        except (runner.Adv3dError, OSError, ValueError) as exc:
            context.scene.adv3d.scene.attack_error = str(exc)
            raise
        self.job_label = f"Attack {context.scene.adv3d.scene.scene_id}"
        return attack_steps(cmd, run_dir, settings["budget"], env=_runner_env())

    def job_cancelled(self, context, job):
        """A failed attack's error line stays in the Scenes panel (the log holds the rest)."""
        context.scene.adv3d.scene.attack_error = job.error if job.state == jobs.FAILED else ""

    def finish_job(self, context, job):
        run_dir = job.result
        review = context.scene.adv3d.review
        review.path = str(run_dir)
        self.report({"INFO"}, f"Attack finished: {run_dir}; opening it in Review")
        if context.window is not None and not bpy.app.background:
            bpy.ops.adv3d.review_load("INVOKE_DEFAULT", filepath=str(run_dir))
        else:
            bpy.ops.adv3d.review_load(filepath=str(run_dir))
        return {"FINISHED"}


def prepare_attack(context) -> tuple[list[str], Path, dict]:
    """Write the scene as edited into its run folder; returns the ``adv3d attack`` command, the
    run folder and the settings (the Scenes panel's)."""
    from adv3d_runner.scene.schema import save_scene

    from .ops_scene import export_scene

    cmd = prefs.runner_command()
    if not cmd:
        raise runner.Adv3dError("no adv3d runner found: install adv3d or set Runner in the add-on preferences")
    props = context.scene.adv3d.scene
    scene, _ = export_scene(context.scene)  # what Export scene would write: edits included
    settings = {"algo": props.attack_algo, "budget": int(props.attack_budget),
                "seconds": float(props.attack_seconds), "autonomy": props.attack_autonomy,
                "seed": int(props.attack_seed), **_panel_files(context)}
    runs = prefs.runs_folder(context)
    staging = runs / ".staging"
    staging.mkdir(parents=True, exist_ok=True)
    tmp = staging / f"{scene.id}.json.gz"
    save_scene(scene, tmp)
    run_dir = runs / run_name(tmp.read_bytes(), settings, scene.id)
    scene_file = side_folder(run_dir) / f"{scene.id}.json.gz"
    if not scene_file.exists():  # on a resume the file is there with the same bytes
        scene_file.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, scene_file)
    props.last_run = str(run_dir)
    return attack_command(cmd, scene_file, run_dir, settings), run_dir, settings


def _panel_files(context) -> dict:
    """The Library and Shape space panels' files (else the preferences' defaults) as absolute
    paths, '' where neither is set (the runner then uses its bundled ones); a set path that does
    not exist is refused here, naming the panel."""
    from .ops_library import library_path
    from .ops_shapes import space_path

    files = {"library": library_path(context.scene.adv3d.library), "shape_space": space_path(context.scene.adv3d.shapes)}
    for key, panel in (("library", "Library"), ("shape_space", "Shape space")):
        if files[key]:
            path = Path(files[key]).expanduser().resolve()
            if not path.is_file():
                raise runner.Adv3dError(f"the {panel} panel's file {path} does not exist")
            files[key] = str(path)
    return files


def _runner_env() -> dict:
    """The runner's environment: Blender's ``PYTHONHOME`` removed (the runner is another Python
    with its own packages)."""
    env = dict(os.environ)
    env.pop("PYTHONHOME", None)
    return env


classes = (ADV3D_OT_scene_attack,)
