"""Realism benchmark: the measures of shapes/realism.py on the library itself and on the attack's shapes.

    .venv/bin/python bench/realism.py [--random 200]

(a) every shape-space vehicle: its CAD model's leave-one-out JSD against the other CAD models,
    and the full report of its decoded latent (checked against its own class's dimensions);
(b) the other library vehicles (buses, trucks, ...): their CAD models' JSD against the
    reference, and the recorded dimensions of every library vehicle against the real ranges;
(c) the JSD's noise floor (1000-point samples drawn from the reference's own distribution)
    and its spread over sample seeds;
(d) the best shapes of the shipped attack runs (docs/results/*/summary.json);
(e) uniform random shapes of the search box: how often each check fails;
(f) time per ``realism_report`` (one core) and per measure;
(g) the normalisation choice: the JSD with the metric window against the same JSD with size
    removed (every footprint, the CAD models' included, scaled to their mean length and width).

Prints the tables and writes ``bench/results/realism.json`` with machine info and the command.
docs/realism.md quotes its numbers.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core for numpy/BLAS (timings)

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.fileio import atomic_write_text  # noqa: E402
from adv3d_runner.machine import machine_info  # noqa: E402
from adv3d_runner.shapes import realism as R  # noqa: E402
from adv3d_runner.shapes.library import load_asset_mesh, load_library  # noqa: E402
from adv3d_runner.shapes.shape_space import ShapeSpace  # noqa: E402

RUNS = ("bo100", "random100", "bruteforce")
SUMMARY_KEYS = ("jsd", "nearest_asset", "nearest_chamfer_m", "mahalanobis", "parts_before_cleanup",
                "floating_parts", "cavities", "parts_after_cleanup", "dropped_volume_fraction",
                "floating_volume_fraction", "genus", "genus_robust", "thinnest_wall_m", "thin_wall_fraction",
                "dimensions_m", "dimension_class", "dimension_excess", "plausible_classes", "flags", "realistic")


def summary(rep: dict) -> dict:
    return {k: rep[k] for k in SUMMARY_KEYS}


def timed_report(space, u_or_z, ref, vehicle_class=None, latent=False) -> tuple[dict, float]:
    t0 = time.perf_counter()
    if latent:
        rep = R.latent_realism_report(space, u_or_z, (1.0, 1.0), ref, vehicle_class)
    else:
        rep = R.realism_report(space, u_or_z, ref, vehicle_class)
    return rep, time.perf_counter() - t0


def library_rows(space, ref, library, times: list) -> list[dict]:
    rows = []
    for i, aid in enumerate(space.asset_ids):
        asset = library.get(aid)
        rep, dt = timed_report(space, space.latents[i], ref, asset.vehicle_class, latent=True)
        times.append(dt)
        rows.append({"id": aid, "class": asset.vehicle_class, "cad_dimensions_m": list(asset.dimensions),
                     "cad_jsd_loo": float(ref.jsd_loo[i]), "decoded_chamfer_loo_m": float(ref.chamfer_loo[i]),
                     "mahalanobis_loo": float(ref.mahalanobis_loo[i]), "decoded": summary(rep)})
    return rows


def other_library_rows(ref, library, space) -> list[dict]:
    rows = []
    for asset in library.assets:
        mesh = load_asset_mesh(library, asset.id)
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        row = {"id": asset.id, "class": asset.vehicle_class, "in_shape_space": asset.in_shape_space,
               "dimensions_m": list(asset.dimensions),
               "dimension_excess": [float(x) for x in R.dimension_excess(asset.dimensions, asset.vehicle_class)],
               "plausible_classes": R.plausible_classes(asset.dimensions)}
        if not asset.in_shape_space:
            pts = R.footprint_centred(R.sample_surface(v, f, R.N_POINTS, 0), v)
            row["cad_jsd"] = R.jsd(R.bev_histogram(pts), ref.histogram)
        rows.append(row)
    return rows


def noise_floor(ref, library, space, space_seeds: int = 20) -> dict:
    """JSD of 1000-point samples of the reference distribution itself, and the spread over seeds."""
    pooled = []
    for i, aid in enumerate(ref.asset_ids):
        mesh = load_asset_mesh(library, aid)
        v = np.asarray(mesh.vertices)
        pooled.append(R.footprint_centred(
            R.sample_surface(v, mesh.faces, R.REFERENCE_POINTS_PER_MODEL, [R.REFERENCE_SEED, i]), v))
    pooled = np.concatenate(pooled)
    rng = np.random.default_rng(0)
    floor = [R.jsd(R.bev_histogram(pooled[rng.choice(len(pooled), R.N_POINTS, replace=False)]), ref.histogram)
             for _ in range(20)]
    spread = {}
    for name, u in (("kenney-car-kit.sedan (decoded)", space.asset_unit("kenney-car-kit.sedan")),
                    ("BO blob, scene 000000", [1.0, 0.6457628700042313, 0.0, 0.0, 0.0])):
        v, f = space.decode_arrays(u)
        vals = [R.jsd(R.bev_histogram(R.sample_surface(v, f, R.N_POINTS, s)), ref.histogram)
                for s in range(space_seeds)]
        spread[name] = {"mean": float(np.mean(vals)), "std": float(np.std(vals)),
                        "min": float(np.min(vals)), "max": float(np.max(vals))}
    return {"floor": {"mean": float(np.mean(floor)), "min": float(np.min(floor)), "max": float(np.max(floor)),
                      "draws": len(floor)},
            "seed_spread": spread}


def attack_rows(space, ref, times: list) -> list[dict]:
    rows = []
    for run in RUNS:
        path = ROOT / "docs" / "results" / run / "summary.json"
        if not path.exists():
            continue
        doc = json.loads(path.read_text())
        for scene, entry in doc["scenes"].items():
            for mode, res in entry["modes"].items():
                for u in res.get("best_unit") or []:
                    rep, dt = timed_report(space, u, ref)
                    times.append(dt)
                    rows.append({"run": run, "scene": scene, "mode": mode, "unit": u, **summary(rep)})
    return rows


def random_rows(space, ref, n: int, times: list) -> dict:
    rng = np.random.default_rng(0)
    flags: dict[str, int] = {}
    realistic = 0
    jsds = []
    for _ in range(n):
        rep, dt = timed_report(space, space.sample_unit(rng), ref)
        times.append(dt)
        jsds.append(rep["jsd"])
        realistic += rep["realistic"]
        for k in rep["flags"]:
            flags[k] = flags.get(k, 0) + 1
    return {"n": n, "realistic": realistic, "flag_counts": flags,
            "jsd": {"min": float(np.min(jsds)), "median": float(np.median(jsds)), "max": float(np.max(jsds))}}


def component_times(space, ref, reps: int = 10) -> dict:
    """Median seconds of each measure on the shape-space assets (one core)."""
    parts: dict[str, list] = {k: [] for k in ("decode", "surface (JSD, Chamfer, dimensions)", "parts",
                                              "genus", "wall thickness")}
    for i in range(min(reps, len(space.latents))):
        z = space.latents[i]
        t0 = time.perf_counter()
        field = space.decode_sdf(z)
        v, f = space.decode_latent(z)
        t1 = time.perf_counter()
        R.shape_surface_measures(v, f, ref)
        t2 = time.perf_counter()
        R.surface_parts(field, space.grid)
        t3 = time.perf_counter()
        R.robust_genus(field, space.grid, surface=(v, f))
        t4 = time.perf_counter()
        R.wall_thickness(field, space.grid)
        t5 = time.perf_counter()
        for key, dt in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            parts[key].append(dt)
    return {k: float(np.median(v)) for k, v in parts.items()}


def size_normalised(points: np.ndarray, length: float, width: float) -> np.ndarray:
    """The footprint scaled to ``length`` x ``width`` metres (the alternative normalisation: size removed)."""
    p = R.footprint_centred(points)
    ext = p[:, :2].max(axis=0) - p[:, :2].min(axis=0)
    p[:, :2] *= np.array([length, width]) / ext
    return p


def normalisation_rows(space, ref, library) -> list[dict]:
    """JSD metric (the module's) against the JSD with size removed: every shape and every CAD
    model scaled to the CAD models' mean footprint, same 8 m window and 100 x 100 bins."""
    meshes = [load_asset_mesh(library, aid) for aid in ref.asset_ids]
    ext = np.array([R.mesh_dimensions(m.vertices)[:2] for m in meshes])
    length, width = ext.mean(axis=0)
    size_free = np.zeros((R.BEV_BINS, R.BEV_BINS), dtype=np.int64)
    for i, mesh in enumerate(meshes):
        pts = R.sample_surface(mesh.vertices, mesh.faces, R.REFERENCE_POINTS_PER_MODEL, [R.REFERENCE_SEED, i])
        size_free += R.bev_histogram(size_normalised(pts, length, width))
    shapes = [(f"{aid} (decoded)", space.decode_arrays(space.asset_unit(aid)))
              for aid in ("kenney-car-kit.sedan", "quaternius-cars.normalcar2", "kenney-car-kit.van")]
    shapes += [("BO blob, scene 000000", space.decode_arrays([1.0, 0.6457628700042313, 0.0, 0.0, 0.0])),
               ("BO flatbed, scene 000004", space.decode_arrays([0.0, 0.7797, 0.5332, 0.9544, 1.0]))]
    for dims in ((3.0, 1.3, 0.9), (4.6, 1.8, 1.45), (7.4, 2.7, 2.1)):
        import trimesh

        b = trimesh.creation.box(extents=dims)
        b.apply_translation((0.0, 0.0, dims[2] / 2))
        shapes.append((f"box {dims[0]} x {dims[1]} x {dims[2]} m", (np.asarray(b.vertices), np.asarray(b.faces))))
    rows = []
    for name, (v, f) in shapes:
        pts = R.sample_surface(v, f, R.N_POINTS, 0)
        rows.append({"shape": name, "dimensions_m": [float(x) for x in R.mesh_dimensions(v)],
                     "jsd_metric": R.jsd(R.bev_histogram(pts), ref.histogram),
                     "jsd_size_removed": R.jsd(R.bev_histogram(size_normalised(pts, length, width)), size_free)})
    return {"mean_footprint_m": [float(length), float(width)], "rows": rows}


def print_tables(doc: dict) -> None:
    print("\n(a) shape-space vehicles: CAD leave-one-out JSD; decoded latent against its own class")
    print("| vehicle | class | CAD JSD (LOO) | decoded JSD | Chamfer LOO m | Mahalanobis LOO | parts | "
          "genus raw/robust | thinnest wall m | decoded L x W x H m | dim. excess | flags |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in doc["library"]:
        d = r["decoded"]
        dims = " x ".join(f"{x:.2f}" for x in d["dimensions_m"])
        print(f"| {r['id']} | {r['class']} | {r['cad_jsd_loo']:.3f} | {d['jsd']:.3f} | "
              f"{r['decoded_chamfer_loo_m']:.3f} | {r['mahalanobis_loo']:.2f} | {d['parts_before_cleanup']} | "
              f"{d['genus']}/{d['genus_robust']} | {d['thinnest_wall_m']:.2f} | {dims} | "
              f"{max(d['dimension_excess']) * 100:.0f} % | {', '.join(d['flags']) or '-'} |")
    print("\n(b) every library vehicle's recorded dimensions against the real ranges of its class")
    print("| vehicle | class | L x W x H m | excess L/W/H | plausible as | CAD JSD |")
    print("|---|---|---|---|---|---|")
    for r in doc["library_dimensions"]:
        ex = "/".join(f"{x * 100:.0f}" for x in r["dimension_excess"])
        jsd = f"{r['cad_jsd']:.3f}" if "cad_jsd" in r else "(in reference)"
        print(f"| {r['id']} | {r['class']} | {' x '.join(f'{x:.2f}' for x in r['dimensions_m'])} | {ex} % | "
              f"{', '.join(r['plausible_classes']) or '-'} | {jsd} |")
    n = doc["noise"]
    print(f"\n(c) JSD noise floor: {n['floor']['mean']:.3f} ({n['floor']['min']:.3f}-{n['floor']['max']:.3f}) "
          f"over {n['floor']['draws']} samples of the reference itself")
    for k, v in n["seed_spread"].items():
        print(f"    {k}: {v['mean']:.3f} ± {v['std']:.3f} over seeds ({v['min']:.3f}-{v['max']:.3f})")
    print("\n(d) best shapes of the shipped attack runs")
    print("| run | scene | mode | JSD | nearest (Chamfer m) | Mahalanobis | L x W x H m | class, excess | "
          "genus raw/robust | wall m | flags |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in doc["attack"]:
        dims = " x ".join(f"{x:.2f}" for x in r["dimensions_m"])
        print(f"| {r['run']} | {r['scene'][-6:]} | {r['mode']} | {r['jsd']:.3f} | "
              f"{r['nearest_asset'].split('.')[-1]} ({r['nearest_chamfer_m']:.3f}) | {r['mahalanobis']:.2f} | {dims} | "
              f"{r['dimension_class']} {max(r['dimension_excess']) * 100:.0f} % | {r['genus']}/{r['genus_robust']} | "
              f"{r['thinnest_wall_m']:.2f} | {', '.join(r['flags']) or '-'} |")
    rnd = doc["random"]
    print(f"\n(e) {rnd['n']} uniform random shapes: {rnd['realistic']} realistic; failed checks "
          + ", ".join(f"{k} {v}" for k, v in sorted(rnd["flag_counts"].items())))
    norm = doc["normalisation"]
    print("\n(g) normalisation: JSD metric against JSD with every footprint scaled to the mean CAD footprint "
          + " x ".join(f"{x:.2f}" for x in norm["mean_footprint_m"]) + " m")
    print("| shape | L x W x H m | JSD metric (used) | JSD size removed |")
    print("|---|---|---|---|")
    for r in norm["rows"]:
        print(f"| {r['shape']} | {' x '.join(f'{x:.2f}' for x in r['dimensions_m'])} | {r['jsd_metric']:.3f} | "
              f"{r['jsd_size_removed']:.3f} |")
    t = doc["timing"]
    print(f"\n(f) realism_report: median {t['report_median_s'] * 1000:.0f} ms, max {t['report_max_s'] * 1000:.0f} ms "
          f"over {t['reports']} shapes; per measure (median ms): "
          + ", ".join(f"{k} {v * 1000:.1f}" for k, v in t["components_median_s"].items()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--random", type=int, default=200, help="uniform random shapes for (e) (default 200)")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "realism.json"))
    args = parser.parse_args()
    info = machine_info("numpy", "scipy", "scikit-image")
    space = ShapeSpace.load()
    library = load_library()
    ref = R.load_reference()
    if not ref.matches(space):
        print("the shipped realism reference is stale: run `adv3d shapes realism-reference`", file=sys.stderr)
        return 1
    R.realism_report(space, [0.5] * space.dim, ref)  # warm up imports
    times: list[float] = []
    doc = {"format": "adv3d-bench", "topic": "realism", "command": "python bench/realism.py " + " ".join(sys.argv[1:]),
           "machine": info,
           "parameters": {"points": R.N_POINTS, "bins": R.BEV_BINS, "window_m": R.BEV_WINDOW_M,
                          "reference_points_per_model": R.REFERENCE_POINTS_PER_MODEL,
                          "covariance_shrinkage": R.COVARIANCE_SHRINKAGE, "wall_percentile": R.WALL_PERCENTILE,
                          "floating_volume_tol": R.FLOATING_VOLUME_TOL,
                          "voxel_m": space.grid.voxel * space.grid.extent_m},
           "limits": {"jsd": ref.jsd_limit, "jsd_loo_min": float(ref.jsd_loo.min()),
                      "nearest_chamfer_m": ref.chamfer_limit_m, "mahalanobis": ref.mahalanobis_limit}}
    print("(a) library ...")
    doc["library"] = library_rows(space, ref, library, times)
    print("(b) library dimensions ...")
    doc["library_dimensions"] = other_library_rows(ref, library, space)
    print("(c) noise ...")
    doc["noise"] = noise_floor(ref, library, space)
    print("(d) attack best shapes ...")
    doc["attack"] = attack_rows(space, ref, times)
    print(f"(e) {args.random} random shapes ...")
    doc["random"] = random_rows(space, ref, args.random, times)
    print("(g) normalisation ...")
    doc["normalisation"] = normalisation_rows(space, ref, library)
    doc["timing"] = {"reports": len(times), "report_median_s": float(np.median(times)),
                     "report_max_s": float(np.max(times)), "components_median_s": component_times(space, ref)}
    print_tables(doc)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
