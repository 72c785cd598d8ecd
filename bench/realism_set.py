"""Set-level realism of the kept attack runs' best shapes against the library.

    .venv/bin/python bench/realism_set.py [--out bench/results/realism_set.json]

For each kept run (docs/results/{bo100,random100,bruteforce}/summary.json) and mode, the best
unit vector of every scene is decoded with the shipped shape space, and the set of those shapes
is compared with the library's CAD models (the realism reference's 1000-point samples) by
``shapes/realism_set.py``: MMD, COV and 1-NNA with PointFlow's Chamfer distance and the pooled
BEV Jensen-Shannon distance. Also the library's own decoded latents as a set (what a generator
reproducing the library would score). docs/realism.md, "Set-level realism", quotes it.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.fileio import atomic_write_text  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402
from adv3d_runner.shapes import realism as R  # noqa: E402
from adv3d_runner.shapes.realism_set import meshes_set_realism  # noqa: E402
from adv3d_runner.shapes.shape_space import ShapeSpace  # noqa: E402

RUNS = ("bo100", "random100", "bruteforce")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "realism_set.json")
    args = ap.parse_args()
    space = ShapeSpace.load()
    ref = R.default_reference(space)
    rows = {}
    lib = [space.decode_latent(z) for z in space.latents]
    rows["library decoded latents"] = meshes_set_realism(lib, ref)
    for run in RUNS:
        summary = json.loads((ROOT / "docs" / "results" / run / "summary.json").read_text())
        by_mode: dict[str, list] = {}
        for scene in summary["scenes"].values():
            for mode, res in scene.get("modes", {}).items():
                for u in res.get("best_unit") or []:
                    by_mode.setdefault(mode, []).append(space.decode_arrays(u))
        for mode, meshes in sorted(by_mode.items()):
            rows[f"{run} {mode}"] = meshes_set_realism(meshes, ref)
    for name, r in rows.items():
        print(f"{name:28s} n={r['n_found']:3d}  MMD-CD {r['mmd_cd_m2']:.4f} m^2  COV {r['cov_cd'] * 100:5.1f} %  "
              f"1-NNA {r['nna_cd'] * 100:5.1f} %  JS distance {r['jsd_distance']:.3f}")
    out = {"command": "python bench/realism_set.py", "machine": machine_info("numpy", "scipy"),
           "shape_space_hash": space.content_hash, "reference": list(ref.asset_ids), "rows": rows}
    atomic_write_text(args.out, json.dumps(out, indent=1) + "\n")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
