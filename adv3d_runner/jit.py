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


def _blas_extension_alone() -> object | None:
    """scipy's ``cython_blas`` extension module, loaded from its own file (None when that fails).

    numba's compilation target, set up at a process's first kernel call, checks that a BLAS is
    available (``numba.np.old_arraymath``: ``import scipy.linalg.cython_blas``); that import
    runs the whole ``scipy.linalg`` package (~0.25 CPU-s, docs/performance.md "Start-up"),
    though only the extension's C function table is used. The same extension, so the same BLAS
    functions; the package stays importable as before."""
    import importlib.machinery
    import importlib.util

    try:
        spec = importlib.util.find_spec("scipy")
    except (ImportError, ValueError):
        return None
    folders = list(spec.submodule_search_locations or ()) if spec else []
    for suffix in importlib.machinery.EXTENSION_SUFFIXES if folders else ():
        path = f"{folders[0]}/linalg/cython_blas{suffix}"
        try:
            loader = importlib.machinery.ExtensionFileLoader(_BLAS, path)
            module = importlib.util.module_from_spec(importlib.util.spec_from_loader(_BLAS, loader, origin=path))
            loader.exec_module(module)
        except (ImportError, OSError):
            continue
        if getattr(module, "__pyx_capi__", None):
            return module
    return None


_BLAS = "scipy.linalg.cython_blas"


def _target_setup_without_scipy_linalg() -> None:
    """Wrap numba's set-up of its CPU target (``CPUContext.load_additional_registries``, whose
    first call imports numba's implementations) so that its BLAS check finds
    :func:`_blas_extension_alone` in ``sys.modules`` instead of importing ``scipy.linalg``. The
    entry is taken out again afterwards (unless the package was imported meanwhile), so a later
    ``import scipy.linalg`` runs as usual, and the wrapper puts the original method back after
    its first call. Nothing changes where numba lacks that method (another numba version): the
    package import then runs as before."""
    import sys

    from numba.core import cpu

    context = getattr(cpu, "CPUContext", None)
    original = vars(context).get("load_additional_registries") if isinstance(context, type) else None
    if original is None:
        return

    def load_additional_registries(self):
        cpu.CPUContext.load_additional_registries = original
        added = False
        if _BLAS not in sys.modules and "scipy.linalg" not in sys.modules:
            module = _blas_extension_alone()
            if module is not None:
                sys.modules[_BLAS] = module
                added = True
        try:
            return original(self)
        finally:
            if added and "scipy.linalg" not in sys.modules:
                sys.modules.pop(_BLAS, None)

    cpu.CPUContext.load_additional_registries = load_additional_registries


_target_setup_without_scipy_linalg()
