"""Comfort, collision and clearance metrics of ego trajectories.

Comfort (paper Table 1): *planning comfort* is measured on every plan the planner outputs and
averaged over the plans of an episode; *driving comfort* on the trajectory the ego actually
executed. Both report the mean absolute lateral acceleration (m/s^2) and the mean absolute
longitudinal jerk (m/s^3).

Definitions, for a trajectory of T samples every ``dt`` (plain finite differences, no
smoothing, so every value is exact for polynomial motion and none is an edge artefact):

* speed at the T - 1 half steps: ``|p[k+1] - p[k]| / dt`` (with yaw given, (T, 3) input: the
  displacement projected on the mean heading of the step, i.e. signed);
* longitudinal acceleration at the T - 2 inner samples: the difference of those speeds / dt;
  jerk at the T - 3 inner half steps: the difference of accelerations / dt;
* lateral acceleration at the T - 2 inner samples: ``v * yaw_rate`` with central differences
  when yaw is given; from positions only ``(v x a) / |v|`` with central velocity and the
  second difference as acceleration (0 where |v| < 1e-3 m/s and the heading is undefined).

On a circle of curvature kappa driven at constant speed v: ``a_lat = v^2 kappa`` and jerk 0.
Too short trajectories (T < 3 for accelerations, T < 4 for jerk) contribute zeros.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..geometry.boxes import box_distance, boxes_overlap

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


def kinematic_profiles(traj: np.ndarray, dt: float = DT) -> dict[str, np.ndarray]:
    """Speed, longitudinal acceleration, jerk and lateral acceleration along trajectories.

    Args:
        traj: (..., T, 3) x, y (m), yaw (rad), or (..., T, 2) positions; sampled every ``dt`` s.
    Returns:
        dict of arrays (see module docstring for where each is sampled): ``speed`` (..., T-1)
        m/s, ``accel`` (..., T-2) m/s^2, ``jerk`` (..., T-3) m/s^3, ``lat_accel`` (..., T-2)
        m/s^2 (left +); lengths are clipped at 0.
    """
    t = np.asarray(traj, dtype=np.float64)
    if t.ndim < 2 or t.shape[-1] not in (2, 3):
        raise ValueError(f"trajectory must be (..., T, 2) or (..., T, 3), got {t.shape}")
    # centre coordinates: differences of large map coordinates lose precision
    x = t[..., 0] - t[..., :1, 0]
    y = t[..., 1] - t[..., :1, 1]
    vx, vy = np.diff(x, axis=-1) / dt, np.diff(y, axis=-1) / dt  # (..., T-1) half steps
    if t.shape[-1] == 3:
        yaw = np.unwrap(t[..., 2], axis=-1)
        mid = 0.5 * (yaw[..., 1:] + yaw[..., :-1])
        speed = vx * np.cos(mid) + vy * np.sin(mid)
        v_c = 0.5 * (speed[..., 1:] + speed[..., :-1])
        lat = v_c * (yaw[..., 2:] - yaw[..., :-2]) / (2 * dt)
    else:
        speed = np.hypot(vx, vy)
        vxc, vyc = 0.5 * (vx[..., 1:] + vx[..., :-1]), 0.5 * (vy[..., 1:] + vy[..., :-1])
        ax, ay = np.diff(vx, axis=-1) / dt, np.diff(vy, axis=-1) / dt
        sc = np.hypot(vxc, vyc)
        moving = sc > _MIN_SPEED
        lat = np.where(moving, (vxc * ay - vyc * ax) / np.where(moving, sc, 1.0), 0.0)
    accel = np.diff(speed, axis=-1) / dt
    jerk = np.diff(accel, axis=-1) / dt
    return {"speed": speed, "accel": accel, "jerk": jerk, "lat_accel": lat}


def trajectory_comfort(traj: np.ndarray, dt: float = DT) -> Comfort:
    """Comfort of one trajectory (T, 3) or (T, 2) (see module docstring)."""
    prof = kinematic_profiles(traj, dt)
    lat, jerk = np.abs(prof["lat_accel"]), np.abs(prof["jerk"])
    ml, xl = (float(lat.mean()), float(lat.max())) if lat.size else (0.0, 0.0)
    mj, xj = (float(jerk.mean()), float(jerk.max())) if jerk.size else (0.0, 0.0)
    return Comfort(ml, mj, xl, xj)


def plan_comfort_cost(plan: np.ndarray, dt: float = DT) -> float:
    """The paper's per-frame planning cost ``c_plan = c_jerk + c_lat`` (Eq. 5) of one plan:
    mean |jerk| + mean |lateral acceleration|."""
    c = trajectory_comfort(plan, dt)
    return c.jerk + c.lat


def planning_comfort(plans: Sequence[np.ndarray], dt: float = DT) -> Comfort:
    """Planning comfort: the comfort of each plan, averaged over the plans (means and maxes)."""
    return mean_comfort([trajectory_comfort(p, dt) for p in plans])


def mean_comfort(comforts: Sequence[Comfort]) -> Comfort:
    """Each field's mean over ``comforts`` (zeros for none): :func:`planning_comfort` of plans
    whose comforts are already known."""
    if len(comforts) == 0:
        return Comfort(0.0, 0.0, 0.0, 0.0)
    return Comfort(*(float(np.mean([getattr(c, f) for c in comforts])) for f in ("lat", "jerk", "max_lat", "max_jerk")))


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
