"""Start-up budget of the ``adv3d`` command (docs/performance.md, "Start-up").

Building the command line must not import the numerical stack: every subcommand's
``register()`` imports only light modules (names, bounds, argument types) and each handler
imports what it needs. Checked with ``python -X importtime`` in a subprocess (the modules a
command loaded, whatever the machine's load) and a generous CPU bound (measured about 0.15
CPU-s on an AMD EPYC VM; the bound is 1.0).
"""
from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Modules ``--help`` of any command must not load (each costs 0.1 to 1.7 CPU-s to import).
HEAVY = ("numpy", "torch", "numba", "scipy", "trimesh", "embreex", "sklearn", "skimage", "matplotlib", "ray")


def _imported(args: list[str], env: dict | None = None) -> tuple[set[str], float, subprocess.CompletedProcess]:
    """Modules a ``python -m adv3d_runner.cli ARGS`` run imported, and its CPU seconds."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "adv3d_runner.cli", *args],
                          capture_output=True, text=True, cwd=ROOT, env={**os.environ, **(env or {})}, timeout=300)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    names = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    return names, cpu, proc


def _top(names: set[str]) -> set[str]:
    return {n.split(".")[0] for n in names}


def test_help_imports_nothing_heavy_and_is_cheap():
    names, cpu, proc = _imported(["--help"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "simulate" in proc.stdout
    assert not (_top(names) & set(HEAVY)), sorted(_top(names) & set(HEAVY))
    assert cpu < 1.0, f"adv3d --help took {cpu:.2f} CPU-s"


def test_building_every_parser_imports_nothing_heavy():
    """Building the parser runs every command's ``register()`` (nested parsers included):
    another command importing numpy there would show here."""
    code = ("import sys; from adv3d_runner.cli import build_parser, _leaf_parsers; "
            "print(len(list(_leaf_parsers(build_parser())))); print(' '.join(sorted(sys.modules)))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    count, names = proc.stdout.splitlines()
    assert int(count) > 20
    heavy = _top(set(names.split())) & set(HEAVY)
    assert not heavy, f"building the adv3d parser imports {sorted(heavy)}"


@pytest.mark.parametrize("words", [["simulate"], ["attack"], ["shapes", "build"], ["train", "detector"]])
def test_subcommand_help_is_cheap(words):
    names, cpu, proc = _imported([*words, "--help"])
    assert proc.returncode == 0, (words, proc.stderr[-2000:])
    assert not (_top(names) & set(HEAVY)), sorted(_top(names) & set(HEAVY))
    assert cpu < 1.5, f"adv3d {' '.join(words)} --help took {cpu:.2f} CPU-s"


def test_simulate_with_the_oracle_loads_no_torch_trimesh_or_scipy_optimize(tmp_path):
    """An episode without a learned model imports no torch; actor meshes come from the mesh
    cache (no trimesh); the tracker loads scipy's assignment alone (no scipy.optimize); numba's
    BLAS check finds scipy's BLAS extension loaded alone (no scipy.linalg, adv3d_runner/jit.py)."""
    scene = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not scene.exists():
        pytest.skip("bundled scene missing")
    env = {"ADV3D_CACHE": str(tmp_path / "cache")}
    # A first run fills the mesh cache (trimesh reads each glb once), in a process of its own:
    # this process may hold the meshes in memory already and then writes no cache.
    args = ["-q", "simulate", str(scene), "--seconds", "0.1", "--autonomy", "oracle", "--out", str(tmp_path / "run0")]
    assert _imported(args, env)[2].returncode == 0
    args = ["-q", "simulate", str(scene), "--seconds", "0.1", "--autonomy", "oracle", "--out", str(tmp_path / "run")]
    names, _, proc = _imported(args, env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    unwanted = ("scipy.optimize", "scipy.linalg")
    assert "torch" not in names and "trimesh" not in names and not set(unwanted) & names, \
        sorted(n for n in names if n.split(".")[0] in ("torch", "trimesh") or n in unwanted)
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_the_trackers_assignment_is_scipys():
    from scipy.optimize import linear_sum_assignment

    from adv3d_runner.autonomy import tracker

    rng = np.random.default_rng(0)
    for _ in range(100):
        cost = rng.random((int(rng.integers(1, 9)), int(rng.integers(1, 9))))
        cost[cost > 0.7] = 1e6
        for got, want in zip(tracker.linear_sum_assignment(cost), linear_sum_assignment(cost)):
            np.testing.assert_array_equal(got, want)


def test_numba_finds_blas_without_scipy_linalg_and_the_package_still_imports():
    """numba's target set-up runs with scipy's BLAS extension loaded alone: BLAS counts as
    available, ``scipy.linalg`` is not imported by it, and importing the package afterwards
    gives the package with the same extension (a fresh process: this one may hold scipy.linalg)."""
    code = ("import sys, numpy as np, adv3d_runner.jit; from numba import njit\n"
            "njit(lambda a: a.sum())(np.ones(3))\n"
            "import numba.np.old_arraymath as oa\n"
            "print(oa._HAVE_BLAS, 'scipy.linalg' in sys.modules)\n"
            "import scipy.linalg\n"
            "print(njit(lambda a, b: a @ b)(np.eye(2), np.full((2, 2), 3.0)).sum(), scipy.linalg.cython_blas.__name__)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["True", "False", "12.0", "scipy.linalg.cython_blas"], proc.stdout
