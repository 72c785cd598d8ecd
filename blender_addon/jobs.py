# SPDX-License-Identifier: GPL-3.0-or-later
"""Long work that never freezes Blender: a steps generator stepped by a modal operator's timer.

The work itself is a *steps generator* (``adv3d_runner.progress``): it does one short piece of
work per ``next()`` (well under ``MAX_STEP_S``) and yields ``None`` or a progress tuple
``(fraction, message, ...)``; its return value is the result. :class:`Job` runs such a generator
in time slices (``SLICE_S`` of work per timer tick, then control goes back to Blender's event
loop), keeps the progress, and can be cancelled (``generator.close()``: the generator's
``finally`` blocks clean up, so nothing is left half written).

:class:`JobOperator` is the operator side (the pattern of Blender's own modal operators):

* ``invoke`` (a click in the UI) starts the job, a window timer and a modal handler; every
  ``TIMER`` event runs one slice, shows the progress in the status bar
  (``workspace.status_text_set``) and the window manager's progress cursor
  (``window_manager.progress_update``); ``Esc`` cancels; other events pass through, so the
  viewport stays usable while the job runs;
* ``execute`` (scripts, ``bpy.ops`` in background mode, where Blender never calls ``invoke``)
  runs the same job to its end.

The event handling is :func:`handle_event` on a :class:`Job`, so it can be tested without a
window (a modal handler needs Blender's event loop, which background mode does not run).
"""
from __future__ import annotations

import time
import traceback
from typing import Any, Callable, Generator

from . import runner

#: Work done per timer tick before control goes back to Blender (seconds).
SLICE_S = 0.05
#: Timer interval of the modal operators (seconds).
TIMER_S = 0.02
#: The longest single step a job may take (the acceptance limit for a blocked UI).
MAX_STEP_S = 0.5

RUNNING, DONE, FAILED, CANCELLED = "running", "done", "failed", "cancelled"


class Waiting(tuple):
    """A step meaning "nothing to do for ``wait_s`` seconds" (a job polling another process):
    ``Waiting(fraction, message, wait_s)``. The slice ends at once, so Blender idles until the
    next timer tick; run to the end (background mode), the job sleeps instead."""

    def __new__(cls, fraction: float, message: str, wait_s: float = 0.25):
        return super().__new__(cls, (fraction, message, wait_s))


class Job:
    """A steps generator run in time slices.

    Attributes:
        label: what the job does ("Build shape space"), for the status bar.
        state: ``RUNNING``, ``DONE``, ``FAILED`` or ``CANCELLED``.
        fraction: progress in [0, 1]; message: the current step's text.
        result: the generator's return value once ``DONE``; error: the message once ``FAILED``.
        max_step_s: the longest single ``next()`` seen (wall s); max_step_cpu_s: the most CPU
            time one step used (this thread's; what the step costs on an idle machine);
            slowest: the progress message before the longest step; max_slice_s: the longest slice.
        n_steps: number of steps run.
    """

    def __init__(self, label: str, steps: Generator[Any, None, Any]):
        self.label = label
        self.steps = steps
        self.state = RUNNING
        self.fraction = 0.0
        self.message = ""
        self.result: Any = None
        self.error = ""
        self.max_step_s = 0.0
        self.max_step_cpu_s = 0.0
        self.slowest = ""
        self.max_slice_s = 0.0
        self.n_steps = 0
        self.started = time.perf_counter()

    def run_slice(self, budget_s: float = SLICE_S, sleep: bool = False) -> str:
        """Run steps until ``budget_s`` has passed (at least one step) or a step says it is
        waiting (``sleep``: wait as it asks and go on); returns the state."""
        if self.state != RUNNING:
            return self.state
        t0 = time.perf_counter()
        while True:
            t, c = time.perf_counter(), time.thread_time()
            before = self.message
            try:
                step = next(self.steps)
            except StopIteration as stop:
                self.result, self.state, self.fraction = stop.value, DONE, 1.0
            except (runner.Adv3dError, OSError, ValueError) as exc:  # bad files, full disk: reported
                self.error, self.state = str(exc), FAILED
            except Exception as exc:  # a bug: reported as one line, the traceback on the console
                traceback.print_exc()
                self.error, self.state = f"internal error ({type(exc).__name__}: {exc})", FAILED
            finally:
                wall = time.perf_counter() - t
                if wall > self.max_step_s:
                    self.max_step_s, self.slowest = wall, before
                self.max_step_cpu_s = max(self.max_step_cpu_s, time.thread_time() - c)
                self.n_steps += 1
            if self.state != RUNNING:
                break
            if isinstance(step, tuple) and len(step) >= 2:
                self.fraction = float(min(max(step[0], 0.0), 1.0))
                self.message = str(step[1])
            if isinstance(step, Waiting):
                if not sleep:
                    break
                time.sleep(step[2])
            if time.perf_counter() - t0 >= budget_s:
                break
        self.max_slice_s = max(self.max_slice_s, time.perf_counter() - t0)
        return self.state

    def run_to_end(self) -> str:
        """Run every remaining step (scripts and background mode)."""
        while self.run_slice(float("inf"), sleep=True) == RUNNING:
            pass
        return self.state

    def cancel(self) -> None:
        """Stop the job: the generator is closed (its ``finally`` blocks run)."""
        if self.state == RUNNING:
            self.steps.close()
            self.state = CANCELLED

    def status_text(self) -> str:
        """The status-bar line."""
        if self.state == RUNNING:
            msg = f": {self.message}" if self.message else ""
            return f"{self.label}{msg} - {100 * self.fraction:.0f}%   (Esc to cancel)"
        if self.state == FAILED:
            return f"{self.label} failed: {self.error}"
        return f"{self.label} {self.state}"


def handle_event(context, job: Job, event_type: str, slice_s: float = SLICE_S) -> str:
    """One modal event for ``job``: ``TIMER`` runs a slice, ``ESC`` cancels; the status bar and
    the progress cursor follow. Returns the job's state."""
    if event_type == "ESC":
        job.cancel()
    elif event_type == "TIMER":
        job.run_slice(slice_s)
    show_progress(context, job)
    return job.state


def show_progress(context, job: Job | None) -> None:
    """Status-bar text and progress cursor for ``job`` (None: clear both)."""
    workspace = getattr(context, "workspace", None)
    if workspace is not None:
        workspace.status_text_set(None if job is None or job.state != RUNNING else job.status_text())
    wm = context.window_manager
    if job is not None and job.state == RUNNING:
        wm.progress_update(int(1000 * job.fraction))


class JobOperator:
    """Mixin for operators whose work is a :class:`Job`.

    Subclasses define ``job_label``, ``start_job(self, context) -> Generator | None`` (None after
    reporting an error) and ``finish_job(self, context, job) -> set`` (called once the job is
    done; the return value is the operator's).
    """

    job_label = "Working"
    #: Operators of this kind with a job running (one at a time per operator type).
    _active: dict[str, Job] = {}

    def _begin(self, context) -> Job | None:
        if type(self).__name__ in JobOperator._active:
            self.report({"ERROR"}, f"{self.job_label} is already running (Esc cancels it)")
            return None
        try:
            steps = self.start_job(context)
        except (runner.Adv3dError, OSError, ValueError, KeyError) as exc:
            from .uiutil import error_text

            self.report({"ERROR"}, error_text(exc))
            return None
        except Exception as exc:  # a bug: one line for the user, the traceback on the console
            traceback.print_exc()
            self.report({"ERROR"}, f"internal error ({type(exc).__name__}: {exc})")
            return None
        return None if steps is None else Job(self.job_label, steps)

    def _end(self, context, job: Job) -> set:
        if job.state == DONE:
            return self.finish_job(context, job)
        if job.state == FAILED:
            self.report({"ERROR"}, job.error)
        else:
            self.report({"WARNING"}, f"{self.job_label} cancelled")
        self.job_cancelled(context, job)
        return {"CANCELLED"}

    def job_cancelled(self, context, job: Job) -> None:
        """Hook: clean-up after a failed or cancelled job (default: nothing)."""

    def execute(self, context):
        job = self._begin(context)
        if job is None:
            return {"CANCELLED"}
        job.run_to_end()
        return self._end(context, job)

    def invoke(self, context, event):
        if context.window is None:  # no window to run a modal handler in
            return self.execute(context)
        job = self._begin(context)
        if job is None:
            return {"CANCELLED"}
        JobOperator._active[type(self).__name__] = job
        wm = context.window_manager
        self._timer = wm.event_timer_add(TIMER_S, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 1000)
        show_progress(context, job)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = JobOperator._active.get(type(self).__name__)
        if job is None:  # unregistered or reloaded under us
            return {"CANCELLED"}
        if event.type not in {"TIMER", "ESC"}:
            return {"PASS_THROUGH"}  # navigation and other tools keep working
        if handle_event(context, job, event.type) == RUNNING:
            return {"RUNNING_MODAL"}
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        show_progress(context, None)
        JobOperator._active.pop(type(self).__name__, None)
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()
        return self._end(context, job)


def cancel_all() -> None:
    """Cancel every running job (unregister)."""
    for job in list(JobOperator._active.values()):
        job.cancel()
    JobOperator._active.clear()


#: Heavy modules imported one per step before work that needs them, in pieces each well under
#: ``MAX_STEP_S`` of CPU: trimesh alone pulls in scipy.spatial, scipy.ndimage and networkx
#: (~1 s of CPU together the first time on a loaded machine).
HEAVY_MODULES = ("scipy.sparse", "scipy.spatial", "scipy.ndimage", "networkx.utils", "networkx.classes",
                 "networkx.algorithms", "networkx", "trimesh.util", "trimesh.graph", "trimesh.creation",
                 "trimesh", "igl", "skimage.measure")


def import_steps(modules=HEAVY_MODULES, fraction: float = 0.0) -> Generator[Any, None, None]:
    """Steps that import ``modules`` not imported yet, one per step (the first Build or review
    of a session would otherwise spend a long first step in imports)."""
    import importlib
    import sys

    for name in modules:
        if name not in sys.modules:
            yield fraction, f"loading {name}"
            try:
                importlib.import_module(name)
            except ImportError:  # optional here: the work itself reports what it lacks
                pass


def steps_of(fn: Callable[[], Any], message: str = "") -> Generator[Any, None, Any]:
    """One function call as a one-step generator (work that is already short)."""
    yield 0.0, message
    return fn()
