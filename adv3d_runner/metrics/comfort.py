"""Comfort, collision and clearance metrics of ego trajectories.

Comfort (paper Table 1): *planning comfort* is measured on every plan the planner outputs and
averaged over the plans of an episode; *driving comfort* on the trajectory the ego actually
executed. Both report the mean absolute lateral acceleration (m/s^2) and the mean absolute
longitudinal jerk (m/s^3).

Definitions, for a trajectory sampled at ``dt``:

* velocity by central finite differences of the positions (``np.gradient``);
* with yaw given ((T, 3) input): signed speed ``v`` = velocity projected on the heading,
  yaw rate from the unwrapped yaw, lateral acceleration ``a_lat = v * yaw_rate``;
* positions only ((T, 2) input): ``a_lat = (v x a) / |v|`` (0 where |v| < 1e-3 m/s, where the
  heading is undefined);
* longitudinal acceleration ``a_lon = dv/dt`` and jerk ``j = d a_lon / dt``.

On a circle of curvature kappa driven at constant speed v: ``a_lat = v^2 kappa`` and ``j = 0``.
Trajectories with fewer than 3 samples have zero jerk (and fewer than 2 zero acceleration).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .boxes import box_distance, boxes_overlap

DT = 0.1
_MIN_SPEED = 1e-3  # m/s; below this a positions-only trajectory has no defined heading


@dataclass
class Comfort:
    """Mean and max absolute lateral acceleration (m/s^2) and longitudinal jerk (m/s^3)."""

    lat: float
    jerk: float
    max_lat: float
    max_jerk: float

    def as_dict(self) -> dict:
        return {"lat": self.lat, "jerk": self.jerk, "max_lat": self.max_lat, "max_jerk": self.max_jerk}


def _grad(x: np.ndarray, dt: float) -> np.ndarray:
    """Finite-difference derivative along axis -1 (central inside, one-sided at the ends)."""
    if x.shape[-1] < 2:
        return np.zeros_like(x)
    return np.gradient(x, dt, axis=-1)


def kinematic_profiles(traj: np.ndarray, dt: float = DT) -> dict[str, np.ndarray]:
    """Speed, longitudinal acceleration, jerk and lateral acceleration along trajectories.

    Args:
        traj: (..., T, 3) x, y (m), yaw (rad), or (..., T, 2) positions; sampled every ``dt`` s.
    Returns:
        dict of (..., T) arrays: ``speed`` (m/s, signed along the heading when yaw is given),
        ``accel`` (m/s^2), ``jerk`` (m/s^3), ``lat_accel`` (m/s^2, left +).
    """
    t = np.asarray(traj, dtype=np.float64)
    if t.ndim < 2 or t.shape[-1] not in (2, 3):
        raise ValueError(f"trajectory must be (..., T, 2) or (..., T, 3), got {t.shape}")
    x, y = t[..., 0], t[..., 1]
    # centre coordinates: finite differences of large map coordinates lose precision
    x = x - x[..., :1]
    y = y - y[..., :1]
    vx, vy = _grad(x, dt), _grad(y, dt)
    if t.shape[-1] == 3:
        yaw = np.unwrap(t[..., 2], axis=-1)
        speed = vx * np.cos(yaw) + vy * np.sin(yaw)
        lat = speed * _grad(yaw, dt)
    else:
        speed = np.hypot(vx, vy)
        ax, ay = _grad(vx, dt), _grad(vy, dt)
        moving = speed > _MIN_SPEED
        lat = np.where(moving, (vx * ay - vy * ax) / np.where(moving, speed, 1.0), 0.0)
    accel = _grad(speed, dt)
    jerk = _grad(accel, dt) if t.shape[-2] >= 3 else np.zeros_like(accel)
    return {"speed": speed, "accel": accel, "jerk": jerk, "lat_accel": lat}


def trajectory_comfort(traj: np.ndarray, dt: float = DT) -> Comfort:
    """Comfort of one trajectory (T, 3) or (T, 2) (see module docstring)."""
    prof = kinematic_profiles(traj, dt)
    lat, jerk = np.abs(prof["lat_accel"]), np.abs(prof["jerk"])
    if lat.size == 0:
        return Comfort(0.0, 0.0, 0.0, 0.0)
    return Comfort(float(lat.mean()), float(jerk.mean()), float(lat.max()), float(jerk.max()))


def plan_comfort_cost(plan: np.ndarray, dt: float = DT) -> float:
    """The paper's per-frame planning cost ``c_plan = c_jerk + c_lat`` (Eq. 5) of one plan:
    mean |jerk| + mean |lateral acceleration|."""
    c = trajectory_comfort(plan, dt)
    return c.jerk + c.lat


def planning_comfort(plans: Sequence[np.ndarray], dt: float = DT) -> Comfort:
    """Planning comfort: the comfort of each plan, averaged over the plans (means and maxes)."""
    if len(plans) == 0:
        return Comfort(0.0, 0.0, 0.0, 0.0)
    cs = [trajectory_comfort(p, dt) for p in plans]
    return Comfort(*(float(np.mean([getattr(c, f) for c in cs])) for f in ("lat", "jerk", "max_lat", "max_jerk")))


def driving_comfort(executed: np.ndarray, dt: float = DT) -> Comfort:
    """Driving comfort: the comfort of the executed ego trajectory (T, 3) or (T, 2)."""
    return trajectory_comfort(executed, dt)


# ------------------------------------------------------------------ collisions and clearance

@dataclass
class CollisionReport:
    """Ego-actor collisions and clearance over an episode.

    Attributes:
        collided: any frame with an overlap.
        first_frame: first frame index with an overlap, or -1.
        frames: (T,) bool, overlap in each frame.
        actors: indices (into the actor axis) of the actors the ego overlapped at least once.
        min_distance: smallest footprint distance (m) to any valid actor over all frames
            (0 when colliding; +inf when no actor was ever valid).
        min_distance_per_frame: (T,) m (+inf in frames without valid actors).
    """

    collided: bool
    first_frame: int
    frames: np.ndarray
    actors: list[int]
    min_distance: float
    min_distance_per_frame: np.ndarray

    def as_dict(self) -> dict:
        md = self.min_distance
        return {"collided": self.collided, "first_frame": self.first_frame, "actors": self.actors,
                "min_distance": md if np.isfinite(md) else None}


def collisions(ego_boxes: np.ndarray, actor_boxes: np.ndarray, actor_valid: np.ndarray | None = None) -> CollisionReport:
    """Collisions (rotated-box overlap of the footprints) between the ego and the actors.

    Args:
        ego_boxes: (T, 5) ego footprint per frame. actor_boxes: (T, N, 5). actor_valid: (T, N)
            bool (default: finite boxes are valid).
    """
    ego = np.asarray(ego_boxes, dtype=np.float64).reshape(-1, 5)
    act = np.asarray(actor_boxes, dtype=np.float64).reshape(len(ego), -1, 5)
    valid = np.all(np.isfinite(act), axis=-1)
    if actor_valid is not None:
        valid &= np.asarray(actor_valid, bool).reshape(valid.shape)
    safe = np.where(valid[..., None], act, 0.0)
    overlap = boxes_overlap(ego[:, None, :], safe) & valid  # (T, N)
    dist = np.where(valid, box_distance(ego[:, None, :], safe), np.inf)
    dist = np.where(overlap, 0.0, dist)
    frames = overlap.any(axis=1)
    per_frame = dist.min(axis=1) if dist.shape[1] else np.full(len(ego), np.inf)
    first = int(np.argmax(frames)) if frames.any() else -1
    return CollisionReport(bool(frames.any()), first, frames, [int(i) for i in np.nonzero(overlap.any(axis=0))[0]],
                           float(per_frame.min()) if len(per_frame) else float("inf"), per_frame)


def min_distance(ego_boxes: np.ndarray, actor_boxes: np.ndarray, actor_valid: np.ndarray | None = None) -> float:
    """Smallest ego-actor footprint distance (m) over an episode (see :func:`collisions`)."""
    return collisions(ego_boxes, actor_boxes, actor_valid).min_distance
