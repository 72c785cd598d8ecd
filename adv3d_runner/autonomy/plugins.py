"""Finding and building the stacks under test (docs/stacks.md).

A stack is named on the command line (``--autonomy``) by:

* a registered name: an entry point of the ``adv3d.stacks`` group (adv3d's own A, A-fast,
  A-lanefollow, B and oracle are registered there by its pyproject.toml, a plugin package
  registers its own the same way);
* ``package.module:factory``: a factory importable from here;
* ``exec:COMMAND ...``: a stack in its own process (and environment), started by the runner,
  speaking the wire protocol (docs/stack_protocol.md, :mod:`.remote`);
* ``tcp://HOST:PORT`` or ``unix:PATH``: such a stack already running, connected to.

A factory takes no arguments and returns either a :class:`~.api.Stack` (the public interface,
wrapped here in :class:`PluginStack`) or one of adv3d's own stacks (which implement the
internal :class:`~.interface.AutonomyStack` and carry a ``stack_info``).
"""
from __future__ import annotations

import importlib
import time
from typing import Any

import numpy as np

from ..errors import ConfigError, StackFailure
from .api import OUTPUTS, Episode, Frame, Lane, LidarSensor, Sensors, Stack, StackInfo, StepOutput
from .interface import AutonomyOutputs, Detections, EgoState, Plan, Predictions, SceneContext, Tracks

from .names import BUILTIN, ENTRY_POINT_GROUP, StackEntry, check_spec, is_remote, registered, stack_spec  # noqa: F401


def build(spec: str) -> tuple[Any, StackInfo]:
    """(the stack as the episode loop drives it, its info) for ``spec``.

    Raises:
        ConfigError: the spec names nothing, the plugin cannot be imported, its factory raises
            or returns something that is not a stack; one line naming the stack.
        StackFailure: a remote stack could not be started or answered badly.
    """
    spec = check_spec(spec)
    if is_remote(spec):
        from .remote import RemoteStack

        stack = RemoteStack.from_spec(spec)
        return PluginStack(stack), stack.info()
    entry = registered().get(spec) or StackEntry(spec, spec, "path")
    factory = _import_factory(entry)
    try:
        made = factory()
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - a plugin's own error, named
        raise ConfigError(f"stack {entry.name!r}: its factory {entry.target} raised {type(exc).__name__}: {exc}") from None
    if isinstance(made, PluginStack):
        return made, made.stack_info
    internal = getattr(made, "stack_info", None)
    if isinstance(internal, StackInfo) and callable(getattr(made, "step", None)):
        return made, internal  # adv3d's own stacks
    missing = [m for m in ("info", "sensors", "reset", "run_step") if not callable(getattr(made, m, None))]
    if missing:
        raise ConfigError(f"stack {entry.name!r}: {entry.target} returned {type(made).__name__}, which lacks "
                          f"{', '.join(missing)} (docs/stacks.md)")
    adapter = PluginStack(made)
    return adapter, adapter.stack_info


def _import_factory(entry: StackEntry):
    module, _, attr = entry.target.partition(":")
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - ImportError or the module's own error
        raise ConfigError(f"stack {entry.name!r}: cannot import {module} ({type(exc).__name__}: {exc})") from None
    factory = getattr(mod, attr, None)
    if not callable(factory):
        raise ConfigError(f"stack {entry.name!r}: {module} has no callable {attr!r}")
    return factory


def info_of(spec: str) -> StackInfo:
    """The info of the stack ``spec`` names (builds it: a remote stack is started and closed)."""
    stack, info = build(spec)
    close = getattr(stack, "close", None)
    if close is not None:
        close()
    return info


# ------------------------------------------------------------------------- the adapter

def _check_array(a: Any, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise StackFailure(f"{what}: expected shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise StackFailure(f"{what}: not finite")
    return arr


def _lanes(context: SceneContext) -> tuple[Lane, ...]:
    out = []
    for lane in context.lane_map.lanes:
        out.append(Lane(int(lane.id), np.asarray(lane.centerline, np.float64),
                        np.broadcast_to(np.asarray(lane.width, np.float64), (len(lane.centerline),)).copy(),
                        None if lane.left is None else int(lane.left), None if lane.right is None else int(lane.right),
                        tuple(int(s) for s in lane.successors),
                        None if lane.speed_limit is None else float(lane.speed_limit)))
    return tuple(out)


def _rig(rig: Any) -> tuple[LidarSensor, ...]:
    if rig is None:
        return ()
    out = []
    for s in getattr(rig, "sensors", ()):
        model = s.model
        out.append(LidarSensor(str(getattr(model, "name", "lidar")), tuple(float(x) for x in s.mount),
                               int(getattr(model, "channels", 0) or len(getattr(model, "elevations", ()))),
                               int(getattr(model, "columns", 0))))
    return tuple(out)


class PluginStack:
    """A public-interface :class:`~.api.Stack` driven by the episode loop (the internal
    :class:`~.interface.AutonomyStack`): builds its :class:`~.api.Episode` and
    :class:`~.api.Frame` s, checks every answer (a malformed one is a
    :class:`~adv3d_runner.errors.StackFailure`, which fails the query, not the run), and
    reports what the stack does not provide as not available."""

    def __init__(self, stack: Stack):
        self.stack = stack
        info = stack.info()
        if not isinstance(info, StackInfo):
            raise ConfigError(f"stack {type(stack).__name__}: info() must return a StackInfo, got {type(info).__name__}")
        sensors = stack.sensors()
        if not isinstance(sensors, Sensors):
            raise ConfigError(f"stack {info.name!r}: sensors() must return a Sensors, got {type(sensors).__name__}")
        self.stack_info, self.wants = info, sensors
        self._gt: tuple[np.ndarray, np.ndarray] | None = None
        self._sensor_ids: np.ndarray | None = None
        self._index = 0
        self._t0 = 0.0

    def reset(self, context: SceneContext) -> None:
        self._index, self._gt, self._sensor_ids = 0, None, None
        self._t0 = None
        self.stack.reset(Episode(context.scene_id, float(context.dt), _lanes(context), _rig(getattr(context, "rig", None))))

    def observe_ground_truth(self, boxes_ego: np.ndarray, n_points: np.ndarray) -> None:
        if self.wants.ground_truth:
            self._gt = (np.asarray(boxes_ego, np.float64), np.asarray(n_points, np.int64))

    def observe_lidar_frame(self, frame: Any) -> None:
        """The simulator's LiDAR frame before :meth:`step`: its per-point sensor indices."""
        self._sensor_ids = np.asarray(getattr(frame, "sensor", np.zeros(0)), np.int8)

    def step(self, points: np.ndarray, ego_state: EgoState) -> AutonomyOutputs:
        pts = np.asarray(points, np.float32).reshape(-1, np.asarray(points).shape[-1] if np.asarray(points).ndim else 3)
        if pts.shape[1] == 3:
            pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], axis=1)
        pts = np.ascontiguousarray(pts[:, :4])
        sensor = self._sensor_ids if self._sensor_ids is not None and len(self._sensor_ids) == len(pts) \
            else np.zeros(len(pts), np.int8)
        if not self.wants.lidar:
            pts, sensor = np.zeros((0, 4), np.float32), np.zeros(0, np.int8)
        if self._t0 is None:
            self._t0 = float(ego_state.time)
        gt = self._gt if self.wants.ground_truth else None
        frame = Frame(self._index, float(ego_state.time) - self._t0, ego_state, pts, sensor,
                      None if gt is None else gt[0], None if gt is None else gt[1])
        self._index += 1
        t = time.perf_counter()
        out = self.stack.run_step(frame)
        elapsed = time.perf_counter() - t
        return self._outputs(out, ego_state, elapsed)

    def _outputs(self, out: Any, ego: EgoState, elapsed: float) -> AutonomyOutputs:
        name = self.stack_info.name
        if not isinstance(out, StepOutput):
            raise StackFailure(f"stack {name!r}: run_step returned {type(out).__name__}, not a StepOutput")
        plan = out.plan
        if not isinstance(plan, Plan):
            raise StackFailure(f"stack {name!r}: StepOutput.plan is {type(plan).__name__}, not a Plan")
        _check_array(plan.trajectory, (3,), f"stack {name!r}: plan.trajectory")
        if len(plan.trajectory) < 2 or not np.isfinite(plan.speed).all():
            raise StackFailure(f"stack {name!r}: plan needs >= 2 finite poses and speeds")
        provided = {"plan"}
        for what in OUTPUTS:
            value = getattr(out, what)
            if value is not None:
                if what not in self.stack_info.provides:
                    raise StackFailure(f"stack {name!r}: answered {what}, which its StackInfo.provides does not list")
                provided.add(what)
            elif what in self.stack_info.provides:
                raise StackFailure(f"stack {name!r}: StackInfo.provides lists {what}, but this frame has none")
        if out.detections is not None:
            _check_array(out.detections.boxes, (5,), f"stack {name!r}: detections.boxes")
        timings = {"stack": elapsed, **{k: float(v) for k, v in (out.timings or {}).items()}}
        return AutonomyOutputs(out.detections if out.detections is not None else Detections(),
                               out.tracks if out.tracks is not None else Tracks(),
                               out.predictions if out.predictions is not None else Predictions(),
                               plan, timings, out.occupancy, provided=frozenset(provided))

    def close(self) -> None:
        close = getattr(self.stack, "close", None)
        if close is not None:
            close()


# ----------------------------------------------------------- adv3d's own stacks' identity

def planner_fingerprint() -> str:
    """sha256 (first 16 hex digits) of the planner's default parameters (limits, weights,
    proposals): retuning the planner changes every closed-loop result, like new weights do."""
    import dataclasses
    import hashlib
    import json

    from .planner.planner import PlannerConfig
    from .planner.proposals import fingerprint_fields

    doc = dataclasses.asdict(PlannerConfig())
    doc["proposals"] = fingerprint_fields(doc["proposals"])  # a rule switched off is not hashed
    text = json.dumps(doc, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def model_fingerprints(models: tuple[str, ...] = ("detector", "predictor")) -> dict[str, str]:
    """sha256 (first 16 hex digits) of every file under assets/models/<model> for each of
    ``models`` (Autonomy-A's by default): a run's results depend on the weights, which may be
    retrained between runs."""
    import hashlib

    from ..fileio import REPO_ROOT

    out = {}
    for sub in models:
        d = REPO_ROOT / "assets" / "models" / sub
        if not d.is_dir():
            continue
        h = hashlib.sha256()
        for f in sorted(p for p in d.rglob("*") if p.is_file() and p.suffix in (".pt", ".json", ".safetensors")):
            h.update(f.relative_to(d).as_posix().encode())
            h.update(f.read_bytes())
        out[sub] = h.hexdigest()[:16]
    return out


def builtin_info(name: str, models: tuple[str, ...], provides: tuple[str, ...]) -> StackInfo:
    """The :class:`~.api.StackInfo` of one of adv3d's own stacks: adv3d's version, and a
    fingerprint of its weights and planner parameters."""
    import hashlib
    import json

    from .. import __version__

    parts = {"models": model_fingerprints(models), "planner": planner_fingerprint()}
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    return StackInfo(name, __version__, frozenset(provides), digest)


def with_info(stack: Any, info: StackInfo) -> Any:
    stack.stack_info = info
    return stack


__all__ = ["ENTRY_POINT_GROUP", "BUILTIN", "StackEntry", "registered", "check_spec", "build", "info_of",
           "PluginStack", "planner_fingerprint", "model_fingerprints", "builtin_info"]
