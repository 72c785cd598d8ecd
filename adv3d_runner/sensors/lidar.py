"""LiDAR sensor rigs and the per-frame simulation (array in, array out).

Pipeline of :func:`simulate_frame` for each sensor of the rig:

1. rays: the beam table in the sensor frame, rotated by the mount pose into the ego frame once
   (:class:`MountedLidar`: one row per laser, each sorted by ego-frame azimuth), rotated by the
   ego yaw per frame;
2. background: one Embree cast against the static background BVH (float32, centred);
3. actors: each actor that can be seen (range, azimuth and elevation windows, see
   :meth:`MountedLidar.candidate_rays`) is hit by casting the rays of its windows, expressed in
   its local frame, against its mesh's BVH, with the current nearest distance as limit (so only
   closer hits come back, nothing is rebuilt);
4. effects: min/max range, intensity = reflectivity x |cos incidence| x exp(-attenuation x
   range), Gaussian range noise and ray drop from the caller's ``numpy.random.Generator``,
   ego masking (rays hitting the ego's mesh, points inside the ego's box);
5. output: points (x, y, z, intensity) in the EGO frame, ring, label (actor index into
   ``actor_ids``, -1 = background) and sensor index; several sensors are concatenated.

Culling only skips rays that cannot reach an actor, and every per-ray computation is
elementwise, so culling returns exactly the points that no culling returns (tested).
"""
from __future__ import annotations

import math
import time
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, field

import numpy as np

from . import kernels
from .beams import LidarModel, get_model
from .draws import draw_f32

__all__ = ["MountedLidar", "LidarRig", "LidarFrame", "simulate_frame", "rotation_rpy",
           "BACKGROUND", "DEFAULT_ATTENUATION"]

#: Label of background points.
BACKGROUND = -1
_EGO = kernels.EGO
#: Atmospheric attenuation of the returned intensity, 1/m (CARLA's default rate).
DEFAULT_ATTENUATION = 0.004
_TWO_PI = 2.0 * np.pi
# Padding of the culling windows: float32 rounding of ray directions and vertices is ~1e-7.
_ANGLE_PAD = 1e-5
_RADIUS_PAD = 1e-3


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation Rz(yaw) @ Ry(pitch) @ Rx(roll) (intrinsic z-y'-x'', REP-103)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


class MountedLidar:
    """A LiDAR model at a mount pose in the ego frame, with its rays precomputed.

    Args:
        model: a :class:`~adv3d_runner.sensors.beams.LidarModel` or a model name.
        mount: (x, y, z, roll, pitch, yaw) of the sensor in the ego frame, metres / radians.

    The rays form a grid of B rows (one per laser, lowest elevation first) by C columns, each
    row sorted by ego-frame azimuth, so an actor's azimuth window is one contiguous segment per
    row and its elevation window a set of rows. Flat ray index = row * C + column.

    Attributes:
        position: (3,) float64 sensor origin in the ego frame.
        dirs: (N, 3) float32 unit ray directions in the ego frame.
        dx, dy, dz: (N,) float32 contiguous columns of ``dirs``.
        ring: (N,) int16 ring index per ray.
        azimuth_key: (N,) float64 ego-frame azimuth in [-pi, pi) plus 2 pi x row: ascending,
            so one ``searchsorted`` finds a window in every row.
        row_elevation: (B, 2) float64 min and max ego-frame elevation of each row.
    """

    def __init__(self, model: LidarModel | str, mount=(0.0, 0.0, 1.8, 0.0, 0.0, 0.0)):
        self.model = get_model(model) if isinstance(model, str) else model
        mount = np.asarray(mount, dtype=np.float64).reshape(6)
        self.mount = mount
        self.position = mount[:3].copy()
        self._z = float(mount[2])
        b, c = self.model.beams, self.model.columns
        dirs_sensor, ring, _ = self.model.ray_table()
        dirs = (dirs_sensor @ rotation_rpy(*mount[3:]).T).reshape(c, b, 3).transpose(1, 0, 2)  # (B, C, 3)
        ring = ring.reshape(c, b).T
        rows = np.argsort(ring[:, 0], kind="stable")  # lowest laser first
        dirs, ring = dirs[rows], ring[rows]
        az = np.arctan2(dirs[..., 1], dirs[..., 0])
        az[az >= np.pi] = -np.pi  # canonical [-pi, pi): one place for the seam
        order = np.argsort(az, axis=1, kind="stable")
        az = np.take_along_axis(az, order, axis=1)
        dirs = np.take_along_axis(dirs, order[..., None], axis=1)
        elev = np.arcsin(np.clip(dirs[..., 2], -1.0, 1.0))
        self.rows, self.columns = b, c
        self.row_elevation = np.stack([elev.min(axis=1), elev.max(axis=1)], axis=1)
        self.azimuth_key = (az + _TWO_PI * np.arange(b)[:, None]).reshape(-1)
        self.dirs = np.ascontiguousarray(dirs.reshape(-1, 3), dtype=np.float32)
        self.dx = np.ascontiguousarray(self.dirs[:, 0])
        self.dy = np.ascontiguousarray(self.dirs[:, 1])
        self.dz = np.ascontiguousarray(self.dirs[:, 2])
        self.ring = np.ascontiguousarray(ring.reshape(-1), dtype=np.int16)
        self._row_offsets = _TWO_PI * np.arange(b)
        # Sensors without per-laser azimuth offsets or tilt have the same column azimuths in
        # every row (up to rounding far below the culling padding): one search serves all rows.
        self._common_azimuth = az[0].copy() if np.abs(az - az[0]).max() < 1e-9 else None
        self._row_starts = np.arange(b, dtype=np.intp) * c
        # Per-frame window searches run on Python lists (bisect): an actor's window costs a few
        # microseconds of Python instead of a dozen small numpy calls.
        self._azimuth_list = None if self._common_azimuth is None else self._common_azimuth.tolist()
        emin, emax = self.row_elevation[:, 0], self.row_elevation[:, 1]
        self._rows_sorted = bool((np.diff(emin) >= 0).all() and (np.diff(emax) >= 0).all())
        self.row_elevation_min, self.row_elevation_max = np.ascontiguousarray(emin), np.ascontiguousarray(emax)
        self._row_min_list, self._row_max_list = emin.tolist(), emax.tolist()
        # Smallest dz of the rays from each flat index on (non-decreasing): the rays from index
        # k on stay above height z_s + max_range * dz_suffix_min[k] within range, so they cannot
        # reach a background wholly below that (:meth:`_Cast.background`).
        self._dz_suffix_min = np.minimum.accumulate(self.dz[::-1])[::-1].astype(np.float64)

    @property
    def n_rays(self) -> int:
        return len(self.dirs)

    def window(self, rows: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
        """Start/end flat indices, in each of ``rows``, of the rays with lo <= azimuth <= hi
        (-pi <= lo <= hi < pi)."""
        off = self._row_offsets[rows]
        return (np.searchsorted(self.azimuth_key, lo + off, "left"),
                np.searchsorted(self.azimuth_key, hi + off, "right"))

    def candidate_rays(self, rel_xy: np.ndarray, ego_yaw: float, xy_radius: float,
                       z_range: tuple[float, float]) -> np.ndarray | None:
        """Flat indices of the rays that can hit a mesh inside a vertical cylinder.

        The cylinder has radius ``xy_radius`` around the actor origin, which lies at ``-rel_xy``
        from the sensor (map frame), and spans ``z_range`` (relative to the ground the sensor
        height is measured from). A ray at elevation e reaches height z_s + rho tan(e) at
        horizontal distance rho, and azimuth never changes along a ray, so rays outside the
        cylinder's azimuth or elevation interval can not hit it. Returns None for "all rays".
        """
        dist = math.hypot(rel_xy[0], rel_xy[1])
        radius = xy_radius * (1.0 + 1e-6) + _RADIUS_PAD
        if dist <= radius:  # sensor inside the bounding circle: every ray may hit
            return None
        half = math.asin(radius / dist) + _ANGLE_PAD
        center = math.atan2(-rel_xy[1], -rel_xy[0]) - ego_yaw
        return _segments_to_indices(*self._window_segments(dist - radius, dist + radius, z_range, center, half))

    def footprint_rays(self, rel_xy: np.ndarray, actor_yaw: float, ego_yaw: float,
                       footprint: tuple[float, float, float, float],
                       z_range: tuple[float, float]) -> np.ndarray | None:
        """Flat indices of the rays of :meth:`footprint_segments` (None: all rays)."""
        seg = self.footprint_segments(rel_xy, actor_yaw, ego_yaw, footprint, z_range)
        return None if seg is None else _segments_to_indices(seg[0], seg[1])

    def footprint_segments(self, rel_xy, actor_yaw: float, ego_yaw: float,
                           footprint: tuple[float, float, float, float],
                           z_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Ray segments [start, end) (flat indices, two (S,) arrays) holding every ray that can
        hit a mesh inside a vertical box: its footprint
        ``(xmin, xmax, ymin, ymax)`` in the actor's frame (yaw ``actor_yaw``, origin at
        ``-rel_xy`` from the sensor, map frame) by ``z_range``. Tighter than the bounding
        cylinder of :meth:`candidate_rays` (a car seen from behind spans a third of its
        circle's azimuths), the same reasoning: a ray can only hit points whose azimuth lies in
        the arc the footprint spans from the sensor and whose elevation lies between the
        box's lowest and highest point at its nearest and farthest horizontal distance.
        Padded like :meth:`candidate_rays`. Returns None for "all rays" (the sensor is above
        the footprint), else (starts, ends, rho0) with rho0 the horizontal distance from the
        sensor to the padded footprint: no point of the mesh is nearer than that. Python floats
        in, so that an actor costs microseconds."""
        ca, sa = math.cos(actor_yaw), math.sin(actor_yaw)
        sx = ca * rel_xy[0] + sa * rel_xy[1]  # the sensor in the actor's frame
        sy = -sa * rel_xy[0] + ca * rel_xy[1]
        x0, x1, y0, y1 = footprint
        pad_x = 1e-6 * max(abs(x0), abs(x1)) + _RADIUS_PAD
        pad_y = 1e-6 * max(abs(y0), abs(y1)) + _RADIUS_PAD
        x0, x1, y0, y1 = x0 - pad_x, x1 + pad_x, y0 - pad_y, y1 + pad_y
        if x0 <= sx <= x1 and y0 <= sy <= y1:
            return None
        rho0 = math.hypot(max(x0 - sx, 0.0, sx - x1), max(y0 - sy, 0.0, sy - y1))
        corners = ((x0, y0), (x1, y0), (x1, y1), (x0, y1))
        rho1 = max(math.hypot(cx - sx, cy - sy) for cx, cy in corners)
        # the sensor is outside the convex footprint: its corners span an arc of less than pi
        # around the direction to its centre
        mid = math.atan2(0.5 * (y0 + y1) - sy, 0.5 * (x0 + x1) - sx)
        deltas = [(math.atan2(cy - sy, cx - sx) - mid + math.pi) % _TWO_PI - math.pi for cx, cy in corners]
        lo, hi = min(deltas), max(deltas)
        center = mid + 0.5 * (lo + hi) + actor_yaw - ego_yaw
        half = 0.5 * (hi - lo) + _ANGLE_PAD
        return (*self._window_segments(rho0, rho1, z_range, center, half), rho0)

    def _window_segments(self, rho0: float, rho1: float, z_range: tuple[float, float], center: float,
                         half: float) -> tuple[np.ndarray, np.ndarray]:
        """Segments [start, end) of the rays within ``half`` of azimuth ``center`` (ego frame)
        that pass between heights ``z_range`` somewhere between horizontal distances ``rho0`` > 0
        and ``rho1``: one per row of the elevation window and azimuth interval (two across the
        seam)."""
        z_lo = z_range[0] - self._z - _RADIUS_PAD
        z_hi = z_range[1] - self._z + _RADIUS_PAD
        e_lo = math.atan(z_lo / (rho0 if z_lo < 0 else rho1)) - _ANGLE_PAD
        e_hi = math.atan(z_hi / (rho0 if z_hi > 0 else rho1)) + _ANGLE_PAD
        if self._rows_sorted:  # rows with max elevation >= e_lo and min elevation <= e_hi
            r0, r1 = bisect_left(self._row_max_list, e_lo), bisect_right(self._row_min_list, e_hi)
            rows = self._row_starts[r0:r1] if r1 > r0 else None
        else:
            rows = np.flatnonzero((self.row_elevation[:, 1] >= e_lo) & (self.row_elevation[:, 0] <= e_hi))
            rows = self._row_starts[rows] if rows.size else None
        if rows is None:
            return _NO_SEGMENT
        intervals = _azimuth_intervals(center, half)
        if self._azimuth_list is not None:
            az = self._azimuth_list
            if len(intervals) == 1:
                lo, hi = intervals[0]
                c0, c1 = bisect_left(az, lo), bisect_right(az, hi)
                return rows + c0, rows + c1
            cols = [(bisect_left(az, lo), bisect_right(az, hi)) for lo, hi in intervals]
            return (np.concatenate([rows + c0 for c0, _ in cols]), np.concatenate([rows + c1 for _, c1 in cols]))
        rows = rows // self.columns
        starts, ends = [], []
        for lo, hi in intervals:
            s, e = self.window(rows, lo, hi)
            starts.append(s)
            ends.append(e)
        return (starts[0], ends[0]) if len(starts) == 1 else (np.concatenate(starts), np.concatenate(ends))


_NO_SEGMENT = (np.zeros(0, np.intp), np.zeros(0, np.intp))


def _segments_to_indices(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, e) for each segment [s, e) (e >= s), vectorised."""
    lengths = ends - starts
    total = int(lengths.sum())
    if total <= 0:
        return np.zeros(0, np.intp)
    offsets = np.cumsum(lengths)
    offsets -= lengths
    return np.repeat(starts - offsets, lengths) + np.arange(total)


def _azimuth_intervals(center: float, half: float) -> list[tuple[float, float]]:
    """center +- half as one or two intervals inside [-pi, pi) (split at the seam)."""
    if half >= np.pi:
        return [(-np.pi, np.pi)]
    center = (center + np.pi) % _TWO_PI - np.pi
    lo, hi = center - half, center + half
    if lo < -np.pi:
        return [(lo + _TWO_PI, np.pi), (-np.pi, hi)]
    if hi >= np.pi:
        return [(lo, np.pi), (-np.pi, hi - _TWO_PI)]
    return [(lo, hi)]


@dataclass
class LidarRig:
    """The ego's LiDARs plus what masks the ego out of their points.

    Attributes:
        sensors: mounted LiDARs (sensor index = position in this list).
        ego_dimensions: (length, width, height) of the ego box (origin at its footprint centre
            on the ground), or None for no box masking.
        ego_margin: metres added around the ego box before masking.
        attenuation: intensity attenuation rate, 1/m.
    """

    sensors: list[MountedLidar]
    ego_dimensions: tuple[float, float, float] | None = None
    ego_margin: float = 0.1
    attenuation: float = DEFAULT_ATTENUATION

    @classmethod
    def single(cls, model: LidarModel | str = "hdl64", mount=(0.0, 0.0, 1.8, 0.0, 0.0, 0.0), **kw) -> "LidarRig":
        """A rig with one sensor."""
        return cls([MountedLidar(model, mount)], **kw)

    @property
    def n_rays(self) -> int:
        return sum(s.n_rays for s in self.sensors)

    def ego_interval(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rays of sensor ``k`` that cross the ego box grown by ``ego_margin``, and the
        distances [t_in, t_out] they spend inside it: (M,) indices, (M,) and (M,) float32.
        Cached."""
        cache = self.__dict__.setdefault("_ego_cache", {})
        key = (k, tuple(self.ego_dimensions), float(self.ego_margin))
        if key not in cache:
            length, width, height = self.ego_dimensions
            mg = self.ego_margin
            lo = np.array([-0.5 * length - mg, -0.5 * width - mg, -mg])
            hi = np.array([0.5 * length + mg, 0.5 * width + mg, height + mg])
            t_in, t_out = _slab_interval(self.sensors[k].position, self.sensors[k].dirs.astype(np.float64), lo, hi)
            rays = np.flatnonzero(t_in <= t_out)
            cache[key] = (rays, t_in[rays], t_out[rays])
        return cache[key]

    def range_floor(self, k: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """Per-ray smallest valid range of sensor ``k`` with the ego box folded in, so that one
        comparison replaces the min-range test and the ego-box test. Cached.

        A return at range t is dropped when t < min_range or when the ray crosses the grown ego
        box and t_in <= t <= t_out. For a ray with t_in <= min_range (every ray when the sensor
        sits inside the box) the two dropped sets join into t <= max(t_out, min_range - ulp),
        i.e. the return is kept iff t >= max(min_range, nextafter(t_out)): exact in float32.

        Returns:
            floor: (N,) float32; keep iff t >= floor (and t < max range).
            rest: (t_in, t_out), (N,) float32 each, for the rays with t_in > min_range (a
                sensor outside the box), which keep the two-sided test (a return is dropped
                iff t_in <= t <= t_out; +inf and -inf for every other ray); None when there
                are none.
        """
        cache = self.__dict__.setdefault("_floor_cache", {})
        dims = None if self.ego_dimensions is None else tuple(self.ego_dimensions)
        key = (k, dims, float(self.ego_margin))
        if key not in cache:
            sensor = self.sensors[k]
            min_range = np.float32(sensor.model.min_range)
            floor = np.full(sensor.n_rays, min_range, np.float32)
            rest = None
            if dims is not None:
                rays, t_in, t_out = self.ego_interval(k)
                simple = t_in <= min_range
                above = np.nextafter(t_out[simple], np.float32(np.inf))
                floor[rays[simple]] = np.maximum(above, min_range)
                if not simple.all():
                    other = ~simple
                    box_in = np.full(sensor.n_rays, np.inf, np.float32)
                    box_out = np.full(sensor.n_rays, -np.inf, np.float32)
                    box_in[rays[other]], box_out[rays[other]] = t_in[other], t_out[other]
                    rest = (box_in, box_out)
            cache[key] = (floor, rest)
        return cache[key]


def _slab_interval(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Ray / axis-aligned box entry and exit distances (slab method), float32 (N,) each."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t1 = (lo - origin) * inv
        t2 = (hi - origin) * inv
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmax = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
    # A direction component of 0 gives +-inf / nan: inside the slab iff the origin is.
    for j in range(3):
        zero = dirs[:, j] == 0
        if zero.any():
            ok = (lo[j] <= origin[j]) & (origin[j] <= hi[j])
            tmin[zero, j] = -np.inf if ok else np.inf
            tmax[zero, j] = np.inf if ok else -np.inf
    t_in = np.maximum(tmin.max(axis=1), 0.0)
    t_out = tmax.min(axis=1)
    return t_in.astype(np.float32), t_out.astype(np.float32)


@dataclass
class LidarFrame:
    """One frame of LiDAR returns (all sensors of a rig), in the ego frame.

    Attributes:
        points: (N, 4) float32 x, y, z (metres, ego frame) and intensity in [0, 1].
        ring: (N,) int16 ring (laser) index, 0 = lowest elevation.
        label: (N,) int32 index into ``actor_ids`` of the actor hit, -1 = background.
        sensor: (N,) int8 index of the sensor in the rig.
        distance: (N,) float32 measured range from the sensor origin, metres (with noise).
        actor_ids: id of each actor label (the world's actor ids, e.g. scene ints).
    """

    points: np.ndarray
    ring: np.ndarray
    label: np.ndarray
    sensor: np.ndarray
    distance: np.ndarray
    actor_ids: tuple = field(default_factory=tuple)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def xyz(self) -> np.ndarray:
        return self.points[:, :3]

    @property
    def intensity(self) -> np.ndarray:
        return self.points[:, 3]

    def label_names(self) -> np.ndarray:
        """(N,) object array of actor ids, ``"background"`` for -1."""
        table = np.array([str(a) for a in self.actor_ids] + ["background"], dtype=object)
        return table[np.where(self.label >= 0, self.label, len(self.actor_ids))]

    def select(self, mask: np.ndarray) -> "LidarFrame":
        """The frame restricted to ``mask`` (bool (N,) or indices)."""
        return LidarFrame(self.points[mask], self.ring[mask], self.label[mask], self.sensor[mask],
                          self.distance[mask], self.actor_ids)

    @staticmethod
    def empty(actor_ids: tuple[str, ...] = ()) -> "LidarFrame":
        return LidarFrame(np.zeros((0, 4), np.float32), np.zeros(0, np.int16), np.zeros(0, np.int32),
                          np.zeros(0, np.int8), np.zeros(0, np.float32), tuple(actor_ids))

    @staticmethod
    def concat(frames: list["LidarFrame"]) -> "LidarFrame":
        if not frames:
            return LidarFrame.empty()
        if len(frames) == 1:
            return frames[0]
        return LidarFrame(*(np.concatenate([getattr(f, name) for f in frames])
                            for name in ("points", "ring", "label", "sensor", "distance")),
                          actor_ids=frames[0].actor_ids)



@dataclass
class RayHits:
    """The nearest hit of every ray of one sensor in one frame, before the sensor effects.

    Attributes:
        t: (N,) float32 distance to the nearest hit (the max range where nothing was hit).
        label: (N,) int32 actor row hit, ``BACKGROUND`` (-1), or the ego body (-3).
        prim_bg: (N,) int32 background face hit by the ray (-1: none), whatever is nearer.
        cos_actor: (N,) float32 |cos incidence| where the nearest hit is an actor (0
            elsewhere), or None when no actor was cast.
    """

    t: np.ndarray
    label: np.ndarray
    prim_bg: np.ndarray
    cos_actor: np.ndarray | None


class _Cast:
    """Per-sensor, per-frame ray geometry shared by the plain and the incremental cast."""

    def __init__(self, sensor: MountedLidar, ego: np.ndarray, stats: dict | None):
        self.sensor, self.model, self.ego = sensor, sensor.model, ego
        self.ego_yaw = float(ego[2])
        self.c, self.s = float(np.cos(ego[2])), float(np.sin(ego[2]))
        px, py, pz = sensor.position
        self.pz = pz
        self.sensor_map = np.array([ego[0] + self.c * px - self.s * py, ego[1] + self.s * px + self.c * py, pz])
        self.sx, self.sy = float(self.sensor_map[0]), float(self.sensor_map[1])
        self.reach = float(self.model.max_range) + _RADIUS_PAD
        self.timer = stats.get("clock", time.perf_counter) if stats is not None else time.perf_counter
        self.embree_s = 0.0
        self.actor_rays = 0
        self.background_rays = 0

    def background(self, world) -> RayHits:
        """Background (and ego body) cast of every ray: tfar starts at max range and becomes
        the nearest distance."""
        sensor, n = self.sensor, self.sensor.n_rays
        c, s = self.c, self.s
        origin_bg = (self.sensor_map - world.origin).astype(np.float32).reshape(1, 3)
        # A ray that stays above the whole background up to max range (from a sensor above it:
        # oz + max_range * dz > z_max) cannot hit it: the rays from the first index where every
        # later ray does are not cast (a suffix: rows go from the lowest laser up, so these are
        # the level and upward rows).
        bg = world.background
        m = n
        if bg.n_faces:
            reach_dz = (bg.z_range[1] + _RADIUS_PAD - float(origin_bg[0, 2])) / float(self.model.max_range)
            if reach_dz < 0:
                m = int(np.searchsorted(sensor._dz_suffix_min, reach_dz, "right"))
        # Ray directions in the map frame (float32, elementwise: identical for any subset).
        dirs = np.empty((m, 3), np.float32)
        kernels.turn_rays(sensor.dx, sensor.dy, sensor.dz, np.float32(c), np.float32(s), dirs)
        t = np.full(n, self.model.max_range, np.float32)
        t0 = self.timer()
        prim, _ = bg.intersect(origin_bg, dirs, t[:m])  # a view: Embree writes into t
        self.embree_s += self.timer() - t0
        self.background_rays += m
        if m < n:
            prim_bg = np.empty(n, np.int32)
            prim_bg[:m] = prim
            prim_bg[m:] = -1
        else:
            prim_bg = prim
        label = np.full(n, BACKGROUND, np.int32)
        # The ego's own body (ego frame, rays in the ego frame): blocks rays, returns nothing.
        if world.ego is not None:
            t0 = self.timer()
            prim_e, _ = world.ego.intersect(sensor.position.astype(np.float32).reshape(1, 3), sensor.dirs, t)
            self.embree_s += self.timer() - t0
            label[prim_e >= 0] = _EGO
        return RayHits(t, label, prim_bg, None)

    def segments(self, bvh, pose):
        """The rays that can reach an actor at ``pose`` as segments of flat indices
        ((S,) starts, (S,) ends, and the nearest horizontal distance of its footprint, see
        :meth:`MountedLidar.footprint_segments`), None for all rays, or False when none can
        (out of range)."""
        relx, rely = self.sx - float(pose[0]), self.sy - float(pose[1])  # actor -> sensor, map frame
        if math.hypot(relx, rely) - bvh.xy_radius > self.reach:
            return False
        return self.sensor.footprint_segments((relx, rely), float(pose[2]), self.ego_yaw, bvh.footprint,
                                              bvh.z_range)

    def window(self, bvh, pose, cull: bool):
        """The rays that can reach an actor at ``pose``: flat indices, None for all rays, or
        False when none can (out of range or an empty window)."""
        if not cull:
            return None
        seg = self.segments(bvh, pose)
        if seg is None or seg is False:
            return seg
        rays = _segments_to_indices(seg[0], seg[1])
        return rays if rays.size else False

    def frames(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per actor pose (K, 3): the sensor origin in the actor's frame, (K, 3) float32, and
        the cos and sin of the ego-to-actor rotation, (K,) float32 each. Elementwise float64
        then one rounding, as for one actor."""
        relx = self.sensor_map[0] - poses[:, 0]
        rely = self.sensor_map[1] - poses[:, 1]
        ca, sa = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        origins = np.empty((len(poses), 3), np.float32)
        origins[:, 0] = ca * relx + sa * rely
        origins[:, 1] = -sa * relx + ca * rely
        origins[:, 2] = self.pz
        phi = self.ego[2] - poses[:, 2]
        return origins, np.cos(phi).astype(np.float32), np.sin(phi).astype(np.float32)

    def actor(self, bvh, pose, rays, limits: np.ndarray) -> "_ActorCast":
        """Cast ``rays`` (flat indices, None: all) against one actor's mesh, each with its
        limit from ``limits`` ((N,) float32, e.g. the current nearest distances); nothing is
        written into the hits yet (:func:`_take_hits` does)."""
        if rays is None:
            rays = np.arange(self.sensor.n_rays)
        origins, cp, sp = self.frames(np.asarray(pose, dtype=np.float64).reshape(1, 3))
        cast = self.turn(rays.astype(np.int64, copy=False), limits, _NO_CUT, cp[0], sp[0], _buffers(len(rays)),
                         bvh.face_normals)
        cast.prim = self.intersect(bvh, origins, cast)
        return cast

    def turn(self, rays: np.ndarray, limits: np.ndarray, cut: np.float32, cp: np.float32, sp: np.float32,
             buffers: "_ActorCast", normals: np.ndarray) -> "_ActorCast":
        """The rays of ``rays`` ((M,) int64) whose limit in ``limits`` is at least ``cut``,
        with their limits and their directions turned by (cp, sp) into an actor's frame (the
        actor's mesh has face ``normals``), written into ``buffers`` (of at least M rows; the
        cast returned holds views of them). Elementwise, so any subset or batch gives the same
        per-ray values."""
        s, b = self.sensor, buffers
        k = kernels.actor_rays(rays, limits, cut, s.dx, s.dy, s.dz, cp, sp, b.rays, b.tfar, b.dirs)
        return _ActorCast(b.rays[:k], b.tfar[:k], None, b.dirs[:k], normals)

    def intersect(self, bvh, origins: np.ndarray, cast: "_ActorCast") -> np.ndarray:
        """Embree call of an actor cast (``origins``: (1, 3) float32 sensor in the actor's
        frame); ``cast.tfar`` becomes the new distances. Returns (K,) int32 faces (-1: none)."""
        t0 = self.timer()
        prim, _ = bvh.intersect(origins, cast.dirs, cast.tfar)  # closer hits overwrite tfar
        self.embree_s += self.timer() - t0
        self.actor_rays += len(cast.rays)
        return prim

    def actors(self, world, hits: RayHits, rows, poses: np.ndarray, cull: bool = True, before_cast=None) -> None:
        """Cast the actors ``rows`` (ascending) one after the other into ``hits`` (fresh from
        :meth:`background`), each with the current nearest distances as limits: the hits of
        :meth:`actor` and :func:`_take_hits` called in a loop.

        Batched: the windows of every actor are found first (Python), then one index array
        holds the rays of all of them, and each actor's Embree call gets its slice turned into
        its frame (:func:`kernels.actor_rays`, into buffers shared by all actors), less the rays
        whose current hit is nearer than the actor's footprint (they cannot change: every point
        of the mesh is at least that far); its hits are written back, |cos incidence|
        included, by one compiled loop (:func:`kernels.take_hits`).

        Args:
            before_cast: called as ``before_cast(i, rays)`` just before actor ``i`` is cast
                (``rays``: its whole window, (M,) flat indices), for the static-hit cache.
        """
        if hits.cos_actor is not None:
            raise ValueError("actors() takes the hits of background() alone")
        sensor = self.sensor
        n = sensor.n_rays
        with_mesh = [(int(i), world.actor_bvh(int(i))) for i in rows]
        with_mesh = [(i, bvh) for i, bvh in with_mesh if bvh is not None]
        if cull and with_mesh and sensor._azimuth_list is not None and sensor._rows_sorted:
            # every actor's window in one compiled call (the Python path below, per actor)
            rows_k = [i for i, _ in with_mesh]
            keep, counts_k, cuts_k, rays = kernels.actor_windows(
                self.sx, self.sy, self.ego_yaw, self.reach, np.ascontiguousarray(poses[rows_k], dtype=np.float64),
                np.stack([bvh.window_shape for _, bvh in with_mesh]), sensor._z, sensor.row_elevation_min,
                sensor.row_elevation_max, sensor._common_azimuth, sensor.columns, n, _RADIUS_PAD, _ANGLE_PAD)
            cast_rows = [i for (i, _), k in zip(with_mesh, keep) if k]
            bvhs = [bvh for (_, bvh), k in zip(with_mesh, keep) if k]
            counts, cuts = counts_k[keep].tolist(), cuts_k[keep]
        else:
            cast_rows, bvhs, starts, ends, cuts = [], [], [], [], []
            for i, bvh in with_mesh:
                seg = self.segments(bvh, poses[i]) if cull else None
                if seg is False:
                    continue
                if seg is None:
                    seg = (np.zeros(1, np.intp), np.full(1, n, np.intp), 0.0)
                cast_rows.append(i)
                bvhs.append(bvh)
                starts.append(seg[0])
                ends.append(seg[1])
                # Embree's float32 distances are within 1e-5 relative of the true ones, far below
                # the 1 mm the footprint is padded by.
                cuts.append(np.float32(seg[2] * (1.0 - 1e-5)))
            if not cast_rows:
                return
            counts = [int((e - s).sum()) for s, e in zip(starts, ends)]
            rays = _segments_to_indices(np.concatenate(starts), np.concatenate(ends)).astype(np.int64, copy=False)
        if not cast_rows or rays.size == 0:
            return
        origins, cp, sp = self.frames(poses[cast_rows])
        buffers = _buffers(max(counts))
        hits.cos_actor = np.zeros(n, np.float32)
        a = 0
        for j, i in enumerate(cast_rows):
            b = a + counts[j]
            if b == a:
                continue
            mine = rays[a:b]
            a = b
            if before_cast is not None:
                before_cast(i, mine)
            cast = self.turn(mine, hits.t, cuts[j], cp[j], sp[j], buffers, bvhs[j].face_normals)
            if len(cast.rays) == 0:
                continue
            cast.prim = self.intersect(bvhs[j], origins[j:j + 1], cast)
            kernels.take_hits(cast.rays, cast.tfar, cast.prim, cast.dirs, cast.normals, i, hits.t, hits.label,
                              hits.cos_actor)

    def record(self, stats: dict | None) -> None:
        if stats is not None:
            stats["embree_s"] = stats.get("embree_s", 0.0) + self.embree_s
            stats["rays_cast"] = stats.get("rays_cast", 0) + self.background_rays + self.actor_rays
            stats["actor_rays"] = stats.get("actor_rays", 0) + self.actor_rays


#: "Keep every ray" for :func:`kernels.actor_rays`.
_NO_CUT = np.float32(-np.inf)


@dataclass
class _ActorCast:
    """The rays of one actor cast: (K,) int64 flat indices, (K,) float32 limits (the new
    distances after the cast), (K,) int32 faces hit (-1: none; None before the cast),
    (K, 3) float32 directions in the actor's frame, and the mesh's (F + 1, 3) face normals."""

    rays: np.ndarray
    tfar: np.ndarray
    prim: np.ndarray | None
    dirs: np.ndarray
    normals: np.ndarray | None


def _buffers(size: int) -> _ActorCast:
    """Empty arrays for :meth:`_Cast.turn` to fill, ``size`` rows."""
    return _ActorCast(np.empty(size, np.int64), np.empty(size, np.float32), None, np.empty((size, 3), np.float32),
                      None)


def _take_hits(hits: RayHits, i: int, cast: _ActorCast) -> np.ndarray:
    """Write the hits of actor ``i``'s cast (:meth:`_Cast.actor`) into ``hits``; returns the
    ray indices it took."""
    hit = cast.prim >= 0
    if not hit.any():
        return cast.rays[:0]
    if hits.cos_actor is None:
        hits.cos_actor = np.zeros(len(hits.t), np.float32)
    kernels.take_hits(cast.rays, cast.tfar, cast.prim, cast.dirs, cast.normals, i, hits.t, hits.label,
                      hits.cos_actor)
    return cast.rays[hit]


def cast_rays(world, sensor: MountedLidar, ego: np.ndarray, poses: np.ndarray, present: np.ndarray,
              cull: bool = True, stats: dict | None = None) -> RayHits:
    """The nearest hit of every ray of one sensor: the background, then the ego body, then each
    present actor in row order, each cast with the current nearest distances as limits.

    Args:
        world: a :class:`~adv3d_runner.sensors.world.LidarWorld`.
        sensor: the sensor. ego: (3,) ego pose. poses: (A, 3) actor poses (map frame).
        present: (P,) ascending rows of the actors present this frame.
        cull: cast only the rays in each actor's window (identical result).
        stats: see :func:`simulate_frame`.
    """
    cast = _Cast(sensor, ego, stats)
    hits = cast.background(world)
    cast.actors(world, hits, present, poses, cull)
    cast.record(stats)
    return hits


def simulate_frame(world, rig: LidarRig, ego_pose, actor_poses=None, rng: np.random.Generator | None = None, *,
                   cull: bool = True, noise: bool = True, drop: bool = True,
                   stats: dict | None = None, cache=None) -> LidarFrame:
    """Simulate one frame of the rig's LiDARs in ``world``.

    Args:
        world: a :class:`~adv3d_runner.sensors.world.LidarWorld`.
        rig: the ego's :class:`LidarRig`.
        ego_pose: (3,) ego x, y (map frame, metres) and yaw (radians).
        actor_poses: (A, 3) x, y, yaw per actor in ``world.actor_ids`` order; rows with a NaN
            are absent this frame. None = no actor present.
        rng: the only source of randomness (range noise, ray drop); None = ideal sensor
            (no noise, no drop).
        cull: skip actors out of range and rays out of each actor's azimuth and elevation
            windows (identical output, faster). False casts every ray against every actor.
        noise, drop: switch range noise / ray drop off even with an rng.
        stats: if a dict, ``embree_s`` (time inside Embree), ``rays_cast`` and
            ``actor_rays`` are accumulated into it; its optional ``clock`` entry is the timer
            (default ``time.perf_counter``; benchmarks on a shared machine pass
            ``time.thread_time``).
        cache: a :class:`~adv3d_runner.sensors.incremental.StaticRayCache` of this world and
            rig: the hits of everything but its dynamic actors are reused for a frame seen
            before (same ego pose and actor poses, bit for bit) and only the rays that can
            reach a dynamic actor are cast again. Identical output (tested); ignored when
            ``cull`` is False.

    Returns:
        :class:`LidarFrame` in the ego frame.
    """
    ego = np.asarray(ego_pose, dtype=np.float64).reshape(3)
    n_actors = len(world.actor_ids)
    if actor_poses is None:
        poses = np.full((n_actors, 3), np.nan)
    else:
        poses = np.asarray(actor_poses, dtype=np.float64).reshape(-1, 3)
        if len(poses) != n_actors:
            raise ValueError(f"actor_poses has {len(poses)} rows for {n_actors} actors")
    present = np.flatnonzero(np.isfinite(poses).all(axis=1))
    actor_refl = world.actor_reflectivity()
    frames = []
    for k, sensor in enumerate(rig.sensors):
        if cache is not None and cull:
            hits = cache.cast(world, rig, k, ego, poses, present, stats)
        else:
            hits = cast_rays(world, sensor, ego, poses, present, cull, stats)
        frames.append(_effects(world, rig, k, ego, hits, actor_refl, rng, noise, drop))
    out = LidarFrame.concat(frames)
    out.actor_ids = tuple(world.actor_ids)
    return out


def _effects(world, rig: LidarRig, k: int, ego: np.ndarray, hits: RayHits, actor_refl: np.ndarray,
             rng: np.random.Generator | None, noise: bool, drop: bool) -> LidarFrame:
    """Sensor effects on one sensor's nearest hits: range limits and ego masking, range noise
    and ray drop, intensity; the points in the ego frame.

    Two compiled passes (:mod:`.kernels`: one over the rays, one over the returns, instead of a
    few dozen numpy passes) around the random draws and the attenuation's exp, which stay in
    numpy so that the frames are the same bytes as numpy's."""
    sensor = rig.sensors[k]
    model = sensor.model
    t, label = hits.t, hits.label

    # Valid returns: min range and the ego box folded into one per-ray floor (LidarRig.range_floor).
    floor, rest = rig.range_floor(k)
    box_in, box_out = (_NONE_F32, _NONE_F32) if rest is None else rest
    idx, fade = kernels.valid_returns(t, label, floor, np.float32(model.max_range), box_in, box_out,
                                      np.float32(-rig.attenuation))
    if idx.size == 0:
        return LidarFrame.empty()
    np.exp(fade, out=fade)  # exp(-attenuation x true range), numpy's own exp (see kernels)

    # Effects drawn from the caller's generator in a fixed order (noise, then drop), one draw
    # per return, so the same returns and seed give the same frame.
    # (draws.draw_f32: numpy's own values, from a compiled loop)
    gauss = uniform = _NONE_F32
    if rng is not None:
        n_gauss = idx.size if noise and model.range_noise > 0 else 0
        n_uniform = idx.size if drop and model.ray_drop > 0 else 0
        if n_gauss or n_uniform:
            gauss, uniform = draw_f32(rng, n_gauss, n_uniform)

    # One pass over the returns (the dropped ones skipped): measured range, the point, and
    # intensity = reflectivity x |cos incidence| x fade, the background's map-frame normals
    # turned into the ego frame (n_map . d_map = n_ego . d_ego).
    c, s = np.float32(np.cos(ego[2])), np.float32(np.sin(ego[2]))
    cos_actor = hits.cos_actor if hits.cos_actor is not None else np.zeros(len(t), np.float32)
    points, ring, lab, dist = kernels.make_returns(
        idx, fade, t, label, hits.prim_bg, cos_actor, sensor.dirs, sensor.ring, world.background_table, c, s,
        actor_refl, gauss, np.float32(model.range_noise), uniform, np.float32(model.ray_drop),
        sensor.position.astype(np.float32))
    return LidarFrame(points, ring, lab, np.full(len(points), k, np.int8), dist)


#: "No draws" / "no ego-box rays" for the kernels (an empty array keeps their signature).
_NONE_F32 = np.zeros(0, np.float32)
