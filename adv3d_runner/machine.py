"""What machine a measurement was taken on: benchmarks and training reports record it."""
from __future__ import annotations

import contextlib

import os
import platform
from importlib.metadata import PackageNotFoundError, version


def _cpuinfo(field: str) -> str | None:
    """The first ``field`` of /proc/cpuinfo (None where there is none)."""
    try:
        with open("/proc/cpuinfo") as lines:
            for line in lines:
                if line.startswith(field):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one)."""
    return _cpuinfo("model name") or platform.processor() or platform.machine()


def machine_info(*packages: str, **extra) -> dict:
    """CPU, cores, load, Python and platform, the numerical configuration
    (:func:`numerical_config`), plus the installed versions of ``packages``.

    Args:
        packages: distribution names whose versions matter to the measurement
            (e.g. "numpy", "embreex", "torch").
        extra: further fields to record as they are.
    """
    info = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "cores_used": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
    }
    for name in packages:
        try:
            info[name] = version(name)
        except PackageNotFoundError:
            info[name] = None
    info["numerics"] = numerical_config()  # the kernels a speed or a result depends on
    info.update(extra)
    return info


def single_thread_env() -> dict[str, str]:
    """Environment variables that keep OpenMP (torch), OpenBLAS (numpy) and MKL to one thread.

    The simulation's numerical work is small per call (a BEV network on one frame, 4x4 Kalman
    updates, a few hundred planner candidates); extra threads only spin and yield against each
    other, on a shared machine or next to other worker processes (``bench/threads.py``). The
    parallelism of adv3d is its worker processes.
    """
    return {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}



@contextlib.contextmanager
def single_thread_children():
    """While the block runs, the environment holds :func:`single_thread_env`'s variables the user
    has not set (a value the user set wins), so processes spawned in it start their numerical
    libraries on one thread (they read the variables when numpy / torch load); restored after."""
    env = {k: v for k, v in single_thread_env().items() if k not in os.environ}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

def limit_threads() -> None:
    """One thread per numerical library in this process: the variables of
    :func:`single_thread_env` for libraries not loaded yet (a value the user set wins), and
    torch's intra-op threads if torch is loaded (torch reads OMP_NUM_THREADS when it starts)."""
    import sys

    for key, value in single_thread_env().items():
        os.environ.setdefault(key, value)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))


# -- the numerical configuration (docs/reliability.md, "Same seed, same result") ------------
#
# The same code and seed give the same bits only where every numerical library runs the same
# kernels: Embree, numpy, OpenBLAS, torch (MKL, oneDNN) and numba each pick theirs by the CPU's
# instruction set. What follows reads those choices (cheaply: nothing heavy is imported), pins
# Embree's, and names the environment variables that make this machine run another CPU's.

#: Embree ISA tiers adv3d pins (``ADV3D_EMBREE_ISA``), lowest first, with the CPU flags
#: (/proc/cpuinfo names) each needs. ``auto`` (the default) takes the highest the CPU has, so
#: every CPU of one tier traces alike; an AVX-only CPU traces as SSE4.2.
EMBREE_TIERS: dict[str, frozenset[str]] = {
    "sse4.2": frozenset({"sse4_2"}),
    "avx2": frozenset({"avx2", "fma"}),
    "avx512": frozenset({"avx512f", "avx512cd", "avx512dq", "avx512bw", "avx512vl"}),
}

#: Emulated CPU configurations: environment variables that make this process and its children
#: run the kernels another CPU would (``adv3d numerics --emulate NAME -- CMD``). Each library's
#: own switch: OpenBLAS's core type, numpy's dispatch, torch's ATen capability, oneDNN's and
#: MKL's instruction sets, numba's target, Embree's ISA.
_AVX512_NUMPY = "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL"
EMULATIONS: dict[str, dict[str, str]] = {
    "avx2": {  # e.g. AMD Zen 1-3, Intel Haswell to Alder Lake
        "OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": _AVX512_NUMPY,
        "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "NUMBA_CPU_NAME": "haswell", "ADV3D_EMBREE_ISA": "avx2"},
    "sse4.2": {  # e.g. Intel Nehalem, or a virtual machine that hides AVX
        "OPENBLAS_CORETYPE": "Nehalem", "NPY_DISABLE_CPU_FEATURES": "AVX F16C FMA3 AVX2 " + _AVX512_NUMPY,
        "ATEN_CPU_CAPABILITY": "default", "ONEDNN_MAX_CPU_ISA": "SSE41", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "NUMBA_CPU_NAME": "nehalem", "ADV3D_EMBREE_ISA": "sse4.2"},
}
#: Environment variables that change a numerical kernel (recorded when set).
NUMERICS_ENV = tuple(sorted({k for env in EMULATIONS.values() for k in env} | {"NUMBA_CPU_FEATURES", "MKL_CBWR"}))


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as /proc/cpuinfo names them (empty where there is none)."""
    return frozenset((_cpuinfo("flags") or "").split())


def cpu_vendor() -> str:
    """``GenuineIntel``, ``AuthenticAMD``, ... (MKL and OpenBLAS choose kernels by it too)."""
    return _cpuinfo("vendor_id") or platform.machine()


def cpu_tier(flags: frozenset[str] | None = None) -> str | None:
    """The highest of :data:`EMBREE_TIERS` whose flags the CPU has (None: below SSE4.2, or
    flags unknown, e.g. not Linux)."""
    flags = cpu_flags() if flags is None else flags
    best = None
    for tier, needs in EMBREE_TIERS.items():
        if needs <= flags:
            best = tier
    return best


def embree_isa() -> str | None:
    """The ISA adv3d's Embree device runs (``ADV3D_EMBREE_ISA``: ``auto`` or one of
    :data:`EMBREE_TIERS`); None where the CPU's tier is unknown (Embree then chooses).

    Raises:
        ConfigError: an unknown value, or a tier this CPU cannot run (it would die of an
            illegal instruction).
    """
    from .errors import ConfigError

    asked = os.environ.get("ADV3D_EMBREE_ISA", "auto").strip().lower() or "auto"
    have = cpu_tier()
    if asked == "auto":
        return have
    if asked not in EMBREE_TIERS:
        raise ConfigError(f"environment variable ADV3D_EMBREE_ISA={asked!r}: expected auto or one of "
                         f"{', '.join(EMBREE_TIERS)}")
    missing = sorted(EMBREE_TIERS[asked] - cpu_flags())
    if missing:
        raise ConfigError(f"environment variable ADV3D_EMBREE_ISA={asked}: this CPU lacks {', '.join(missing)} "
                         f"(it runs at most {have})")
    return asked


def embree_native_isa(flags: frozenset[str] | None = None) -> str | None:
    """The ISA Embree chooses by itself on this CPU (``embreex``'s own device takes no
    configuration): the tier, or ``avx`` on an AVX CPU without AVX2."""
    flags = cpu_flags() if flags is None else flags
    tier = cpu_tier(flags)
    return "avx" if tier == "sse4.2" and "avx" in flags else tier


def openblas_core() -> str | None:
    """The OpenBLAS kernel numpy runs (``Haswell``, ``SkylakeX``, ``Zen``, ...), read from
    the library numpy bundles; None where there is no such library."""
    import ctypes
    import glob

    import numpy as np

    folder = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(folder, "*openblas*"))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in ("openblas_get_corename64_", "scipy_openblas_get_corename64_", "openblas_get_corename"):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return fn().decode()
    return None


def numpy_simd() -> str:
    """The highest SIMD target numpy dispatches to here (``AVX512_ICL``, ``AVX2``, ...):
    numpy's float32 transcendental functions round differently per target."""
    try:
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # numpy >= 2 moved it
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    enabled = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    return enabled[-1] if enabled else "baseline"


def torch_capability() -> str:
    """ATen's CPU capability (``AVX512``, ``AVX2``, ``DEFAULT``): read from torch when it is
    loaded, else derived from the CPU and ``ATEN_CPU_CAPABILITY`` the way ATen does (so a
    process without torch records what its torch would run)."""
    import sys

    torch = sys.modules.get("torch")
    if torch is not None:
        return str(torch.backends.cpu.get_cpu_capability())
    flags = cpu_flags()
    best = ("AVX512" if {"avx512f", "avx512bw", "avx512vl", "avx512dq", "fma"} <= flags
            else "AVX2" if {"avx2", "fma"} <= flags else "DEFAULT")
    order = ("DEFAULT", "AVX2", "AVX512")
    asked = os.environ.get("ATEN_CPU_CAPABILITY", "").strip().upper()
    if asked in order and order.index(asked) < order.index(best):
        return asked
    return best


def numba_target() -> str:
    """The CPU numba compiles for: ``NUMBA_CPU_NAME`` where set, else the host's LLVM name."""
    name = os.environ.get("NUMBA_CPU_NAME")
    if name:
        return name
    try:
        import llvmlite.binding as llvm

        return f"host ({llvm.get_host_cpu_name()})"
    except ImportError:
        return "host"


def numerical_config() -> dict[str, str]:
    """The numerical configuration: every choice that can change a result's last bits, flat
    (``run.json`` ``versions.numerics``, sanity files, experiment tables; a resume on another
    configuration names what changed). ``key`` is a short digest of the fields that decide the
    bits (the CPU's model name is recorded but not part of it)."""
    import hashlib
    import json

    def dist(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "-"

    cfg = {
        "cpu": cpu_model(),
        "cpu_vendor": cpu_vendor(),
        "cpu_tier": str(cpu_tier()),
        "embree": dist("embreex"),
        "embree_isa": str(embree_isa()),
        "numpy": dist("numpy"),
        "numpy_simd": numpy_simd(),
        "blas": f"openblas {openblas_core()}",
        "torch": dist("torch"),
        "torch_capability": torch_capability(),
        "numba": dist("numba"),
        "numba_target": numba_target(),
    }
    env = {k: os.environ[k] for k in NUMERICS_ENV if os.environ.get(k)}
    cfg["env"] = " ".join(f"{k}={v}" for k, v in env.items()) or "-"
    bits = {k: v for k, v in cfg.items() if k not in ("cpu", "env")}
    if "NUMBA_CPU_NAME" not in env:
        bits["numba_target"] = "host"  # the host's name is the CPU's, not a kernel choice
    for k in ("ONEDNN_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS", "MKL_CBWR"):
        bits[k] = env.get(k, "auto")
    cfg["key"] = hashlib.sha256(json.dumps(bits, sort_keys=True).encode()).hexdigest()[:12]
    return cfg


def describe_numerics(cfg: dict[str, str] | None = None) -> str:
    """One line for reports and logs: ``AMD EPYC (avx512): Embree avx512, numpy AVX512_ICL, ...``."""
    c = numerical_config() if cfg is None else cfg
    return (f"{c['cpu']} ({c['cpu_tier']}): Embree {c['embree_isa']}, numpy {c['numpy_simd']}, {c['blas']}, "
            f"torch {c['torch_capability']}, numba {c['numba_target']} [key {c['key']}]")
