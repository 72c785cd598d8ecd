"""Frame changes between the map and a moving pose (the ego): boxes and angles.

A pose is ``(x, y, yaw)`` in the map frame (m, m, rad CCW from the map's +x). A box is
``(x, y, length, width, yaw)`` (:mod:`adv3d_runner.geometry.boxes`). The ego frame has its origin
at the pose and +x along its heading; localisation is perfect, so these are exact rigid motions.
"""
from __future__ import annotations

import numpy as np

from .angles import wrap_angle
from .boxes import as_boxes


def boxes_to_frame(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Express map-frame boxes (..., 5) in the frame of ``pose`` (x, y, yaw) (e.g. the ego)."""
    b = as_boxes(boxes)
    x0, y0, yaw0 = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3))
    c, s = np.cos(yaw0), np.sin(yaw0)
    dx, dy = b[..., 0] - x0, b[..., 1] - y0
    out = b.copy()
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 4] = wrap_angle(b[..., 4] - yaw0)
    return out


def boxes_from_frame(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Inverse of :func:`boxes_to_frame`: boxes in the frame of ``pose`` -> map frame."""
    b = as_boxes(boxes)
    x0, y0, yaw0 = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3))
    c, s = np.cos(yaw0), np.sin(yaw0)
    out = b.copy()
    out[..., 0] = x0 + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = y0 + s * b[..., 0] + c * b[..., 1]
    out[..., 4] = wrap_angle(b[..., 4] + yaw0)
    return out
