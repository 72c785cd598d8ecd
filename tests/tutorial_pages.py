"""Run a tutorial page's commands as written (docs/tutorials/*.md).

Every fenced ``sh`` block of a page is run line by line in an empty folder, except blocks whose
title says "not run" (the full-size commands beside the tiny ones). ``$ADV3D`` is this
checkout; ``adv3d`` runs this checkout's command line with this Python, ``python`` is this
Python, and a leading ``NAME=VALUE`` sets an environment variable (``PYTHONPATH=.``: the
folder the commands run in, before the checkout).
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TUTORIALS = ROOT / "docs" / "tutorials"
#: Shell tools a page may use besides adv3d, python and what its environment installs.
SHELL_TOOLS = ("cp", "mkdir")


def blocks(text: str, lang: str) -> list[tuple[str, str]]:
    """(info string after the language, body) of every fenced block of ``lang``."""
    return re.findall(rf"^```{lang}([^\n]*)\n(.*?)^```", text, flags=re.S | re.M)


def commands(page: str) -> list[str]:
    """The command lines a page's reader runs, in order (continuation lines joined)."""
    text = (TUTORIALS / page).read_text()
    out = []
    for info, body in blocks(text, "sh"):
        if "not run" in info:
            continue
        for line in body.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                out.append(line.strip())
    return out


def run(line: str, cwd: Path, timeout: float = 900, env: dict | None = None) -> subprocess.CompletedProcess:
    """One command of a page, as its reader would run it with this checkout."""
    line = line.replace("$ADV3D", str(ROOT)).replace("exec:python ", f"exec:{sys.executable} ")
    words = shlex.split(line)
    env = {**os.environ, **(env or {})}
    while "=" in words[0]:
        key, value = words.pop(0).split("=", 1)
        env[key] = os.pathsep.join([str(cwd / value) if value == "." else value, str(ROOT)])
    env.setdefault("PYTHONPATH", str(ROOT))
    if words[0] == "adv3d":
        words = [sys.executable, "-m", "adv3d_runner.cli", "-q", *words[1:]]
    elif words[0] == "python":
        words = [sys.executable, *words[1:]]
    elif words[0] == "ray" and not (Path(sys.executable).parent / "ray").is_file():
        words = [sys.executable, "-m", "ray.scripts.scripts", *words[1:]]   # Ray's command line
    elif words[0] in SHELL_TOOLS:
        words = [shutil.which(words[0]) or words[0], *words[1:]]
    else:
        tool = Path(sys.executable).parent / words[0]
        assert tool.is_file(), f"the page runs {words[0]!r}, which is not installed beside {sys.executable}"
        words = [str(tool), *words[1:]]
    return subprocess.run(words, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def run_all(page: str, cwd: Path, env: dict | None = None) -> list[str]:
    """Run every command of ``page`` in ``cwd``; their standard outputs, in order. ``export
    NAME=VALUE ...`` sets variables for the commands after it."""
    env = dict(env or {})
    outputs = []
    for line in commands(page):
        if line.startswith("export "):
            env.update(word.split("=", 1) for word in shlex.split(line)[1:])
            continue
        res = run(line, cwd, env=env)
        assert res.returncode == 0, f"{page}: {line}\n{res.stderr[-3000:]}"
        outputs.append(res.stdout)
    return outputs
