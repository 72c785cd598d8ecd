"""Compiled per-ray loops of the LiDAR pipeline (:mod:`adv3d_runner.sensors.lidar`).

Why compiled (docs/lidar.md): each of these is one pass over the rays or returns that numpy
can only write as a dozen passes (gathers, temporaries, masks), and their sum cost more than
half of what the pipeline spends outside Embree. Every kernel computes each value with the
same float32 operations in the same order as the numpy code it replaced (no FMA: numba's
default contracts nothing), so the frames are the same bytes (``tests/test_lidar_pinned.py``).
Transcendentals stay in numpy (numpy's float32 ``exp`` is a SIMD version that need not round
like the C library's); the random draws are :mod:`.draws`'s (numpy's values).

Conventions: float32 arrays and scalars (``np.float32``; a Python float would make numba
compute in float64), flat ray indices int64, C-contiguous arrays, so each kernel sees one
signature and compiles once (cached in ``__pycache__``).
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import kernel

__all__ = ["turn_rays", "actor_rays", "take_hits", "valid_returns", "make_returns", "count_labels", "actor_windows"]

#: Label of the rays blocked by the ego's own body (no return).
EGO = -3


@kernel
def turn_rays(dx, dy, dz, c, s, out):
    """The first ``len(out)`` rays turned about z: out[k] = (c dx - s dy, s dx + c dy, dz).

    Args:
        dx, dy, dz: (N,) float32 unit direction components (ego frame).
        c, s: float32 cos and sin of the turn (the ego yaw: ego -> map frame).
        out: (M, 3) float32, M <= N, written.
    """
    for k in range(out.shape[0]):
        out[k, 0] = c * dx[k] - s * dy[k]
        out[k, 1] = s * dx[k] + c * dy[k]
        out[k, 2] = dz[k]


@kernel
def actor_rays(rays, limits, cut, dx, dy, dz, c, s, out_rays, out_tfar, out_dirs):
    """The rays of an actor's window that can still reach it, turned into its frame.

    Args:
        rays: (M,) int64 flat ray indices (the window).
        limits: (N,) float32 current nearest distance per ray (metres).
        cut: float32; a ray whose limit is below it is left out (nothing of the actor is
            nearer than its footprint; -inf keeps every ray).
        dx, dy, dz: (N,) float32 ego-frame ray directions.
        c, s: float32 cos and sin of the ego-to-actor turn about z.
        out_rays: (>= M,) int64; out_tfar: (>= M,) float32; out_dirs: (>= M, 3) float32:
            written for the K rays kept, in window order: index, limit, direction in the
            actor's frame (c dx - s dy, s dx + c dy, dz).

    Returns:
        K, the number of rays kept.
    """
    k = 0
    for j in range(rays.shape[0]):
        r = rays[j]
        lim = limits[r]
        if lim >= cut:
            out_rays[k] = r
            out_tfar[k] = lim
            out_dirs[k, 0] = c * dx[r] - s * dy[r]
            out_dirs[k, 1] = s * dx[r] + c * dy[r]
            out_dirs[k, 2] = dz[r]
            k += 1
    return k


@kernel
def take_hits(rays, tfar, prim, dirs, normals, value, t, label, cos):
    """Write an actor cast's hits into a sensor's per-ray arrays.

    Args:
        rays: (K,) int64 flat indices of the rays cast; tfar: (K,) float32 their distances
            after the cast (metres); prim: (K,) int32 face hit (-1: no closer hit);
            dirs: (K, 3) float32 their directions in the actor's frame.
        normals: (F + 1, 3) float32 unit face normals of the actor's mesh.
        value: the label written (the actor's row).
        t: (N,) float32, label: (N,) int32, cos: (N,) float32 |cos incidence|: written where
            a ray hit, ((nx dx + ny dy) + nz dz, as numpy's einsum sums it).

    Returns:
        the number of hits.
    """
    n = 0
    for h in range(prim.shape[0]):
        f = prim[h]
        if f >= 0:
            r = rays[h]
            t[r] = tfar[h]
            label[r] = value
            cos[r] = abs(normals[f, 0] * dirs[h, 0] + normals[f, 1] * dirs[h, 1] + normals[f, 2] * dirs[h, 2])
            n += 1
    return n


@kernel
def valid_returns(t, label, floor, max_range, box_in, box_out, neg_att):
    """The rays with a valid return: floor <= t < max_range, not blocked by the ego body, and
    (where ``box_in`` is not empty) not inside the ego box.

    Args:
        t: (N,) float32 nearest distance (metres); label: (N,) int32.
        floor: (N,) float32 smallest valid range per ray (``LidarRig.range_floor``).
        max_range: float32.
        box_in, box_out: (N,) float32 distances [in, out] a ray spends in the ego box (a
            return there is dropped; +inf / -inf for rays that do not cross it), or (0,) each.
        neg_att: float32 minus the attenuation rate (1/m).

    Returns:
        idx: (n,) int64 their flat indices, ascending; fade: (n,) float32 neg_att x t (the
        caller takes its exp).
    """
    n = t.shape[0]
    box = box_in.shape[0] > 0
    idx = np.empty(n, np.int64)
    fade = np.empty(n, np.float32)
    m = 0
    for r in range(n):
        tr = t[r]
        if tr >= floor[r] and tr < max_range and label[r] != EGO:
            if box and tr >= box_in[r] and tr <= box_out[r]:
                continue
            idx[m] = r
            fade[m] = tr * neg_att
            m += 1
    return idx[:m], fade[:m]


@kernel
def make_returns(idx, fade, t, label, prim_bg, cos_actor, dirs, ring, faces, c, s, actor_refl,
                 gauss, sigma, uniform, p_drop, position):
    """The returns of one sensor: range noise and ray drop, the points and their intensity.

    Args:
        idx: (n,) int64 rays with a valid return and fade: (n,) float32 their attenuation
            factor, exp(-attenuation x true range) (:func:`valid_returns`, then numpy's exp).
        t: (N,) float32 true range (metres); label: (N,) int32; prim_bg: (N,) int32 background
            face (-1: none); cos_actor: (N,) float32 |cos incidence| where an actor was hit.
        dirs: (N, 3) float32 ego-frame directions; ring: (N,) int16.
        faces: (F + 1, 4) float32 background face table: map-frame unit normal, reflectivity
            (last row zero, for a miss).
        c, s: float32 cos and sin of the ego yaw (normals map -> ego: (c nx + s ny, c ny - s nx)).
        actor_refl: (A,) float32 reflectivity per actor row.
        gauss: (n,) float32 standard normal draws (range noise) or (0,): none.
        sigma: float32 range noise, metres.
        uniform: (n,) float32 uniform draws (ray drop: dropped when < p_drop) or (0,): none.
        p_drop: float32.
        position: (3,) float32 sensor position in the ego frame (metres).

    Returns:
        points: (m, 4) float32 x, y, z in the ego frame and intensity
        (min(|cos|, 1) x reflectivity) x fade; ring: (m,) int16; label: (m,) int32;
        dist: (m,) float32 measured range (with noise).
    """
    n = idx.shape[0]
    noisy = gauss.shape[0] > 0
    dropping = uniform.shape[0] > 0
    m = n
    if dropping:
        m = 0
        for j in range(n):
            if uniform[j] >= p_drop:
                m += 1
    points = np.empty((m, 4), np.float32)
    out_ring = np.empty(m, np.int16)
    out_label = np.empty(m, np.int32)
    dist = np.empty(m, np.float32)
    zero, one = np.float32(0.0), np.float32(1.0)
    miss = faces.shape[0] - 1
    k = 0
    for j in range(n):
        if dropping and uniform[j] < p_drop:
            continue
        r = idx[j]
        d = t[r]
        if noisy:
            d = d + gauss[j] * sigma
            if d < zero:
                d = zero
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        lab = label[r]
        if lab >= 0:
            refl = actor_refl[lab]
            cos = cos_actor[r]
        else:
            f = prim_bg[r]
            if f < 0:
                f = miss
            fx, fy = faces[f, 0], faces[f, 1]
            nx = c * fx + s * fy
            ny = c * fy - s * fx
            refl = faces[f, 3]
            cos = abs(nx * dx + ny * dy + faces[f, 2] * dz)
        if cos > one:
            cos = one
        points[k, 0] = dx * d + position[0]
        points[k, 1] = dy * d + position[1]
        points[k, 2] = dz * d + position[2]
        points[k, 3] = cos * refl * fade[j]
        out_ring[k] = ring[r]
        out_label[k] = lab
        dist[k] = d
        k += 1
    return points, out_ring, out_label, dist


@kernel
def count_labels(label, n):
    """Returns per actor row the number of returns labelled with it: ``np.bincount(label[label
    >= 0], minlength=n)`` in one pass (int64, (n,)), or (0,) when a label is n or more (the
    caller then takes numpy's bincount, which grows its output).

    Args:
        label: (m,) int32 labels of a frame's returns (actor row, or negative: none).
        n: the number of rows counted.
    """
    out = np.zeros(n, np.int64)
    for k in range(label.shape[0]):
        v = label[k]
        if v >= 0:
            if v >= n:
                return np.zeros(0, np.int64)
            out[v] += 1
    return out


@kernel
def actor_windows(sx, sy, ego_yaw, reach, poses, shapes, sensor_z, row_min, row_max, azimuth, columns, n_rays,
                  radius_pad, angle_pad):
    """The rays that can reach each actor, for a sensor whose rows share one column azimuth
    table and whose row elevations are sorted: :meth:`MountedLidar.footprint_segments` (through
    ``_Cast.segments``) for every actor in one call, their rays concatenated.

    Args:
        sx, sy: the sensor in the map frame (m); ego_yaw: rad; reach: max range + pad (m).
        poses: (K, 3) float64 actor poses (x, y, yaw) in the map frame.
        shapes: (K, 7) float64 per actor mesh: xy radius, footprint (xmin, xmax, ymin, ymax)
            and z range (zmin, zmax), metres, in the actor's frame.
        sensor_z: mount height (m); row_min, row_max: (B,) float64 min / max elevation per row
            (both ascending); azimuth: (C,) float64 ascending column azimuths in [-pi, pi);
            columns: C; n_rays: B x C.
        radius_pad, angle_pad: the windows' padding (m, rad).
    Returns:
        keep: (K,) bool, False where the actor is out of range (no cast at all); counts (K,)
        int64 rays per actor; cuts (K,) float32 the footprint's nearest horizontal distance
        less 1e-5 of it (0 where every ray is taken); rays (sum counts,) int64 flat ray
        indices, actor after actor, each window interval by interval and row by row (the
        order of the Python windows).

    The same float64 steps as the Python methods; the transcendentals are the C library's
    (CPython's ``math.hypot`` is its own and may differ in the last bit), which the windows'
    padding (``radius_pad``, ``angle_pad``: far above rounding) makes irrelevant: a ray at a
    window's edge cannot hit the mesh, so the hits are the same (``tests/test_lidar.py``)."""
    K = poses.shape[0]
    pi = np.pi
    two_pi = 2.0 * np.pi
    keep = np.zeros(K, np.bool_)
    counts = np.zeros(K, np.int64)
    cuts = np.zeros(K, np.float32)
    # per actor: row range [r0, r1) and up to two column intervals [c0, c1), or every ray
    win = np.zeros((K, 6), np.int64)
    n_int = np.zeros(K, np.int64)  # 0: empty, 1 or 2 intervals, 3: every ray
    for k in range(K):
        relx, rely = sx - poses[k, 0], sy - poses[k, 1]
        if math.hypot(relx, rely) - shapes[k, 0] > reach:
            continue
        keep[k] = True
        yaw = poses[k, 2]
        ca, sa = math.cos(yaw), math.sin(yaw)
        px = ca * relx + sa * rely  # the sensor in the actor's frame
        py = -sa * relx + ca * rely
        x0, x1, y0, y1 = shapes[k, 1], shapes[k, 2], shapes[k, 3], shapes[k, 4]
        pad_x = 1e-6 * max(abs(x0), abs(x1)) + radius_pad
        pad_y = 1e-6 * max(abs(y0), abs(y1)) + radius_pad
        x0, x1, y0, y1 = x0 - pad_x, x1 + pad_x, y0 - pad_y, y1 + pad_y
        if x0 <= px <= x1 and y0 <= py <= y1:  # the sensor above the footprint: every ray
            n_int[k] = 3
            counts[k] = n_rays
            continue
        rho0 = math.hypot(max(max(x0 - px, 0.0), px - x1), max(max(y0 - py, 0.0), py - y1))
        cuts[k] = np.float32(rho0 * (1.0 - 1e-5))
        rho1 = 0.0
        mid = math.atan2(0.5 * (y0 + y1) - py, 0.5 * (x0 + x1) - px)
        lo, hi = np.inf, -np.inf
        for c in range(4):
            cx = x0 if c == 0 or c == 3 else x1
            cy = y0 if c < 2 else y1
            rho1 = max(rho1, math.hypot(cx - px, cy - py))
            d = (math.atan2(cy - py, cx - px) - mid + pi) % two_pi - pi
            lo, hi = min(lo, d), max(hi, d)
        center = mid + 0.5 * (lo + hi) + yaw - ego_yaw
        half = 0.5 * (hi - lo) + angle_pad
        z_lo = shapes[k, 5] - sensor_z - radius_pad
        z_hi = shapes[k, 6] - sensor_z + radius_pad
        e_lo = math.atan(z_lo / (rho0 if z_lo < 0 else rho1)) - angle_pad
        e_hi = math.atan(z_hi / (rho0 if z_hi > 0 else rho1)) + angle_pad
        r0 = np.searchsorted(row_max, e_lo, side="left")
        r1 = np.searchsorted(row_min, e_hi, side="right")
        if r1 <= r0:
            continue
        # the azimuth interval(s), split at the seam
        if half >= pi:
            a0, a1, b0, b1, m = -pi, pi, 0.0, 0.0, 1
        else:
            center = (center + pi) % two_pi - pi
            a0, a1 = center - half, center + half
            if a0 < -pi:
                a0, a1, b0, b1, m = a0 + two_pi, pi, -pi, a1, 2
            elif a1 >= pi:
                a0, a1, b0, b1, m = a0, pi, -pi, a1 - two_pi, 2
            else:
                b0, b1, m = 0.0, 0.0, 1
        c0 = np.searchsorted(azimuth, a0, side="left")
        c1 = np.searchsorted(azimuth, a1, side="right")
        win[k, 0], win[k, 1], win[k, 2], win[k, 3] = r0, r1, c0, c1
        per_row = c1 - c0
        if m == 2:
            d0 = np.searchsorted(azimuth, b0, side="left")
            d1 = np.searchsorted(azimuth, b1, side="right")
            win[k, 4], win[k, 5] = d0, d1
            per_row += d1 - d0
        n_int[k] = m
        counts[k] = (r1 - r0) * per_row
    rays = np.empty(counts.sum(), np.int64)
    j = 0
    for k in range(K):
        if n_int[k] == 3:
            for i in range(n_rays):
                rays[j] = i
                j += 1
            continue
        for q in range(n_int[k]):
            c0, c1 = win[k, 2 + 2 * q], win[k, 3 + 2 * q]
            for r in range(win[k, 0], win[k, 1]):
                base = r * columns
                for i in range(base + c0, base + c1):
                    rays[j] = i
                    j += 1
    return keep, counts, cuts, rays
