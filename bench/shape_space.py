"""Shape-space benchmark: speed against error for the SDF method/resolution, K and decoding.

    .venv/bin/python bench/shape_space.py [--quick]

(a) SDF method x resolution against a high-resolution winding-number reference, on a few
    library assets: volume IoU (Monte Carlo, trilinear occupancy), symmetric mean surface
    distance (mm) between the zero level sets, SDF time per asset.
(b) K = 1..8: leave-one-out reconstruction error of every shape-space asset: PCA fitted
    without the asset, the asset's SDF projected on it and decoded; symmetric mean surface
    distance (cm) to the asset's own surface at the same resolution (so only the PCA error
    is measured). K = 0 is the mean shape.
    Also the share of left-out vehicles whose latent (K = 3) lies inside the latent box of
    the others (the box the attack searches).
(c) decode time (unit vector -> metric mesh arrays, one core) against resolution.
(d) time to build the whole library's shape space at the default resolution (full mode).
(e) the real-CAD-like hard-case suite (``tests/cad_hardcases.py``) at 64^3: decoded length,
    width, height error against the source mesh, solid outside the body, CPU time per vehicle,
    for ``winding`` (visibility-oriented) against ``winding-outward`` (shape space v1).

Prints the tables and writes ``bench/results/shape_space.json`` (``shape_space.quick.json``
with --quick) with machine info and the command.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core for numpy/BLAS (decode timing)

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import machine_info as _machine_info  # noqa: E402
from adv3d_runner.shapes.cleaning import clean_mesh  # noqa: E402
from adv3d_runner.shapes.decode import extract_surface  # noqa: E402
from adv3d_runner.shapes.library import load_asset_mesh, load_library  # noqa: E402
from adv3d_runner.shapes.sdf import METHODS, GridSpec, grid_for_dimensions, sdf_volume  # noqa: E402
from adv3d_runner.shapes.shape_space import (  # noqa: E402
    DEFAULT_RESOLUTION,
    fit_pca,
    library_sdfs,
    shape_space_from_sdfs,
)


def machine_info() -> dict:
    return _machine_info("numpy", "libigl", "scikit-image", "trimesh")


# ------------------------------------------------------------------------------ geometry


def surface_unit(field: np.ndarray, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set in unit-cube coordinates (not re-centred), for comparisons."""
    from skimage.measure import marching_cubes

    vol = np.pad(field, 1, constant_values=grid.truncation)
    v, f, _, _ = marching_cubes(vol, 0.0, method="lewiner")
    return (v - 1.0) * grid.voxel - 0.5, f.astype(np.int64)


def occupancy(field: np.ndarray, pts_unit: np.ndarray) -> np.ndarray:
    from scipy.ndimage import map_coordinates

    n = field.shape[0]
    idx = ((pts_unit + 0.5) * (n - 1)).T
    return map_coordinates(field, idx, order=1, mode="nearest") < 0


def sample_surface(v: np.ndarray, f: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(f), size=count, p=area / area.sum())
    r = rng.random((count, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    t = tri[pick]
    return t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])


def mean_surface_distance(a: tuple, b: tuple, rng: np.random.Generator, count: int = 20000) -> float:
    """Symmetric mean point-to-surface distance between meshes a and b (their units)."""
    import igl

    pa = sample_surface(*a, count, rng)
    pb = sample_surface(*b, count, rng)
    dab, _, _ = igl.point_mesh_squared_distance(pa, b[0], b[1])
    dba, _, _ = igl.point_mesh_squared_distance(pb, a[0], a[1])
    return 0.5 * (float(np.sqrt(dab).mean()) + float(np.sqrt(dba).mean()))


def volume_iou(f_test: np.ndarray, f_ref: np.ndarray, box: np.ndarray, rng: np.random.Generator, count: int = 400000) -> float:
    pts = box[0] + rng.random((count, 3)) * (box[1] - box[0])
    a = occupancy(f_test, pts)
    b = occupancy(f_ref, pts)
    return float(np.sum(a & b) / max(np.sum(a | b), 1))


# ------------------------------------------------------------------------------ parts


_MESHES: dict = {}


def mesh_of(library, aid: str):
    """Load each asset once (the library may be rewritten while the bench runs)."""
    if aid not in _MESHES:
        _MESHES[aid] = load_asset_mesh(library, aid)
    return _MESHES[aid]


def part_a(library, grid64: GridSpec, asset_ids: list[str], resolutions: list[int], ref_res: int, rng) -> list[dict]:
    rows = []
    for aid in asset_ids:
        mesh = mesh_of(library, aid)
        ref_grid = GridSpec(ref_res, grid64.extent_m, grid64.ground_z, grid64.truncation)
        t0 = time.process_time()
        ref = sdf_volume(mesh.vertices, mesh.faces, ref_grid, "winding")
        t_ref = time.process_time() - t0
        ref_surf = surface_unit(ref, ref_grid)
        lo, hi = ref_surf[0].min(axis=0) - 0.02, ref_surf[0].max(axis=0) + 0.02
        print(f"  reference {aid} at {ref_res}^3: {t_ref:.1f} s", flush=True)
        for method in METHODS:
            for n in resolutions:
                g = GridSpec(n, grid64.extent_m, grid64.ground_z, grid64.truncation)
                t0 = time.process_time()
                try:
                    f = sdf_volume(mesh.vertices, mesh.faces, g, method)
                except Exception as exc:  # noqa: BLE001 - a method failing on an asset is a result
                    rows.append({"asset": aid, "method": method, "resolution": n, "error": str(exc)})
                    continue
                dt = time.process_time() - t0
                iou = volume_iou(f, ref, np.stack([lo, hi]), rng)
                msd = mean_surface_distance(surface_unit(f, g), ref_surf, rng) * grid64.extent_m * 1000
                rows.append({"asset": aid, "method": method, "resolution": n, "sdf_time_s": dt, "iou": iou,
                             "mean_surface_distance_mm": msd})
                print(f"  {aid:34s} {method:9s} {n:4d}^3  IoU {iou:.4f}  MSD {msd:6.1f} mm  {dt:6.2f} s", flush=True)
    return rows


def part_b(sdfs: np.ndarray, ids: list[str], grid: GridSpec, kmax: int, rng) -> list[dict]:
    m = len(ids)
    flat = sdfs.reshape(m, -1)
    own = [surface_unit(sdfs[i], grid) for i in range(m)]
    rows = []
    for i in range(m):
        rest = np.delete(flat, i, axis=0)
        kk = min(kmax, m - 2)
        mean, comps, _, _, rank = fit_pca(rest, kk)
        x = flat[i].astype(np.float64) - mean
        z = comps @ x
        # inside the K = 3 latent box of the others (the box the attack's unit vectors span)
        z_rest = (rest.astype(np.float64) - mean) @ comps[:3].T
        inside_box = bool(np.all((z[:3] >= z_rest.min(axis=0)) & (z[:3] <= z_rest.max(axis=0))))
        for k in range(0, kk + 1):
            field = (mean + z[:k] @ comps[:k]).astype(np.float32).reshape(sdfs.shape[1:])
            try:
                rec = surface_unit(field, grid)
                err = mean_surface_distance(rec, own[i], rng, 8000) * grid.extent_m * 100
            except (ValueError, RuntimeError):
                err = float("nan")
            rows.append({"asset": ids[i], "k": k, "loo_mean_surface_distance_cm": err, "inside_k3_box": inside_box})
    return rows


def part_c(spaces: dict[int, object], rng, repeats: int = 15) -> list[dict]:
    rows = []
    for n, sp in spaces.items():
        us = [np.full(sp.dim, 0.5)] + [sp.sample_unit(rng) for _ in range(4)]
        times, tris = [], []
        for u in us:
            sp.decode_arrays(u)  # warm
            ts = []
            for _ in range(repeats):
                t0 = time.process_time()
                v, f = sp.decode_arrays(u)
                ts.append(time.process_time() - t0)
            times.append(float(np.median(ts)))
            tris.append(len(f))
        rows.append({"resolution": n, "decode_ms_median": 1000 * float(np.median(times)),
                     "decode_ms_max_over_u": 1000 * float(np.max(times)), "triangles_median": int(np.median(tris))})
    return rows


def summarise_a(rows: list[dict]) -> list[dict]:
    out = []
    keys = sorted({(r["method"], r["resolution"]) for r in rows}, key=lambda t: (METHODS.index(t[0]), t[1]))
    for method, n in keys:
        rs = [r for r in rows if r["method"] == method and r["resolution"] == n and "iou" in r]
        if not rs:
            continue
        out.append({"method": method, "resolution": n, "iou_mean": float(np.mean([r["iou"] for r in rs])),
                    "iou_min": float(np.min([r["iou"] for r in rs])),
                    "msd_mm_mean": float(np.mean([r["mean_surface_distance_mm"] for r in rs])),
                    "sdf_time_s_mean": float(np.mean([r["sdf_time_s"] for r in rs])), "assets": len(rs)})
    return out


def part_e(resolution: int = 64) -> dict:
    """The hard-case suite: decoded dimensions and solid outside the body, winding vs v1."""
    from tests.cad_hardcases import CASES, hardcase_car

    grid = grid_for_dimensions([(5.5, 2.0, 1.9)], resolution)
    voxel_m = grid.voxel * grid.extent_m
    rows = []
    for case in CASES:
        for seed in (0, 1):
            car = hardcase_car(case, seed=seed)
            import trimesh

            mesh, report = clean_mesh(trimesh.Trimesh(car.vertices, car.faces, process=False))
            for method in ("winding", "winding-outward"):
                t0 = time.process_time()
                field = sdf_volume(mesh.vertices, mesh.faces, grid, method)
                cpu = time.process_time() - t0
                v, _ = extract_surface(field, grid)
                err = np.ptp(v, axis=0) - np.asarray(car.dimensions)
                nodes = grid.to_metric(grid.points())
                inside = field.ravel() < 0
                outside_by = car.outside_distance(nodes[inside])
                rows.append({"case": case, "seed": seed, "method": method, "parts": car.parts,
                             "boundary_edges": report["boundary_edges"], "dims_error_m": err.tolist(),
                             "max_abs_dims_error_m": float(np.abs(err).max()),
                             "solid_nodes_outside_body": int(np.sum(outside_by > voxel_m)),
                             "max_solid_outside_m": float(outside_by.max()) if len(outside_by) else 0.0,
                             "sdf_cpu_s": cpu})
                print(f"  {case:13s} {seed} {method:16s} dims err {np.round(err, 3)} outside "
                      f"{rows[-1]['solid_nodes_outside_body']:3d} cpu {cpu:5.2f} s", flush=True)
    summary = []
    for method in ("winding", "winding-outward"):
        rs = [r for r in rows if r["method"] == method]
        summary.append({"method": method, "cars": len(rs),
                        "passed": int(sum(r["max_abs_dims_error_m"] <= 0.05 and r["solid_nodes_outside_body"] == 0
                                          for r in rs)),
                        "mean_abs_dims_error_cm": 100 * float(np.mean([np.abs(r["dims_error_m"]) for r in rs])),
                        "max_abs_dims_error_cm": 100 * float(np.max([r["max_abs_dims_error_m"] for r in rs])),
                        "cars_with_solid_outside": int(sum(r["solid_nodes_outside_body"] > 0 for r in rs)),
                        "sdf_cpu_s_mean": float(np.mean([r["sdf_cpu_s"] for r in rs]))})
    return {"resolution": resolution, "voxel_m": voxel_m, "summary": summary, "rows": rows}


def summarise_b(rows: list[dict]) -> list[dict]:
    out = []
    for k in sorted({r["k"] for r in rows}):
        e = np.array([r["loo_mean_surface_distance_cm"] for r in rows if r["k"] == k])
        out.append({"k": k, "loo_msd_cm_mean": float(np.nanmean(e)), "loo_msd_cm_median": float(np.nanmedian(e)),
                    "loo_msd_cm_max": float(np.nanmax(e)), "failed": int(np.isnan(e).sum())})
    return out


def inside_box_share(rows: list[dict]) -> dict:
    per_asset = {r["asset"]: r["inside_k3_box"] for r in rows}
    return {"assets": len(per_asset), "inside": int(sum(per_asset.values())),
            "share": float(np.mean(list(per_asset.values()))),
            "outside_assets": sorted(a for a, v in per_asset.items() if not v)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 assets, resolutions 32-64, reference 128, library at 32^3")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--library", type=Path, default=None, help="library.json (default: the bundled library)")
    args = ap.parse_args()
    quick = args.quick
    rng = np.random.default_rng(0)
    resolutions = [32, 48, 64] if quick else [32, 48, 64, 100, 128]
    ref_res = 128 if quick else 192
    lib_res = 32 if quick else DEFAULT_RESOLUTION
    result: dict = {"command": " ".join([Path(sys.executable).name] + sys.argv), "quick": quick, "machine": machine_info(),
                    "times": "CPU time of this process (time.process_time), one BLAS/OpenMP thread; machine shared"}

    library = load_library(args.library) if args.library else load_library()
    assets = library.shape_space_assets()
    print(f"library: {len(assets)} shape-space assets", flush=True)

    # (d) whole-library build at the default resolution (also gives the SDFs for (b)).
    t0 = time.process_time()
    grid, assets, sdfs, _ = library_sdfs(library, lib_res, progress=False, mesh_loader=mesh_of)
    t_sdf = time.process_time() - t0
    t1 = time.process_time()
    space = shape_space_from_sdfs(sdfs, [a.id for a in assets], grid, 3)
    blob = space.to_bytes()
    t_pca = time.process_time() - t1
    result["d_build"] = {"resolution": lib_res, "assets": len(assets), "sdf_s": t_sdf, "pca_and_serialise_s": t_pca,
                         "total_s": t_sdf + t_pca, "file_bytes": len(blob),
                         "explained_variance_ratio": space.explained_variance_ratio.tolist()}
    print(f"(d) build {len(assets)} assets at {lib_res}^3: SDF {t_sdf:.1f} s + PCA/serialise {t_pca:.2f} s "
          f"= {t_sdf + t_pca:.1f} s, file {len(blob) / 1e6:.2f} MB", flush=True)

    # (b) K against leave-one-out error.
    print("(b) leave-one-out reconstruction ...", flush=True)
    rows_b = part_b(sdfs, [a.id for a in assets], grid, 8, rng)
    result["b_k_loo"] = {"resolution": lib_res, "summary": summarise_b(rows_b),
                         "left_out_inside_k3_box": inside_box_share(rows_b), "rows": rows_b}

    # (e) hard-case suite, winding against the v1 method.
    print("(e) real-CAD-like hard cases ...", flush=True)
    result["e_hardcases"] = part_e() if not quick else part_e(48)

    # (a) SDF method x resolution on a few assets spread over the library.
    grid64 = GridSpec(64, grid.extent_m, grid.ground_z, grid.truncation)
    by_source = {}
    for a in assets:
        by_source.setdefault(a.id.split(".")[0], []).append(a.id)
    pick = []
    for ids in by_source.values():
        pick += ids[:1] if quick else ids[:2]
    pick = pick[:2] if quick else pick[:4]
    if not quick and "openmaterial-examples.coupe" in [a.id for a in assets]:
        pick.append("openmaterial-examples.coupe")  # the CAD-like one: 41k triangles, interior, open panels
    print(f"(a) SDF methods x resolutions on {pick}, reference winding {ref_res}^3 ...", flush=True)
    rows_a = part_a(library, grid64, pick, resolutions, ref_res, rng)
    result["a_sdf"] = {"reference": f"winding {ref_res}^3", "assets": pick, "summary": summarise_a(rows_a), "rows": rows_a}

    # (c) decode time against resolution: spaces over the (a) assets' winding SDFs.
    spaces = {}
    for n in resolutions:
        g = GridSpec(n, grid.extent_m, grid.ground_z, grid.truncation)
        vols = np.stack([sdf_volume(*_va(mesh_of(library, aid)), g) for aid in pick])
        spaces[n] = shape_space_from_sdfs(vols, pick, g, min(3, len(pick)))
    spaces[lib_res] = space
    spaces = dict(sorted(spaces.items()))
    rows_c = part_c(spaces, rng)
    result["c_decode"] = rows_c

    # ---- tables
    print("\n(a) SDF method x resolution (mean over assets; reference winding %d^3)" % ref_res)
    print(f"{'method':10s} {'N':>5s} {'IoU mean':>9s} {'IoU min':>8s} {'MSD mm':>8s} {'SDF s/asset':>12s}")
    for r in result["a_sdf"]["summary"]:
        print(f"{r['method']:10s} {r['resolution']:5d} {r['iou_mean']:9.4f} {r['iou_min']:8.4f} {r['msd_mm_mean']:8.1f} {r['sdf_time_s_mean']:12.2f}")
    print(f"\n(b) K against leave-one-out reconstruction error ({len(assets)} assets, {lib_res}^3)")
    print(f"{'K':>3s} {'mean cm':>8s} {'median cm':>10s} {'max cm':>8s}")
    for r in result["b_k_loo"]["summary"]:
        print(f"{r['k']:3d} {r['loo_msd_cm_mean']:8.2f} {r['loo_msd_cm_median']:10.2f} {r['loo_msd_cm_max']:8.2f}")
    print("\n(c) decode time (unit vector -> mesh arrays, one core)")
    print(f"{'N':>5s} {'median ms':>10s} {'max ms':>8s} {'triangles':>10s}")
    for r in rows_c:
        print(f"{r['resolution']:5d} {r['decode_ms_median']:10.2f} {r['decode_ms_max_over_u']:8.2f} {r['triangles_median']:10d}")
    box = result["b_k_loo"]["left_out_inside_k3_box"]
    print(f"left-out vehicles inside the others' K=3 latent box: {box['inside']}/{box['assets']} ({box['share']:.0%})")
    print("\n(e) hard-case suite (dims within 5 cm and no solid outside the body)")
    for r in result["e_hardcases"]["summary"]:
        print(f"{r['method']:16s} passed {r['passed']}/{r['cars']}  mean |dims err| {r['mean_abs_dims_error_cm']:.1f} cm  "
              f"max {r['max_abs_dims_error_cm']:.1f} cm  cars with solid outside {r['cars_with_solid_outside']}  "
              f"SDF CPU {r['sdf_cpu_s_mean']:.2f} s")
    d = result["d_build"]
    print(f"\n(d) whole library ({d['assets']} assets) at {d['resolution']}^3: {d['total_s']:.1f} s "
          f"(SDF {d['sdf_s']:.1f} s), file {d['file_bytes'] / 1e6:.2f} MB")

    out = args.out or ROOT / "bench" / "results" / ("shape_space.quick.json" if quick else "shape_space.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"\nwrote {out}")
    return 0


def _va(mesh):
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


if __name__ == "__main__":
    sys.exit(main())
