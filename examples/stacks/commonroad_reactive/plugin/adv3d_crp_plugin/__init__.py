"""adv3d plugin: the stack ``C`` (Autonomy-C).

Installed into adv3d's own environment (``bash examples/stacks/commonroad_reactive/install.sh``);
it only says how to start the stack: ``server.py`` of this example, run by the planner's own
virtual environment (``examples/stacks/commonroad_reactive/.venv``, numpy 2 and CommonRoad's
packages, which adv3d's environment cannot hold), spoken to over the wire protocol
(docs/stack_protocol.md). ``$ADV3D_CRP_PYTHON`` names another interpreter for the server.
"""
from __future__ import annotations

import os
from pathlib import Path

#: examples/stacks/commonroad_reactive (this package is installed editable, in place).
EXAMPLE = Path(__file__).resolve().parents[2]


def command() -> list[str]:
    """argv that starts Autonomy-C's server."""
    python = Path(os.environ.get("ADV3D_CRP_PYTHON") or EXAMPLE / ".venv" / "bin" / "python")
    server = EXAMPLE / "server.py"
    if not python.exists():
        raise FileNotFoundError(f"{python} is missing: run `bash {EXAMPLE / 'install.sh'}` first")
    if not server.is_file():
        raise FileNotFoundError(f"{server} is missing (the plugin must be installed editable from the example)")
    return [str(python), str(server)]


def make():
    """The ``adv3d.stacks`` factory of ``C``: a stack in its own process."""
    from adv3d_runner.autonomy.api import remote_stack

    return remote_stack(command())
