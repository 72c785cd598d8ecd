"""Lane (polyline) geometry: arc length, resampling, projection, curvature, offsets.

Every function takes centre lines as (P, 2) float64 arrays in metres and is robust to
degenerate input: repeated points and zero-length segments are dropped first
(``clean_polyline``), and a polyline that collapses to a single point behaves like a point
(arc length 0, heading 0 along +x). Nothing here returns NaN for finite input.

Conventions: ``s`` is the arc length from the first point (m); ``d`` is the signed lateral
offset, positive to the LEFT of the driving direction (m); headings are radians CCW from +x.
Queries before the start or after the end are extrapolated along the first / last segment, so
``s`` can be negative or longer than the lane.
"""
from __future__ import annotations

import numpy as np

EPS = 1e-9  # segments shorter than this (m) are treated as zero length


def clean_polyline(points: np.ndarray, eps: float = EPS) -> np.ndarray:
    """Drop consecutive points closer than ``eps`` (repeated points, zero-length segments).

    Args:
        points: (P, 2) m, P >= 1.
    Returns:
        (P', 2) float64, 1 <= P' <= P, consecutive points more than ``eps`` apart.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError("polyline has no points")
    if not np.all(np.isfinite(pts)):
        raise ValueError("polyline has non-finite coordinates")
    return pts[_kept_indices(pts, eps)]


def _kept_indices(points: np.ndarray, eps: float = EPS) -> np.ndarray:
    """Indices ``clean_polyline`` keeps: each kept point is more than ``eps`` from the
    previous kept one (a run of near-duplicates collapses to its first point)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return np.arange(len(pts))
    step = np.hypot(*np.diff(pts, axis=0).T)
    keep = np.flatnonzero(np.concatenate([[True], step > eps]))
    kept = pts[keep]
    if len(kept) < 2 or np.all(np.hypot(*np.diff(kept, axis=0).T) > eps):
        return keep  # the usual case, vectorised
    out = [0]  # rare: creeping sub-eps steps; compare against the last kept point
    for i in range(1, len(pts)):
        if np.hypot(*(pts[i] - pts[out[-1]])) > eps:
            out.append(i)
    return np.asarray(out)


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each point: (P, 2) -> (P,) m, starting at 0 (repeats add 0)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    seg = np.hypot(*np.diff(pts, axis=0).T) if len(pts) > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(seg)])


def length(points: np.ndarray) -> float:
    """Total length (m)."""
    return float(arc_length(points)[-1])


def _segments(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clean polyline, cumulative s, unit directions (S, 2) and lengths (S,) of its segments.
    A single point gets one zero-length segment along +x."""
    pts = clean_polyline(points)
    if len(pts) == 1:
        return np.vstack([pts, pts]), np.zeros(2), np.array([[1.0, 0.0]]), np.zeros(1)
    delta = np.diff(pts, axis=0)
    seg_len = np.hypot(delta[:, 0], delta[:, 1])
    return pts, arc_length(pts), delta / seg_len[:, None], seg_len


def polyline_segments(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cleaned polyline (P', 2), cumulative s (P',), unit directions (S, 2) and lengths (S,)
    of its segments: what :func:`project` and :func:`point_at` compute first, for callers that
    query one polyline many times (:func:`project_on_segments`, :func:`point_on_segments`)."""
    return _segments(points)


def segment_headings(points: np.ndarray) -> np.ndarray:
    """Heading of each segment of the cleaned polyline: (S,) rad."""
    _, _, unit, _ = _segments(points)
    return np.arctan2(unit[:, 1], unit[:, 0])


def point_at(points: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Point at arc length ``s`` (any shape (...)) -> (..., 2) m; extrapolates beyond the ends."""
    return point_on_segments(_segments(points), s)


def point_on_segments(segments: tuple, s: np.ndarray | float) -> np.ndarray:
    """:func:`point_at` on a polyline's ``_segments`` computed before (the same numbers)."""
    pts, cum, unit, _ = segments
    s = np.asarray(s, dtype=np.float64)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(unit) - 1)
    return pts[idx] + (s - cum[idx])[..., None] * unit[idx]


def heading_at(points: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Heading (rad) of the segment under arc length ``s`` (...) -> (...)."""
    _, cum, unit, _ = _segments(points)
    s = np.asarray(s, dtype=np.float64)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(unit) - 1)
    return np.arctan2(unit[idx, 1], unit[idx, 0])


def pose_at(points: np.ndarray, s: np.ndarray | float, d: np.ndarray | float = 0.0) -> np.ndarray:
    """Pose (x, y, heading) at arc length ``s`` and lateral offset ``d`` (left +): (..., 3)."""
    s = np.asarray(s, dtype=np.float64)
    xy = point_at(points, s)
    h = heading_at(points, s)
    d = np.broadcast_to(np.asarray(d, dtype=np.float64), h.shape)
    normal = np.stack([-np.sin(h), np.cos(h)], axis=-1)
    return np.concatenate([xy + d[..., None] * normal, h[..., None]], axis=-1)


def project(points: np.ndarray, xy: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project query points onto the polyline.

    Args:
        points: (P, 2) centre line.
        xy: (N, 2) or (2,) query points, m.
    Returns:
        s (N,) arc length of the closest point (extrapolated along the end segments for points
        before the start / past the end), d (N,) signed lateral offset (left +), heading (N,)
        of the closest segment. Scalars for a (2,) query.
    """
    return project_on_segments(_segments(points), xy, chunk)


_NEAREST_SEGMENT: list = []  # [corridor.nearest_segment or None], found on first use


def _compiled():
    """``corridor.nearest_segment`` (compiled), or None where numba is missing. Imported late:
    this module is below ``corridor`` and must import without numba."""
    if not _NEAREST_SEGMENT:
        try:
            from .corridor import nearest_segment
        except ImportError:
            nearest_segment = None
        _NEAREST_SEGMENT.append(nearest_segment)
    return _NEAREST_SEGMENT[0]


def project_on_segments(segments: tuple, xy: np.ndarray, chunk: int = 4096
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`project` on a polyline's ``_segments`` computed before (the same numbers).

    The nearest segment of each point in one compiled pass (``corridor.nearest_segment``), the
    headings by numpy's arctan2 as before: the corridor builder projects one point per lane
    chain every plan, and the numpy version (:func:`project_on_segments_numpy`) spent ~20
    array calls on it. Without numba (the Blender add-on ships none) the numpy version."""
    pts, cum, unit, seg_len = segments
    q = np.asarray(xy, dtype=np.float64)
    single = q.ndim == 1
    q = q.reshape(-1, 2)
    nearest_segment = _compiled()
    if nearest_segment is None or not np.isfinite(q).all():  # numpy's NaN rules (argmin: the first NaN)
        return project_on_segments_numpy(segments, xy, chunk)
    out_s, out_d, best = nearest_segment(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]),
                                          np.ascontiguousarray(pts, dtype=np.float64),
                                          np.ascontiguousarray(cum, dtype=np.float64),
                                          np.ascontiguousarray(unit, dtype=np.float64),
                                          np.ascontiguousarray(seg_len, dtype=np.float64))
    out_h = np.empty(len(q))
    for lo in range(0, len(q), chunk):  # arctan2 over the same chunks as the numpy version
        u = unit[best[lo:lo + chunk]]
        out_h[lo:lo + chunk] = np.arctan2(u[:, 1], u[:, 0])
    if single:
        return out_s[0], out_d[0], out_h[0]
    return out_s, out_d, out_h


def project_on_segments_numpy(segments: tuple, xy: np.ndarray, chunk: int = 4096
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`project_on_segments` in numpy, chunks of (n, S) temporaries (the definition the
    compiled pass is tested against; non-finite points take it)."""
    pts, cum, unit, seg_len = segments
    q = np.asarray(xy, dtype=np.float64)
    single = q.ndim == 1
    q = q.reshape(-1, 2)
    S = len(unit)
    out_s = np.empty(len(q))
    out_d = np.empty(len(q))
    out_h = np.empty(len(q))
    for lo in range(0, len(q), chunk):
        qq = q[lo:lo + chunk]
        rel = qq[:, None, :] - pts[None, :S, :]  # (n, S, 2)
        t = np.einsum("nsk,sk->ns", rel, unit)
        # interior segments clamp to [0, len]; the first/last extend to infinity backwards/forwards
        lo_b = np.zeros(S)
        hi_b = seg_len.copy()
        lo_b[0] = -np.inf
        hi_b[-1] = np.inf
        tc = np.clip(t, lo_b, hi_b)
        foot = pts[None, :S, :] + tc[..., None] * unit[None]
        dist2 = np.sum((qq[:, None, :] - foot) ** 2, axis=-1)
        best = np.argmin(dist2, axis=1)
        rows = np.arange(len(qq))
        u = unit[best]
        r = rel[rows, best]
        out_s[lo:lo + chunk] = cum[best] + tc[rows, best]
        out_d[lo:lo + chunk] = u[:, 0] * r[:, 1] - u[:, 1] * r[:, 0]  # cross(u, r): left +
        out_h[lo:lo + chunk] = np.arctan2(u[:, 1], u[:, 0])
    if single:
        return out_s[0], out_d[0], out_h[0]
    return out_s, out_d, out_h


def resample(points: np.ndarray, step: float) -> np.ndarray:
    """Resample at (about) uniform spacing ``step`` m, keeping both end points.

    Returns:
        (M, 2); a degenerate (single-point) polyline returns that point once.
    """
    if step <= 0:
        raise ValueError("step must be > 0")
    pts = clean_polyline(points)
    total = length(pts)
    if total <= EPS:
        return pts[:1].copy()
    n = max(1, int(np.ceil(total / step - 1e-9)))
    return point_at(pts, np.linspace(0.0, total, n + 1))


def vertex_normals(points: np.ndarray) -> np.ndarray:
    """Unit left normals at each point of the cleaned polyline: (P', 2).

    Interior normals bisect the adjacent segments' normals (a mitre join without the length
    correction, which keeps offsets bounded at sharp corners)."""
    pts, _, unit, _ = _segments(points)
    seg_n = np.stack([-unit[:, 1], unit[:, 0]], axis=1)
    n = np.empty((len(pts), 2))
    n[0] = seg_n[0]
    n[-1] = seg_n[-1]
    if len(pts) > 2:
        mid = seg_n[:-1] + seg_n[1:]
        norm = np.hypot(mid[:, 0], mid[:, 1])
        # a U-turn (opposite segments) has no bisector: fall back to the incoming normal
        ok = norm > 1e-9
        mid[ok] /= norm[ok, None]
        mid[~ok] = seg_n[:-1][~ok]
        n[1:-1] = mid
    return n


def lane_bounds(centerline: np.ndarray, width: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) (P, 2) bounds of a lane: its centre line (P, 2), not cleaned, offset by
    +-width/2 (scalar or (P,) m) along each vertex's normal (the mean of its segments'
    directions); the CommonRoad lanelets adv3d writes have these as their bounds."""
    c = np.asarray(centerline, dtype=np.float64)
    w = np.broadcast_to(np.asarray(width, dtype=np.float64), (len(c),))
    seg = np.diff(c, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
    tangent = np.empty_like(c)
    tangent[0], tangent[-1] = seg[0], seg[-1]
    tangent[1:-1] = seg[:-1] + seg[1:]
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    normal = np.c_[-tangent[:, 1], tangent[:, 0]]
    half = 0.5 * w[:, None]
    return c + half * normal, c - half * normal


def offset_polyline(points: np.ndarray, d: np.ndarray | float) -> np.ndarray:
    """Offset the cleaned polyline by ``d`` m to the left (negative: right); ``d`` scalar or
    one value per *original* point (values of dropped duplicates are dropped too)."""
    raw = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(d, dtype=np.float64)
    if d.ndim:
        keep = _kept_indices(raw)
        d = d.reshape(-1)[keep]
    pts = clean_polyline(raw)
    return pts + np.reshape(d, (-1, 1)) * vertex_normals(pts)


def curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature (1/m, left turn +) at each point of the cleaned polyline: (P',).

    Turning angle between adjacent segments divided by the mean of their lengths; 0 at the
    ends and for straight or degenerate polylines."""
    pts, _, unit, seg_len = _segments(points)
    k = np.zeros(len(pts))
    if len(unit) >= 2:
        cross = unit[:-1, 0] * unit[1:, 1] - unit[:-1, 1] * unit[1:, 0]
        dot = np.sum(unit[:-1] * unit[1:], axis=1)
        turn = np.arctan2(cross, dot)
        k[1:-1] = turn / (0.5 * (seg_len[:-1] + seg_len[1:]))
    return k


def curvature_at(points: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Curvature (1/m) interpolated along arc length at ``s``."""
    pts = clean_polyline(points)
    return np.interp(np.asarray(s, dtype=np.float64), arc_length(pts), curvature(pts))


def width_at(points: np.ndarray, widths: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Lane width (m) interpolated along arc length at ``s`` (per-point ``widths`` (P,))."""
    raw = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    keep = _kept_indices(raw)
    w = np.asarray(widths, dtype=np.float64).reshape(-1)
    if w.size == 1:
        return np.full(np.shape(s), float(w[0]))
    return np.interp(np.asarray(s, dtype=np.float64), arc_length(raw[keep]), w[keep])
