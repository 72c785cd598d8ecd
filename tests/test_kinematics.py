"""Kinematic bicycle: exact arcs, zero speed, full steering, braking to a stop, inverse controls."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adv3d_runner.dynamics import bicycle as km


def _fit_circle(xy):
    """Least-squares circle (centre, radius) through points (algebraic fit)."""
    A = np.c_[2 * xy, np.ones(len(xy))]
    b = np.sum(xy ** 2, axis=1)
    (cx, cy, c), *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.array([cx, cy]), math.sqrt(c + cx * cx + cy * cy)


def test_zero_speed_zero_accel_does_not_move():
    p = km.BicycleParams()
    s0 = np.array([3.0, -2.0, 0.7, 0.0])
    for steer in (0.0, p.max_steer, -p.max_steer):
        out = km.rollout(s0, np.zeros((1, 30)), steer=np.full((1, 30), steer), params=p)
        assert np.all(np.isfinite(out))
        assert np.array_equal(out[0, -1], s0)


def test_braking_from_rest_stays_at_rest_and_speed_never_negative():
    out = km.rollout(np.array([0, 0, 0, 0.0]), np.full((1, 20), -5.0), curvature=np.zeros((1, 20)))
    assert np.array_equal(out[0, -1], [0, 0, 0, 0])
    # from 3 m/s at -5 m/s^2: stops after 0.6 s, having covered v^2 / (2 a) = 0.9 m
    out = km.rollout(np.array([0, 0, 0, 3.0]), np.full((1, 20), -5.0), curvature=np.full((1, 20), 0.0))
    assert np.all(out[0, :, 3] >= 0)
    assert out[0, -1, 0] == pytest.approx(0.9)
    assert out[0, 6:, 3].max() == 0.0


@pytest.mark.parametrize("steer", [0.3, -0.3, 0.6, 5.0])
def test_full_steering_circle_radius(steer):
    p = km.BicycleParams(wheelbase=2.9, max_steer=0.6)
    eff = float(np.clip(steer, -p.max_steer, p.max_steer))  # commands beyond the limit are clipped
    out = km.rollout(np.array([0, 0, 0, 8.0]), np.zeros((1, 200)), steer=np.full((1, 200), steer), params=p)[0]
    centre, radius = _fit_circle(out[:, :2])
    assert radius == pytest.approx(p.wheelbase / math.tan(abs(eff)), rel=1e-9)
    assert np.allclose(np.hypot(*(out[:, :2] - centre).T), radius, atol=1e-9)
    assert np.sign(out[-1, 2]) == np.sign(eff) or abs(out[-1, 2]) < 1e-12
    assert np.allclose(out[:, 3], 8.0)


def test_slip_reference_point_radius():
    p = km.BicycleParams(wheelbase=3.0, lr=1.4)
    delta = 0.25
    out = km.rollout(np.array([0, 0, 0, 5.0]), np.zeros((1, 300)), steer=np.full((1, 300), delta), params=p)[0]
    _, radius = _fit_circle(out[:, :2])
    assert radius == pytest.approx(math.hypot(p.wheelbase / math.tan(delta), p.lr), rel=1e-9)
    assert km.curvature_to_steer(km.steer_to_curvature(delta, p), p) == pytest.approx(delta)


def test_exact_step_matches_fine_euler_integration():
    p = km.BicycleParams()
    s0 = np.array([1.0, 2.0, 0.3, 12.0])
    a, kappa, dt = 1.2, 0.02, 0.1
    exact = km.step(s0, a, curvature=kappa, dt=dt, params=p)
    n = 20000
    x, y, yaw, v = s0
    h = dt / n
    for _ in range(n):  # tiny Euler steps converge to the exact solution
        x += v * math.cos(yaw) * h
        y += v * math.sin(yaw) * h
        yaw += v * kappa * h
        v += a * h
    assert np.allclose(exact, [x, y, yaw, v], atol=2e-4)


def test_straight_line_and_vectorised_rollout(rng):
    B, T = 7, 25
    acc = rng.uniform(-3, 2, (B, T))
    kap = rng.uniform(-0.05, 0.05, (B, T))
    kap[0] = 0.0
    out = km.rollout(np.array([0, 0, 0, 10.0]), acc, curvature=kap)
    assert out.shape == (B, T + 1, 4) and np.all(np.isfinite(out))
    assert np.allclose(out[0, :, 1], 0.0) and np.allclose(out[0, :, 2], 0.0)
    # each row equals its own single rollout
    one = km.rollout(np.array([0, 0, 0, 10.0]), acc[3:4], curvature=kap[3:4])
    assert np.allclose(one[0], out[3])


def test_controls_from_trajectory_round_trip(rng):
    T = 40
    acc = rng.normal(0, 1.0, T)
    kap = rng.normal(0, 0.02, T)
    s0 = np.array([100.0, -50.0, 2.0, 15.0])
    traj = km.rollout(s0, acc[None], curvature=kap[None])[0]
    a1, k1 = km.controls_from_trajectory(traj[:, :3], traj[:, 3])
    assert np.allclose(a1, acc, atol=1e-9) and np.allclose(k1, kap, atol=1e-9)
    a2, k2 = km.controls_from_trajectory(traj[:, :3], v0=15.0)
    assert np.allclose(a2, acc, atol=1e-6) and np.allclose(k2, kap, atol=1e-9)
    again = km.rollout(s0, a2[None], curvature=k2[None])[0]
    assert np.allclose(again, traj, atol=1e-6)
    # a standing trajectory gives zero controls, no NaN
    a0, k0 = km.controls_from_trajectory(np.zeros((5, 3)), np.zeros(5))
    assert np.all(a0 == 0) and np.all(k0 == 0)


def test_advance_on_trajectory():
    poses = np.array([[0, 0, 0], [1, 0, 0.1], [2, 0.1, 0.2]], float)
    pose, v = km.advance_on_trajectory(poses, np.array([10.0, 11.0, 12.0]), dt=0.1)
    assert np.allclose(pose, poses[1]) and v == pytest.approx(11.0)
    pose, v = km.advance_on_trajectory(poses, np.array([10.0, 11.0, 12.0]), dt=0.05)
    assert np.allclose(pose, [0.5, 0, 0.05]) and v == pytest.approx(10.5)


def test_bad_params_and_controls():
    with pytest.raises(ValueError):
        km.BicycleParams(wheelbase=0.0)
    with pytest.raises(ValueError):
        km.BicycleParams(max_steer=math.pi / 2)
    with pytest.raises(ValueError):
        km.step(np.zeros(4), 0.0)
