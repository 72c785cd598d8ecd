"""The add-on's only door into ``adv3d_runner`` (numpy-only parts: shapes and scene).

Imports are done lazily, inside functions, so registering the add-on stays instant and a
missing optional piece only disables the operator that needs it. Nothing here imports bpy or
torch; this module can be unit-tested without Blender.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from adv3d_runner.errors import Adv3dError, FileFormatError

__all__ = ["Adv3dError", "FileFormatError", "load_space", "clear_space_cache"]

# Loaded shape spaces keyed by absolute path; the file's mtime and size invalidate an entry, so
# a rebuild on disk is picked up without restarting Blender.
_SPACES: dict[str, tuple[tuple[float, int], Any]] = {}


def load_space(path: str | os.PathLike) -> Any:
    """The ``ShapeSpace`` stored at ``path`` (cached while the file is unchanged)."""
    from adv3d_runner.shapes.shape_space import ShapeSpace

    p = Path(path).expanduser().resolve()
    try:
        st = p.stat()
    except OSError:
        raise FileFormatError(p, "$", "an existing shape-space .npz file", "file not found") from None
    stamp = (st.st_mtime, st.st_size)
    hit = _SPACES.get(str(p))
    if hit is not None and hit[0] == stamp:
        return hit[1]
    space = ShapeSpace.load(p)
    _SPACES[str(p)] = (stamp, space)
    return space


def clear_space_cache() -> None:
    _SPACES.clear()


def unit_vector(latent: np.ndarray | list[float], k: int, width_scale: float, length_scale: float) -> np.ndarray:
    """The shape space's unit input ``[z_1..z_K, width, length]`` in [0, 1]^(K+2)."""
    u = np.empty(k + 2, dtype=np.float64)
    u[:k] = np.asarray(latent, dtype=np.float64)[:k]
    u[k] = width_scale
    u[k + 1] = length_scale
    return np.clip(u, 0.0, 1.0)


def save_space(space, path: str | os.PathLike) -> Path:
    """Write a shape space atomically and drop any cached copy of that path."""
    out = space.save(Path(path))
    _SPACES.pop(str(Path(path).expanduser().resolve()), None)
    return out
