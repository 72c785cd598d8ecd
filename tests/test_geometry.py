"""Ground-floor geometry: angle wrapping and frame changes (boxes are in test_metrics.py)."""
from __future__ import annotations

import numpy as np

from adv3d_runner.geometry.angles import wrap_angle
from adv3d_runner.geometry.frames import boxes_from_frame, boxes_to_frame


def test_wrap_angle_range_and_values():
    a = np.array([-3 * np.pi, -np.pi, 0.0, np.pi, 2.5 * np.pi, 7.0])
    w = wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    assert wrap_angle(np.pi) == -np.pi  # half-open interval [-pi, pi)


def test_wrap_angle_dtypes():
    assert wrap_angle(np.arange(3)).dtype == np.float64          # ints become float64
    assert wrap_angle(np.zeros(3, np.float32)).dtype == np.float32  # float32 beam tables stay
    assert np.ndim(wrap_angle(1.0)) == 0


def test_frame_change_round_trip_and_heading():
    pose = np.array([10.0, -4.0, 3.0])
    boxes = np.array([[12.0, -3.0, 4.5, 1.9, -3.1], [0.0, 0.0, 1.0, 1.0, 0.5]])
    local = boxes_to_frame(boxes, pose)
    assert np.all(np.abs(local[:, 4]) <= np.pi)
    np.testing.assert_allclose(boxes_from_frame(local, pose), boxes, atol=1e-12)
    # a box at the pose, heading like the pose, sits at the origin with yaw 0
    np.testing.assert_allclose(boxes_to_frame(np.r_[pose[:2], 4.0, 2.0, pose[2]], pose), [0, 0, 4, 2, 0], atol=1e-12)


def test_wrap_angle_equals_its_numpy_expression():
    """The scalar fast path (Python float arithmetic) and the array path against the numpy
    expression, bit for bit and type for type: both sides of every multiple of pi, zeros,
    huge, tiny and non-finite angles, float32 and integer inputs."""
    from adv3d_runner.geometry.angles import wrap_angle_numpy

    rng = np.random.default_rng(4)
    k = np.arange(-6, 7) * np.pi
    vals = np.r_[k, np.nextafter(k, np.inf), np.nextafter(k, -np.inf), 0.0, -0.0, 1e-300, -1e-300, 1e300, -1e300,
                 np.inf, -np.inf, np.nan, rng.normal(0, 10, 2000), rng.normal(0, 1e6, 200)]
    with np.errstate(invalid="ignore", over="ignore"):  # inf and 1e300 (as float32) warn
        _compare_wraps(vals, wrap_angle_numpy)


def _compare_wraps(vals, wrap_angle_numpy):
    for v in vals:
        for x in (float(v), np.float64(v)):
            got, want = wrap_angle(x), wrap_angle_numpy(x)
            assert type(got) is type(want) and np.asarray(got).tobytes() == np.asarray(want).tobytes()
    for arr in (vals, vals.astype(np.float32), np.arange(-20, 20), vals[:0]):
        got, want = wrap_angle(arr), wrap_angle_numpy(arr)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    for x in (np.float32(3.5), 7, np.int64(-9)):
        assert np.asarray(wrap_angle(x)).tobytes() == np.asarray(wrap_angle_numpy(x)).tobytes()
