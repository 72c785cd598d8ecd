"""A stack in its own process that misbehaves on purpose (tests/test_stacks.py):

    python tests/stacks/broken_server.py MODE

MODE: ok (a constant-speed plan), crash (exits on frame 3), crash-odd COUNTER (exits on frame 3
of every other episode, counted in the file COUNTER across restarts), hang (never answers frame 3), garbage (answers frame 3 with bytes that
are not msgpack), nan (a NaN plan on frame 3), version (answers hello with protocol 99),
silent (never answers hello), error (reports an error on frame 3).

It uses only adv3d's self-contained wire module, as a stack in another environment would.
"""
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "adv3d_runner", "autonomy"))
import wire  # noqa: E402

MODE = sys.argv[1]
state = {"episodes": 0}


def plan(frame, bad=False):
    x, y, yaw = frame["ego"]["pose"]
    v = frame["ego"]["speed"]
    s = v * 0.1 * np.arange(31)
    traj = np.stack([x + s * np.cos(yaw), y + s * np.sin(yaw), np.full(31, yaw)], axis=1)
    if bad:
        traj[5, 0] = np.nan
    return {"plan": {"trajectory": traj, "speed": np.full(31, v), "dt": 0.1}}


def handle(msg):
    kind = msg["type"]
    if kind == "hello":
        if MODE == "silent":
            time.sleep(3600)
        return {"type": "hello", "protocol": 99 if MODE == "version" else wire.PROTOCOL_VERSION,
                "info": {"name": f"broken-{MODE}", "version": "0.1", "provides": [], "fingerprint": ""},
                "sensors": {"lidar": True, "ground_truth": False}}
    if kind == "reset":
        state["episodes"] += 1
        if MODE == "crash-odd":  # count across the processes the runner restarts
            path = sys.argv[2]
            n = int(open(path).read() or 0) + 1 if os.path.exists(path) else 1
            open(path, "w").write(str(n))
            state["episodes"] = n
        return {"type": "ok"}
    frame = msg["frame"]
    if frame["index"] == 3:
        if MODE == "crash" or (MODE == "crash-odd" and state["episodes"] % 2 == 1):
            print("simulated crash of the stack", file=sys.stderr, flush=True)
            os._exit(3)
        if MODE == "hang":
            time.sleep(3600)
        if MODE == "garbage":
            sys.stdout.buffer.write(wire._HEADER.pack(5) + b"\xc1\xc1\xc1\xc1\xc1")
            sys.stdout.buffer.flush()
            return None
        if MODE == "error":
            raise RuntimeError("the planner found no trajectory")
    return {"type": "step", "output": plan(frame, bad=MODE == "nan" and frame["index"] == 3)}


wire.serve_messages(handle, sys.stdin.buffer, sys.stdout.buffer)
