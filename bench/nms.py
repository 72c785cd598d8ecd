"""Rotated NMS benchmark: this code's ``rotated_nms`` against another commit's (with that
commit's ``geometry/boxes.py``), on the inputs a detector really gives it, interleaved call by
call.

    .venv/bin/python bench/nms.py --base COMMIT [--seconds 3]

Collects every ``rotated_nms`` input of two Autonomy-A queries (one closed, one open loop) on
``highway-benchmark-000000``, ``-000010`` and ``-000041``, plus 300 random clutters (1-80
overlapping boxes), then times both versions on each input (CPU time of this thread, one core,
one thread per library) and checks that they return the same bytes. Writes
``bench/results/nms.json``.
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import limit_threads, machine_info  # noqa: E402


def _git_show(commit: str, path: str) -> str:
    return subprocess.run(["git", "show", f"{commit}:{path}"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout


def _file_module(name: str, source: str, names: dict | None = None):
    """A module run from ``source`` written to a temporary file (numba caches only file-backed
    kernels), inside ``adv3d_runner.geometry`` so relative imports resolve; ``names`` are set
    before it runs."""
    import importlib.util
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="adv3d-nms-base-")) / f"{name}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"adv3d_runner.geometry.{name}", path)
    mod = importlib.util.module_from_spec(spec)
    mod.__dict__.update(names or {})
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _base_nms(commit: str):
    """``rotated_nms`` (and the helpers up to ``decode``) of ``commit``, calling that commit's
    ``geometry/boxes.py``."""
    import adv3d_runner.geometry  # noqa: F401  (the package the base modules live in)

    base_boxes = _file_module("_nms_base_boxes", _git_show(commit, "adv3d_runner/geometry/boxes.py"))
    src = _git_show(commit, "adv3d_runner/autonomy/detector.py")
    a, b = src.index("def rotated_nms("), src.index("\ndef decode(")
    head = "from __future__ import annotations\nimport math\nimport numpy as np\nfrom adv3d_runner.jit import kernel\n\n\n"
    names = {k: getattr(base_boxes, k) for k in dir(base_boxes) if not k.startswith("__")}
    return _file_module("_nms_base_detector", head + src[a:b], names).rotated_nms


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="commit whose rotated_nms is compared")
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    limit_threads()
    import adv3d_runner.autonomy.detector as D
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import SceneWorkspace

    base_nms = _base_nms(args.base)
    inputs, this_nms = [], D.rotated_nms

    def grab(bx, sc, *a, **k):
        inputs.append((np.array(bx), np.array(sc), a, k))
        return this_nms(bx, sc, *a, **k)

    D.rotated_nms = grab
    try:
        for scene in ("000000", "000010", "000041"):
            ws = SceneWorkspace(str(ROOT / "scenes" / "highway" / f"highway-benchmark-{scene}.json.gz"),
                                QuerySettings(autonomy="A", seconds=args.seconds))
            for q, u in enumerate(np.random.default_rng(1).random((2, 5))):
                ws.evaluate(u, q % 2 == 0)
    finally:
        D.rotated_nms = this_nms
    n_real = len(inputs)
    rng = np.random.default_rng(0)
    for _ in range(300):
        k = int(rng.integers(1, 80))
        c = rng.normal(0, 3, (k, 2))
        dims = np.exp(rng.normal(1.2, 0.3, (k, 2)))
        inputs.append((np.c_[c, dims, rng.uniform(-np.pi, np.pi, k)], rng.random(k), (0.1,), {}))
    t = {"base": np.zeros(len(inputs)), "this": np.zeros(len(inputs))}
    differ = 0
    for j, (bx, sc, a, k) in enumerate(inputs):
        order = (("base", base_nms), ("this", this_nms)) if j % 2 else (("this", this_nms), ("base", base_nms))
        out = {}
        for name, fn in order:
            t0 = time.thread_time()
            out[name] = fn(bx, sc, *a, **k)
            t[name][j] = time.thread_time() - t0
        differ += not all(x.tobytes() == y.tobytes() for x, y in zip(out["base"], out["this"]))

    def row(sl):
        return {name: {"ms_per_call_mean": 1e3 * float(v[sl].mean()), "ms_per_call_median": 1e3 * float(np.median(v[sl]))}
                for name, v in t.items()}

    doc = {"format": "adv3d.bench", "topic": "nms", "command": " ".join([Path(sys.executable).name] + sys.argv),
           "machine": machine_info("numpy"), "base": args.base, "inputs_from_episodes": n_real,
           "inputs_random": len(inputs) - n_real, "inputs_differing": differ,
           "candidates_per_episode_input_mean": float(np.mean([len(x[0]) for x in inputs[:n_real]])),
           "episodes": row(slice(0, n_real)), "random": row(slice(n_real, None))}
    out = ROOT / "bench" / "results" / "nms.json"
    out.write_text(__import__("json").dumps(doc, indent=1) + "\n")
    print({k: doc[k] for k in ("inputs_from_episodes", "inputs_random", "inputs_differing", "episodes", "random")})
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
