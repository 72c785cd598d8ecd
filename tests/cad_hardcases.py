"""Synthetic real-CAD-like vehicle meshes: the hard cases of production-car CAD, from primitives.

Real CAD bodies are not closed meshes: they are hundreds of separate open panels (seams are
gaps, not shared edges), wound any way (panel by panel and, inside a panel, face by face),
with missing windows, interiors (seats, dashboard), mirrors thinner than a voxel, double-walled
cabins (outer skin + inner trim), and parts poking through the body (wheels, exhaust). Each
car here is built from *closed convex primitives* (the reference solid: their union) and then
broken into such a soup, so a test knows exactly where the solid is.

Used by ``tests/test_sdf_hardcases.py`` and ``bench/shape_space.py`` (part e).

    car = hardcase_car("all", seed=0)
    car.vertices, car.faces          # the soup, metres, library convention (+x front, z = 0 ground)
    car.inside(points)               # (P,) bool: inside the reference solid
    car.outside_distance(points)     # (P,) lower bound of the distance to the solid (0 inside)
    car.dimensions                   # (L, W, H) of the soup's bounding box
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

#: Feature sets of the suite: each case adds some hard features to a plain panelled body.
CASES = {
    "panels": ("panels", "flip_parts"),
    "open_windows": ("panels", "flip_parts", "flip_faces", "no_side_windows"),
    "interior": ("panels", "flip_parts", "seats", "dashboard"),
    "mirrors": ("panels", "flip_parts", "mirrors"),
    "double_wall": ("panels", "flip_parts", "double_wall", "glass"),
    "poking": ("panels", "flip_parts", "exhaust", "wheels_through"),
    "all": ("panels", "flip_parts", "flip_faces", "no_side_windows", "seats", "dashboard", "mirrors",
            "double_wall", "exhaust", "wheels_through", "roof_panel"),
}


@dataclass
class HardCaseCar:
    """A soup and the closed convex primitives whose union is its solid."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    solids: list = field(default_factory=list)  # closed convex trimesh primitives
    parts: int = 0

    @property
    def dimensions(self) -> tuple[float, float, float]:
        ext = np.ptp(self.vertices[np.unique(self.faces)], axis=0)
        return float(ext[0]), float(ext[1]), float(ext[2])

    def _plane_distance(self, points: np.ndarray) -> np.ndarray:
        """(S, P) max over each convex solid's face planes of the signed plane distance."""
        out = []
        for s in self.solids:
            n = np.asarray(s.face_normals)
            d = np.einsum("ij,ij->i", n, np.asarray(s.triangles)[:, 0])
            out.append((points @ n.T - d).max(axis=1))
        return np.stack(out)

    def inside(self, points: np.ndarray) -> np.ndarray:
        return np.any(self._plane_distance(points) < 0, axis=0)

    def outside_distance(self, points: np.ndarray) -> np.ndarray:
        """Lower bound of the distance from each point to the solid (max plane distance)."""
        return np.maximum(self._plane_distance(points).min(axis=0), 0.0)


def _box(extents, centre) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return b


def _prism(x_bottom, x_top, y_bottom, y_top, z0, z1) -> trimesh.Trimesh:
    """A cabin: convex hull of a bottom and a smaller top rectangle."""
    pts = [(x, y, z0) for x in x_bottom for y in (-y_bottom, y_bottom)]
    pts += [(x, y, z1) for x in x_top for y in (-y_top, y_top)]
    return trimesh.convex.convex_hull(np.array(pts, dtype=float))


def _wheel(x, y, radius=0.32, width=0.22) -> trimesh.Trimesh:
    w = trimesh.creation.cylinder(radius=radius, height=width, sections=16)
    w.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    w.apply_translation((x, y, radius))
    return w


def _panels(mesh: trimesh.Trimesh, rng: np.random.Generator, cell: float, flip_parts: bool, flip_faces: bool,
            drop=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split a closed primitive into separate open panels (no shared vertices between panels)."""
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=cell / 3)
    c = v[f].mean(axis=1)
    if drop is not None:
        keep = ~drop(c, v[f])
        f, c = f[keep], c[keep]
    # panels: faces grouped by a jittered grid cell of their centroid (and by face normal so a
    # panel does not wrap a sharp edge every time)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    key = np.floor((c + rng.uniform(0, cell, 3)) / cell).astype(np.int64)
    key = np.c_[key, np.argmax(np.abs(n), axis=1) * 2 + (n[np.arange(len(n)), np.argmax(np.abs(n), axis=1)] > 0)]
    _, label = np.unique(key, axis=0, return_inverse=True)
    label = label.reshape(-1)
    out = []
    for p in range(label.max() + 1):
        pf = f[label == p]
        used, inv = np.unique(pf, return_inverse=True)
        # seams are gaps and overlaps of a few mm, never shared vertices (as in CAD exports)
        pv, pf = v[used] + rng.uniform(-0.003, 0.003, 3), inv.reshape(-1, 3)
        if flip_parts and rng.random() < 0.5:
            pf = pf[:, ::-1]
        if flip_faces:
            sel = rng.random(len(pf)) < 0.08
            pf[sel] = pf[sel][:, ::-1]
        out.append((pv, pf.copy()))
    return out


def _closed_part(mesh: trimesh.Trimesh, rng: np.random.Generator, flip: bool) -> tuple[np.ndarray, np.ndarray]:
    f = np.asarray(mesh.faces)
    if flip and rng.random() < 0.5:
        f = f[:, ::-1]
    return np.asarray(mesh.vertices, dtype=float), f.copy()


def hardcase_car(case: str = "all", seed: int = 0, length: float = 4.6, width: float = 1.8,
                 height: float = 1.45) -> HardCaseCar:
    """One car of the suite (``CASES``): a sedan of ``length x width x height`` (body without
    mirrors) built as a CAD-like soup.

    Args:
        case: a key of ``CASES``.
        seed: panel layout and windings.
    """
    feats = set(CASES[case])
    rng = np.random.default_rng(seed)
    cell = 0.45  # panel size: ~100-300 panels per car
    z_sill, z_belt = 0.28, 0.9
    body = _box((length, width, z_belt - z_sill), (0, 0, (z_sill + z_belt) / 2))
    xb = (-0.30 * length, 0.22 * length)
    xt = (-0.22 * length, 0.08 * length)
    cabin = _prism(xb, xt, 0.46 * width, 0.36 * width, z_belt - 0.02, height)
    # wheels 2 cm inside the body side (CAD tyres are not flush with the panels); poking: 3 cm out
    wy = width / 2 - 0.13 + (0.05 if "wheels_through" in feats else 0.0)
    wheels = [_wheel(sx * 0.31 * length, sy * wy) for sx in (-1, 1) for sy in (-1, 1)]
    solids = [body, cabin] + wheels
    flip_parts, flip_faces = "flip_parts" in feats, "flip_faces" in feats
    pieces: list[tuple[np.ndarray, np.ndarray]] = []

    def cabin_drop(c, tri):
        if "no_side_windows" not in feats and "glass" not in feats:
            return np.zeros(len(c), dtype=bool)
        # side windows: the cabin's side faces between belt line and roof, away from the pillars
        side = np.abs(np.abs(c[:, 1]) - 0.41 * width) < 0.06 * width
        side &= (c[:, 2] > z_belt + 0.08) & (c[:, 2] < height - 0.1)
        side &= ((c[:, 0] > xb[0] + 0.35) & (c[:, 0] < -0.15)) | ((c[:, 0] > 0.0) & (c[:, 0] < xt[1] + 0.05))
        return side

    if "panels" in feats:
        pieces += _panels(body, rng, cell, flip_parts, flip_faces)
        pieces += _panels(cabin, rng, cell, flip_parts, flip_faces, drop=cabin_drop)
    else:
        pieces += [_closed_part(body, rng, flip_parts), _closed_part(cabin, rng, flip_parts)]
    if "glass" in feats:
        # single-sided glass sheets closing the side windows, slightly inset
        for sy in (-1, 1):
            for x0, x1 in ((xb[0] + 0.45, -0.2), (0.05, xt[1])):
                z0, z1 = z_belt + 0.12, height - 0.14
                yy = sy * (0.41 * width - 0.01)
                gv = np.array([[x0, yy, z0], [x1, yy, z0], [x1, yy, z1], [x0, yy, z1]])
                gf = np.array([[0, 1, 2], [0, 2, 3]])
                pieces.append((gv, gf if rng.random() < 0.5 else gf[:, ::-1]))
    for w in wheels:
        pieces.append(_closed_part(w, rng, flip_parts))
    if "seats" in feats:
        for sx in (-0.45, 0.25):
            for sy in (-1, 1):
                seat = _box((0.5, 0.5, 0.35), (sx, sy * 0.32, z_belt - 0.05))
                back = _box((0.12, 0.5, 0.45), (sx - 0.25, sy * 0.32, z_belt + 0.25))
                pieces += [_closed_part(seat, rng, True), _closed_part(back, rng, True)]
    if "dashboard" in feats:
        dash = _box((0.3, 0.8 * width, 0.2), (xb[1] - 0.35, 0, z_belt))
        pieces += _panels(dash, rng, cell, True, flip_faces)
    if "double_wall" in feats:
        # inner trim: the cabin shrunk 5 cm, facing into the cabin, as separate panels
        inner = cabin.copy()
        ctr = np.array([np.mean(xb), 0.0, (z_belt + height) / 2])
        half = np.ptp(cabin.vertices, axis=0) / 2
        inner.vertices = ctr + (inner.vertices - ctr) * (half - 0.05) / half
        inner.invert()
        pieces += _panels(inner, rng, cell, False, flip_faces)
    if "mirrors" in feats:
        for sy in (-1, 1):
            # 2 cm thick (a quarter of a 64^3 voxel), 20 cm out from the body side
            m = _box((0.02, 0.30, 0.12), (xb[1] - 0.05, sy * (width / 2 + 0.05), z_belt - 0.02))
            solids.append(m)
            pieces.append(_closed_part(m, rng, flip_parts))
    if "exhaust" in feats:
        ex = trimesh.creation.cylinder(radius=0.04, height=0.5, sections=10)
        ex.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        ex.apply_translation((-length / 2 + 0.19, 0.45, 0.36))  # 6 cm out of the back
        solids.append(ex)
        pieces.append(_closed_part(ex, rng, flip_parts))
    if "roof_panel" in feats:
        # a roof skin as one curved open sheet lying on the cabin roof, wound inwards
        x0, x1 = xt
        xs = np.linspace(x0, x1, 8)
        ys = np.linspace(-0.36 * width, 0.36 * width, 6)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        gz = height - 0.03 * (gy / (0.36 * width)) ** 2
        rv = np.c_[gx.ravel(), gy.ravel(), gz.ravel()]
        idx = np.arange(len(rv)).reshape(len(xs), len(ys))
        rf = np.concatenate([np.c_[idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()],
                             np.c_[idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()]])
        pieces.append((rv, rf[:, ::-1]))  # normals down, into the cabin

    offsets = np.cumsum([0] + [len(p[0]) for p in pieces[:-1]])
    vertices = np.concatenate([p[0] for p in pieces])
    faces = np.concatenate([p[1] + o for p, o in zip(pieces, offsets)]).astype(np.int64)
    # convention: origin at the footprint centre, z = 0 at the lowest point
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    vertices = vertices - shift
    moved = []
    for s in solids:
        s = s.copy()
        s.apply_translation(-shift)
        moved.append(s)
    return HardCaseCar(case, vertices, faces, moved, parts=len(pieces))
