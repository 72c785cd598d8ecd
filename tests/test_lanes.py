"""Lane geometry on regular and degenerate polylines (repeated points, zero-length segments)."""
from __future__ import annotations

import numpy as np
import pytest

from adv3d_runner.scene import lanes as lg

DEGENERATE = {
    "repeated_start": np.array([[0, 0], [0, 0], [0, 0], [10, 0], [20, 0]], float),
    "repeated_middle": np.array([[0, 0], [10, 0], [10, 0], [10, 1e-12], [20, 0]], float),
    "repeated_end": np.array([[0, 0], [10, 0], [20, 0], [20, 0]], float),
    "single_point": np.array([[5, 5], [5, 5], [5, 5]], float),
    "one_point": np.array([[1, 2]], float),
    "u_turn": np.array([[0, 0], [10, 0], [0, 0]], float),
}


@pytest.mark.parametrize("name", sorted(DEGENERATE))
def test_degenerate_polylines_never_give_nan(name, rng):
    pts = DEGENERATE[name]
    q = rng.uniform(-30, 30, (50, 2))
    s, d, h = lg.project(pts, q)
    assert np.isfinite(s).all() and np.isfinite(d).all() and np.isfinite(h).all()
    assert np.isfinite(lg.point_at(pts, np.linspace(-5, 30, 20))).all()
    assert np.isfinite(lg.pose_at(pts, np.linspace(-5, 30, 20), 1.5)).all()
    assert np.isfinite(lg.curvature(pts)).all()
    assert np.isfinite(lg.vertex_normals(pts)).all()
    assert np.isfinite(lg.offset_polyline(pts, 2.0)).all()
    r = lg.resample(pts, 1.0)
    assert np.isfinite(r).all() and len(r) >= 1
    assert np.all(np.diff(lg.arc_length(pts)) >= 0)


def test_repeated_points_do_not_change_geometry(rng):
    clean = np.array([[0, 0], [10, 0], [20, 5]], float)
    dirty = np.array([[0, 0], [0, 0], [10, 0], [10, 0], [10, 0], [20, 5], [20, 5]], float)
    q = rng.uniform(-10, 30, (100, 2))
    for a, b in zip(lg.project(clean, q), lg.project(dirty, q)):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert lg.length(dirty) == pytest.approx(lg.length(clean))
    np.testing.assert_allclose(lg.resample(dirty, 2.0), lg.resample(clean, 2.0))
    # per-point widths follow the cleaning of their points
    w = np.array([3, 3, 4, 4, 4, 5, 5], float)
    assert lg.offset_polyline(dirty, w).shape == (3, 2)
    np.testing.assert_allclose(lg.width_at(dirty, w, [0.0, lg.length(clean)]), [3.0, 5.0])


def test_single_point_behaves_like_a_point():
    pts = DEGENERATE["single_point"]
    s, d, h = lg.project(pts, np.array([8.0, 9.0]))
    assert np.hypot(s, d) == pytest.approx(5.0)
    assert lg.length(pts) == 0.0
    assert lg.resample(pts, 1.0).shape == (1, 2)


def test_project_and_point_at_are_inverse(rng):
    theta = np.linspace(0, np.pi / 2, 200)
    arc = np.c_[100 * np.sin(theta), 100 * (1 - np.cos(theta))]  # left turn, radius 100
    s = rng.uniform(5, lg.length(arc) - 5, 50)
    d = rng.uniform(-3, 3, 50)
    pose = lg.pose_at(arc, s, d)
    s2, d2, h2 = lg.project(arc, pose[:, :2])
    np.testing.assert_allclose(s2, s, atol=0.05)
    np.testing.assert_allclose(d2, d, atol=0.01)
    np.testing.assert_allclose(h2, pose[:, 2], atol=0.01)
    k = lg.curvature(arc)[1:-1]
    np.testing.assert_allclose(k, 1 / 100, rtol=1e-3)
    assert lg.curvature_at(arc[::-1], 50.0) == pytest.approx(-1 / 100, rel=1e-3)  # right turn


def test_extrapolation_and_signs():
    line = np.array([[0, 0], [10, 0]], float)
    s, d, h = lg.project(line, np.array([[-5, 2], [15, -3]], float))
    np.testing.assert_allclose(s, [-5, 15])
    np.testing.assert_allclose(d, [2, -3])  # left positive
    np.testing.assert_allclose(lg.point_at(line, [-1, 12]), [[-1, 0], [12, 0]])


def test_resample_spacing():
    line = np.array([[0, 0], [10, 0], [10, 10]], float)
    r = lg.resample(line, 3.0)
    gaps = np.hypot(*np.diff(r, axis=0).T)
    assert r[0].tolist() == [0, 0] and r[-1].tolist() == [10, 10]
    assert gaps.max() <= 3.0 + 1e-9
    with pytest.raises(ValueError):
        lg.resample(line, 0.0)
    with pytest.raises(ValueError):
        lg.clean_polyline(np.array([[0, np.nan]]))


def test_compiled_projection_is_the_numpy_definition_bit_for_bit():
    """``project_on_segments`` (compiled nearest segment) against ``project_on_segments_numpy``
    (the definition): s, d and heading the same bytes for random polylines (integer vertices:
    ties between segments), points near and far, one point and many, and NaN points."""
    rng = np.random.default_rng(0)
    for it in range(300):
        pts = np.cumsum(rng.normal(0.0, 5.0, (int(rng.integers(1, 30)), 2)), axis=0)
        if it % 5 == 0:
            pts = np.round(pts)
        seg = lg.polyline_segments(pts)
        q = rng.normal(pts.mean(axis=0), 20.0, (int(rng.integers(1, 50)), 2))
        if it % 7 == 0:
            q = pts[rng.integers(len(pts), size=len(q))] + 0.0  # on the vertices
        if it % 11 == 0:
            q[0, 1] = np.nan
        for xy in (q, q[-1]):
            with np.errstate(invalid="ignore"):
                got, want = lg.project_on_segments(seg, xy), lg.project_on_segments_numpy(seg, xy)
            for a, b in zip(got, want):
                assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
