"""Shared pytest fixtures."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent


def load_bench(name: str) -> ModuleType:
    """``bench/<name>.py`` as a module (the benches are scripts, not package members); registered
    in ``sys.modules`` under ``name`` because their dataclasses look their module up."""
    spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="module")
def addon(tmp_path_factory):
    """The adv3d add-on registered in the ``bpy`` module for one test module (skipped without bpy),
    with a cache folder of its own (``ADV3D_CACHE``: realism references built for test spaces
    start absent, and the user's cache is not touched)."""
    import os

    pytest.importorskip("bpy")
    import blender_addon
    from blender_addon import runner

    old = os.environ.get("ADV3D_CACHE")
    os.environ["ADV3D_CACHE"] = str(tmp_path_factory.mktemp("adv3d_cache"))
    runner.clear_reference_state()
    blender_addon.register()
    yield blender_addon
    blender_addon.unregister()
    runner.clear_reference_state()
    if old is None:
        os.environ.pop("ADV3D_CACHE", None)
    else:
        os.environ["ADV3D_CACHE"] = old
