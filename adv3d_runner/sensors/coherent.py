"""Coherent Embree casts that return the reference hits bit for bit.

Why: Embree's ``RTC_RAY_QUERY_FLAG_COHERENT`` traverses a packet of neighbouring rays with one
frustum, and a LiDAR frame's packets (16 neighbouring azimuths of one laser) are as coherent
as rays get: a frame's background cast takes under a third of the time (9.7 -> 2.9 ms on the
generated highway; ``bench/lidar.py --coherent``). Its per-face arithmetic is the
reference query's (over 297 million rays of 51 episodes no ray hit the same face at another
distance), but it decides near-ties differently: where two faces are hit at the same distance
or within an ulp (coplanar overlapping road patches, a ray through a shared edge) it may report
the other face, and then the intensity (the face's reflectivity and normal) or the distance's
last bit changes. So a coherent hit is kept only where it carries a certificate that no other
face can compete, and every other ray is cast again with the reference (incoherent) query:

* a hit at a point p of face B competes with another face only if that face comes within
  ``margin`` of p. Per face, once per mesh (:func:`face_certificates`): B is *crowded* unless
  every other face lies more than ``margin`` from B's inner triangle (B shrunk by ``2 margin``
  from each edge), shown by a separating axis (and a crowded face's cells, see below); a hit is
  certified when neither its face nor, on a crowded face, its cell is crowded,
  its barycentric distance to each edge of B is at least ``2.5 margin`` (so p lies in the inner
  triangle despite the rounding of u and v), the ray meets the face at more than
  ``MIN_SIN_INCIDENCE`` (the rounding of a distance grows as 1/sin of that angle) and the hit is
  more than ``margin`` before the ray's limit (the traversal culls against the limit);
* a coherent miss is cast again: for a ray lying in a face's plane the coherent query can miss
  a hit that the reference query reports (``tests/test_raycast.py``'s "in plane" rays on a car
  mesh), and a hit within rounding of the limit may be culled.

The margin (2 mm) is about twenty times the rounding of a float32 distance on a background a
kilometre across, and below the 5 mm by which the generated highway's lane markings stand on
the road (a lower margin certifies more rays; a margin above 5 mm crowds every marked road face).
A crowded face is then cut into cells (:func:`crowded_cells`) and only the cells near another
face count as crowded. On a generated highway frame about 2 % of the background hits and every
miss (12 % of the rays) are cast again; on a CommonRoad road, whose lanelet patches overlap near
the ego, 15 % of the hits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..jit import kernel

__all__ = ["MARGIN_M", "MIN_SIN_INCIDENCE", "FaceCertificates", "cached_face_certificates", "face_certificates",
           "uncertain_rays"]

#: Distance within which another face counts as a competitor, metres (see the module docstring).
MARGIN_M = 0.002
#: Rays meeting a face at a smaller |sin(angle)| are cast again.
MIN_SIN_INCIDENCE = 0.01
# Separating axes shorter than this (parallel edges) are skipped: they separate nothing.
_MIN_AXIS = 1e-12
#: Above this many face boxes overlapping along x (a background of long strips, say) the
#: certificates would cost more than they save, and such a mesh is cast with the reference
#: query alone (:func:`face_certificates` returns None).
MAX_SWEEP_PAIRS = 20_000_000
# The sweep's pairs are made in chunks of about this many (memory).
_CHUNK_PAIRS = 1_000_000


@dataclass(frozen=True)
class FaceCertificates:
    """What a coherent hit needs to be kept, per face of one mesh.

    Attributes:
        crowded: (F,) bool, another face comes within ``margin`` of the face's inner triangle
            (or the face is too small to have one): its hits are always cast again.
        altitudes: (F, 3) float64 altitude from vertex k onto the opposite edge, metres.
        normals: (F, 3) float64 unit face normals (zero for degenerate faces).
        margin: metres.
        cell_slot: (F,) int32 row of a crowded face in the cell tables (-1: none, every hit on
            the face is cast again).
        cell_frame: (S, 3) float64 per row: the incentre's barycentric (u, v) and 1 / k, the
            inner triangle's scale (its barycentric u' = (u - u_c) / k + u_c).
        cell_crowded: (S, 2 CELLS^2) bool per row: which cells of the inner triangle (a
            CELLS x CELLS midpoint grid, see :func:`cell_index`) another face comes near.
    """

    crowded: np.ndarray
    altitudes: np.ndarray
    normals: np.ndarray
    margin: float
    cell_slot: np.ndarray
    cell_frame: np.ndarray
    cell_crowded: np.ndarray


def face_certificates(vertices: np.ndarray, faces: np.ndarray, margin: float = MARGIN_M) -> FaceCertificates | None:
    """Per-face certificates of a triangle mesh (see the module docstring); None where the mesh
    has too many overlapping face boxes for them (``MAX_SWEEP_PAIRS``).

    Args:
        vertices: (V, 3) float vertex positions, metres (the coordinates Embree sees).
        faces: (F, 3) int vertex indices.
        margin: metres.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    if len(tri) == 0:
        return FaceCertificates(np.zeros(0, bool), np.zeros((0, 3)), np.zeros((0, 3)), float(margin))
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 0)
    edge_len = np.stack([np.linalg.norm(tri[:, (k + 2) % 3] - tri[:, (k + 1) % 3], axis=1) for k in range(3)], axis=1)
    altitudes = np.divide(area2[:, None], edge_len, out=np.zeros_like(edge_len), where=edge_len > 0)

    inner, has_inner = inner_triangles(tri, 2.0 * margin)
    crowded = ~has_inner
    pairs = candidate_pairs(tri.min(axis=1), tri.max(axis=1), margin)
    if pairs is None:
        return None
    i, j = pairs
    near_b, near_a = [], []
    for b, a in ((i, j), (j, i)):
        keep = has_inner[b]
        b, a = b[keep], a[keep]
        near = ~separated(tri[a], inner[b], margin)
        crowded[b[near]] = True
        near_b.append(b[near])
        near_a.append(a[near])
    slot, frame, table = crowded_cells(tri, inner, has_inner, np.concatenate(near_b), np.concatenate(near_a), margin)
    return FaceCertificates(crowded, altitudes, normals, float(margin), slot, frame, table)


#: Bumped when :func:`face_certificates` changes what it computes (the cache key holds it).
CERTIFICATES_VERSION = 1
#: Meshes with fewer faces are certified directly: hashing and reading a cache file cost more.
CACHE_MIN_FACES = 2000
_ARRAYS = ("crowded", "altitudes", "normals", "cell_slot", "cell_frame", "cell_crowded")


def certificates_cache_path(vertices: np.ndarray, faces: np.ndarray, margin: float = MARGIN_M):
    """The cache file of a mesh's certificates: ``<cache>/certificates/<key>.npz``
    (:func:`adv3d_runner.fileio.user_cache_dir`), ``key`` the SHA-256 of the float32 vertices,
    the int32 faces, the margin and :data:`CERTIFICATES_VERSION`."""
    import hashlib

    from ..fileio import user_cache_dir

    h = hashlib.sha256(np.ascontiguousarray(vertices, np.float32).tobytes())
    h.update(np.ascontiguousarray(faces, np.int32).tobytes())
    h.update(f"\0{float(margin)!r}\0v{CERTIFICATES_VERSION}\0{len(faces)}".encode())
    return user_cache_dir() / "certificates" / f"{h.hexdigest()[:40]}.npz"


def _load_certificates(path, n_faces: int, margin: float) -> FaceCertificates | None | bool:
    """A cache file's certificates; ``False`` when it is missing, unreadable or inconsistent
    (``None`` is a stored "too many overlapping faces")."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "none" in z.files:
                return None
            a = {k: z[k] for k in _ARRAYS}
    except Exception:  # noqa: BLE001 - a missing, truncated or foreign file raises many types
        return False
    n_slots = len(a["cell_frame"])
    ok = (a["crowded"].dtype == bool and a["crowded"].shape == (n_faces,)
          and a["altitudes"].dtype == np.float64 and a["altitudes"].shape == (n_faces, 3)
          and a["normals"].dtype == np.float64 and a["normals"].shape == (n_faces, 3)
          and a["cell_slot"].dtype == np.int32 and a["cell_slot"].shape == (n_faces,)
          and a["cell_frame"].dtype == np.float64 and a["cell_frame"].shape == (n_slots, 3)
          and a["cell_crowded"].dtype == bool and a["cell_crowded"].shape == (n_slots, 2 * CELLS * CELLS + 1)
          and (n_faces == 0 or (a["cell_slot"].min() >= -1 and a["cell_slot"].max() < n_slots)))
    if not ok:
        return False
    return FaceCertificates(a["crowded"], a["altitudes"], a["normals"], float(margin), a["cell_slot"],
                            a["cell_frame"], a["cell_crowded"])


def cached_face_certificates(vertices: np.ndarray, faces: np.ndarray,
                             margin: float = MARGIN_M) -> FaceCertificates | None:
    """:func:`face_certificates`, kept in the user's cache by the mesh's content (a scene's
    background is certified once per machine, not in every process: 0.2 CPU-s of a generated
    highway's world build; docs/performance.md). The file is read without pickle, its shapes,
    dtypes and slot indices checked (zip's CRC catches a damaged member); a file that fails is
    ignored and rewritten. Meshes under :data:`CACHE_MIN_FACES` faces are certified directly."""
    from ..fileio import atomic_path, npz_bytes

    if len(faces) < CACHE_MIN_FACES:
        return face_certificates(vertices, faces, margin)
    path = certificates_cache_path(vertices, faces, margin)
    cached = _load_certificates(path, len(faces), margin) if path.exists() else False
    if cached is not False:
        return cached
    cert = face_certificates(vertices, faces, margin)
    members = {"none": np.zeros(0)} if cert is None else {k: getattr(cert, k) for k in _ARRAYS}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_bytes(npz_bytes(members))
    except OSError:
        pass  # a read-only cache: certified again next time
    return cert


#: Cells per side of a crowded face's inner triangle (2 CELLS^2 cells): only the cells that
#: another face comes near are cast again, not the whole face (coplanar road patches overlap at
#: their ends).
CELLS = 4


def crowded_cells(tri: np.ndarray, inner: np.ndarray, has_inner: np.ndarray, near_b: np.ndarray,
                  near_a: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell tables of the crowded faces that have an inner triangle (see :class:`FaceCertificates`).

    A cell is crowded when a near face (``near_a[k]`` of ``near_b[k]``) is not shown more than
    1.5 ``margin`` from it: the extra half margin covers the rounding of the hit's u, v, which
    places the hit in its cell."""
    faces = np.unique(near_b)
    slot = np.full(len(tri), -1, np.int32)
    slot[faces] = np.arange(len(faces), dtype=np.int32)
    n_cells = 2 * CELLS * CELLS
    table = np.ones((len(faces), n_cells + 1), bool)  # + "outside the inner triangle"
    frame = np.zeros((len(faces), 3))
    if not len(faces):
        return slot, frame, table
    side = np.stack([np.linalg.norm(tri[faces, (k + 2) % 3] - tri[faces, (k + 1) % 3], axis=1) for k in range(3)], axis=1)
    bary_c = side / side.sum(axis=1, keepdims=True)  # the incentre's barycentric weights
    e_in = np.linalg.norm(inner[faces, 1] - inner[faces, 0], axis=1)
    e_out = np.linalg.norm(tri[faces, 1] - tri[faces, 0], axis=1)
    frame[:, 0], frame[:, 1] = bary_c[:, 1], bary_c[:, 2]
    frame[:, 2] = e_out / e_in  # 1 / k
    corners, exists = cell_corners()
    cells = np.einsum("ckw,fwd->fckd", corners, inner[faces])  # (S, n_cells, 3, 3)
    table[:, :n_cells][:, exists] = False  # the rest (no cell, outside) stays crowded
    rows = slot[near_b]
    for c in np.flatnonzero(exists):
        sep = separated(tri[near_a], cells[rows, c], 1.5 * margin)
        table[rows[~sep], c] = True
    return slot, frame, table


def cell_corners() -> tuple[np.ndarray, np.ndarray]:
    """(2 CELLS^2, 3, 3) barycentric weights (w, u, v) of each cell's corners, in
    :func:`cell_index` order, and (2 CELLS^2,) bool: the cell exists (the "down" cells past the
    hypotenuse do not)."""
    n = CELLS
    corners = np.zeros((2 * n * n, 3, 3))
    exists = np.zeros(2 * n * n, bool)
    for i in range(n):
        for j in range(n - i):
            up = [(i, j), (i + 1, j), (i, j + 1)]
            down = [(i + 1, j), (i + 1, j + 1), (i, j + 1)]
            for k, pts in ((2 * (i * n + j), up), (2 * (i * n + j) + 1, down)):
                if k % 2 and i + j > n - 2:
                    continue
                for q, (a, b) in enumerate(pts):
                    corners[k, q] = (1 - (a + b) / n, a / n, b / n)
                exists[k] = True
    return corners, exists


def inner_triangles(tri: np.ndarray, inset: float) -> tuple[np.ndarray, np.ndarray]:
    """The points of each triangle at least ``inset`` from every edge: a triangle scaled about the
    incentre by (r - inset) / r (r: the inradius).

    Args:
        tri: (F, 3, 3) float64 triangles.
    Returns:
        (F, 3, 3) inner triangles and (F,) bool: the inner triangle exists (r > inset).
    """
    side = np.stack([np.linalg.norm(tri[:, (k + 2) % 3] - tri[:, (k + 1) % 3], axis=1) for k in range(3)], axis=1)
    perimeter = side.sum(axis=1)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    safe = np.where(perimeter > 0, perimeter, 1.0)
    inradius = np.where(perimeter > 0, area2 / safe, 0.0)
    incentre = np.einsum("fk,fkd->fd", side, tri) / safe[:, None]
    ok = inradius > inset
    scale = np.where(ok, (inradius - inset) / np.where(inradius > 0, inradius, 1.0), 0.0)
    return incentre[:, None, :] + (tri - incentre[:, None, :]) * scale[:, None, None], ok


def candidate_pairs(lo: np.ndarray, hi: np.ndarray, pad: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Pairs (i < j in sweep order) whose boxes, grown by ``pad``, overlap; None when more than
    ``MAX_SWEEP_PAIRS`` boxes overlap along x (the sweep axis).

    Args:
        lo, hi: (F, 3) box corners.
    Returns:
        two (P,) int64 index arrays, or None.
    """
    order = np.argsort(lo[:, 0], kind="stable")
    lo_s, hi_s = lo[order], hi[order]
    end = np.searchsorted(lo_s[:, 0], hi_s[:, 0] + pad, "right")
    count = end - np.arange(len(lo_s)) - 1
    if int(count.sum()) > MAX_SWEEP_PAIRS:
        return None
    done = np.concatenate([[0], np.cumsum(count)])
    out_i, out_j = [], []
    start = 0
    while start < len(lo_s):  # in chunks of about _CHUNK_PAIRS x-overlaps: bounded memory
        stop = max(start + 1, int(np.searchsorted(done, done[start] + _CHUNK_PAIRS, "right")) - 1)
        c = count[start:stop]
        i = np.repeat(np.arange(start, stop), c)
        j = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c) + i + 1
        overlap = np.all((lo_s[j] <= hi_s[i] + pad) & (lo_s[i] <= hi_s[j] + pad), axis=1)
        out_i.append(order[i[overlap]])
        out_j.append(order[j[overlap]])
        start = stop
    return np.concatenate(out_i), np.concatenate(out_j)


def separated(a: np.ndarray, b: np.ndarray, gap: float) -> np.ndarray:
    """Whether one of the separating-axis candidates of two triangles (both normals, the 9 edge
    cross products, and each face's in-plane edge normals) shows them more than ``gap`` apart.
    True is proof that they are (a projection never exceeds the distance); False is not proof
    of the opposite, which only costs a cast.

    Args:
        a, b: (P, 3, 3) float64 triangles.
    Returns:
        (P,) bool.
    """
    out = np.zeros(len(a), bool)
    todo = np.arange(len(a))
    for axis_of in _axes():
        if not len(todo):
            break
        ta, tb = a[todo], b[todo]
        axis = axis_of(ta, tb)
        norm = np.linalg.norm(axis, axis=1)
        usable = norm > _MIN_AXIS
        unit = axis / np.where(usable, norm, 1.0)[:, None]
        pa = np.einsum("pkd,pd->pk", ta, unit)
        pb = np.einsum("pkd,pd->pk", tb, unit)
        apart = np.maximum(pb.min(axis=1) - pa.max(axis=1), pa.min(axis=1) - pb.max(axis=1))
        done = usable & (apart > gap)
        out[todo[done]] = True
        todo = todo[~done]  # the next axes only for the pairs not yet separated
    return out


def _edge(t: np.ndarray, k: int) -> np.ndarray:
    return t[:, (k + 1) % 3] - t[:, k]


def _normal(t: np.ndarray) -> np.ndarray:
    return np.cross(_edge(t, 0), _edge(t, 1))


def _axes():
    """The candidate axes as functions of the two (P, 3, 3) triangle arrays: in-plane edge
    normals first (they separate a road's coplanar neighbours), then the normals and the edge
    cross products."""
    return ([lambda a, b, k=k: np.cross(_normal(b), _edge(b, k)) for k in range(3)]
            + [lambda a, b, k=k: np.cross(_normal(a), _edge(a, k)) for k in range(3)]
            + [lambda a, b: _normal(a), lambda a, b: _normal(b)]
            + [lambda a, b, p=p, q=q: np.cross(_edge(a, p), _edge(b, q)) for p in range(3) for q in range(3)])


@kernel
def uncertain_rays(prim, t, uv, dirs, limit, crowded, altitudes, normals, cell_slot, cell_frame, cell_crowded,
                   margin, min_sin):
    """The rays whose coherent result must be cast again: every miss and every hit without a
    certificate.

    Args:
        prim: (N,) int32 coherent face hit (-1: miss).
        t: (N,) float32 coherent distances (``limit`` where missed).
        uv: (N, 2) float32 barycentric u, v of the hits.
        dirs: (N, 3) float32 ray directions.
        limit: (N,) float32 the rays' real limits.
        crowded, altitudes, normals, cell_slot, cell_frame, cell_crowded: a
            :class:`FaceCertificates`' arrays.
        margin, min_sin: floats (see the module docstring).
    Returns:
        (K,) int64 indices of the uncertain rays.
    """
    n = prim.shape[0]
    out = np.empty(n, np.int64)
    k = 0
    edge_min = 2.5 * margin
    min_sin2 = min_sin * min_sin
    for i in range(n):
        f = prim[i]
        if f < 0:  # cast again: the coherent query can miss a hit of a ray in a face's plane
            out[k] = i
            k += 1
            continue
        u, v = np.float64(uv[i, 0]), np.float64(uv[i, 1])
        if ((1.0 - u - v) * altitudes[f, 0] < edge_min or u * altitudes[f, 1] < edge_min
                or v * altitudes[f, 2] < edge_min
                or (crowded[f] and cell_is_crowded(cell_slot[f], u, v, cell_frame, cell_crowded))):
            out[k] = i
            k += 1
            continue
        # squared forms of |n.d| / |d| < min_sin and (limit - t) |d| <= margin (no square root)
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        length2 = dx * dx + dy * dy + dz * dz
        dot = normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz
        ahead = np.float64(limit[i]) - np.float64(t[i])
        if dot * dot < min_sin2 * length2 or ahead <= 0.0 or ahead * ahead * length2 <= margin * margin:
            out[k] = i
            k += 1
    return out[:k]


@kernel
def cell_is_crowded(slot, u, v, frame, table):
    """Whether the hit at barycentric (u, v) of a crowded face (row ``slot``; -1: no table)
    lies in a crowded cell of the face's inner triangle, or outside it."""
    if slot < 0:
        return True
    uc, vc, inv_k = frame[slot, 0], frame[slot, 1], frame[slot, 2]
    return table[slot, cell_index((u - uc) * inv_k + uc, (v - vc) * inv_k + vc)]


@kernel
def cell_index(u, v):
    """The cell of barycentric (u, v) in a CELLS x CELLS midpoint grid of a triangle: the up
    cell (i, j) is 2 (i CELLS + j), the down cell next to it 2 (i CELLS + j) + 1 (see
    :func:`cell_corners`); a point outside the triangle gets 2 CELLS^2, the last column of the
    tables (always crowded)."""
    n = CELLS
    x, y = u * n, v * n
    if x < 0.0 or y < 0.0 or x + y >= n:
        return 2 * n * n
    i, j = int(x), int(y)
    down = (x - i) + (y - j) >= 1.0
    return 2 * (i * n + j) + (1 if down else 0)
