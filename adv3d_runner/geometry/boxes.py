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
"""
from __future__ import annotations

import numpy as np

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
    hl = 0.5 * np.maximum(b[..., 2], 0.0)
    hw = 0.5 * np.maximum(b[..., 3], 0.0)
    c, s = np.cos(b[..., 4]), np.sin(b[..., 4])
    lx = np.stack([hl, hl, -hl, -hl], axis=-1)  # (..., 4) local x of each corner
    ly = np.stack([-hw, hw, hw, -hw], axis=-1)
    x = b[..., 0, None] + c[..., None] * lx - s[..., None] * ly
    y = b[..., 1, None] + s[..., None] * lx + c[..., None] * ly
    return np.stack([x, y], axis=-1)


def box_areas(boxes: np.ndarray) -> np.ndarray:
    """Areas (m^2) of boxes (..., 5) -> (...); non-positive dimensions give 0."""
    b = as_boxes(boxes)
    return np.maximum(b[..., 2], 0.0) * np.maximum(b[..., 3], 0.0)


def polygon_area(poly: np.ndarray) -> np.ndarray:
    """Signed shoelace area of polygons (..., V, 2) -> (...) (CCW positive)."""
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside(points: np.ndarray, poly: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """points (n, P, 2) inside (or on) convex CCW quads poly (n, 4, 2) -> (n, P) bool."""
    edge = np.roll(poly, -1, axis=1) - poly  # (n, 4, 2)
    rel = points[:, :, None, :] - poly[:, None, :, :]  # (n, P, 4, 2)
    cr = _cross(edge[:, None, :, :], rel)  # (n, P, 4)
    return np.all(cr >= -tol[:, None, None], axis=-1)


def _intersection_area_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact intersection area of paired boxes a[i], b[i] ((n, 5) each, positive area) -> (n,)."""
    n = len(a)
    if n == 0:
        return np.zeros(0)
    # Work relative to a's centre: keeps precision for large map coordinates.
    origin = a[:, None, :2]
    pa = box_corners(a) - origin
    pb = box_corners(b) - origin
    scale = np.maximum(np.max(np.abs(np.concatenate([pa, pb], axis=1)), axis=(1, 2)), 1e-12)
    tol = _REL_TOL * scale * scale  # cross products are m^2

    in_a = _inside(pa, pb, tol)  # corners of a inside b
    in_b = _inside(pb, pa, tol)

    # Edge crossings: a_i + t r_i = b_j + u s_j.
    r = np.roll(pa, -1, axis=1) - pa  # (n, 4, 2)
    s = np.roll(pb, -1, axis=1) - pb
    denom = _cross(r[:, :, None, :], s[:, None, :, :])  # (n, 4, 4)
    qp = pb[:, None, :, :] - pa[:, :, None, :]  # (n, 4, 4, 2)
    parallel = np.abs(denom) <= tol[:, None, None]
    safe = np.where(parallel, 1.0, denom)
    t = _cross(qp, s[:, None, :, :]) / safe
    u = _cross(qp, r[:, :, None, :]) / safe
    eps = 1e-9
    cross_ok = (~parallel) & (t >= -eps) & (t <= 1 + eps) & (u >= -eps) & (u <= 1 + eps)
    cross_pts = pa[:, :, None, :] + t[..., None] * r[:, :, None, :]  # (n, 4, 4, 2)

    pts = np.concatenate([pa, pb, cross_pts.reshape(n, 16, 2)], axis=1)  # (n, 24, 2)
    valid = np.concatenate([in_a, in_b, cross_ok.reshape(n, 16)], axis=1)
    count = valid.sum(axis=1)

    # Order the valid candidates by angle around their mean (an interior point of the convex
    # intersection); invalid ones sort last and are replaced by the last valid vertex, which
    # adds zero-length edges and so leaves the shoelace sum unchanged.
    cnt = np.maximum(count, 1)
    centre = np.sum(np.where(valid[..., None], pts, 0.0), axis=1) / cnt[:, None]
    rel = pts - centre[:, None, :]
    ang = np.where(valid, np.arctan2(rel[..., 1], rel[..., 0]), 10.0)
    order = np.argsort(ang, axis=1, kind="stable")
    rel = np.take_along_axis(rel, order[..., None], axis=1)
    last = rel[np.arange(n), cnt - 1]  # (n, 2)
    pad = np.arange(_N_CAND)[None, :] >= count[:, None]
    rel = np.where(pad[..., None], last[:, None, :], rel)
    area = np.abs(polygon_area(rel))
    area[count < 3] = 0.0
    return area


def _pair_candidates(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) whose boxes can overlap: both finite with positive area, and centres
    closer than the sum of their half diagonals."""
    fa = np.all(np.isfinite(a), axis=1) & (box_areas(np.nan_to_num(a)) > 0)
    fb = np.all(np.isfinite(b), axis=1) & (box_areas(np.nan_to_num(b)) > 0)
    ra = 0.5 * np.hypot(a[:, 2], a[:, 3])
    rb = 0.5 * np.hypot(b[:, 2], b[:, 3])
    with np.errstate(invalid="ignore"):
        dist = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
        near = dist <= (ra[:, None] + rb[None, :]) * (1 + 1e-9)
    near &= fa[:, None] & fb[None, :]
    return np.nonzero(near)


def intersection_area_pairwise(a: np.ndarray, b: np.ndarray, chunk: int = 20000) -> np.ndarray:
    """Intersection areas (m^2) of every box in ``a`` (N, 5) with every box in ``b`` (M, 5) -> (N, M)."""
    a = as_boxes(a).reshape(-1, 5)
    b = as_boxes(b).reshape(-1, 5)
    out = np.zeros((len(a), len(b)))
    if len(a) == 0 or len(b) == 0:
        return out
    ii, jj = _pair_candidates(a, b)
    for lo in range(0, len(ii), chunk):
        i, j = ii[lo:lo + chunk], jj[lo:lo + chunk]
        out[i, j] = _intersection_area_pairs(a[i], b[j])
    # Exactness guard: the intersection can never exceed either area (rounding only).
    return np.minimum(out, np.minimum(box_areas(np.nan_to_num(a))[:, None], box_areas(np.nan_to_num(b))[None, :]))


def iou_pairwise(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """BEV IoU of every box in ``a`` (N, 5) with every box in ``b`` (M, 5) -> (N, M) in [0, 1].

    Zero-area or non-finite boxes give 0 (never NaN)."""
    a = as_boxes(a).reshape(-1, 5)
    b = as_boxes(b).reshape(-1, 5)
    inter = intersection_area_pairwise(a, b)
    area_a = np.where(np.all(np.isfinite(a), axis=1), box_areas(np.nan_to_num(a)), 0.0)
    area_b = np.where(np.all(np.isfinite(b), axis=1), box_areas(np.nan_to_num(b)), 0.0)
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
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    ok &= (box_areas(np.nan_to_num(a)) > 0) & (box_areas(np.nan_to_num(b)) > 0)
    idx = np.nonzero(ok)[0]
    inter = np.minimum(_intersection_area_pairs(a[idx], b[idx]),
                       np.minimum(box_areas(a[idx]), box_areas(b[idx])))
    union = box_areas(a[idx]) + box_areas(b[idx]) - inter
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
