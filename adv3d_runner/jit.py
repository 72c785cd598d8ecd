"""Compiled loops: the one place that says how numba compiles adv3d's kernels.

Why numba: the per-frame hot loops (the planner's rollout of ~25 candidates over 50
steps, the LiDAR effects over ~110k returns, rotated NMS over a few dozen boxes) are short
sequences of operations on small arrays, or one pass that numpy can only express as dozens of
passes. numpy's per-call overhead (~1 us) and its temporaries then cost more than the
arithmetic; a compiled loop does not pay them. numba compiles plain Python over numpy arrays,
needs no C toolchain, and its compiled functions are cached on disk next to their module.

Conventions for every kernel:

* no ``fastmath`` and no ``parallel``: IEEE arithmetic in the written order (the results are
  deterministic and, where a kernel replaces numpy code, bit for bit the same unless its
  docstring says otherwise), and no thread pool spinning against the process's other threads
  (:mod:`adv3d_runner.machine`, ``bench/threads.py``);
* ``cache=True``: compiled once per checkout (the first ``adv3d simulate`` of a fresh clone
  spends about 12 s compiling the kernels an episode uses: 15.2 s against 3.0 s for a 0.5 s
  episode of ``highway-benchmark-000000`` here, 2026-11-27, after the predictor's and the
  Embree binding's kernels; 6.5 s before them), then loaded from ``__pycache__`` by every
  process, workers included;
* a kernel takes and returns arrays (the caller checks shapes and dtypes, so a kernel sees one
  signature and compiles once).
"""
from __future__ import annotations

from typing import Callable

import numba


def kernel(fn: Callable) -> Callable:
    """Compile ``fn`` as an adv3d kernel (see the module docstring)."""
    return numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")(fn)
