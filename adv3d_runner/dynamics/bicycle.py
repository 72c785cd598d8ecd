"""Kinematic bicycle model: exact constant-control steps, vectorised rollouts, and the inverse
(trajectory -> controls) used for "perfect control".

State ``(x, y, yaw, v)``: position (m) of a reference point on the vehicle's axis, heading
(rad), speed of that point (m/s, >= 0; no reversing). Controls per step of ``dt``: longitudinal
acceleration ``a`` (m/s^2) and either a steering angle ``delta`` (rad) or a path curvature
``kappa`` (1/m) of the reference point.

Geometry (Polack et al. 2017): with wheelbase ``L`` and the reference point ``lr`` metres in
front of the rear axle, the slip angle is ``beta = atan(lr tan(delta) / L)``, the point moves in
direction ``yaw + beta`` and ``yaw' = v cos(beta) tan(delta) / L``. With ``lr = 0`` (rear axle)
the point follows circles of radius ``L / tan(delta)`` and ``kappa = tan(delta) / L``. The
default ``lr = 0`` treats the given pose as a no-slip reference, which is what the planner and
the comfort metrics assume (heading = direction of travel).

Each step holds the controls constant over ``dt`` and integrates exactly: with constant
steering the path is a circular arc (a straight line for kappa = 0) and the arc length is
``v dt + a dt^2 / 2``, cut short where the speed reaches zero (the vehicle then stops; speed is
clamped at 0). The arc formula uses ``sinc`` so it is exact and NaN-free at kappa = 0 and at
zero speed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.angles import wrap_angle

DT = 0.1


@dataclass(frozen=True)
class BicycleParams:
    """Vehicle parameters.

    Attributes:
        wheelbase: L, m (> 0).
        lr: distance from the rear axle to the reference point, m (0 = rear axle).
        max_steer: steering limit, rad (< pi/2).
        max_accel: m/s^2, max_decel: m/s^2 (positive number), limits applied to controls.
        max_speed: m/s.
    """

    wheelbase: float = 2.9
    lr: float = 0.0
    max_steer: float = 0.6
    max_accel: float = 4.0
    max_decel: float = 8.0
    max_speed: float = 50.0

    def __post_init__(self) -> None:
        if not self.wheelbase > 0:
            raise ValueError("wheelbase must be > 0")
        if not 0 < self.max_steer < np.pi / 2:
            raise ValueError("max_steer must be in (0, pi/2)")

    @property
    def max_curvature(self) -> float:
        """Largest path curvature (1/m) of the reference point at full steering."""
        d = self.max_steer
        return float(np.cos(np.arctan(self.lr * np.tan(d) / self.wheelbase)) * np.tan(d) / self.wheelbase)


def _slip(delta: np.ndarray, p: BicycleParams) -> np.ndarray:
    return np.arctan(p.lr * np.tan(delta) / p.wheelbase)


def steer_to_curvature(delta: np.ndarray | float, p: BicycleParams) -> np.ndarray:
    """Path curvature (1/m) of the reference point for a steering angle: ``cos(beta) tan(delta) / L``
    (rear axle: ``tan(delta) / L``; in general ``1 / sqrt((L / tan delta)^2 + lr^2)``)."""
    d = np.asarray(delta, dtype=np.float64)
    return np.cos(_slip(d, p)) * np.tan(d) / p.wheelbase


def curvature_to_steer(kappa: np.ndarray | float, p: BicycleParams) -> np.ndarray:
    """Inverse of :func:`steer_to_curvature` (clipped to the steering limit)."""
    k = np.asarray(kappa, dtype=np.float64)
    k = np.clip(k, -p.max_curvature, p.max_curvature)
    # kappa = sin(beta) / lr and tan(delta) = L tan(beta) / lr; rear axle: tan(delta) = L kappa
    if p.lr == 0:
        return np.arctan(p.wheelbase * k)
    beta = np.arcsin(np.clip(k * p.lr, -1.0, 1.0))
    return np.arctan(p.wheelbase * np.tan(beta) / p.lr)


def _arc(s: np.ndarray, kappa: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displacement (dx, dy) and heading change along an arc of length s and curvature kappa
    starting in ``direction``; exact, stable at kappa -> 0."""
    dth = kappa * s
    chord = s * np.sinc(dth / (2 * np.pi))  # np.sinc(x) = sin(pi x)/(pi x): s sin(dth/2)/(dth/2)
    mid = direction + 0.5 * dth
    return chord * np.cos(mid), chord * np.sin(mid), dth


def step(state: np.ndarray, accel: np.ndarray | float, steer: np.ndarray | float | None = None,
         curvature: np.ndarray | float | None = None, dt: float = DT,
         params: BicycleParams = BicycleParams()) -> np.ndarray:
    """Advance states (..., 4) by ``dt`` under constant controls (broadcasting).

    Give exactly one of ``steer`` (rad) or ``curvature`` (1/m); both are clipped to the steering
    limit, the acceleration to ``[-max_decel, max_accel]``.
    Returns:
        (..., 4) next states; speed in [0, max_speed].
    """
    if (steer is None) == (curvature is None):
        raise ValueError("give exactly one of steer or curvature")
    st = np.asarray(state, dtype=np.float64)
    x, y, yaw, v = st[..., 0], st[..., 1], st[..., 2], np.maximum(st[..., 3], 0.0)
    a = np.minimum(np.maximum(np.asarray(accel, dtype=np.float64), -params.max_decel), params.max_accel)
    if steer is not None:
        delta = np.clip(np.asarray(steer, dtype=np.float64), -params.max_steer, params.max_steer)
        kappa = steer_to_curvature(delta, params)
        beta = _slip(delta, params)
    else:
        k_max = params.max_curvature
        kappa = np.minimum(np.maximum(np.asarray(curvature, dtype=np.float64), -k_max), k_max)
        beta = np.arcsin(np.clip(kappa * params.lr, -1.0, 1.0)) if params.lr else 0.0
    v_end = v + a * dt
    # arc length over the step; a braking vehicle stops when v reaches 0 and stays there
    stops = v_end < 0
    t_stop = np.where(stops, v / np.where(a < 0, -a, 1.0), dt)
    s = np.maximum(np.where(stops, 0.5 * v * t_stop, v * dt + 0.5 * a * dt * dt), 0.0)
    v_end = np.minimum(np.maximum(v_end, 0.0), params.max_speed)
    dx, dy, dth = _arc(s, kappa, yaw + beta)
    x1, y1, yaw1, v1 = np.broadcast_arrays(x + dx, y + dy, yaw + dth, v_end)
    out = np.empty(x1.shape + (4,))
    out[..., 0], out[..., 1], out[..., 2], out[..., 3] = x1, y1, yaw1, v1
    return out


def rollout(state0: np.ndarray, accel: np.ndarray, steer: np.ndarray | None = None,
            curvature: np.ndarray | None = None, dt: float = DT,
            params: BicycleParams = BicycleParams()) -> np.ndarray:
    """Roll out many control sequences at once.

    Args:
        state0: (B, 4) or (4,) initial states.
        accel: (B, T) m/s^2; steer (B, T) rad or curvature (B, T) 1/m (exactly one).
    Returns:
        (B, T + 1, 4) states, index 0 = ``state0``. Yaw is continuous (not wrapped).
    """
    a = np.atleast_2d(np.asarray(accel, dtype=np.float64))
    ctrl = steer if steer is not None else curvature
    if (steer is None) == (curvature is None):
        raise ValueError("give exactly one of steer or curvature")
    c = np.atleast_2d(np.asarray(ctrl, dtype=np.float64))
    a, c = np.broadcast_arrays(a, c)
    B, T = a.shape
    s0 = np.broadcast_to(np.asarray(state0, dtype=np.float64).reshape(-1, 4), (B, 4))
    out = np.empty((B, T + 1, 4))
    out[:, 0] = s0
    for k in range(T):
        if steer is not None:
            out[:, k + 1] = step(out[:, k], a[:, k], steer=c[:, k], dt=dt, params=params)
        else:
            out[:, k + 1] = step(out[:, k], a[:, k], curvature=c[:, k], dt=dt, params=params)
    return out


def controls_from_trajectory(poses: np.ndarray, speeds: np.ndarray | None = None, dt: float = DT,
                             v0: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Controls that reproduce a trajectory with :func:`step` ("perfect control").

    Each step between consecutive poses is fitted with the constant-curvature arc that joins
    them with the observed heading change (``kappa = dyaw / s``, ``s = chord / sinc(dyaw / 2)``),
    and the acceleration that covers that arc length in ``dt``.

    Args:
        poses: (T + 1, 3) x, y, yaw (rad) at 0, dt, ..., T dt.
        speeds: (T + 1,) m/s when known (then ``a = dv / dt``); otherwise the speed profile is
            reconstructed from the arc lengths starting at ``v0`` (default: first arc / dt).
    Returns:
        accel (T,) m/s^2, curvature (T,) 1/m. Steps without motion get curvature 0.
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    d = np.diff(p[:, :2], axis=0)
    chord = np.hypot(d[:, 0], d[:, 1])
    dyaw = np.diff(np.unwrap(p[:, 2]))
    s = chord / np.sinc(dyaw / (2 * np.pi))
    moving = s > 1e-9
    kappa = np.where(moving, dyaw / np.where(moving, s, 1.0), 0.0)
    if speeds is not None:
        v = np.asarray(speeds, dtype=np.float64).reshape(-1)
        return np.diff(v) / dt, kappa
    v_prev = s[0] / dt if v0 is None else float(v0)
    acc = np.empty(len(s))
    for k in range(len(s)):  # s = v dt + a dt^2 / 2
        acc[k] = 2.0 * (s[k] - v_prev * dt) / (dt * dt)
        v_prev = max(v_prev + acc[k] * dt, 0.0)
    return acc, kappa


def advance_on_trajectory(poses: np.ndarray, speeds: np.ndarray, dt: float = DT,
                          plan_dt: float = DT) -> tuple[np.ndarray, float]:
    """Perfect control: the ego state ``dt`` after the start of a plan.

    Args:
        poses: (T, 3) plan poses at 0, plan_dt, ...; speeds: (T,) m/s.
    Returns:
        pose (3,) and speed at time ``dt`` (linear interpolation between plan samples; the last
        sample is held beyond the plan's end).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(speeds, dtype=np.float64).reshape(-1)
    t = np.arange(len(p)) * plan_dt
    yaw = np.unwrap(p[:, 2])
    pose = np.array([np.interp(dt, t, p[:, 0]), np.interp(dt, t, p[:, 1]), np.interp(dt, t, yaw)])
    pose[2] = wrap_angle(pose[2])
    return pose, float(np.interp(dt, t, v))
