"""Angles: the one place that wraps headings (radians).

Every heading the project stores or compares is wrapped to [-pi, pi) by :func:`wrap_angle`;
nothing inlines the formula, so a change of convention is a one-line change.
"""
from __future__ import annotations

import numpy as np


def wrap_angle(yaw: np.ndarray | float) -> np.ndarray:
    """Wrap angles (rad) to [-pi, pi).

    Args:
        yaw: scalar or array of angles in radians, any shape.

    Returns:
        Array of the same shape; float64 unless the input is already a float array, whose
        dtype is kept (LiDAR beam tables are float32).
    """
    a = np.asarray(yaw)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    return (a + np.pi) % (2 * np.pi) - np.pi
