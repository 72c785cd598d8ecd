"""The tests that touch numerics pass under an emulated other CPU (docs/reliability.md, "Same
seed, same result"): each emulation this CPU can run (``adv3d numerics --emulate``) makes numpy,
OpenBLAS, torch (MKL, oneDNN), numba and Embree run the kernels an AVX2-only or an SSE4.2 CPU
would. Slow (about 10 minutes per emulation on 2 cores); the whole fast suite the same way::

    adv3d numerics --emulate avx2 -- python -m pytest -m "not slow" -q
    adv3d numerics --emulate sse4.2 -- python -m pytest -m "not slow" -q
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from adv3d_runner.machine import EMBREE_TIERS, EMULATIONS, cpu_tier
from adv3d_runner.machine_cli import emulation_env

ROOT = Path(__file__).resolve().parent.parent

#: numerics, LiDAR, the planner, the detector, the predictor, the searchers, the shape space
NUMERIC_TESTS = ("test_numerics.py", "test_raycast.py", "test_coherent_cast.py", "test_lidar.py",
                 "test_lidar_pinned.py", "test_incremental.py", "test_draws.py", "test_planner.py",
                 "test_detector.py", "test_predictor.py", "test_tracker.py", "test_attack_search.py",
                 "test_mesh_io.py", "test_shape_space.py", "test_sdf.py", "test_episode.py", "test_metrics.py")


def _runnable(name: str) -> bool:
    have = cpu_tier()
    return have is not None and list(EMBREE_TIERS).index(name) <= list(EMBREE_TIERS).index(have)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EMULATIONS))
def test_numeric_tests_pass_under_an_emulated_cpu(name):
    if not _runnable(name):
        pytest.skip(f"this CPU cannot run the {name} kernels")
    files = [str(ROOT / "tests" / f) for f in NUMERIC_TESTS if (ROOT / "tests" / f).exists()]
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "not slow", "-p", "no:cacheprovider", *files],
                         cwd=ROOT, env=emulation_env(name), capture_output=True, text=True, timeout=3600)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert " passed" in out.stdout.splitlines()[-1]
