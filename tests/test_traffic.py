"""IDM / MOBIL: stability at zero gap and zero speed, no reversing, safe lane changes."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.dynamics.traffic import IDMParams, Traffic, equilibrium_speed, idm_acceleration, integrate

P = IDMParams()


def test_idm_zero_gap_and_zero_speed_are_finite():
    v = np.array([0.0, 0.0, 10.0, 30.0, 0.0, 5.0])
    gap = np.array([0.0, -1.0, 0.0, -5.0, np.inf, 1e-12])
    acc = idm_acceleration(v, 30.0, gap, 0.0)
    assert np.isfinite(acc).all()
    assert np.all(acc[[0, 1, 2, 3, 5]] == -P.b_max)  # touching: strongest braking
    assert acc[4] == pytest.approx(P.a)  # standing on a free road: full acceleration
    assert np.all(acc >= -P.b_max) and np.all(acc <= P.a)


def test_idm_grid_never_nan(rng):
    v = rng.uniform(-1, 40, 10_000)
    v0 = rng.uniform(0, 40, 10_000)
    gap = rng.choice([0.0, -1.0, np.inf, 1.0, 50.0], 10_000) * rng.uniform(0, 2, 10_000)
    acc = idm_acceleration(v, v0, gap, rng.uniform(0, 40, 10_000))
    assert np.isfinite(acc).all()


def test_integrate_never_reverses():
    s = np.zeros(4)
    v = np.array([0.0, 0.5, 10.0, 0.0])
    acc = np.array([-9.0, -9.0, -9.0, 0.0])
    s2, v2 = integrate(s, v, acc, 0.1)
    assert np.all(v2 >= 0) and np.all(s2 >= s)
    assert s2[0] == 0.0 and v2[0] == 0.0
    assert s2[1] == pytest.approx(0.5 ** 2 / 18)  # stops inside the step


def test_follower_stops_behind_stopped_leader():
    """A lane end is a standing obstacle: a vehicle at 30 m/s stops before it, never passes."""
    tr = Traffic(lane_start=[-np.inf], lane_end=[150.0])
    tr.add(0.0, 0, 30.0, 4.5, 30.0)
    gaps = []
    for _ in range(400):
        tr.step(0.1)
        gaps.append(150.0 - tr.s[0] - 2.25)
        assert np.all(tr.v >= 0) and np.isfinite(tr.s).all()
    assert min(gaps) > 0.5
    assert tr.v[0] < 0.05


def test_zero_gap_start_recovers_without_nan():
    tr = Traffic(lane_start=[-np.inf], lane_end=[np.inf])
    tr.add(10.0, 0, 0.0, 4.5, 30.0)
    tr.add(5.5, 0, 0.0, 4.5, 30.0)  # bumper to bumper (gap 1 m) and 0-length gap below
    tr.add(1.0, 0, 0.0, 4.5, 30.0)  # overlapping its leader by 0 m
    prev = tr.s.copy()
    for _ in range(100):
        tr.step(0.1)
        assert np.isfinite(tr.s).all() and np.all(tr.v >= 0) and np.all(tr.s >= prev)
        prev = tr.s.copy()
    assert tr.v[0] > 5  # the leader drives off, the others follow
    assert tr.v[2] > 0


def _two_lane(follower_gap: float) -> Traffic:
    """Vehicle 0 behind a crawling leader (1) in lane 0; a fast vehicle (2) in lane 1 at
    ``follower_gap`` m behind vehicle 0 (negative: alongside)."""
    tr = Traffic(lane_start=[-np.inf, -np.inf], lane_end=[np.inf, np.inf])
    tr.add(100.0, 0, 25.0, 4.5, 30.0)
    tr.add(115.0, 0, 5.0, 4.5, 5.0)
    tr.add(100.0 - follower_gap, 1, 25.0, 4.5, 30.0)
    return tr


@pytest.mark.parametrize("offset", [0.0, 2.0, -2.0, 5.0])
def test_mobil_never_changes_into_occupied_gap(offset):
    tr = _two_lane(offset)  # lane 1 occupied right beside vehicle 0
    tr.step(0.1)  # step 0 considers left changes
    assert tr.lane[0] == 0


def test_mobil_changes_when_gap_is_free():
    tr = _two_lane(80.0)
    tr.step(0.1)
    assert tr.lane[0] == 1  # the same situation with a free gap does change


def test_mobil_respects_safe_braking_of_new_follower():
    tr = _two_lane(12.0)  # free but close: the new follower at 25 m/s would have to brake hard
    tr.v[2] = 35.0
    tr.step(0.1)
    assert tr.lane[0] == 0


def test_simulation_is_deterministic(rng):
    def run():
        tr = Traffic(lane_start=[-np.inf, -np.inf, -np.inf], lane_end=[np.inf, np.inf, 400.0], road_end=2000)
        r = np.random.default_rng(7)
        for k in range(3):
            for s in np.sort(r.uniform(0, 350, 12)):
                tr.add(s, k, r.uniform(10, 25), 4.5, r.normal(30, 3))
        for _ in range(200):
            tr.step(0.1)
        return tr
    a, b = run(), run()
    np.testing.assert_array_equal(a.s, b.s)
    np.testing.assert_array_equal(a.lane, b.lane)
    assert np.isfinite(a.s).all() and np.all(a.v >= 0)
    # nobody is left in the dropped lane (2) far past its end; all merged or waiting at it
    beyond = a.active & (a.lane == 2) & (a.s > 400.0)
    assert not beyond.any()


def test_equilibrium_speed_is_steady():
    gap = np.array([5.0, 20.0, 60.0])
    v = equilibrium_speed(gap, 30.0)
    acc = idm_acceleration(v, 30.0, gap, v)
    np.testing.assert_allclose(acc, 0.0, atol=1e-6)
    assert np.all(np.diff(v) > 0)
