"""Inputs that set a size, refused before anything is allocated: the real commands on each
hostile input, with their exit code, first line of error, wall time and peak memory (RSS of the
command's process).

    .venv/bin/python bench/memory_bounds.py      # bench/results/memory_bounds.json

Cases (docs/reliability.md, "Memory"): a vertex-deformation lattice of 1000 x 1000 x 1000
nodes; a BO budget whose GP matrices pass the budget; a scene with dt = 1e-9 (validated and
simulated); a scene of 10^6 one-frame actors (6 MB gzipped; validated and simulated); 10 001
actors; 1 000 actors over 100 000 frames. Each must end in one line, exit code 1 or 2, in
seconds, and well under the 4 GiB memory budget.
"""
from __future__ import annotations

import gzip
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"


def _scene(actors: int | None = None, frames: int | None = None, dt: float | None = None) -> bytes:
    """The bundled scene as gzip bytes, with ``actors`` one-frame actors, ``frames`` and
    ``dt`` replaced where given."""
    doc = json.loads(gzip.decompress(SCENE.read_bytes()))
    if dt is not None:
        doc["dt"] = dt
    if frames is not None:
        doc["frames"] = frames
    body = json.dumps(doc, separators=(",", ":")).encode()
    if actors is not None:
        one = (b'{"id":%d,"class":"car","dimensions":[4.5,1.8,1.5],"asset":null,'
               b'"track":{"start":0,"x":[%d.0],"y":[0.0],"yaw":[0.0]}}')
        listed = b",".join(one % (i, i % 1000) for i in range(actors))
        start = body.index(b'"actors":[') + len(b'"actors":[')
        assert body.endswith(b"]}")  # the actors list ends the document
        body = body[:start] + listed + b"]}"
    return gzip.compress(body, 6)


def run(argv: list[str]) -> dict:
    """Run ``argv``; its exit code, the first line it printed, wall time and peak RSS (MiB)."""
    t0 = time.perf_counter()
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: stdout and stderr to the pipe (scenes validate reports on stdout)
        os.dup2(w, 2)
        os.dup2(w, 1)
        os.close(r)
        os.execv(argv[0], argv)
    os.close(w)
    err = b""
    while chunk := os.read(r, 65536):
        err += chunk
    os.close(r)
    _, status, usage = os.wait4(pid, 0)
    lines = [ln for ln in err.decode(errors="replace").splitlines() if ln.strip()]
    return {"command": " ".join(Path(a).name if a.startswith("/tmp") else a for a in argv[1:]),
            "exit_code": os.waitstatus_to_exitcode(status), "error": lines[0] if lines else "",
            "error_lines": len(lines), "wall_s": round(time.perf_counter() - t0, 2),
            "peak_rss_mib": round(usage.ru_maxrss / 1024, 1)}


def main() -> None:
    adv3d = str(ROOT / ".venv" / "bin" / "adv3d")
    out = ROOT / "bench" / "results" / "memory_bounds.json"
    cases = []
    with tempfile.TemporaryDirectory(prefix="adv3d-mem-") as tmp:
        t = Path(tmp)
        files = {"dt.json.gz": _scene(dt=1e-9), "million.json.gz": _scene(actors=10**6),
                 "actors10001.json.gz": _scene(actors=10_001),
                 "actors1000x100000.json.gz": _scene(actors=1000, frames=100_000)}
        for name, data in files.items():
            (t / name).write_bytes(data)
        sizes = {name: round(len(data) / 2**20, 2) for name, data in files.items()}
        plan = [
            ("baseline: validate the bundled scene", [adv3d, "scenes", "validate", str(SCENE)]),
            ("vd lattice 1000,1000,1000", [adv3d, "attack", str(SCENE), "--shape-model", "vd", "--vd-lattice",
                                           "1000,1000,1000", "--out", str(t / "run1")]),
            ("BO budget 20000", [adv3d, "attack", str(SCENE), "--budget", "20000", "--out", str(t / "run2")]),
            ("dt 1e-9: validate", [adv3d, "scenes", "validate", str(t / "dt.json.gz")]),
            ("dt 1e-9: simulate", [adv3d, "simulate", str(t / "dt.json.gz"), "--out", str(t / "sim1")]),
            ("10^6 one-frame actors: validate", [adv3d, "scenes", "validate", str(t / "million.json.gz")]),
            ("10^6 one-frame actors: simulate", [adv3d, "simulate", str(t / "million.json.gz"), "--out",
                                                 str(t / "sim2")]),
            ("10 001 actors: validate", [adv3d, "scenes", "validate", str(t / "actors10001.json.gz")]),
            ("1 000 actors x 100 000 frames: validate", [adv3d, "scenes", "validate",
                                                         str(t / "actors1000x100000.json.gz")]),
        ]
        for label, argv in plan:
            res = {"case": label, **run(argv)}
            res["wrote_nothing"] = not any((t / d).exists() for d in ("run1", "run2", "sim1", "sim2"))
            cases.append(res)
            print(f"{label}: exit {res['exit_code']} in {res['wall_s']} s, peak {res['peak_rss_mib']} MiB: "
                  f"{res['error'][:160]}", flush=True)
    sys.path.insert(0, str(ROOT))
    from adv3d_runner.fileio import MEMORY_BUDGET
    from adv3d_runner.machine import machine_info

    doc = {"command": "bench/memory_bounds.py", "memory_budget_gib": MEMORY_BUDGET / 2**30, "file_mib": sizes,
           "machine": machine_info(), "load_average_at_end": list(os.getloadavg()), "cases": cases}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
