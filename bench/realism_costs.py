"""What realism costs per attack query and per Blender slider change (docs/realism.md).

    .venv/bin/python bench/realism_costs.py [--shapes 60] [--queries 4] [--quick]

Measures, as single-thread CPU time (``time.process_time``), on seeded random shapes of the
shipped shape space:

* ``query_figures``: the cheap figures every journal line carries (``ActorShapes.figures``:
  JSD, nearest CAD model by Chamfer, Mahalanobis, dimensions), on the already decoded mesh;
* ``full_report``: the whole realism report (``realism.realism_report``), decode included;
* ``query``: whole closed-loop 5 s queries with Autonomy-A on benchmark scene 000000 (the
  episode evaluator, figures included), to put the two in proportion;
* Blender (no scipy: the realism module's numpy fallbacks, forced here by hiding
  ``scipy.spatial`` and ``scipy.ndimage``): the live slider figures (``quick_measures(chamfer=False)``),
  the same with the Chamfer search, and the full report;
* vertex deformation: building the lattice weights of a template and deforming it;
* the BO searcher's ask at D = 5 (latent) and D = 162 (vertex deformation, 6 x 3 x 3 lattice)
  after 50 and 99 told queries.

Writes bench/results/realism_costs.json (``--quick``: realism_costs.quick.json).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

SCENE = "scenes/highway/highway-benchmark-000000.json.gz"


def _stats(ms: list[float]) -> dict:
    a = np.asarray(ms, dtype=np.float64)
    return {"median_ms": round(float(np.median(a)), 2), "p95_ms": round(float(np.percentile(a, 95)), 2),
            "max_ms": round(float(a.max()), 2), "n": int(len(a))}


def _cpu_ms(fn) -> float:
    t0 = time.process_time()
    fn()
    return (time.process_time() - t0) * 1000.0


def measure_figures(space, units: np.ndarray) -> dict:
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.shape_models import ActorShapes
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.shapes import realism

    ref = realism.default_reference(space)
    shapes = ActorShapes(QuerySettings(), load_scene(REPO / SCENE), [3], space)
    shapes._reference = ref
    decode, figures, full = [], [], []
    for u in units:
        out = {}
        decode.append(_cpu_ms(lambda: out.update(zip(("o", "i"), shapes.decode_query(u)))))
        figures.append(_cpu_ms(lambda: shapes.figures(out["o"], out["i"])))
        full.append(_cpu_ms(lambda: realism.realism_report(space, u, ref, vehicle_class="sedan")))
    return {"decode": _stats(decode), "query_figures": _stats(figures), "full_report": _stats(full)}


def measure_queries(n: int) -> dict:
    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import EpisodeEvaluator, Query, workspace_for

    settings = QuerySettings(seconds=5.0)
    ev = EpisodeEvaluator(settings)
    ref = str(REPO / SCENE)
    setup = _cpu_ms(lambda: workspace_for(ref, settings))
    rng = np.random.default_rng(0)
    ms = [_cpu_ms(lambda: ev.evaluate(Query(ref, rng.random(5)))) for _ in range(n)]
    return {"workspace_setup_ms": round(setup, 1), "query": _stats(ms),
            "setting": "closed loop, 5 s (50 frames), Autonomy-A, scene 000000, cheap figures included"}


def measure_blender(space, units: np.ndarray) -> dict:
    """The add-on's paths without scipy (Blender ships none): realism's numpy fallbacks."""
    import importlib

    from adv3d_runner.shapes import realism

    importlib.import_module("skimage.measure")  # loaded before scipy is hidden (Blender's wheel set has it)

    saved = {k: sys.modules.get(k) for k in ("scipy.spatial", "scipy.ndimage")}
    for k in saved:
        sys.modules[k] = None  # type: ignore[assignment] - "import scipy.spatial" now raises ImportError
    try:
        assert realism._kdtree(np.zeros((2, 3))) is None
        ref = realism.default_reference(space)
        ref._trees = None
        live, live_chamfer, full = [], [], []
        for u in units:
            v, f = space.decode_arrays(u)
            z = space.unit_to_latent(u)[0]
            live.append(_cpu_ms(lambda: realism.quick_measures(v, f, ref, latent=z, latents=space.latents,
                                                               chamfer=False)))
            live_chamfer.append(_cpu_ms(lambda: realism.quick_measures(v, f, ref, latent=z, latents=space.latents)))
            full.append(_cpu_ms(lambda: realism.realism_report(space, u, ref)))
    finally:
        for k, mod in saved.items():
            if mod is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = mod
        ref._trees = None
    return {"live_figures": _stats(live), "live_with_chamfer": _stats(live_chamfer), "full_report": _stats(full),
            "slider_target_ms": 50.0}


def measure_vd(space) -> dict:
    from adv3d_runner.attack.shape_models import own_meshes
    from adv3d_runner.attack.vertex_deform import VertexDeformation
    from adv3d_runner.scene.schema import load_scene

    (v, f), = own_meshes(load_scene(REPO / SCENE), [3])
    box: dict = {}
    build = _cpu_ms(lambda: box.setdefault("vd", VertexDeformation(v, f, 0.5)))
    vd = box["vd"]
    rng = np.random.default_rng(0)
    deform = [_cpu_ms(lambda: vd.deform(rng.random(vd.dim))) for _ in range(20)]
    return {"template_vertices": int(len(v)), "template_faces": int(len(f)), "dim": vd.dim,
            "build_ms": round(build, 2), "deform": _stats(deform)}


def measure_bo(quick: bool) -> dict:
    from adv3d_runner.attack.search import BayesOpt

    def value(x: np.ndarray) -> float:
        return float(-np.sum((x - 0.3) ** 2))

    out = {}
    for dim in (5, 162):
        for told in ((50,) if quick else (50, 99)):
            bo = BayesOpt(dim, seed=0, budget=told + 3, n_initial=told)  # history: a Latin hypercube (no GP)
            while bo.n_told < told:
                X = bo.ask(1)
                bo.tell(X, [value(X[0])])
            ms = []
            for _ in range(3):
                box: dict = {}
                ms.append(_cpu_ms(lambda: box.update(X=bo.ask(1))))
                bo.tell(box["X"], [value(box["X"][0])])
            out[f"D{dim}_told{told}"] = _stats(ms)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=60)
    parser.add_argument("--queries", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="10 shapes, 1 query, one BO history")
    args = parser.parse_args()
    n_shapes, n_queries = (10, 1) if args.quick else (args.shapes, args.queries)

    from adv3d_runner.shapes.shape_space import ShapeSpace

    space = ShapeSpace.load()
    units = np.random.default_rng(0).random((n_shapes, space.dim))
    res = {"command": "python bench/realism_costs.py" + (" --quick" if args.quick else ""),
           "machine": {"platform": platform.platform(), "python": platform.python_version(),
                       "note": "2-core machine shared with other jobs; single-thread CPU times (time.process_time)"},
           "shapes": n_shapes}
    res["figures"] = measure_figures(space, units)
    res["queries"] = measure_queries(n_queries)
    res["blender"] = measure_blender(space, units)
    res["vertex_deformation"] = measure_vd(space)
    res["bo_ask"] = measure_bo(args.quick)
    q = res["queries"]["query"]["median_ms"]
    res["share_of_query"] = {"query_figures": round(res["figures"]["query_figures"]["median_ms"] / q, 4),
                             "full_report": round(res["figures"]["full_report"]["median_ms"] / q, 4),
                             "query_figures_vs_1s_query": round(res["figures"]["query_figures"]["median_ms"] / 1000, 4),
                             "full_report_vs_1s_query": round(res["figures"]["full_report"]["median_ms"] / 1000, 4)}
    out = REPO / "bench" / "results" / ("realism_costs.quick.json" if args.quick else "realism_costs.json")
    out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps({k: res[k] for k in ("figures", "queries", "blender", "vertex_deformation", "bo_ask",
                                          "share_of_query")}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
