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
    if type(yaw) is float or type(yaw) is np.float64:
        # One float (the tracker wraps ~16 a frame): Python's float % is numpy's remainder
        # (fmod, then the divisor added where the signs differ, a zero given the divisor's
        # sign), so the same bits as the array expression, as a numpy float64 like it.
        return np.float64((float(yaw) + _PI) % _TWO_PI - _PI)
    a = np.asarray(yaw)
    if a.dtype.kind != "f":
        a = a.astype(np.float64)
    return (a + np.pi) % (2 * np.pi) - np.pi


def wrap_angle_numpy(yaw: np.ndarray | float) -> np.ndarray:
    """:func:`wrap_angle` as numpy alone (the test's reference)."""
    a = np.asarray(yaw)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    return (a + np.pi) % (2 * np.pi) - np.pi


_PI = float(np.pi)
_TWO_PI = 2 * float(np.pi)
