"""Rotated bird's-eye-view (BEV) boxes: corners, areas, exact overlap, IoU and distance.

A box is ``(x, y, length, width, yaw)``: footprint centre (m), extent along the box's own +x
(length) and +y (width) in m, yaw in rad CCW from the map's +x. Arrays of boxes are
``(..., 5)`` float64.

Degenerate input never produces NaN:

* a box with non-positive length or width has zero area; its IoU with anything is 0;
* non-finite boxes (NaN/inf in any field) have IoU 0 with everything and infinite distance;
* identical boxes have IoU exactly 1 (up to rounding), touching boxes IoU 0, nested boxes
  ``area(small) / area(big)``.

The intersection of two convex polygons is itself convex; its vertices are (a) the corners of
each box inside the other and (b) the crossings of their edges. We gather these candidates for
many pairs at once, order them by angle around their mean and apply the shoelace formula. Pairs
too far apart to touch (centre distance > sum of half diagonals) are skipped, so pairwise IoU
over a frame of detections costs little more than the candidate pairs that actually overlap.
The per-pair loops (corners, candidates, ordering, shoelace) are compiled
(:mod:`adv3d_runner.jit`) and give the bits the numpy passes they replaced gave; the angles
stay ``np.arctan2``.
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import kernel

# Candidate vertices per pair: 4 + 4 corners and 4 x 4 edge crossings.
_N_CAND = 24
# Relative tolerance for the inside / on-segment tests, scaled by the boxes' size.
_REL_TOL = 1e-9


def as_boxes(boxes: np.ndarray) -> np.ndarray:
    """Validate and convert to a float64 ``(..., 5)`` array (raises ValueError on a bad shape)."""
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != 5:
        if arr.size == 0:
            return arr.reshape(0, 5)
        raise ValueError(f"boxes must have shape (..., 5) (x, y, length, width, yaw), got {arr.shape}")
    return arr


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners of rotated boxes, counter-clockwise from front-right.

    Args:
        boxes: (..., 5) x, y, length, width, yaw (m, rad).
    Returns:
        (..., 4, 2) m: front-right, front-left, rear-left, rear-right. Negative lengths and
        widths are clipped to 0 (a degenerate box collapses to a segment or a point).
    """
    b = as_boxes(boxes)
    flat = b.reshape(-1, 5)
    # cos / sin in numpy (its SIMD versions), the rest compiled: a dozen numpy calls' overhead
    # per call was most of the cost of an IoU over a few boxes.
    return _corners(flat, np.cos(flat[:, 4]), np.sin(flat[:, 4])).reshape(b.shape[:-1] + (4, 2))


@kernel
def _corners(b: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """:func:`box_corners` of boxes ``b`` (n, 5) with c = cos(yaw), s = sin(yaw) (n,) -> (n, 4, 2) m.

    Corner k has local coordinates (lx, ly) = (hl, -hw), (hl, hw), (-hl, hw), (-hl, -hw) and is
    x + c lx - s ly, y + s lx + c ly (half length and width clipped at 0 as ``np.maximum`` does,
    NaN kept)."""
    n = b.shape[0]
    out = np.empty((n, 4, 2))
    for i in range(n):
        hl = 0.5 * _clip0(b[i, 2])
        hw = 0.5 * _clip0(b[i, 3])
        for k in range(4):
            lx = hl if k < 2 else -hl
            ly = -hw if k == 0 or k == 3 else hw
            out[i, k, 0] = b[i, 0] + c[i] * lx - s[i] * ly
            out[i, k, 1] = b[i, 1] + s[i] * lx + c[i] * ly
    return out


@kernel
def _clip0(v: float) -> float:
    """``np.maximum(v, 0.0)`` of one float (NaN stays NaN, -0.0 becomes 0.0)."""
    return v if v > 0.0 or v != v else 0.0


def box_areas(boxes: np.ndarray) -> np.ndarray:
    """Areas (m^2) of boxes (..., 5) -> (...); non-positive dimensions give 0."""
    b = as_boxes(boxes)
    return np.maximum(b[..., 2], 0.0) * np.maximum(b[..., 3], 0.0)


def polygon_area(poly: np.ndarray) -> np.ndarray:
    """Signed shoelace area of polygons (..., V, 2) -> (...) (CCW positive)."""
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1)


def _intersection_area_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact intersection area of paired boxes a[i], b[i] ((n, 5) each, positive area) -> (n,) m^2.

    The corners come from :func:`box_corners` and the candidates' angles from ``np.arctan2``
    (numpy's SIMD transcendentals, which a compiled ``atan2`` need not match bit for bit); the
    loops around them are compiled (:func:`_clip_candidates`, :func:`_ordered_area`).
    """
    n = len(a)
    if n == 0:
        return np.zeros(0)
    rel, valid, count = _clip_candidates(box_corners(a), box_corners(b), np.ascontiguousarray(a[:, :2]))
    ang = np.arctan2(rel[..., 1], rel[..., 0])
    return _ordered_area(rel, valid, count, ang)


# Compiled (adv3d_runner.jit): per pair 8 inside tests and 16 edge crossings over 4-vertex
# arrays, which numpy can only do as ~40 passes over (n, 24)-sized temporaries; the loops below
# are the same IEEE operations in the same order as those passes were, so the same bits.

@kernel
def _clip_candidates(ca: np.ndarray, cb: np.ndarray, origin: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate vertices of the intersection of each pair of convex CCW quads.

    Args:
        ca, cb: (n, 4, 2) corners of boxes a[i] and b[i] (m, map frame).
        origin: (n, 2) a[i]'s centre (m); everything is computed relative to it (precision
            with large map coordinates).
    Returns:
        rel (n, 24, 2) m: the candidates (a's 4 corners, b's 4 corners, the 16 crossings of
        a's edge k with b's edge l at 8 + 4 k + l) relative to the mean of the valid ones
        (0 where not valid); valid (n, 24) bool: a corner inside (or on) the other box, an edge
        crossing within both segments; count (n,) int64 valid candidates.
    """
    n = ca.shape[0]
    rel = np.zeros((n, _N_CAND, 2))
    valid = np.zeros((n, _N_CAND), np.bool_)
    count = np.zeros(n, np.int64)
    pts = np.empty((_N_CAND, 2))
    pa = np.empty((4, 2))
    pb = np.empty((4, 2))
    r = np.empty((4, 2))
    s = np.empty((4, 2))
    eps = 1e-9
    for i in range(n):
        scale = 0.0  # max |coordinate| (NaN propagates, as in np.max)
        for k in range(4):
            for d in range(2):
                pa[k, d] = ca[i, k, d] - origin[i, d]
                pb[k, d] = cb[i, k, d] - origin[i, d]
                for v in (abs(pa[k, d]), abs(pb[k, d])):
                    if v > scale or v != v:
                        scale = v
        if scale < 1e-12:
            scale = 1e-12
        tol = _REL_TOL * scale * scale  # cross products are m^2
        for k in range(4):
            k1 = (k + 1) % 4
            for d in range(2):
                r[k, d] = pa[k1, d] - pa[k, d]
                s[k, d] = pb[k1, d] - pb[k, d]
        for k in range(4):
            pts[k, 0], pts[k, 1] = pa[k, 0], pa[k, 1]
            pts[4 + k, 0], pts[4 + k, 1] = pb[k, 0], pb[k, 1]
            valid[i, k] = _inside(pa[k, 0], pa[k, 1], pb, s, tol)  # corners of a inside b
            valid[i, 4 + k] = _inside(pb[k, 0], pb[k, 1], pa, r, tol)
        for k in range(4):  # edge crossings: pa[k] + t r[k] = pb[l] + u s[l]
            for m in range(4):
                c = 8 + 4 * k + m
                denom = r[k, 0] * s[m, 1] - r[k, 1] * s[m, 0]
                qx = pb[m, 0] - pa[k, 0]
                qy = pb[m, 1] - pa[k, 1]
                parallel = abs(denom) <= tol
                safe = 1.0 if parallel else denom
                t = (qx * s[m, 1] - qy * s[m, 0]) / safe
                u = (qx * r[k, 1] - qy * r[k, 0]) / safe
                valid[i, c] = (not parallel) and t >= -eps and t <= 1 + eps and u >= -eps and u <= 1 + eps
                pts[c, 0] = pa[k, 0] + t * r[k, 0]
                pts[c, 1] = pa[k, 1] + t * r[k, 1]
        cnt = 0
        cx = 0.0  # numpy's sum over this axis: from 0.0, term by term
        cy = 0.0
        for c in range(_N_CAND):
            if valid[i, c]:
                cx += pts[c, 0]
                cy += pts[c, 1]
                cnt += 1
            else:
                cx += 0.0
                cy += 0.0
        count[i] = cnt
        cx /= max(cnt, 1)
        cy /= max(cnt, 1)
        for c in range(_N_CAND):
            if valid[i, c]:
                rel[i, c, 0] = pts[c, 0] - cx
                rel[i, c, 1] = pts[c, 1] - cy
    return rel, valid, count


@kernel
def _inside(px: float, py: float, poly: np.ndarray, edge: np.ndarray, tol: float) -> bool:
    """Point (px, py) inside (or on, within ``tol`` m^2) the convex CCW quad ``poly`` (4, 2)
    whose edges are ``edge`` (4, 2) (edge k from vertex k to k + 1)."""
    for k in range(4):
        if not edge[k, 0] * (py - poly[k, 1]) - edge[k, 1] * (px - poly[k, 0]) >= -tol:
            return False
    return True


@kernel
def _ordered_area(rel: np.ndarray, valid: np.ndarray, count: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """Shoelace area (m^2) of each pair's valid candidates ordered by angle around their mean.

    Args:
        rel, valid, count: from :func:`_clip_candidates`. ang: (n, 24) rad, arctan2 of ``rel``.
    Returns:
        (n,) m^2, 0 with fewer than 3 valid candidates.

    The valid candidates sort by angle (a stable sort, invalid ones last); the places after
    them repeat the last valid vertex (zero-length edges) so that the 24 shoelace terms are
    summed in numpy's pairwise order for 24 numbers.
    """
    n = rel.shape[0]
    area = np.zeros(n)
    key = np.empty(_N_CAND)
    order = np.empty(_N_CAND, np.int64)
    x = np.empty(_N_CAND)
    y = np.empty(_N_CAND)
    terms = np.empty(_N_CAND)
    for i in range(n):
        if count[i] < 3:
            continue
        for c in range(_N_CAND):  # stable insertion sort, NaN after everything (as np.argsort)
            key[c] = ang[i, c] if valid[i, c] else 10.0
            j = c
            while j > 0 and (key[c] < key[order[j - 1]]
                             or (key[order[j - 1]] != key[order[j - 1]] and key[c] == key[c])):
                order[j] = order[j - 1]
                j -= 1
            order[j] = c
        for c in range(_N_CAND):
            o = order[min(c, count[i] - 1)]
            x[c] = rel[i, o, 0]
            y[c] = rel[i, o, 1]
        for c in range(_N_CAND):
            c1 = (c + 1) % _N_CAND
            terms[c] = x[c] * y[c1] - x[c1] * y[c]
        area[i] = abs(0.5 * _pairwise_sum24(terms))
    return area


@kernel
def _pairwise_sum24(v: np.ndarray) -> float:
    """Sum of 24 float64 in numpy's order (``np.sum`` over a contiguous axis of 24: 0.0 plus
    eight running sums over three blocks of 8 added as a balanced tree)."""
    r0, r1, r2, r3 = v[0], v[1], v[2], v[3]
    r4, r5, r6, r7 = v[4], v[5], v[6], v[7]
    for i in range(8, 24, 8):
        r0 += v[i]
        r1 += v[i + 1]
        r2 += v[i + 2]
        r3 += v[i + 3]
        r4 += v[i + 4]
        r5 += v[i + 5]
        r6 += v[i + 6]
        r7 += v[i + 7]
    return 0.0 + (((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)))  # from numpy's 0.0


@kernel
def _finite_areas(b: np.ndarray) -> np.ndarray:
    """:func:`box_areas` (m^2) of boxes ``b`` (n, 5) with 0 for non-finite boxes -> (n,).

    Compiled: the same arithmetic, without the ~10 numpy calls (isfinite, nan_to_num, ...) it
    took per call."""
    n = b.shape[0]
    out = np.zeros(n)
    for i in range(n):
        finite = True
        for k in range(5):
            finite = finite and math.isfinite(b[i, k])
        if finite:
            out[i] = _clip0(b[i, 2]) * _clip0(b[i, 3])
    return out


def _pair_candidates(a: np.ndarray, b: np.ndarray, area_a: np.ndarray, area_b: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) whose boxes can overlap: both finite with positive area (``area_a``,
    ``area_b``: :func:`_finite_areas`), and centres closer than the sum of their half diagonals."""
    ra = 0.5 * np.hypot(a[:, 2], a[:, 3])
    rb = 0.5 * np.hypot(b[:, 2], b[:, 3])
    with np.errstate(invalid="ignore"):
        dist = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
        near = dist <= (ra[:, None] + rb[None, :]) * (1 + 1e-9)
    near &= (area_a > 0)[:, None] & (area_b > 0)[None, :]
    return np.nonzero(near)


def _intersections(a: np.ndarray, b: np.ndarray, area_a: np.ndarray, area_b: np.ndarray,
                   chunk: int = 20000) -> np.ndarray:
    """:func:`intersection_area_pairwise` of (N, 5) and (M, 5) boxes with their
    :func:`_finite_areas` -> (N, M) m^2."""
    out = np.zeros((len(a), len(b)))
    if len(a) == 0 or len(b) == 0:
        return out
    ii, jj = _pair_candidates(a, b, area_a, area_b)
    for lo in range(0, len(ii), chunk):
        i, j = ii[lo:lo + chunk], jj[lo:lo + chunk]
        out[i, j] = _intersection_area_pairs(a[i], b[j])
    # Exactness guard: the intersection can never exceed either area (rounding only).
    return np.minimum(out, np.minimum(area_a[:, None], area_b[None, :]))


def intersection_area_pairwise(a: np.ndarray, b: np.ndarray, chunk: int = 20000) -> np.ndarray:
    """Intersection areas (m^2) of every box in ``a`` (N, 5) with every box in ``b`` (M, 5) -> (N, M)."""
    a = as_boxes(a).reshape(-1, 5)
    b = as_boxes(b).reshape(-1, 5)
    return _intersections(a, b, _finite_areas(a), _finite_areas(b), chunk)


def iou_pairwise(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """BEV IoU of every box in ``a`` (N, 5) with every box in ``b`` (M, 5) -> (N, M) in [0, 1].

    Zero-area or non-finite boxes give 0 (never NaN)."""
    a = as_boxes(a).reshape(-1, 5)
    b = as_boxes(b).reshape(-1, 5)
    area_a, area_b = _finite_areas(a), _finite_areas(b)
    inter = _intersections(a, b, area_a, area_b)
    union = area_a[:, None] + area_b[None, :] - inter
    iou = np.where(union > 1e-12, inter / np.where(union > 1e-12, union, 1.0), 0.0)
    return np.clip(iou, 0.0, 1.0)


def iou_paired(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of ``a[i]`` with ``b[i]``: (N, 5), (N, 5) -> (N,)."""
    a = as_boxes(a).reshape(-1, 5)
    b = as_boxes(b).reshape(-1, 5)
    if a.shape != b.shape:
        raise ValueError(f"paired boxes need equal shapes, got {a.shape} and {b.shape}")
    out = np.zeros(len(a))
    if len(a) == 0:
        return out
    area_a, area_b = _finite_areas(a), _finite_areas(b)
    idx = np.flatnonzero((area_a > 0) & (area_b > 0))
    area_a, area_b = area_a[idx], area_b[idx]
    inter = np.minimum(_intersection_area_pairs(a[idx], b[idx]), np.minimum(area_a, area_b))
    union = area_a + area_b - inter
    out[idx] = np.clip(inter / np.maximum(union, 1e-12), 0.0, 1.0)
    return out


def box_separation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed separating-axis gap (m) between rotated boxes, broadcasting (..., 5).

    The largest gap between the boxes' projections over the four candidate axes: > 0 when they
    are apart (a lower bound of :func:`box_distance`, equal to it when the closest features are
    parallel edges, e.g. two cars side by side or nose to tail), 0 when they touch, < 0 (minus
    the smallest overlap) when they overlap. About 4x cheaper than the exact distance.
    Non-finite boxes give +inf.
    """
    with np.errstate(invalid="ignore"):
        gap = -_axis_overlaps(as_boxes(a), as_boxes(b)).min(axis=-1)
    return np.where(np.isfinite(gap), gap, np.inf)


def _axis_overlaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Projection overlap (m) of two boxes on each of the 4 candidate separating axes (the local
    x and y axes of each box; unit vectors even for degenerate boxes): (..., 4).

    Closed form for rectangles: on box a's x axis the overlap is
    ``hl_a + (hl_b |cos dyaw| + hw_b |sin dyaw|) - |centre offset . x_a|``, and so on.
    """
    hla, hwa = 0.5 * np.maximum(a[..., 2], 0.0), 0.5 * np.maximum(a[..., 3], 0.0)
    hlb, hwb = 0.5 * np.maximum(b[..., 2], 0.0), 0.5 * np.maximum(b[..., 3], 0.0)
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    ca, sa = np.cos(a[..., 4]), np.sin(a[..., 4])
    cb, sb = np.cos(b[..., 4]), np.sin(b[..., 4])
    c = np.abs(ca * cb + sa * sb)  # |cos(yaw_b - yaw_a)|
    s = np.abs(ca * sb - sa * cb)  # |sin(yaw_b - yaw_a)|
    o1 = hla + hlb * c + hwb * s - np.abs(dx * ca + dy * sa)
    o2 = hwa + hlb * s + hwb * c - np.abs(-dx * sa + dy * ca)
    o3 = hlb + hla * c + hwa * s - np.abs(dx * cb + dy * sb)
    o4 = hwb + hla * s + hwa * c - np.abs(-dx * sb + dy * cb)
    return np.stack(np.broadcast_arrays(o1, o2, o3, o4), axis=-1)


def boxes_overlap(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Whether the interiors of rotated boxes overlap (separating-axis test), broadcasting.

    Args:
        a, b: (..., 5) boxes; broadcast against each other.
        tol: m; projections must overlap by more than this on every axis, so boxes that only
            touch (shared edge or corner) do not overlap. Zero-area boxes never overlap.
    Returns:
        (...) bool.
    """
    overlap = _axis_overlaps(as_boxes(a), as_boxes(b))
    with np.errstate(invalid="ignore"):
        return np.all(overlap > tol, axis=-1) & np.isfinite(overlap).all(axis=-1)


def _point_segment_distance(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    d = s1 - s0
    L2 = np.sum(d * d, axis=-1)
    t = np.clip(np.sum((p - s0) * d, axis=-1) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    t = np.where(L2 > 0, t, 0.0)
    foot = s0 + t[..., None] * d
    return np.linalg.norm(p - foot, axis=-1)


def box_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance (m) between the footprints of rotated boxes, broadcasting (..., 5).

    0 when the boxes overlap or touch; +inf when either box is non-finite. Exact for convex
    polygons: the closest points of two disjoint rectangles lie on a corner of one and an edge
    of the other.
    """
    a = as_boxes(a)
    b = as_boxes(b)
    ca, cb = box_corners(a), box_corners(b)
    ca, cb = np.broadcast_arrays(ca, cb)
    origin = ca[..., :1, :]  # precision with large map coordinates
    ca = ca - origin
    cb = cb - origin
    ea0, ea1 = ca, np.roll(ca, -1, axis=-2)
    eb0, eb1 = cb, np.roll(cb, -1, axis=-2)
    # corners of a (v) against edges of b (e), and the other way round: (..., 4, 4)
    d_ab = _point_segment_distance(ca[..., :, None, :], eb0[..., None, :, :], eb1[..., None, :, :])
    d_ba = _point_segment_distance(cb[..., :, None, :], ea0[..., None, :, :], ea1[..., None, :, :])
    dist = np.minimum(d_ab.min(axis=(-1, -2)), d_ba.min(axis=(-1, -2)))
    with np.errstate(invalid="ignore"):
        dist = np.where(boxes_overlap(a, b, tol=0.0), 0.0, dist)
        finite = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    return np.where(finite, dist, np.inf)
