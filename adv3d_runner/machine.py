"""What machine a measurement was taken on: benchmarks and training reports record it."""
from __future__ import annotations

import os
import platform
from importlib.metadata import PackageNotFoundError, version


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one)."""
    try:
        with open("/proc/cpuinfo") as lines:
            for line in lines:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(*packages: str, **extra) -> dict:
    """CPU, cores, load, Python and platform, plus the installed versions of ``packages``.

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
