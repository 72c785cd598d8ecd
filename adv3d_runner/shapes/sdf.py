"""Truncated signed distance volumes of vehicle meshes on a common N^3 grid.

Real CAD is rarely a clean solid: bodies are open (missing windows), made of separate
self-intersecting parts, hold interior parts (seats, engine) and mix face orientations. The
inside/outside test therefore must not rely on a watertight, consistently oriented mesh.

Methods (``METHODS``):

``winding`` (default)
    1. orient faces consistently inside each edge-connected patch (``igl.bfs_orient``), then
       turn each patch so its front is its side seen from outside
       (:func:`orient_patches_by_visibility`): a closed patch by the sign of its volume, an
       open one by rays cast from both of its sides (the side whose rays escape more often is
       the front, Takayama et al. 2014), a patch hidden from both sides is left as it is. Real
       CAD is hundreds of open panels wound any way; orienting each panel away from its own
       centroid (the rule of ``winding-outward``) turns concave panels inwards, which puts
       solid blobs beside the body and slabs on the roof;
    2. sign from the generalised winding number (``igl.fast_winding_number``): inside where
       w > 0.5. Interior parts and overlapping parts only raise w (1 -> 2), open bodies give a
       fractional w that is still > 0.5 in a mostly closed cabin;
    3. sealed hollows (double-walled shells: the winding number is ~0 inside them) are
       filled: free space a flood fill from the border cannot reach, see
       ``fill_enclosed_cavities``;
    4. unsigned distance (libigl AABB: ``igl.signed_distance`` with the unsigned sign type and
       an upper bound at the truncation) to the *boundary* pieces only: triangles, split to
       about a voxel, whose two sides have different inside/outside status. Interior parts and
       faces hidden inside overlapping parts would otherwise create small |SDF| pockets inside
       the body that a PCA blend can turn into spurious surfaces;
    5. parts thinner than a voxel (mirrors, exhaust pipes) that fall between grid nodes are
       kept: :func:`capture_thin_parts` makes the node nearest to them inside.
``winding-outward`` (the method of shape space v1, kept for the benchmark)
    As ``winding`` but step 1 orients every patch away from its own centroid
    (``cleaning.orient_faces`` rule ``"outward"``: ``igl.orient_outward``) and there is no
    step 5.
``floodfill`` (the paper's mesh2sdf style)
    Unsigned distance to all faces; voxels closer than 0.75 voxel to a face are walls; the
    outside is the wall-free region connected to the grid border (6-connectivity). Robust to
    orientation and interiors, but the surface is biased outwards by up to the wall width and
    holes wider than 1.5 voxels leak (the cabin of a car with missing windows fills with
    "outside").
``rayvote``
    Unsigned distance as ``winding``; a grid point is inside when at least 10 of 14 rays from
    it hit the mesh (Embree, first hit only). Orientation-free and blind to interiors and
    overlaps, but it is a vote: deep concave corners (where >= 10 directions are blocked) fill
    in, and a cabin that sees out through more than 4 window openings empties.

Grid (``GridSpec``): nodes at ``-0.5 + i / (N - 1)`` on each axis of the unit cube. A metric
vehicle mesh (library convention: +x forward, z up, origin at the footprint centre on the
ground) maps to the unit cube by ``x / E, y / E, z / E + ground_z`` where ``E`` (``extent_m``,
the paper's common scale factor) is 1.1 x the largest dimension over the *shape-space* assets
(buses and trucks are not in the shape space and would waste resolution), and ``ground_z`` puts
the ground plane so the tallest shape-space vehicle is vertically centred. Every vehicle thus
shares the ground plane (wheels line up, which is what PCA should see). SDF values are in
unit-cube units (metres / E), negative inside, clamped to ``[-truncation, truncation]``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Sequence

import numpy as np

from ..errors import Adv3dError, ConfigError
from ..progress import Steps, run_steps
from .cleaning import orient_faces
from .names import METHODS  # noqa: F401  (re-exported)

#: Grid points per piece in the stepwise SDF (:func:`sdf_volume_steps`): one piece of libigl
#: work takes well under 0.1 s at 64^3, so the add-on's UI never waits long.
STEP_POINTS = 32768
DEFAULT_METHOD = "winding"
#: Truncation in unit-cube units: 0.1 x the cube edge (~0.55 m for a 5 m car). Wide enough that
#: linear PCA blends of neighbouring surfaces stay distance-like (a narrow band blends like an
#: occupancy grid and gives blobby interpolations).
DEFAULT_TRUNCATION = 0.1
#: Common-scale margin of the paper: the cube edge is 1.1 x the largest dimension.
SCALE_MARGIN = 1.1


@dataclass(frozen=True)
class GridSpec:
    """Where the SDF samples lie.

    Attributes:
        resolution: N, samples per axis (N^3 in all).
        extent_m: cube edge in metres (the common scale factor E).
        ground_z: z of the ground plane in unit-cube coordinates.
        truncation: SDF clamp in unit-cube units.
    """

    resolution: int
    extent_m: float
    ground_z: float
    truncation: float = DEFAULT_TRUNCATION

    def __post_init__(self) -> None:
        if not (isinstance(self.resolution, (int, np.integer)) and 8 <= int(self.resolution) <= 512):
            raise ConfigError(f"SDF resolution must be an integer in [8, 512], got {self.resolution!r}")
        for name in ("extent_m", "ground_z", "truncation"):
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"grid {name} must be finite, got {getattr(self, name)!r}")
        if self.extent_m <= 0 or self.truncation <= 0:
            raise ConfigError("grid extent_m and truncation must be positive")

    @property
    def voxel(self) -> float:
        """Node spacing in unit-cube units."""
        return 1.0 / (self.resolution - 1)

    def axis(self) -> np.ndarray:
        """(N,) node coordinates along one axis, unit-cube units."""
        return np.linspace(-0.5, 0.5, self.resolution)

    def points(self) -> np.ndarray:
        """(N^3, 3) float64 node coordinates, ``volume[i, j, k]`` order (x slowest)."""
        ax = self.axis()
        grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1)
        return grid.reshape(-1, 3)

    def to_unit(self, vertices_m: np.ndarray) -> np.ndarray:
        """(V, 3) metric vehicle coordinates -> unit-cube coordinates."""
        out = np.asarray(vertices_m, dtype=np.float64) / self.extent_m
        out[:, 2] += self.ground_z
        return out

    def to_metric(self, vertices_u: np.ndarray) -> np.ndarray:
        """(V, 3) unit-cube coordinates -> metric vehicle coordinates (ground at z = 0)."""
        out = np.array(vertices_u, dtype=np.float64)
        out[:, 2] -= self.ground_z
        return out * self.extent_m

    def as_dict(self) -> dict:
        d = asdict(self)
        d["resolution"] = int(d["resolution"])
        return {k: (float(v) if k != "resolution" else v) for k, v in d.items()}


def grid_for_dimensions(
    dimensions: Iterable[Sequence[float]], resolution: int, truncation: float = DEFAULT_TRUNCATION
) -> GridSpec:
    """Grid spec shared by a set of vehicles.

    Args:
        dimensions: (length, width, height) in metres per vehicle.
        resolution: N.
        truncation: SDF clamp in unit-cube units.
    """
    dims = np.asarray(list(dimensions), dtype=np.float64).reshape(-1, 3)
    if len(dims) == 0 or not np.all(np.isfinite(dims)) or np.any(dims <= 0):
        raise ConfigError("need at least one vehicle with positive finite dimensions to size the SDF grid")
    extent = SCALE_MARGIN * float(dims.max())
    ground_z = -0.5 * float(dims[:, 2].max()) / extent
    return GridSpec(int(resolution), extent, ground_z, float(truncation))


# ----------------------------------------------------------------------------------- helpers


def clean_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Drop faces with repeated indices or zero area (they carry no orientation).

    Returns:
        (F', 3) int64 faces.
    """
    # kept hand-written: area relative to the mesh's size, which trimesh's absolute-height
    # nondegenerate_faces is not; library meshes are already cleaned, user meshes may not be
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    v = np.asarray(vertices, dtype=np.float64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.einsum("ij,ij->i", cross, cross)
    scale = max(float(np.ptp(v, axis=0).max()), 1e-12) if len(v) else 1.0
    return f[area2 > (1e-14 * scale * scale) ** 2]


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) generalised winding number of ``points`` w.r.t. the triangle soup (fast, Barnes-Hut)."""
    import igl

    return igl.fast_winding_number(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(points, dtype=np.float64),
    )


def unsigned_distance(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, upper_bound: float = np.inf
) -> np.ndarray:
    """(P,) Euclidean distance from ``points`` to the triangles (libigl AABB tree).

    With a finite ``upper_bound`` the tree search stops at that distance (3x faster for a
    truncated SDF); farther points get exactly ``upper_bound``.
    """
    import igl

    p = np.ascontiguousarray(points, dtype=np.float64)
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if not np.isfinite(upper_bound):
        sq, _, _ = igl.point_mesh_squared_distance(p, v, f)
        return np.sqrt(np.maximum(sq, 0.0))
    d, _, _, _ = igl.signed_distance(
        p, v, f, sign_type=igl.SignedDistanceType.SIGNED_DISTANCE_TYPE_UNSIGNED,
        lower_bound=-float(upper_bound), upper_bound=float(upper_bound),
    )
    d = np.abs(d)
    d[~np.isfinite(d)] = upper_bound  # libigl reports points beyond the bound as NaN
    return np.minimum(d, upper_bound)


def boundary_faces(
    vertices: np.ndarray, faces: np.ndarray, inside_fn, eps: float, max_edge: float, return_inside_points: bool = False
):
    """Pieces of the surface whose two sides differ in inside/outside status (the solid's
    boundary); hidden faces inside overlapping parts and interior parts are dropped.

    Args:
        vertices: (V, 3) float64, faces: (F, 3) int64.
        inside_fn: (P, 3) points -> (P,) bool.
        eps: offset from the face centroid along its normal, unit-cube units.
        max_edge: triangles are split until no edge is longer than this first.
        return_inside_points: also return points just inside the solid along the boundary.
    Returns:
        vertices (V', 3) and faces (B, 3) of the boundary pieces; with ``return_inside_points``
        also (Q, 3) points ``eps`` inside the solid: 4 per boundary piece (its centroid and the
        midpoints between the centroid and its corners).
    """
    return run_steps(boundary_faces_steps(vertices, faces, inside_fn, eps, max_edge,
                                          return_inside_points=return_inside_points))


def boundary_faces_steps(vertices: np.ndarray, faces: np.ndarray, inside_fn, eps: float, max_edge: float,
                         chunk: int | None = None, return_inside_points: bool = False) -> Steps[tuple]:
    """:func:`boundary_faces` as a steps generator (``progress.run_steps``); the probes are
    classified ``chunk`` points at a time."""
    from trimesh.remesh import subdivide_to_size

    # A large triangle can be partly hidden inside another part (low-poly CAD): split triangles
    # to about one voxel so each piece is classified on its own.
    vertices, faces = subdivide_to_size(vertices, faces, max_edge=max_edge, max_iter=12)
    yield
    tri = vertices[faces]
    centroid = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    probe = np.concatenate([centroid + eps * normal, centroid - eps * normal])
    side = yield from chunked(inside_fn, probe, chunk)
    n = len(faces)
    is_boundary = side[:n] != side[n:]
    if not return_inside_points:
        return vertices, faces[is_boundary]
    # inward = -normal where the back side is the inside
    inward = np.where(side[n:, None], -normal, normal)[is_boundary]
    sel = tri[is_boundary]
    c = centroid[is_boundary]
    spots = np.concatenate([c[:, None], 0.5 * (c[:, None] + sel)], axis=1)  # (B, 4, 3)
    points = (spots + eps * inward[:, None]).reshape(-1, 3)
    return vertices, faces[is_boundary], points


def _patch_labels_and_closed(faces: np.ndarray, patch: np.ndarray) -> np.ndarray:
    """(P,) bool: patch has no boundary edge (every edge of it used by exactly two of its faces)."""
    n_patches = int(patch.max()) + 1
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(patch, 3)
    key = np.c_[owner, edges]
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    open_edge = counts[inverse.reshape(-1)] == 1
    has_open = np.bincount(owner[open_edge], minlength=n_patches) > 0
    return ~has_open


#: Directions of the visibility rays (a Fibonacci sphere, fixed: the same mesh always gets the
#: same orientation) and how many faces of each patch cast them.
_VIS_DIRECTIONS = 24
_VIS_SAMPLES_PER_PATCH = 64


def _fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i + 0.1234  # offset: no ray runs along an axis-aligned face
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


def orient_patches_by_visibility(
    vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-4, min_visibility: float = 0.0
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Orient a triangle soup so every patch faces the side it is seen from.

    Each edge-connected, orientable patch is first wound consistently (``igl.bfs_orient``).
    Then, per patch: a *closed* patch (no boundary edge) is turned so its signed volume is
    positive (exact for any closed part, hidden ones such as seats included); an *open* patch
    (a CAD panel) casts rays from up to 64 of its faces in 24 fixed directions from both of its
    sides (Embree); it is turned when its back side's rays escape to infinity more often,
    cosine- and area-weighted, than its front side's (the visibility rule of Takayama et al.
    2014, "A Simple Method for Correcting Facet Orientations in Polygon Meshes Based on Ray
    Casting", with fixed directions instead of random ones so the result is deterministic).

    An open patch whose rays escape from neither side is *hidden*: interior trim, the inner
    skin of a double wall, the top of a body panel under the cabin. Its orientation cannot be
    told, and a wrongly wound hidden panel punches a hole in the winding number of the solid
    around it, so such patches are reported (``hidden`` mask) for the caller to leave out of
    the inside test; they cannot be part of the outer surface.

    libigl has this method (``igl.embree.reorient_facets_raycast``) but draws random ray
    directions without a seed, so its result changes from run to run.

    With ``min_visibility`` > 0, an open patch whose better side escapes for less than that
    share of its (cosine- and area-weighted) rays counts as hidden too: the inner skin of a
    double-walled body seen only through the window openings. Left in the sign, its winding,
    facing the cabin, cancels the outer skin's there (w ~ 0) and the car decodes as a hollow
    shell; the outer skin faces half of all directions and escapes for most of them.

    Args:
        vertices: (V, 3) float64, unit-cube coordinates (``eps`` is in these units).
        faces: (F, 3) int64 (degenerate faces removed).
        eps: ray origins are moved this far off the face along its normal.
        min_visibility: share of escaping rays below which an open patch is hidden (0: only
            patches seen from neither side, as the shape-space build).
    Returns:
        (F, 3) int64 faces (same order), (F,) bool mask of the faces of hidden open patches,
        and a report ``{"patches", "closed", "open", "hidden", "patches_turned",
        "faces_turned"}``.
    """
    import igl
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f0 = np.ascontiguousarray(faces, dtype=np.int64)
    ff, patch = igl.bfs_orient(f0)
    ff = np.asarray(ff, dtype=np.int64)
    patch = np.asarray(patch, dtype=np.int64).reshape(-1)
    n_patches = int(patch.max()) + 1
    closed = _patch_labels_and_closed(ff, patch)
    tri = v[ff]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    turn = np.zeros(n_patches, dtype=bool)

    # closed patches: signed volume about the patch's own centroid
    centre = np.zeros((n_patches, 3))
    counts = np.bincount(patch, minlength=n_patches).astype(np.float64)
    for k in range(3):
        centre[:, k] = np.bincount(patch, weights=tri[:, :, k].mean(axis=1), minlength=n_patches) / counts
    t = tri - centre[patch][:, None, :]
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2]))
    volume = np.bincount(patch, weights=vol, minlength=n_patches)
    turn[closed] = volume[closed] < 0

    # open patches: visibility from both sides
    open_ids = np.flatnonzero(~closed)
    hidden_patch = np.zeros(n_patches, dtype=bool)
    if len(open_ids):
        order = np.argsort(patch, kind="stable")
        starts = np.searchsorted(patch[order], np.arange(n_patches))
        ends = np.searchsorted(patch[order], np.arange(n_patches), side="right")
        picks = []
        for p in open_ids:
            members = order[starts[p]:ends[p]]
            members = members[area[members] > 0]
            if len(members) > _VIS_SAMPLES_PER_PATCH:
                members = members[np.linspace(0, len(members) - 1, _VIS_SAMPLES_PER_PATCH).round().astype(np.int64)]
            picks.append(members)
        sample = np.concatenate(picks)
        dirs = _fibonacci_directions(_VIS_DIRECTIONS)
        cos = normal[sample] @ dirs.T  # (S, D)
        centroid = tri[sample].mean(axis=1)
        caster = RayMeshIntersector(trimesh.Trimesh(v, ff, process=False), scale_to_box=False)
        front = np.zeros(len(sample))
        back = np.zeros(len(sample))
        front_all = np.zeros(len(sample))
        back_all = np.zeros(len(sample))
        for j, d in enumerate(dirs):
            side = np.where(cos[:, j] >= 0, 1.0, -1.0)
            origins = centroid + (eps * side)[:, None] * normal[sample]
            escaped = ~caster.intersects_any(origins, np.broadcast_to(d, origins.shape))
            w = np.abs(cos[:, j]) * escaped
            front += np.where(side > 0, w, 0.0)
            back += np.where(side < 0, w, 0.0)
            front_all += np.where(side > 0, np.abs(cos[:, j]), 0.0)
            back_all += np.where(side < 0, np.abs(cos[:, j]), 0.0)
        weight = area[sample]
        owner = patch[sample]
        f_score = np.bincount(owner, weights=front * weight, minlength=n_patches)
        b_score = np.bincount(owner, weights=back * weight, minlength=n_patches)
        turn[open_ids] = b_score[open_ids] > f_score[open_ids]
        hidden_patch[open_ids] = (f_score[open_ids] == 0) & (b_score[open_ids] == 0)
        if min_visibility > 0:
            f_all = np.bincount(owner, weights=front_all * weight, minlength=n_patches)
            b_all = np.bincount(owner, weights=back_all * weight, minlength=n_patches)
            share = np.maximum(f_score / np.maximum(f_all, 1e-300), b_score / np.maximum(b_all, 1e-300))
            hidden_patch[open_ids] |= share[open_ids] < min_visibility
    flip = turn[patch]
    ff[flip] = ff[flip][:, ::-1]
    changed = int(np.sum(np.any(ff != f0, axis=1)))
    report = {"patches": n_patches, "closed": int(closed.sum()), "open": int(len(open_ids)),
              "hidden": int(hidden_patch.sum()), "patches_turned": int(turn.sum()), "faces_turned": changed}
    return ff, hidden_patch[patch], report


#: Depth given to a node that stands for a part thinner than a voxel, in voxels: the part
#: decodes as a sheet this thick around the node (0.02 voxel: 2 mm at 9.6 cm; well above the
#: decoder's 1e-3 voxel nudge, so the sign survives).
THIN_PART_DEPTH = 0.02


def capture_thin_parts(
    inside: np.ndarray, dist: np.ndarray, inside_points: np.ndarray, grid: GridSpec
) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep solid parts thinner than a voxel that fall between the grid nodes.

    A mirror 2-5 cm thick on a 9.6 cm grid often has no node inside it, so marching cubes would
    not see it (and the vehicle would lose its mirrors' width). Points just inside the solid
    along its boundary (``boundary_faces(..., return_inside_points=True)``) whose grid cell has
    no inside corner are *unrepresented*; the node nearest to each becomes inside, with the
    depth ``THIN_PART_DEPTH`` voxel, so the part decodes as a thin sheet through those nodes:
    its ends are where the nodes nearest to the part's ends are, within half a voxel (4.8 cm at
    64^3 over a 6.05 m cube) on either side. (A depth taken from the distance field would push
    every end outwards by about a third of a voxel.)

    Thick parts are represented wherever a grid node falls inside them, so only sub-voxel
    pieces are touched: thin parts, and the tips of sharp convex edges, which grow by at most
    half a voxel. Restricting it to parts away from the body (tried: no inside node among the
    26 neighbours) lost the mirrors of the Quaternius cars, which stand out 6 cm from the body.

    Args:
        inside: (N^3,) bool; dist: (N^3,) unsigned distance to the boundary, unit-cube units.
        inside_points: (Q, 3) unit-cube points just inside the solid.
    Returns:
        inside, dist (new arrays) and the number of nodes captured.
    """
    n = grid.resolution
    h = grid.voxel
    vol = inside.reshape(n, n, n)
    g = (np.asarray(inside_points, dtype=np.float64) + 0.5) / h
    g = g[np.all((g >= 0) & (g <= n - 1), axis=1)]
    if len(g) == 0:
        return inside, dist, 0
    base = np.clip(np.floor(g).astype(np.int64), 0, n - 2)
    represented = np.zeros(len(g), dtype=bool)
    for corner in np.ndindex(2, 2, 2):
        c = base + np.asarray(corner)
        represented |= vol[c[:, 0], c[:, 1], c[:, 2]]
    pick = np.clip(np.rint(g[~represented]).astype(np.int64), 0, n - 1)
    if len(pick) == 0:
        return inside, dist, 0
    captured = np.zeros((n, n, n), dtype=bool)
    captured[pick[:, 0], pick[:, 1], pick[:, 2]] = True
    captured &= ~vol
    flat = captured.ravel()
    if not flat.any():
        return inside, dist, 0
    inside = inside | flat
    dist = dist.copy()
    dist[flat] = THIN_PART_DEPTH * h
    return inside, dist, int(flat.sum())


def chunked(fn, points: np.ndarray, chunk: int | None = None) -> Steps[np.ndarray]:
    """``fn(points)`` evaluated ``chunk`` rows at a time, yielding after each piece (a steps
    generator); returns the concatenation. Only for per-point functions (each row's result
    does not depend on the other rows: winding numbers, distances, ray votes), so the result
    is bit-identical to one call."""
    chunk = chunk or len(points) or 1
    if len(points) <= chunk:
        out = fn(points)
        yield
        return out
    parts = []
    for s in range(0, len(points), chunk):
        parts.append(fn(points[s : s + chunk]))
        yield
    return np.concatenate(parts)


_RAY_DIRS = None


def _vote_directions() -> np.ndarray:
    """14 unit directions (6 axes + 8 diagonals), slightly rotated so no ray runs exactly along
    axis-aligned faces (grazing rays make hit/miss counts unstable)."""
    global _RAY_DIRS
    if _RAY_DIRS is None:
        d = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
        d += [[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]
        d = np.asarray(d, dtype=np.float64)
        a, b = 0.0123, 0.0271  # fixed small rotation about z then x
        rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
        d = d @ (rx @ rz).T
        _RAY_DIRS = d / np.linalg.norm(d, axis=1, keepdims=True)
    return _RAY_DIRS


def ray_escape_inside(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """(P,) bool: inside when at most 4 of 14 rays escape without hitting the mesh."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    # Unit-cube coordinates are small and centred: float32 for Embree is exact enough.
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    caster = RayMeshIntersector(mesh, scale_to_box=False)
    dirs = _vote_directions()
    escapes = np.zeros(len(points), dtype=np.int32)
    for d in dirs:
        for s in range(0, len(points), chunk):
            p = points[s : s + chunk]
            hit = caster.intersects_any(p, np.broadcast_to(d, p.shape))
            escapes[s : s + chunk] += ~hit
    return escapes <= 4


def enclosed_free_space(dist_all: np.ndarray, n: int, wall: float) -> np.ndarray:
    """(N^3,) bool: nodes farther than ``wall`` from every face that cannot be reached from the
    grid border without passing within ``wall`` of a face (6-connected flood fill)."""
    from scipy import ndimage

    free = (dist_all >= wall).reshape(n, n, n)
    labels, _ = ndimage.label(free)
    border = np.unique(
        np.concatenate(
            [labels[0].ravel(), labels[-1].ravel(), labels[:, 0].ravel(), labels[:, -1].ravel(),
             labels[:, :, 0].ravel(), labels[:, :, -1].ravel()]
        )
    )
    outside = np.isin(labels, border[border > 0])
    return (free & ~outside).ravel()


def fill_enclosed_cavities(
    vertices: np.ndarray, faces: np.ndarray, inside: np.ndarray, dist: np.ndarray, grid: GridSpec, bound: float
) -> tuple[np.ndarray, np.ndarray]:
    """Make sealed hollows solid and keep inside distances away from hidden walls.

    Game and CAD bodies are often double-walled shells (outer skin + interior trim joined at a
    rim, one orientable patch): the winding number is then ~0 inside the cabin or cargo box and
    the vehicle would be hollow. Free space that a flood fill from the grid border cannot reach
    (gaps narrower than 1.5 voxels count as closed) is made inside, grown by one node
    (26-neighbourhood) so the band along the hollow's walls joins it (on walls thinner than a
    voxel this moves the outer surface out by < 1 voxel).

    Inside distances are then bounded below by the voxel distance transform of the inside set
    minus one voxel: faces that are now interior (the hollow's walls) would otherwise leave
    near-zero values deep inside the solid, which PCA blends turn into bubbles. Where the
    boundary faces are the true surface the exact distance is already larger, so it stays.

    Args:
        vertices, faces: oriented mesh in unit-cube coordinates.
        inside: (N^3,) bool winding-number inside test; dist: (N^3,) unsigned distance to the
            boundary pieces (clamped at ``bound``).
    Returns:
        inside, dist (new arrays).
    """
    return run_steps(fill_enclosed_cavities_steps(vertices, faces, inside, dist, grid, bound))


def fill_enclosed_cavities_steps(vertices: np.ndarray, faces: np.ndarray, inside: np.ndarray, dist: np.ndarray,
                                 grid: GridSpec, bound: float,
                                 chunk: int | None = None) -> Steps[tuple[np.ndarray, np.ndarray]]:
    """:func:`fill_enclosed_cavities` as a steps generator (distances ``chunk`` points at a time)."""
    from scipy import ndimage

    n = grid.resolution
    dist_all = yield from chunked(lambda p: unsigned_distance(vertices, faces, p, bound), grid.points(), chunk)
    hollow = enclosed_free_space(dist_all, n, 0.75 * grid.voxel) & ~inside
    yield
    if not hollow.any():
        return inside, dist
    grown = ndimage.binary_dilation(hollow.reshape(n, n, n), structure=np.ones((3, 3, 3), dtype=bool))
    inside = inside | grown.ravel()
    depth = ndimage.distance_transform_edt(inside.reshape(n, n, n)).ravel() * grid.voxel
    dist = np.where(inside, np.maximum(dist, np.minimum(depth - grid.voxel, bound)), dist)
    return inside, dist


# ----------------------------------------------------------------------------------- SDF


def sdf_volume(vertices_m: np.ndarray, faces: np.ndarray, grid: GridSpec, method: str = DEFAULT_METHOD,
               min_visibility: float = 0.0) -> np.ndarray:
    """Truncated SDF of a metric vehicle mesh on ``grid``.

    Args:
        vertices_m: (V, 3) metres, library convention (origin at footprint centre on ground).
        faces: (F, 3) triangle indices.
        grid: the common grid.
        method: one of ``METHODS``.
        min_visibility: ``winding``: open patches seen from outside along less than this share
            of their rays leave the sign (:func:`orient_patches_by_visibility`; 0 as the build).
    Returns:
        (N, N, N) float32, unit-cube units, negative inside, clamped to +-truncation.
    Raises:
        ConfigError: unknown method.
        Adv3dError: the mesh leaves the grid cube or encloses no volume.
    """
    return run_steps(sdf_volume_steps(vertices_m, faces, grid, method, min_visibility=min_visibility))


def sdf_volume_steps(vertices_m: np.ndarray, faces: np.ndarray, grid: GridSpec, method: str = DEFAULT_METHOD,
                     chunk: int = STEP_POINTS, min_visibility: float = 0.0) -> Steps[np.ndarray]:
    """:func:`sdf_volume` as a steps generator (``progress.run_steps``): the per-point libigl /
    Embree queries run ``chunk`` grid points at a time with a ``yield`` between pieces (the
    Blender add-on's Build stays responsive); the result is the same array, bit for bit."""
    if method not in METHODS:
        raise ConfigError(f"unknown SDF method {method!r}; choose one of {', '.join(METHODS)}")
    v = grid.to_unit(vertices_m)
    f = clean_faces(v, faces)
    if len(f) == 0:
        raise Adv3dError("mesh has no non-degenerate faces")
    # The border nodes must stay outside (decoding pads with "outside" anyway).
    if np.abs(v[np.unique(f)]).max() >= 0.5:
        raise Adv3dError(
            f"mesh does not fit the SDF grid (cube edge {grid.extent_m:.3f} m, ground at {grid.ground_z:+.3f}); "
            "is it larger than the shape-space assets the grid was sized for?"
        )
    pts = grid.points()
    n = grid.resolution
    bound = grid.truncation * 1.01  # distances past the truncation are clamped anyway
    eps = 1e-4  # probe offset for boundary faces: 0.5 mm at a 5.5 m cube, thinner than any panel

    if method in ("winding", "winding-outward"):
        if method == "winding":
            fo, hidden, _ = (orient_patches_by_visibility(v, f, eps, min_visibility) if min_visibility > 0
                             else orient_patches_by_visibility(v, f, eps))
            fw = fo[~hidden] if (~hidden).any() else fo  # hidden panels stay out of the sign
        else:
            fo, _ = orient_faces(v, f, rule="outward")
            fw = fo
        yield

        def inside_fn(p: np.ndarray) -> np.ndarray:
            return winding_numbers(v, fw, p) > 0.5

        inside = yield from chunked(inside_fn, pts, chunk)
        vb, fb, inner = yield from boundary_faces_steps(v, fo, inside_fn, eps, grid.voxel, chunk,
                                                        return_inside_points=True)
        if not len(fb):
            vb, fb = v, fo
        dist = yield from chunked(lambda p: unsigned_distance(vb, fb, p, bound), pts, chunk)
        inside, dist = yield from fill_enclosed_cavities_steps(v, fo, inside, dist, grid, bound, chunk)
        if method == "winding":
            inside, dist, _ = capture_thin_parts(inside, dist, inner, grid)
    elif method == "rayvote":

        def inside_fn(p: np.ndarray) -> np.ndarray:
            return ray_escape_inside(v, f, p)

        inside = yield from chunked(inside_fn, pts, chunk)
        vb, fb = yield from boundary_faces_steps(v, f, inside_fn, eps, grid.voxel, chunk)
        if not len(fb):
            vb, fb = v, f
        dist = yield from chunked(lambda p: unsigned_distance(vb, fb, p, bound), pts, chunk)
    else:  # floodfill
        dist = yield from chunked(lambda p: unsigned_distance(v, f, p, bound), pts, chunk)
        wall = 0.75 * grid.voxel
        # mesh2sdf style: every wall node counts as inside, which biases the surface outwards.
        inside = enclosed_free_space(dist, n, wall) | (dist < wall)

    if not inside.any():
        raise Adv3dError("mesh encloses no volume on this grid (no grid node is inside it)")
    sdf = np.where(inside, -dist, dist)
    np.clip(sdf, -grid.truncation, grid.truncation, out=sdf)
    return sdf.reshape(n, n, n).astype(np.float32)

