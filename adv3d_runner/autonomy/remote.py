"""A stack in its own process, over the wire protocol (docs/stack_protocol.md).

:class:`RemoteStack` is adv3d's side: it starts the stack's process (``exec:COMMAND``) or
connects to one already running (``tcp://HOST:PORT``, ``unix:PATH``), and implements the public
:class:`~.api.Stack` by messages. Every wait has a timeout; a stack that crashes, hangs,
answers malformed data, NaN or another protocol version raises
:class:`~adv3d_runner.errors.StackFailure` (in an attack: that query fails, the run goes on),
and its process is killed, never left behind; the next episode starts a fresh one.

:func:`serve` is the reference server for a Python stack that can import adv3d:
``python -m adv3d_runner.autonomy.remote package.module:factory`` serves the factory's stack on
stdin/stdout, so ``--autonomy "exec:python -m adv3d_runner.autonomy.remote mystack:make"`` runs
an in-process stack out of process. A stack in another environment copies
:mod:`.wire` (self-contained) and answers the same messages.
"""
from __future__ import annotations

import atexit
import os
import select
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from typing import Any

import numpy as np

from ..errors import ConfigError, StackFailure
from . import wire
from .api import Episode, Frame, Lane, LidarSensor, Sensors, StackInfo, StepOutput
from .interface import Detections, EgoState, Plan, Predictions, Tracks

#: Seconds a stack may take to start and say hello, and to answer one message.
START_TIMEOUT = float(os.environ.get("ADV3D_STACK_START_TIMEOUT", "120"))
STEP_TIMEOUT = float(os.environ.get("ADV3D_STACK_TIMEOUT", "30"))

_LIVE: "weakref.WeakSet[RemoteStack]" = weakref.WeakSet()


@atexit.register
def _close_all() -> None:  # no orphan stack process outlives the runner
    for stack in list(_LIVE):
        stack.close()


#: Pipe capacity asked for (Linux; capped by /proc/sys/fs/pipe-max-size for non-root users): a
#: 2 MB frame then crosses in one write instead of 32 rounds of 64 KB (bench/stack_protocol.py).
PIPE_BYTES = 8 * 2**20


def _widen_pipe(fd: int) -> None:
    try:
        import fcntl

        fcntl.fcntl(fd, 1031, PIPE_BYTES)  # F_SETPIPE_SZ
    except (OSError, ImportError):
        try:
            limit = int(open("/proc/sys/fs/pipe-max-size").read())
            fcntl.fcntl(fd, 1031, limit)
        except (OSError, ValueError, ImportError, NameError):
            pass  # keep the default: slower, not wrong


def _die_with_parent() -> None:
    """In the child, before exec: get SIGKILL when the runner dies, even by SIGKILL (Linux)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - not Linux: atexit and close() still end it
        pass


# ----------------------------------------------------------------- dataclasses <-> wire maps

def ego_to_wire(e: EgoState) -> dict:
    return {"pose": np.asarray(e.pose, np.float64), "speed": float(e.speed), "acceleration": float(e.acceleration),
            "curvature": float(e.curvature), "time": float(e.time), "length": float(e.length),
            "width": float(e.width), "wheelbase": float(e.wheelbase)}


def episode_to_wire(ep: Episode) -> dict:
    return {"scene_id": ep.scene_id, "dt": ep.dt,
            "lanes": [{"id": ln.id, "centerline": np.asarray(ln.centerline, np.float64),
                       "width": np.asarray(ln.width, np.float64), "left": ln.left, "right": ln.right,
                       "successors": list(ln.successors), "speed_limit": ln.speed_limit} for ln in ep.lanes],
            "rig": [{"model": s.model, "mount": list(s.mount), "channels": s.channels, "columns": s.columns}
                    for s in ep.rig]}


def episode_from_wire(m: dict) -> Episode:
    lanes = tuple(Lane(int(ln["id"]), np.asarray(ln["centerline"], np.float64), np.asarray(ln["width"], np.float64),
                       ln.get("left"), ln.get("right"), tuple(ln.get("successors", ())), ln.get("speed_limit"))
                  for ln in m["lanes"])
    rig = tuple(LidarSensor(s["model"], tuple(s["mount"]), int(s["channels"]), int(s["columns"])) for s in m["rig"])
    return Episode(str(m["scene_id"]), float(m["dt"]), lanes, rig)


def frame_to_wire(f: Frame) -> dict:
    out = {"index": f.index, "time": f.time, "ego": ego_to_wire(f.ego),
           "points": np.ascontiguousarray(f.points, np.float32), "sensor": np.ascontiguousarray(f.sensor, np.int8)}
    if f.ground_truth is not None:
        out["ground_truth"] = np.asarray(f.ground_truth, np.float64)
        out["ground_truth_points"] = np.asarray(f.ground_truth_points, np.int64)
    return out


def frame_from_wire(m: dict) -> Frame:
    e = m["ego"]
    ego = EgoState(np.asarray(e["pose"], np.float64), float(e["speed"]), float(e["acceleration"]),
                   float(e["curvature"]), float(e["time"]), float(e["length"]), float(e["width"]),
                   float(e["wheelbase"]))
    return Frame(int(m["index"]), float(m["time"]), ego, m["points"], m["sensor"], m.get("ground_truth"),
                 m.get("ground_truth_points"))


def output_to_wire(o: StepOutput) -> dict:
    plan: dict[str, Any] = {"trajectory": o.plan.trajectory, "speed": o.plan.speed, "dt": o.plan.dt}
    for key in ("acceleration", "curvature"):
        if getattr(o.plan, key) is not None:
            plan[key] = np.asarray(getattr(o.plan, key), np.float64)
    out: dict[str, Any] = {"plan": plan, "timings": dict(o.timings)}
    if o.detections is not None:
        out["detections"] = {"boxes": o.detections.boxes, "scores": o.detections.scores}
    if o.tracks is not None:
        out["tracks"] = {"ids": o.tracks.ids, "boxes": o.tracks.boxes, "velocities": o.tracks.velocities,
                         "scores": o.tracks.scores}
    if o.predictions is not None:
        out["predictions"] = {"track_ids": o.predictions.track_ids, "trajectories": o.predictions.trajectories,
                              "probabilities": o.predictions.probabilities, "dt": o.predictions.dt}
    return out


def _finite(a: Any, what: str, tail: tuple[int, ...] | None = None) -> np.ndarray:
    arr = np.asarray(a, np.float64)
    if tail is not None and (arr.ndim != 1 + len(tail) or arr.shape[1:] != tail):
        raise StackFailure(f"{what}: expected shape (N, {', '.join(map(str, tail))}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise StackFailure(f"{what}: not finite (NaN or inf)")
    return arr


def output_from_wire(m: Any, name: str) -> StepOutput:
    """A ``step`` answer's ``output`` map -> :class:`StepOutput`, every field checked."""
    where = f"stack {name!r}"
    try:
        p = m["plan"]
        traj = _finite(p["trajectory"], f"{where}: plan.trajectory", (3,))
        extra = {k: _finite(p[k], f"{where}: plan.{k}") for k in ("acceleration", "curvature") if p.get(k) is not None}
        plan = Plan(traj, _finite(p["speed"], f"{where}: plan.speed"), dt=float(p.get("dt", 0.1)), **extra)
        det = tracks = preds = None
        if m.get("detections") is not None:
            d = m["detections"]
            det = Detections(_finite(d["boxes"], f"{where}: detections.boxes", (5,)),
                             _finite(d["scores"], f"{where}: detections.scores"))
        if m.get("tracks") is not None:
            t = m["tracks"]
            ids = np.asarray(t["ids"], np.int64).reshape(-1)
            tracks = Tracks(ids, _finite(t["boxes"], f"{where}: tracks.boxes", (5,)),
                            _finite(t["velocities"], f"{where}: tracks.velocities", (2,)),
                            _finite(t["scores"], f"{where}: tracks.scores"),
                            np.zeros(len(ids), np.int64),  # not part of the protocol: seen this frame
                            np.zeros((len(ids), 0, 3)), np.zeros((len(ids), 0), bool))
        if m.get("predictions") is not None:
            q = m["predictions"]
            preds = Predictions(np.asarray(q["track_ids"], np.int64), _finite(q["trajectories"], f"{where}: predictions"),
                                _finite(q["probabilities"], f"{where}: predictions.probabilities"),
                                float(q.get("dt", 0.1)))
        timings = {str(k): float(v) for k, v in (m.get("timings") or {}).items()}
    except StackFailure:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise StackFailure(f"{where}: malformed step answer ({type(exc).__name__}: {exc})") from None
    return StepOutput(plan, det, tracks, preds, None, timings)


# ----------------------------------------------------------------------------- the client

class RemoteStack:
    """The public :class:`~.api.Stack` of a stack in another process.

    Args:
        command: argv that starts the stack (it reads messages on stdin, answers on stdout);
            or None with ``address`` to connect.
        address: ``("tcp", (host, port))`` or ``("unix", path)`` of a running stack.
    """

    def __init__(self, command: list[str] | None = None, address: tuple[str, Any] | None = None, label: str = ""):
        if (command is None) == (address is None):
            raise ConfigError("RemoteStack needs a command or an address")
        self.command, self.address = command, address
        self.label = label or (" ".join(command) if command else f"{address[0]}:{address[1]}")
        self._proc: subprocess.Popen | None = None
        self._sock: socket.socket | None = None
        self._in = self._out = None
        self._stderr = None
        self._info: StackInfo | None = None
        self._sensors: Sensors | None = None
        _LIVE.add(self)
        self._start()

    @classmethod
    def from_spec(cls, spec: str) -> "RemoteStack":
        if spec.startswith("exec:"):
            argv = shlex.split(spec[len("exec:"):])
            if not argv:
                raise ConfigError(f"stack {spec!r}: exec: needs a command")
            return cls(command=argv, label=spec)
        if spec.startswith("tcp://"):
            host, _, port = spec[len("tcp://"):].rpartition(":")
            if not host or not port.isdigit():
                raise ConfigError(f"stack {spec!r}: expected tcp://HOST:PORT")
            return cls(address=("tcp", (host, int(port))), label=spec)
        if spec.startswith("unix:"):
            return cls(address=("unix", spec[len("unix:"):]), label=spec)
        raise ConfigError(f"stack {spec!r}: not a remote stack address")

    # -- connection
    def _start(self) -> None:
        try:
            if self.command is not None:
                self._stderr = tempfile.TemporaryFile()
                self._proc = subprocess.Popen(self.command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                              stderr=self._stderr, preexec_fn=_die_with_parent,
                                              start_new_session=True, bufsize=0)
                self._in, self._out = self._proc.stdout, self._proc.stdin
                for pipe in (self._in, self._out):
                    _widen_pipe(pipe.fileno())
            else:
                kind, where = self.address
                family = socket.AF_INET if kind == "tcp" else socket.AF_UNIX
                self._sock = socket.socket(family, socket.SOCK_STREAM)
                self._sock.settimeout(START_TIMEOUT)
                self._sock.connect(where)
                self._in, self._out = self._sock.makefile("rb", buffering=0), self._sock.makefile("wb", buffering=0)
        except OSError as exc:
            self.close()
            raise StackFailure(f"stack {self.label!r} could not be started or reached: {exc}") from None
        os.set_blocking(self._out.fileno(), False)  # writes wait in select, with the deadline
        hello = self._call({"type": "hello", "protocol": wire.PROTOCOL_VERSION}, START_TIMEOUT, expect="hello")
        if hello.get("protocol") != wire.PROTOCOL_VERSION:
            self.close()
            raise StackFailure(f"stack {self.label!r} speaks protocol version {hello.get('protocol')!r}, adv3d "
                               f"speaks {wire.PROTOCOL_VERSION} (docs/stack_protocol.md)")
        try:
            i, s = hello["info"], hello.get("sensors") or {}
            info = StackInfo(str(i["name"]), str(i["version"]), frozenset(i.get("provides", ())),
                             str(i.get("fingerprint", "")))
            sensors = Sensors(bool(s.get("lidar", True)), bool(s.get("ground_truth", False)))
        except (KeyError, TypeError, ValueError) as exc:
            self.close()
            raise StackFailure(f"stack {self.label!r}: malformed hello ({exc})") from None
        if self._info is not None and (info.name, info.version, info.fingerprint) != (
                self._info.name, self._info.version, self._info.fingerprint):
            self.close()
            raise StackFailure(f"stack {self.label!r} restarted as another stack ({info.name} {info.version})")
        self._info, self._sensors = info, sensors

    def _alive(self) -> bool:
        return (self._proc is not None and self._proc.poll() is None) or self._sock is not None

    def _why_dead(self) -> str:
        if self._proc is None:
            return "the connection closed"
        code = self._proc.poll()
        tail = ""
        if self._stderr is not None:
            self._stderr.seek(0)
            text = self._stderr.read().decode(errors="replace").strip().splitlines()
            tail = f"; its last words: {text[-1][:300]}" if text else ""
        return f"its process exited with code {code}{tail}"

    def _call(self, message: dict, timeout: float, expect: str) -> dict:
        if self._in is None or not self._alive():
            raise StackFailure(f"stack {self.label!r} is not running ({self._why_dead()})")
        try:
            deadline = time.monotonic() + timeout
            for part in wire.encode_parts(message):
                self._send(part, deadline, message["type"], timeout)
            answer = wire.decode(self._read_body(deadline, message["type"], timeout))
        except StackFailure:
            raise
        except (EOFError, BrokenPipeError, ConnectionError, OSError) as exc:
            if self._proc is not None:
                try:  # it closed its end: give it a moment to exit, to say how it ended
                    self._proc.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    pass
            why = self._why_dead() if self._proc is not None and self._proc.poll() is not None else str(exc)
            self.close()
            raise StackFailure(f"stack {self.label!r} failed during {message['type']!r}: {why}") from None
        except wire.ProtocolError as exc:
            self.close()
            raise StackFailure(f"stack {self.label!r} answered {message['type']!r} with a malformed message: {exc}") \
                from None
        if answer["type"] == "error":
            raise StackFailure(f"stack {self.label!r} reported an error during {message['type']!r}: "
                               f"{answer.get('message', '')}")
        if answer["type"] != expect:
            self.close()
            raise StackFailure(f"stack {self.label!r} answered {message['type']!r} with {answer['type']!r}")
        return answer

    def _send(self, data: bytes, deadline: float, what: str, timeout: float) -> None:
        """Write all of ``data`` before ``deadline`` (a stack that stops reading cannot block us)."""
        fd, view = self._out.fileno(), memoryview(data)
        while len(view):
            left = deadline - time.monotonic()
            ready = select.select([], [fd], [], max(left, 0.0))[1] if left > 0 else []
            if not ready:
                self.close()
                raise StackFailure(f"stack {self.label!r} did not take {what!r} within {timeout:g} s (ADV3D_STACK_TIMEOUT)")
            try:
                view = view[os.write(fd, view):]  # non-blocking: takes what fits
            except BlockingIOError:
                continue

    def _read(self, n: int, deadline: float, what: str, timeout: float) -> bytes:
        """``n`` bytes of the answer, waiting at most until ``deadline`` (the streams are
        unbuffered, so ``select`` sees every byte that has not been read)."""
        fd, chunks, got = self._in.fileno(), [], 0
        while got < n:
            left = deadline - time.monotonic()
            ready = select.select([fd], [], [], max(left, 0.0))[0] if left > 0 else []
            if not ready:
                self.close()
                raise StackFailure(f"stack {self.label!r} did not answer {what!r} within {timeout:g} s "
                                   f"(ADV3D_STACK_TIMEOUT)")
            chunk = os.read(fd, min(n - got, 1 << 20))
            if not chunk:
                raise EOFError(f"the stream ended after {got} of {n} bytes")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def _read_body(self, deadline: float, what: str, timeout: float) -> bytes:
        (size,) = wire._HEADER.unpack(self._read(wire._HEADER.size, deadline, what, timeout))
        if size > wire.MAX_MESSAGE_BYTES:
            raise wire.ProtocolError(f"message of {size} bytes announced, over the limit ({wire.MAX_MESSAGE_BYTES})")
        return self._read(size, deadline, what, timeout)

    # -- the public Stack
    def info(self) -> StackInfo:
        return self._info

    def sensors(self) -> Sensors:
        return self._sensors

    def reset(self, episode: Episode) -> None:
        if not self._alive() or self._in is None:
            self._start()  # a fresh process after a failure
        self._call({"type": "reset", "episode": episode_to_wire(episode)}, STEP_TIMEOUT, expect="ok")

    def run_step(self, frame: Frame) -> StepOutput:
        answer = self._call({"type": "step", "frame": frame_to_wire(frame)}, STEP_TIMEOUT, expect="step")
        return output_from_wire(answer.get("output"), self._info.name)

    def close(self) -> None:
        """End the connection and the process (kill after a short grace)."""
        proc, self._proc = self._proc, None
        for stream in (self._out, self._in):
            try:
                if stream is not None:
                    if stream is self._out and proc is not None and proc.poll() is None:
                        wire.write_message(stream, {"type": "close"})
                    stream.close()
            except (OSError, ValueError):
                pass
        self._in = self._out = None
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None
        if proc is not None:
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except OSError:
                    proc.kill()
                proc.wait()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


# ---------------------------------------------------------------------- the reference server

def handler_for(stack: Any):
    """The message handler of :func:`wire.serve_messages` for a public :class:`~.api.Stack`."""
    def handle(msg: dict) -> dict | None:
        kind = msg["type"]
        if kind == "hello":
            info, sensors = stack.info(), stack.sensors()
            return {"type": "hello", "protocol": wire.PROTOCOL_VERSION,
                    "info": {"name": info.name, "version": info.version, "provides": sorted(info.provides),
                             "fingerprint": info.fingerprint},
                    "sensors": {"lidar": sensors.lidar, "ground_truth": sensors.ground_truth}}
        if kind == "reset":
            stack.reset(episode_from_wire(msg["episode"]))
            return {"type": "ok"}
        if kind == "step":
            return {"type": "step", "output": output_to_wire(stack.run_step(frame_from_wire(msg["frame"])))}
        return {"type": "error", "message": f"unknown message type {kind!r}"}
    return handle


def serve(stack: Any, stream_in=None, stream_out=None) -> None:
    """Serve ``stack`` (a public :class:`~.api.Stack`) on stdin/stdout until ``close``."""
    wire.serve_messages(handler_for(stack), stream_in or sys.stdin.buffer, stream_out or sys.stdout.buffer)


def main(argv: list[str] | None = None) -> int:
    """``python -m adv3d_runner.autonomy.remote package.module:factory``."""
    import importlib

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or ":" not in args[0]:
        print("usage: python -m adv3d_runner.autonomy.remote package.module:factory", file=sys.stderr)
        return 2
    module, _, attr = args[0].partition(":")
    stack = getattr(importlib.import_module(module), attr)()
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # the stack's prints must not corrupt the message stream
    serve(stack, sys.stdin.buffer, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["RemoteStack", "serve", "handler_for", "main", "START_TIMEOUT", "STEP_TIMEOUT"]
