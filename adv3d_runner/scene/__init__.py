"""Driving scenes: the scene file contract, generators and importers, background geometry.

Import what you need from the submodules; ``schema`` (numpy only) is re-exported here:
``load_scene``, ``save_scene``, ``Scene`` and the parts it is made of. The re-export is lazy
(on first access), so importing ``adv3d_runner.scene.cli`` to build the command line loads
no numpy (docs/performance.md).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

_SCHEMA_NAMES = ("Actor", "Background", "Barrier", "Ego", "Lane", "Lidar", "Scene", "Source", "StaticMesh", "Track",
                 "default_sensors", "load_scene", "save_scene", "scene_equal")
__all__ = list(_SCHEMA_NAMES)

if TYPE_CHECKING:
    from .schema import (  # noqa: F401
        Actor, Background, Barrier, Ego, Lane, Lidar, Scene, Source, StaticMesh, Track,
        default_sensors, load_scene, save_scene, scene_equal,
    )


def __getattr__(name: str) -> Any:
    if name in _SCHEMA_NAMES:
        from . import schema

        return getattr(schema, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
