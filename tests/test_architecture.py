"""The layer contract (docs/architecture.md) is declared in pyproject.toml and enforced by
import-linter; these tests check that it holds on the tree and that it would catch a break."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LINT = Path(sys.executable).parent / "lint-imports"


def _lint(root: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(root))
    return subprocess.run([str(LINT), "--no-cache"], cwd=root, env=env, capture_output=True, text=True, timeout=120)


def test_layers_hold_on_the_tree():
    res = _lint(REPO)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "1 kept, 0 broken" in res.stdout


def test_an_upward_import_breaks_the_contract(tmp_path):
    for pkg in ("adv3d_runner", "blender_addon"):
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    lanes = tmp_path / "adv3d_runner" / "scene" / "lanes.py"
    lanes.write_text(lanes.read_text() + "\nfrom ..sim import episode  # the scene layer reaching up\n")
    res = _lint(tmp_path)
    assert res.returncode != 0
    assert "adv3d_runner.scene.lanes -> adv3d_runner.sim.episode" in res.stdout
