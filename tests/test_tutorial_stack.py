"""docs/tutorials/test_your_stack.md, run as written: its stack file and its commands, from an
empty folder (about a minute)."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "tutorials" / "test_your_stack.md"


def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}[^\n]*\n(.*?)```", text, flags=re.S)


def _run(line: str, cwd: Path) -> subprocess.CompletedProcess:
    """One command of the page: ``[PYTHONPATH=.] adv3d ...`` with this checkout's Python."""
    line = line.replace("$ADV3D", str(ROOT)).replace("exec:python ", f"exec:{sys.executable} ")
    words = shlex.split(line)
    env = {**os.environ}
    while "=" in words[0]:
        key, value = words.pop(0).split("=", 1)
        env[key] = os.pathsep.join([str(cwd / value) if value == "." else value, str(ROOT)])
    env.setdefault("PYTHONPATH", str(ROOT))
    assert words[0] == "adv3d", line
    return subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "-q", *words[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def test_the_tutorial_runs_as_written(tmp_path):
    text = PAGE.read_text()
    (python,) = [b for b in _blocks(text, "python")]
    (tmp_path / "mystack.py").write_text(python)
    outputs = []
    for block in _blocks(text, "sh"):
        for line in block.strip().splitlines():
            res = _run(line, tmp_path)
            assert res.returncode == 0, f"{line}\n{res.stderr}"
            outputs.append(res.stdout)
    assert json.loads(outputs[0])["name"] == "my-stack"
    metrics = json.loads((tmp_path / "sim" / "metrics.json").read_text())
    assert metrics["detection"] is None and "detections" in metrics["not_available"]
    assert (tmp_path / "attack" / "report.md").is_file()

    def costs(run):
        return [json.loads(x)["cost"] for x in (tmp_path / run / "queries.jsonl").read_text().splitlines()]

    assert costs("attack") == costs("attack-remote") and len(costs("attack")) == 8
    for run in ("attack", "attack-remote"):
        assert json.loads((tmp_path / run / "run.json").read_text())["versions"]["stack"]["name"] == "my-stack"
