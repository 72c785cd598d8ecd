"""Shared pytest fixtures."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="module")
def addon():
    """The adv3d add-on registered in the ``bpy`` module for one test module (skipped without bpy)."""
    pytest.importorskip("bpy")
    import blender_addon

    blender_addon.register()
    yield blender_addon
    blender_addon.unregister()
