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
