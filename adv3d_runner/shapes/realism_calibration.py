"""Calibration of the realism checks: hard cases of real cars, known-unrealistic shapes, and the
confusion table of a set of reports under a set of limits (docs/realism.md, "Calibration").

Hard cases are what real CAD has and a low-poly library car has not: door mirrors and spoilers
thinner than a voxel, open panels (missing side windows), interiors (seats, dashboard) and
double walls (an inner skin 3 cm inside the outer one). They are real cars and must pass.
Unrealistic shapes must fail: the paper's free per-vertex deformation at 0.5 m and 1 m, blobs
(unions of ellipsoids), the 1.36 m-wide "sedan" of the demo (5.10 x 1.36 x 1.68 m), a car front
fused to a 7.4 m flatbed. ``bench/realism_calibration.py`` adds the real files (library, TORCS,
OpenMaterial) and the project's lattice deformation, runs every report and writes the result.

Every generator takes and returns ``trimesh.Trimesh`` meshes in the vehicle frame (metres, +x
front, z up, footprint centre at the origin, lowest point on the ground) and is deterministic
for a given seed.
"""
from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any, Iterable, Sequence

import numpy as np

from .realism import _AT_MOST, RealismLimits, check_flags

#: Thickness of the generated thin parts (mirror plates, spoiler): thinner than the 9.6 cm voxel.
THIN_PART_M = 0.02
#: Share of the real set that the calibrated limits must pass, and of the unrealistic set that
#: they must fail (the targets).
TARGET_REAL_PASS = 0.95
TARGET_UNREALISTIC_FAIL = 0.95


# ----------------------------------------------------------------------------- helpers


def _box(lo: Sequence[float], hi: Sequence[float]):
    import trimesh

    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    box = trimesh.creation.box(extents=hi - lo)
    box.apply_translation(0.5 * (lo + hi))
    return box


def _union(parts: list):
    """Concatenated meshes (overlapping parts are fine: the SDF takes a union)."""
    import trimesh

    return trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in parts])


def _grounded(mesh):
    v = np.asarray(mesh.vertices, dtype=np.float64).copy()
    lo, hi = v.min(axis=0), v.max(axis=0)
    v -= [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]]
    out = mesh.copy()
    out.vertices = v
    return out


def _side_at(mesh, x: float, z: float, band: float = 0.15) -> float:
    """Half width of the body near (x, z): the largest |y| of vertices within ``band``."""
    v = np.asarray(mesh.vertices)
    near = (np.abs(v[:, 0] - x) < band) & (np.abs(v[:, 2] - z) < band)
    return float(np.abs(v[near, 1]).max()) if near.any() else 0.5 * float(np.ptp(v[:, 1]))


# ----------------------------------------------------------------------------- hard cases (real)


def with_mirrors(mesh, thickness: float = THIN_PART_M, reach: float = 0.2):
    """Door mirrors: two plates ``thickness`` thick (x), 0.15 m high, sticking out ``reach`` beyond
    the side at the A-pillar (30 % of the length from the front, 62 % of the height)."""
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    x = hi[0] - 0.3 * (hi[0] - lo[0])
    z = lo[2] + 0.62 * (hi[2] - lo[2])
    parts = [mesh]
    for s in (1.0, -1.0):
        y0 = _side_at(mesh, x, z) - 0.03
        ys = sorted([s * y0, s * (y0 + reach + 0.03)])
        parts.append(_box([x - thickness / 2, ys[0], z - 0.075], [x + thickness / 2, ys[1], z + 0.075]))
    return _union(parts)


def with_spoiler(mesh, thickness: float = THIN_PART_M):
    """A rear spoiler: a plate ``thickness`` thick, 0.25 m deep, 85 % of the width, 0.12 m above
    the rear deck on two posts of the same thickness."""
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    rear = v[v[:, 0] < lo[0] + 0.4]
    deck = float(rear[:, 2].max()) if len(rear) else hi[2] * 0.7
    w = 0.425 * (hi[1] - lo[1])
    x0, x1 = lo[0] + 0.05, lo[0] + 0.30
    plate = _box([x0, -w, deck + 0.12], [x1, w, deck + 0.12 + thickness])
    posts = [_box([x0 + 0.1, s * 0.5 * w - thickness, deck - 0.05], [x0 + 0.1 + thickness, s * 0.5 * w + thickness,
                                                                      deck + 0.13]) for s in (1.0, -1.0)]
    return _union([mesh, plate, *posts])


def with_open_windows(mesh):
    """Open panels: the faces of the side windows removed (|normal y| > 0.5 between 55 % and
    90 % of the height), as CAD without glass is."""
    import trimesh

    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    h = np.ptp(v[:, 2])
    c = v[f].mean(axis=1)
    n = trimesh.Trimesh(v, f, process=False).face_normals
    drop = (np.abs(n[:, 1]) > 0.5) & (c[:, 2] > v[:, 2].min() + 0.55 * h) & (c[:, 2] < v[:, 2].min() + 0.9 * h)
    return trimesh.Trimesh(v, f[~drop], process=False)


def with_interior(mesh):
    """An interior: four seats and a dashboard (boxes) inside the cabin."""
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    L, W, H = hi - lo
    floor = lo[2] + 0.3 * H
    parts = [mesh]
    for fx in (0.45, 0.7):
        for s in (1.0, -1.0):
            cx, cy = hi[0] - fx * L, s * 0.22 * W
            parts.append(_box([cx - 0.25, cy - 0.22, floor], [cx + 0.25, cy + 0.22, floor + 0.25 * H]))
    dash_x = hi[0] - 0.32 * L
    parts.append(_box([dash_x - 0.15, -0.4 * W, floor + 0.15 * H], [dash_x + 0.15, 0.4 * W, floor + 0.3 * H]))
    return _union(parts)


def with_double_walls(mesh, gap: float = 0.03):
    """Double walls: an inner skin ``gap`` inside the outer one (vertex normals), wound inwards,
    as bodies modelled with their inner trim are."""
    import trimesh

    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    inner = trimesh.Trimesh(np.asarray(m.vertices) - gap * m.vertex_normals, np.asarray(m.faces)[:, ::-1],
                            process=False)
    return _union([m, inner])


HARD_CASES = {"mirrors": with_mirrors, "spoiler": with_spoiler, "open-windows": with_open_windows,
              "interior": with_interior, "double-walls": with_double_walls}


def hard_cases(name: str, mesh) -> list[tuple[str, Any]]:
    """Every hard case of one real car, and all of them at once: [(name, mesh)]."""
    out = [(f"{name}+{k}", fn(mesh)) for k, fn in HARD_CASES.items()]
    allm = mesh
    for fn in (with_interior, with_double_walls, with_open_windows, with_mirrors, with_spoiler):
        allm = fn(allm)
    out.append((f"{name}+all", allm))
    return out


# ----------------------------------------------------------------------------- unrealistic shapes


def narrow_sedan(mesh, dimensions: Sequence[float] = (5.10, 1.36, 1.68)):
    """A car scaled to the demo's best shape, 5.10 x 1.36 x 1.68 m: narrower than any road car."""
    from .mesh_io import scale_to_dimensions

    return scale_to_dimensions(mesh, tuple(dimensions))[0]


def fused_flatbed(mesh, length: float = 7.4, width: float = 2.69, keep_front: float = 0.35):
    """The front ``keep_front`` of a car fused to a flat bed, ``length`` x ``width`` in all (the BO
    flatbed of scene 000004 is 7.40 x 2.69 x 2.13 m)."""
    import trimesh

    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    lo, hi = v.min(axis=0), v.max(axis=0)
    cut = hi[0] - keep_front * (hi[0] - lo[0])
    front = trimesh.Trimesh(v, f[v[f][:, :, 0].mean(axis=1) > cut], process=False)
    h = hi[2] - lo[2]
    bed = _box([hi[0] - length, -width / 2, lo[2] + 0.45 * h], [cut + 0.2, width / 2, lo[2] + 0.6 * h])
    frame = _box([hi[0] - length, -0.4, lo[2] + 0.25], [cut + 0.2, 0.4, lo[2] + 0.45 * h])
    return _grounded(_union([front, bed, frame]))


def blob(rng: np.random.Generator, dims: Sequence[float] | None = None, parts: int = 4):
    """A union of ``parts`` ellipsoids in an L x W x H box (default: random, 2.5-6 x 1.2-2.6 x
    0.8-2.2 m), centred and grounded."""
    import trimesh

    d = np.asarray(dims if dims is not None else rng.uniform([2.5, 1.2, 0.8], [6.0, 2.6, 2.2]), dtype=np.float64)
    out = []
    for _ in range(parts):
        r = d * rng.uniform(0.25, 0.5, 3)
        c = (rng.random(3) - 0.5) * (d - 2 * r)
        s = trimesh.creation.icosphere(subdivisions=3)
        s.vertices = s.vertices * r + c
        out.append(s)
    m = _union(out)
    v = np.asarray(m.vertices)
    m.vertices = (v - v.mean(axis=0)) * (d / np.ptp(v, axis=0))
    return _grounded(m)


def vertex_noise(mesh, bound: float, rng: np.random.Generator):
    """The paper's vertex deformation: every vertex of the template (its own low-poly vertices,
    as the paper deforms a 252-vertex mean shape) moved by uniform noise in [-bound, bound]^3
    (its l-infinity bound); coincident vertices are merged first so the surface stays joined."""
    import trimesh

    m = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    m.vertices = np.asarray(m.vertices) + rng.uniform(-bound, bound, (len(m.vertices), 3))
    return _grounded(m)


def mean_shape_template(space, step: int = 3):
    """The shape space's mean shape decoded on every ``step``-th grid node: the paper's vertex
    deformation template ("a decoded mean shape with 252 vertices"; 298 here at step 3)."""
    from .decode import extract_surface
    from .sdf import GridSpec

    import trimesh

    g = space.grid
    n = g.resolution
    sub = np.asarray(space.mean, dtype=np.float32).reshape(n, n, n)[::step, ::step, ::step]
    m = sub.shape[0]
    coarse = GridSpec(m, g.extent_m * (m - 1) * step / (n - 1), g.ground_z, g.truncation)
    return trimesh.Trimesh(*extract_surface(sub, coarse), process=False)


def unrealistic_shapes(base: Iterable[tuple[str, Any]], seed: int = 0, blobs: int = 6,
                       noise_template=None) -> list[tuple[str, Any]]:
    """Known-unrealistic meshes from base cars: per car the narrow sedan, the fused flatbed and
    vertex noise at 0.5 m and 1 m (on ``noise_template`` scaled to the car's box when given,
    e.g. ``mean_shape_template``: the paper's template); plus ``blobs`` blobs and the BO blob's
    2.93 x 1.31 x 0.93 m."""
    from .mesh_io import scale_to_dimensions

    rng = np.random.default_rng(seed)
    out = []
    for name, mesh in base:
        out.append((f"{name}>narrow-5.10x1.36x1.68", narrow_sedan(mesh)))
        out.append((f"{name}>front+flatbed-7.4m", fused_flatbed(mesh)))
        tmpl = mesh if noise_template is None else scale_to_dimensions(
            noise_template, tuple(np.ptp(np.asarray(mesh.vertices), axis=0)))[0]
        for b in (0.5, 1.0):
            out.append((f"{name}>vertex-noise-{b:g}m", vertex_noise(tmpl, b, rng)))
    for i in range(blobs):
        out.append((f"blob-{i}", blob(rng)))
    out.append(("blob-2.93x1.31x0.93", blob(rng, (2.93, 1.31, 0.93))))
    return out


# ----------------------------------------------------------------------------- confusion, limits


def confusion(records: Sequence[dict], limits: dict) -> dict:
    """Confusion table and per-check pass rates of reports under ``limits`` (resolved numbers).

    Args:
        records: ``{"name", "kind": "real" | "unrealistic", "report"}``; a report that failed to
            compute carries ``"error"`` instead and counts as failing.
        limits: ``RealismLimits.resolve`` output.
    Returns:
        ``{"real": {"n", "pass", "fail", "pass_rate"}, "unrealistic": {..., "fail_rate"},
        "per_check": {check: {"real_pass_rate", "unrealistic_fail_rate"}}, "flags": {name: [...]}}``.
    """
    out: dict = {"per_check": {}, "flags": {}}
    for kind in ("real", "unrealistic"):
        recs = [r for r in records if r["kind"] == kind]
        flags = [check_flags(r["report"], limits) if "report" in r else ["error"] for r in recs]
        n_pass = sum(1 for f in flags if not f)
        out[kind] = {"n": len(recs), "pass": n_pass, "fail": len(recs) - n_pass,
                     "pass_rate": n_pass / len(recs) if recs else None,
                     "fail_rate": (len(recs) - n_pass) / len(recs) if recs else None}
        for r, f in zip(recs, flags):
            out["flags"][r["name"]] = f
    for key in _AT_MOST:
        row = {}
        for kind in ("real", "unrealistic"):
            recs = [r for r in records if r["kind"] == kind and "report" in r]
            ok = [key not in check_flags(r["report"], limits) for r in recs]
            row[f"{kind}_pass_rate"] = float(np.mean(ok)) if ok else None
        out["per_check"][key] = row
    return out


def propose_limits(records: Sequence[dict], base: RealismLimits, resolved: dict, quantile: float = 1.0) -> RealismLimits:
    """Limits that pass the real set: per check, the base limit or the real set's ``quantile``
    (1.0: its extreme) when that is more permissive. Dimension excess stays with the cited
    ranges (``base``). The caller checks the unrealistic set's fail rate under the result
    (``confusion``)."""
    real = [r["report"] for r in records if r["kind"] == "real" and "report" in r]
    if not real:
        return base

    def q(key: str, hi: bool) -> float:
        vals = np.array([float(r[key]) for r in real if r.get(key) is not None])
        return float(np.quantile(vals, quantile if hi else 1.0 - quantile))

    return replace(
        base,
        jsd_max=max(resolved["jsd"], q("jsd", True)),
        nearest_chamfer_max_m=max(resolved["nearest_chamfer_m"], q("nearest_chamfer_m", True)),
        mahalanobis_max=max(resolved["mahalanobis"], q("mahalanobis", True)),
        floating_volume_max=max(resolved["floating_volume_fraction"], q("floating_volume_fraction", True)),
        genus_robust_max=int(max(resolved["genus_robust"], q("genus_robust", True))),
        thinnest_wall_min_m=min(resolved["thinnest_wall_m"], q("thinnest_wall_m", False)),
    )


def limits_dict(limits: RealismLimits) -> dict:
    """JSON-able ``RealismLimits``."""
    return asdict(limits)
